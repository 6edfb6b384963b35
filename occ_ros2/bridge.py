"""The bridge: OCC daemons' OpenIGTLink interfaces on one side, ROS 2 topics (DDS) on the other.

The bridge is an ordinary OpenIGTLink client of each daemon: of a *viewer* port (3D Slicer's,
18944 on the slave) for the poses and the state, and optionally of an *operator* port (18947)
for commands. The daemons know nothing of ROS 2; a viewer-only bridge cannot move the robot.

Per namespace ``NS`` (e.g. ``/occ/slave``) it publishes, CRTK names where CRTK has one (topic
``X`` is ``rt/X`` on the wire, as rmw_cyclonedds names it):

================================  ===========================  ==============================
topic                             type                         from
================================  ===========================  ==============================
``NS/measured_cp``                geometry_msgs/PoseStamped    TRANSFORM ``Tip`` in the base
                                                               frame (Base⁻¹·Tip), metres;
                                                               frame_id ``<leaf>_base``
``NS/base/measured_cp``           geometry_msgs/PoseStamped    TRANSFORM ``Base``; frame_id
                                                               the world frame (``world``)
``NS/measured_js``                sensor_msgs/JointState       NDARRAY ``Joints`` (positions;
                                                               names from its metadata)
``NS/operating_state``            crtk_msgs/OperatingState     STATUS of a state, GetState
``NS/state``                      std_msgs/String              the daemon's own state name
``NS/status``                     std_msgs/String              every STATUS (alerts included)
``NS/command_reply``              std_msgs/String              RTS_COMMAND to a command
================================  ===========================  ==============================

and takes commands on ``NS/state_command`` (crtk_msgs/StringStamped, CRTK's topic) and
``NS/command`` (std_msgs/String, publishable without crtk_msgs installed): CRTK's words
``enable``, ``disable``, ``pause``, ``resume`` become ``Enable``, ``Disable``, ``Stop``, ``Run``;
any other word (``Run``, ``EStop``, ``Reset``, ``GetState``, ``GetStats``, ``Clutch`` ...) goes
to the daemon as it is, as an IGTL COMMAND on the operator port. The reply is published on
``NS/command_reply`` as ``"<Name> <SUCCESS|FAIL>: <message>"``.

QoS, as ROS 2 would: poses and replies reliable, volatile, keep last 10 (ROS 2's default, which
every subscriber matches; sensor-data QoS would be refused by a default reliable subscriber);
the two state topics reliable, *transient local*, keep last 1, so a subscriber that comes later
gets the current state at once (ROS 2's "latched" topics); the command subscriptions ROS 2's
default.

``operating_state`` maps the daemon's states onto CRTK's meta-states: INIT, READY, SHUTDOWN ->
DISABLED; ENABLED -> ENABLED; RUNNING -> ENABLED and ``is_busy`` (following its master);
STOPPED -> PAUSED; FAULT, ESTOP -> FAULT. ``is_homed`` is true past INIT (the daemons' joints
are absolute: there is no homing). The exact state is on ``NS/state``.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from cyclonedds.core import GuardCondition, ReadCondition, SampleState, WaitSet
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

import igtl
from igtl.messages.base import Message
from igtl.transport import TCPClient
from occ.stats import Histogram

from . import msgs

log = logging.getLogger("occ_ros2")

#: the Cyclone DDS configuration the bridge uses unless told otherwise: loopback, no multicast
DEFAULT_CONFIG = Path(__file__).with_name("cyclonedds-lo.xml")

MM = 1e-3

#: the daemon's states (occ.safety.RobotState values) as CRTK meta-states
CRTK_STATE = {
    "INIT": "DISABLED",
    "READY": "DISABLED",
    "SHUTDOWN": "DISABLED",
    "ENABLED": "ENABLED",
    "RUNNING": "ENABLED",
    "STOPPED": "PAUSED",
    "FAULT": "FAULT",
    "ESTOP": "FAULT",
}

#: CRTK's state commands, as the daemon's operator commands
CRTK_COMMANDS = {"enable": "Enable", "disable": "Disable", "pause": "Stop", "resume": "Run"}

#: plain CDR (XCDR1), what rmw_cyclonedds writes and reads; a Cyclone writer may otherwise
#: choose XCDR2, which a ROS 2 Humble reader does not accept
_REPR = Policy.DataRepresentation(use_cdrv0_representation=True)
QOS_DEFAULT = Qos(
    Policy.Reliability.Reliable(duration(milliseconds=100)),
    Policy.Durability.Volatile,
    Policy.History.KeepLast(10),
    _REPR,
)
QOS_LATCHED = Qos(
    Policy.Reliability.Reliable(duration(milliseconds=100)),
    Policy.Durability.TransientLocal,
    Policy.History.KeepLast(1),
    _REPR,
)
#: ROS 2's sensor-data profile (best effort, keep last 5): for subscribers of pose streams
QOS_SENSOR = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5), _REPR)


def topic_name(ns: str, leaf: str) -> str:
    """The DDS topic of ROS 2 topic ``ns/leaf``: ROS topics are ``rt/`` + the name without
    its leading slash."""
    return "rt/" + f"{ns.strip('/')}/{leaf}".strip("/")


def quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix, w >= 0 (the largest-component method, stable near
    180 degrees, where taking w from the trace alone loses precision)."""
    m = r
    tr = float(m[0, 0] + m[1, 1] + m[2, 2])
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2.0
        q = (0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s)
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2.0
        q = ((m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s)
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2.0
        q = ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s)
    x, y, z, w = (float(v) for v in q)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    sign = -1.0 if w < 0.0 else 1.0  # q and -q are the same rotation: one canonical form
    return (sign * x / n, sign * y / n, sign * z / n, sign * w / n)


def pose_stamped(matrix_m: np.ndarray, stamp: msgs.Time, frame_id: str) -> msgs.PoseStamped:
    """A PoseStamped of a 4x4 transform whose translation is in metres."""
    x, y, z = (float(v) for v in matrix_m[:3, 3])
    qx, qy, qz, qw = quaternion(matrix_m[:3, :3])
    return msgs.PoseStamped(
        header=msgs.Header(stamp=stamp, frame_id=frame_id),
        pose=msgs.Pose(msgs.Point(x, y, z), msgs.Quaternion(qx, qy, qz, qw)),
    )


def parse_endpoint(text: str) -> tuple[str, int, str]:
    """``HOST:PORT=NAMESPACE`` -> (host, port, namespace); the namespace starts with ``/``."""
    where, sep, ns = text.partition("=")
    host, _, port = where.rpartition(":")
    if not sep or not host or not port.isdigit() or not ns.strip("/"):
        raise ValueError(f"expected HOST:PORT=/NAMESPACE, got {text!r}")
    if not all(part.isidentifier() for part in ns.strip("/").split("/")):
        raise ValueError(f"not a ROS 2 namespace: {ns!r}")
    return host, int(port), "/" + ns.strip("/")


@dataclass
class _Counters:
    tips: int = 0
    tips_without_base: int = 0
    bases: int = 0
    statuses: int = 0
    commands: int = 0
    replies: int = 0
    commands_refused: int = 0
    publish_errors: int = 0


@dataclass
class Robot:
    """One daemon as seen by the bridge: its namespace, its links, its DDS endpoints."""

    ns: str
    leaf: str
    viewer: TCPClient | None = None
    operator: TCPClient | None = None
    base_m: np.ndarray | None = None
    state: str | None = None
    writers: dict[str, DataWriter] = field(default_factory=dict)
    readers: list[tuple[DataReader[Any], Callable[[Any], str]]] = field(default_factory=list)
    counters: _Counters = field(default_factory=_Counters)


class Bridge:
    """Publishes what the daemons send, forwards commands (module docstring).

    ``latency_us`` measures the bridge itself: from the decoded message in the IGTL client's
    callback to the DDS write having returned, per published pose.
    """

    def __init__(
        self,
        viewers: Sequence[tuple[str, int, str]] = (),
        operators: Sequence[tuple[str, int, str]] = (),
        *,
        domain_id: int = 0,
        config: str | None = None,
        world_frame: str = "world",
    ) -> None:
        self.domain_id = domain_id
        self.world_frame = world_frame
        # Domain() applies the configuration to this domain id in this process; it must exist
        # before the participant and live as long as it
        self._domain = Domain(domain_id, config) if config is not None else None
        self.participant = DomainParticipant(domain_id)
        self.robots: dict[str, Robot] = {}
        self.latency_us = Histogram()
        self._lock = threading.Lock()
        self._cmd_id = 0
        # command id -> (robot, name); bounded: a daemon that never answers must not grow it
        self._pending: OrderedDict[int, tuple[Robot, str]] = OrderedDict()
        self._stopping = threading.Event()
        self._stop = GuardCondition(self.participant)
        self._waitset = WaitSet(self.participant)
        self._waitset.attach(self._stop)
        self._thread: threading.Thread | None = None
        for host, port, ns in viewers:
            robot = self._robot(ns)
            robot.viewer = self._client(robot, host, port, "viewer")
        for host, port, ns in operators:
            robot = self._robot(ns)
            robot.operator = self._client(robot, host, port, "operator")

    # ------------------------------------------------------------------ setup
    def _robot(self, ns: str) -> Robot:
        if ns in self.robots:
            return self.robots[ns]
        leaf = ns.strip("/").rsplit("/", 1)[-1]
        robot = Robot(ns=ns, leaf=leaf)
        dp = self.participant

        def writer(leaf_name: str, cls: type[Any], qos: Qos) -> None:
            robot.writers[leaf_name] = DataWriter(
                dp, Topic(dp, topic_name(ns, leaf_name), cls), qos
            )

        writer("measured_cp", msgs.PoseStamped, QOS_DEFAULT)
        writer("base/measured_cp", msgs.PoseStamped, QOS_DEFAULT)
        writer("measured_js", msgs.JointState, QOS_DEFAULT)
        writer("operating_state", msgs.OperatingState, QOS_LATCHED)
        writer("state", msgs.String, QOS_LATCHED)
        writer("status", msgs.String, QOS_DEFAULT)
        writer("command_reply", msgs.String, QOS_DEFAULT)
        for leaf_name, cls, text in (
            ("state_command", msgs.StringStamped, lambda s: s.string),
            ("command", msgs.String, lambda s: s.data),
        ):
            reader: DataReader[Any] = DataReader(
                dp, Topic(dp, topic_name(ns, leaf_name), cls), QOS_DEFAULT
            )
            self._waitset.attach(ReadCondition(reader, SampleState.NotRead))
            robot.readers.append((reader, text))
        self.robots[ns] = robot
        return robot

    def _client(self, robot: Robot, host: str, port: int, role: str) -> TCPClient:
        client: TCPClient

        def on_connect(peer: Any) -> None:
            # as 3D Slicer does: a v2 STATUS first, so the daemon answers in header version 2;
            # then ask the state (a late joiner must not wait for the next change)
            client.send(igtl.StatusMessage(header_version=2, metadata={"dummy": "dummy"}))
            self._send_command(robot, client, "GetState", quiet=True)

        client = TCPClient(
            host,
            port,
            on_message=lambda peer, msg: self._on_igtl(robot, msg),
            on_connect=on_connect,
            name=f"occ-ros2-{role}-{robot.leaf}",
        )
        return client

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> Bridge:
        for robot in self.robots.values():
            for client in (robot.viewer, robot.operator):
                if client is not None:
                    client.start()
        self._thread = threading.Thread(target=self._command_loop, name="occ-ros2-dds", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stopping.set()
        self._stop.set(True)  # wakes the waitset at once
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        for robot in self.robots.values():
            for client in (robot.viewer, robot.operator):
                if client is not None:
                    client.stop()

    def __enter__(self) -> Bridge:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def wait_connected(self, timeout: float = 5.0) -> bool:
        end = time.monotonic() + timeout
        for robot in self.robots.values():
            for client in (robot.viewer, robot.operator):
                if client is not None and not client.wait_connected(
                    max(0.0, end - time.monotonic())
                ):
                    return False
        return True

    # ------------------------------------------------------------------ IGTL -> DDS
    def _publish(self, robot: Robot, leaf: str, sample: Any) -> None:
        try:
            robot.writers[leaf].write(sample)
        except Exception as err:  # noqa: BLE001 - a DDS error must not end the IGTL thread
            robot.counters.publish_errors += 1
            log.warning("%s: publishing %s failed: %s", robot.ns, leaf, err)

    def _on_igtl(self, robot: Robot, msg: Message) -> None:
        t_in = time.perf_counter()
        mtype = msg.message_type
        stamp = msgs.Time.from_seconds(msg.timestamp if msg.timestamp > 0.0 else time.time())
        if mtype == "TRANSFORM":
            m = msg.matrix  # type: ignore[attr-defined]
            m[:3, 3] *= MM
            if msg.device_name == "Base":
                robot.base_m = m
                robot.counters.bases += 1
                self._publish(robot, "base/measured_cp", pose_stamped(m, stamp, self.world_frame))
            elif msg.device_name == "Tip":
                if robot.base_m is None:
                    # the daemon sends Tip before Base each period: the very first Tip has no
                    # base to be expressed in yet
                    robot.counters.tips_without_base += 1
                    return
                local = np.linalg.solve(robot.base_m, m)  # Base^-1 . Tip
                robot.counters.tips += 1
                self._publish(
                    robot, "measured_cp", pose_stamped(local, stamp, f"{robot.leaf}_base")
                )
            else:
                return
            self.latency_us.add((time.perf_counter() - t_in) * 1e6)
        elif mtype == "NDARRAY" and msg.device_name == "Joints":
            values = [float(v) for v in np.asarray(msg.array).ravel()]  # type: ignore[attr-defined]
            names = msg.metadata.get("joints", "")
            joint_names = names.split(",") if names else [f"joint{i}" for i in range(len(values))]
            if len(joint_names) != len(values):
                joint_names = [f"joint{i}" for i in range(len(values))]
            self._publish(
                robot,
                "measured_js",
                msgs.JointState(
                    header=msgs.Header(stamp=stamp, frame_id=""),
                    name=joint_names,
                    position=values,
                ),
            )
        elif mtype == "STATUS":
            robot.counters.statuses += 1
            name = getattr(msg, "error_name", "")
            text = getattr(msg, "status_message", "")
            if name == "" and text == "":
                return  # a keep-alive or greeting, nothing to say
            self._publish(robot, "status", msgs.String(data=f"{name}: {text}"))
            if name in CRTK_STATE:
                self._set_state(robot, name, stamp)
        elif mtype == "RTS_COMMAND":
            self._on_reply(robot, msg, stamp)

    def _set_state(self, robot: Robot, state: str, stamp: msgs.Time) -> None:
        if state == robot.state:
            return
        robot.state = state
        self._publish(robot, "state", msgs.String(data=state))
        self._publish(
            robot,
            "operating_state",
            msgs.OperatingState(
                header=msgs.Header(stamp=stamp, frame_id=""),
                state=CRTK_STATE[state],
                is_homed=state != "INIT",
                is_busy=state == "RUNNING",
            ),
        )

    def _on_reply(self, robot: Robot, msg: Message, stamp: msgs.Time) -> None:
        cid = int(getattr(msg, "command_id", 0))
        with self._lock:
            pending = self._pending.pop(cid, None)
        status = msg.metadata.get("Status", "?")
        text = msg.metadata.get("Message", "")
        name = pending[1] if pending is not None else getattr(msg, "command_name", "")
        if name == "GetState" and status == "SUCCESS":
            # "state=RUNNING; alert=...": the state, whoever asked
            for part in text.split(";"):
                key, _, value = part.strip().partition("=")
                if key == "state" and value in CRTK_STATE:
                    self._set_state(robot, value, stamp)
        if pending is None:
            return  # our own GetState on connect
        robot.counters.replies += 1
        self._publish(robot, "command_reply", msgs.String(data=f"{name} {status}: {text}"))

    # ------------------------------------------------------------------ DDS -> IGTL
    def _command_loop(self) -> None:
        while not self._stopping.is_set():
            self._waitset.wait(duration(milliseconds=500))
            for robot in self.robots.values():
                for reader, text in robot.readers:
                    for sample in reader.take(N=16):
                        self.command(robot.ns, str(text(sample)))

    def command(self, ns: str, word: str) -> None:
        """Forward one command word to the daemon of ``ns`` (what the DDS subscriptions do)."""
        robot = self.robots[ns]
        word = word.strip()
        name = CRTK_COMMANDS.get(word.lower(), word)
        robot.counters.commands += 1
        if not name or not name.replace("_", "").isalnum():
            self._refuse(robot, name or "(empty)", "not a command name")
        elif robot.operator is None:
            self._refuse(robot, name, f"no operator interface for {ns} (occ-ros2 --operator)")
        elif not self._send_command(robot, robot.operator, name):
            self._refuse(robot, name, "operator interface not connected")

    def _refuse(self, robot: Robot, name: str, why: str) -> None:
        robot.counters.commands_refused += 1
        self._publish(robot, "command_reply", msgs.String(data=f"{name} FAIL: {why}"))

    def _send_command(
        self, robot: Robot, client: TCPClient, name: str, quiet: bool = False
    ) -> bool:
        with self._lock:
            self._cmd_id = (self._cmd_id + 1) & 0xFFFFFFFF
            cid = self._cmd_id
            if not quiet:
                self._pending[cid] = (robot, name)
                while len(self._pending) > 256:
                    self._pending.popitem(last=False)
        cmd = igtl.CommandMessage(
            command_id=cid,
            command_name=name,
            command="",
            device_name="occ-ros2",
            header_version=2,
        )
        if client.send(cmd) == 1:
            return True
        with self._lock:
            self._pending.pop(cid, None)
        return False

    # ------------------------------------------------------------------ reporting
    def stats(self) -> dict[str, Any]:
        out: dict[str, Any] = {"domain_id": self.domain_id}
        for ns, robot in self.robots.items():
            out[ns] = {"state": robot.state, **vars(robot.counters)}
        if self.latency_us.count:
            s = self.latency_us.summary()
            out["igtl_to_dds_us"] = {
                "n": self.latency_us.count,
                **{k: round(s[k], 1) for k in ("p50", "p99", "max")},
            }
        return out
