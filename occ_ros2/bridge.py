"""The bridge: OCC daemons' OpenIGTLink interfaces on one side, ROS 2 topics (DDS) on the other.

The bridge is an ordinary OpenIGTLink client of each daemon: of a *viewer* port (3D Slicer's,
18944 on the slave) for the poses and the state, and optionally of an *operator* port (18947)
for commands. The daemons know nothing of ROS 2; a viewer-only bridge cannot move the robot.

Per namespace ``NS`` (e.g. ``/occ/slave``, leaf ``slave``) it publishes, CRTK names where CRTK
has one and the dVRK's frame conventions (topic ``X`` is ``rt/X`` on the wire, as every ROS 2
RMW names it):

=============================  ===========================  =================================
topic                          type                         from
=============================  ===========================  =================================
``NS/measured_cp``             geometry_msgs/PoseStamped    TRANSFORM ``Tip`` (world), metres;
                                                            frame_id the world frame
``NS/local/measured_cp``       geometry_msgs/PoseStamped    the tip in the base frame
                                                            (Base⁻¹·Tip); frame_id
                                                            ``<leaf>_base``
``NS/base/measured_cp``        geometry_msgs/PoseStamped    TRANSFORM ``Base``; frame_id the
                                                            world frame (``world``)
``NS/measured_js``             sensor_msgs/JointState       NDARRAY ``Joints`` (positions;
                                                            names from its metadata); frame_id
                                                            ``<leaf>``
``NS/setpoint_js``             sensor_msgs/JointState       NDARRAY ``Setpoints`` (when the
                                                            daemon's viewer output sends it)
``NS/setpoint_cp``,            geometry_msgs/PoseStamped    TRANSFORM ``SetpointTip`` (when
``NS/local/setpoint_cp``                                    sent), as measured_cp
``NS/measured_cf``             geometry_msgs/WrenchStamped  SENSOR or NDARRAY ``Force`` (a
                                                            master's displayed force, N); frame_id
                                                            ``<leaf>_base`` or TRANSFORM
                                                            ``TipForce`` (a slave's contact force,
                                                            metadata
                                                            ``force_n``); frame_id the world
                                                            frame
``NS/operating_state``         crtk_msgs/OperatingState     STATUS of a state, GetState;
                                                            ``is_busy`` from the keyframe
                                                            controller's run STATUS
``NS/state``                   std_msgs/String              the daemon's own state name
``NS/status``                  std_msgs/String              every STATUS (alerts included),
                                                            once whichever link it came on
``NS/command_reply``           std_msgs/String              the answer to a command
``/tf``                        tf2_msgs/TFMessage           ``<leaf>_base`` -> ``<leaf>_tip``
                                                            at the pose rate
``/tf_static``                 tf2_msgs/TFMessage           world -> ``<leaf>_base`` of every
                                                            robot (latched; again on change)
=============================  ===========================  =================================

Commands come on ``NS/state_command`` (crtk_msgs/StringStamped, CRTK's topic) and ``NS/command``
(std_msgs/String, publishable without crtk_msgs). CRTK's words (lower case: ``enable``,
``disable``, ``pause``, ``resume``, ``home``, ``unhome``) follow CRTK's state table
(:data:`CRTK_TABLE`): the bridge answers the no-ops itself (``enable`` when ENABLED), forwards
the others as the daemon's commands (``enable`` out of READY: ``Enable`` then ``Run``, so that
a CRTK client moves with CRTK's words alone), and refuses what CRTK refuses. Where CRTK would
retry out of FAULT (``enable``, ``disable``), the daemon's latch wins: the fault stays until an
operator's ``Reset``, and the reply says so; likewise a STOPPED that this bridge's ``pause`` did
not cause (a safety stop) is the daemon's ``Run``'s to resume, not CRTK's. Any other word
(``Run``, ``EStop``, ``Reset``, ``GetState``, ``GetStats``, ``Clutch`` ...) goes to the daemon as
it is, as an IGTL COMMAND on the operator port. The reply is published on ``NS/command_reply``
as ``"<Name> <SUCCESS|FAIL>: <message>"`` (a CRTK word's: ``"enable SUCCESS: Enable: <answer>;
Run: <answer>"``), and ``operating_state`` again after every CRTK word (a fresh stamp: CRTK
clients wait for one). A command may begin with a request id of the client's choosing,
``"[ID] word"`` (1..64 letters, digits, ``_.:-``); its reply begins ``"[ID] "``: every client of
the namespace reads the one reply topic and tells its own replies by their id, as a ROS 2
service client tells its response by its request's id. A move is named by its goal's header
stamp (``"[sec.nanosec] move_cp SUCCESS: ..."``).

Forces: ``NS/servo_cf`` (geometry_msgs/WrenchStamped, N, frame ``<leaf>_base``: the frame of
``measured_cf``) becomes a SENSOR ``ServoCF`` on the operator port, which a master displays
with its slave's force (teleop-master ``external_force_device``), for as long as it keeps
coming (``external_force_timeout_ms``).

Moves: ``NS/move_jp`` (sensor_msgs/JointState: positions, by name or all in the daemon's order)
and ``NS/move_cp`` (geometry_msgs/PoseStamped: the tip position, metres, frame_id the world
frame or ``<leaf>_base``; the orientation is not used: the arms are positioned by their tip)
become the daemon's keyframe commands on the operator port, for a daemon whose controller is
``keyframe``: ``KeyframeClear``, ``KeyframeAdd`` (one keyframe at the goal, at time
:func:`move_time`: the largest joint change over ``move_joint_speed``, or the tip's distance
over ``move_tip_speed``, at least :data:`MOVE_MIN_S`; Cartesian goals in the daemon's world mm,
the frame of its ``Tip``) and ``KeyframePlan`` (linear, stop: the daemon checks every tick and
previews the plan in 3D Slicer as any plan). The daemon's acknowledgement step stays: only a
bridge started with ``ack_moves`` (``--ack-moves``: whoever starts it with operator rights
decides) sends ``KeyframeAck`` itself; otherwise the plan waits for an operator's, and the reply
``move_jp WAITING: plan N waits for an operator's KeyframeAck Plan=N ...`` says so (also on
``NS/status``). One reply per move on ``command_reply``: ``SUCCESS`` (running), ``WAITING`` or
``FAIL`` with the daemon's reason (no keyframe controller, a plan refused by its checks, the
robot not RUNNING, a plan running already).

QoS, as ROS 2 would: poses and replies reliable, volatile, keep last 10 (ROS 2's default, which
every subscriber matches; sensor-data QoS would be refused by a default reliable subscriber);
the two state topics reliable, *transient local*, keep last 1, so a subscriber that comes later
gets the current state at once (ROS 2's "latched" topics); tf2's own QoS for ``/tf`` and
``/tf_static``; the command subscriptions ROS 2's default. Every endpoint carries its type's
ROS 2 Jazzy type hash in USER_DATA (:func:`typed_qos`), as the rmw implementations do.

``operating_state`` maps the daemon's states onto CRTK's meta-states: INIT, READY, SHUTDOWN ->
DISABLED; RUNNING (motion commands executed) -> ENABLED; ENABLED (holding, "send Run first")
and STOPPED -> PAUSED; FAULT, ESTOP -> FAULT. ``is_busy``
is CRTK's: true only while a move or a homing runs. Homing has nothing to do (the daemons'
joints are absolute: ``is_homed`` is true past INIT), following a master is not a move; a move
is a keyframe plan running: from the keyframe controller's STATUS ``KEYFRAME_RUNNING`` to its
``KEYFRAME_ENDED`` (whoever acknowledged the plan), and from the controller's statistics
(``GetStats``) when the bridge connects mid-run. The exact state is on ``NS/state``.

``rate_hz`` (``--rate``, at most :data:`MAX_RATE_HZ`) caps what the bridge publishes per pose
topic; it cannot exceed what the daemon's viewer output sends (its ``rate_hz``).
"""

from __future__ import annotations

import json
import logging
import math
import re
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np
from cyclonedds.core import GuardCondition, ReadCondition, SampleState, WaitSet
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader, InvalidSample
from cyclonedds.topic import Topic
from cyclonedds.util import duration

import igtl
from igtl.messages.base import Message
from igtl.messages.sensor import NEWTON
from igtl.transport import TCPClient
from occ.core.stats import Histogram
from occ.haptics.forceviz import parse_force

from . import msgs

log = logging.getLogger("occ_ros2")

#: the Cyclone DDS configuration the bridge uses unless told otherwise: loopback, no multicast
DEFAULT_CONFIG = Path(__file__).with_name("cyclonedds-lo.xml")

MM = 1e-3

#: the daemon's states (occ.core.safety.RobotState values) as CRTK meta-states. CRTK's ENABLED
#: is "accepts motion commands" (crtk_python_client's examples enable, then move): the daemon's
#: RUNNING. Its ENABLED (powered, holding, "send Run first") and STOPPED (holding after a stop)
#: are CRTK's PAUSED: powered, not moving, motion commands not executed.
CRTK_STATE = {
    "INIT": "DISABLED",
    "READY": "DISABLED",
    "SHUTDOWN": "DISABLED",
    "ENABLED": "PAUSED",
    "RUNNING": "ENABLED",
    "STOPPED": "PAUSED",
    "FAULT": "FAULT",
    "ESTOP": "FAULT",
}

LATCHED = (
    "the daemon's {state} is latched until an operator's Reset (command Reset, after the "
    "cause is found); a CRTK retry does not clear it"
)
#: a STOPPED this bridge's ``pause`` did not cause: a safety stop, a cell's, an operator's
HELD = (
    "the daemon is STOPPED ({why}) and not by this bridge's pause: a stop is resumed by the "
    "daemon's Run (command Run), sent once its cause is known; CRTK's {word} does not"
)
ABSOLUTE = "the joint sensors are absolute: always homed"
HOMED = "homed: the joint sensors are absolute"

CrtkAction = tuple[str, str | tuple[str, ...]]


def _crtk_table() -> dict[tuple[str, str], CrtkAction]:
    """CRTK's state table over the daemon's states (docs/ROS2.md). ``("send", (A, B))``: the
    daemon's operator commands A then B (B when A succeeded); ``("ok", why)``: nothing to do,
    SUCCESS; ``("fail", why)``: refused. A pair not listed is refused as CRTK refuses it
    ("not valid in <meta-state>"); INIT and SHUTDOWN refuse every word. ``Run`` out of STOPPED
    is sent only when this bridge's own ``pause`` stopped the robot (:meth:`Bridge._crtk`)."""
    table: dict[tuple[str, str], CrtkAction] = {
        ("enable", "READY"): ("send", ("Enable", "Run")),
        ("enable", "ENABLED"): ("send", ("Run",)),
        ("enable", "STOPPED"): ("send", ("Run",)),
        ("enable", "RUNNING"): ("ok", "already ENABLED"),
        ("disable", "READY"): ("ok", "already DISABLED"),
        ("pause", "RUNNING"): ("send", ("Stop",)),
        ("pause", "ENABLED"): ("ok", "already PAUSED"),
        ("pause", "STOPPED"): ("ok", "already PAUSED"),
        ("resume", "ENABLED"): ("send", ("Run",)),
        ("resume", "STOPPED"): ("send", ("Run",)),
        ("resume", "RUNNING"): ("ok", "already ENABLED"),
    }
    for state in ("ENABLED", "STOPPED", "RUNNING"):
        table[("disable", state)] = ("send", ("Disable",))
    for state in ("FAULT", "ESTOP"):
        table[("enable", state)] = ("fail", LATCHED)
        table[("disable", state)] = ("fail", LATCHED)
    for state in ("READY", "ENABLED", "STOPPED", "RUNNING", "FAULT", "ESTOP"):
        table[("home", state)] = ("ok", HOMED)
        table[("unhome", state)] = ("fail", ABSOLUTE)
    return table


CRTK_TABLE = _crtk_table()
CRTK_WORDS = ("enable", "disable", "pause", "resume", "home", "unhome")
#: the STATUS names of the daemon's alarms (occ/core/alarms.py): one that comes while this
#: bridge's pause holds the robot ends the bridge's claim to resume it
ALARMS = frozenset({"ALERT", "COLLISION", "SUPERVISOR", "WATCHDOG", "CELL"})

#: a request id (docs/ROS2.md, "Replies"): ``[ID] word`` on ``command`` or ``state_command``
#: (or a move goal's header stamp), echoed as ``[ID] `` before its reply
REQUEST_ID = re.compile(r"[A-Za-z0-9_.:-]{1,64}")
#: how many stamped STATUS messages a robot remembers to drop their copy on its other link
STATUS_MEMORY = 64


def split_request(text: str) -> tuple[str, str]:
    """``"[ID] word"`` -> ``(ID, word)``; ``"word"`` -> ``("", word)``. ValueError for a
    request id that is not 1..64 letters, digits or ``_.:-`` in brackets."""
    text = text.strip()
    if not text.startswith("["):
        return "", text
    rid, sep, word = text[1:].partition("]")
    if not sep or REQUEST_ID.fullmatch(rid) is None:
        raise ValueError(
            f"{text[:80]!r}: a request id is 1..64 letters, digits or _.:- in brackets "
            'before the command ("[42] enable")'
        )
    return rid, word.strip()


def stamp_request(header: Any) -> str:
    """A move goal's request id: its header stamp as ``sec.nanosec`` (a client stamps its goal;
    an unstamped goal has none)."""
    sec, nsec = int(header.stamp.sec), int(header.stamp.nanosec)
    return "" if sec == 0 and nsec == 0 else f"{sec}.{nsec:09d}"


def _named(rid: str) -> str:
    return f"[{rid}] " if rid else ""


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


#: tf2's QoS: /tf reliable, volatile, keep last 100 (tf2_ros' broadcaster); /tf_static
#: reliable, transient local, keep last 1 (its static broadcaster: the one message holds every
#: fixed frame of the publisher, and a listener that comes later gets it at once)
QOS_TF = Qos(
    Policy.Reliability.Reliable(duration(milliseconds=100)),
    Policy.Durability.Volatile,
    Policy.History.KeepLast(100),
    _REPR,
)
QOS_TF_STATIC = QOS_LATCHED

#: the highest ROS-side publishing rate (--rate): the poses of a daemon's viewer output at up to
#: 100 Hz; above it the bridge's Python thread, not the daemon, would set the pace
MAX_RATE_HZ = 100.0

#: the time a move is given (:func:`move_time`): distance over a conservative speed, at least
#: this long. Defaults: 0.05 rad/s or m/s for the joint that changes most (a plan's peak speed is
#: 4/3 of its mean, so 0.067: within every shipped joint's limit, insertion's 0.1 m/s
#: included), 10 mm/s for the tip. The daemon's checks have the last word: a time too short for
#: a joint is refused with the joint named.
MOVE_MIN_S = 1.0
MOVE_JOINT_SPEED = 0.05
MOVE_TIP_SPEED = 0.01
#: a move whose daemon commands got no answer for this long is given up (a long plan's check
#: takes seconds: 30-70 us per tick of motion)
MOVE_TIMEOUT_S = 60.0
#: KeyframeAck sent before the plan's preview went out is refused; asked again this often,
#: this many times (the preview goes with the daemon's next keyframe-path output)
ACK_RETRY_S = 0.1
ACK_RETRIES = 50
#: how long operating_state waits for the answer to the bridge's GetStats on connecting
PROBE_WAIT_S = 1.0
#: the keyframe controller's STATUS names of a run's start and end
#: (occ/controllers/keyframe/controller.py STATUS_RUNNING, STATUS_ENDED; a test checks they
#: agree)
KEYFRAME_RUNNING = "KEYFRAME_RUNNING"
KEYFRAME_ENDED = "KEYFRAME_ENDED"


def plan_running(stats_json: str) -> bool:
    """Whether a daemon's statistics (GetStats) say that a keyframe plan runs: the keyframe
    controller's ``running`` (the plan's number, else null), alone or among several."""
    try:
        snap = json.loads(stats_json)
    except ValueError:
        return False
    ctrl = snap.get("controller") if isinstance(snap, dict) else None
    if not isinstance(ctrl, dict):
        return False
    if isinstance(ctrl.get("keyframe"), dict):
        ctrl = ctrl["keyframe"]
    return isinstance(ctrl.get("running"), int) and "runs_completed" in ctrl


def move_time(distance: float, speed: float) -> float:
    """A move's duration (s): ``distance / speed``, rounded up to the millisecond, at least
    :data:`MOVE_MIN_S`."""
    return max(MOVE_MIN_S, math.ceil(distance / speed * 1e3 - 1e-9) / 1e3)


def typed_qos(qos: Qos, cls: type[Any]) -> Qos:
    """``qos`` plus the USER_DATA a ROS 2 Jazzy endpoint of type ``cls`` carries (its type
    hash, :func:`occ_ros2.msgs.user_data`): Jazzy and later nodes compare it on discovery."""
    return Qos(*qos, Policy.Userdata(data=msgs.user_data(cls)))


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


def transform_stamped(
    matrix_m: np.ndarray, stamp: msgs.Time, parent: str, child: str
) -> msgs.TransformStamped:
    """tf2's TransformStamped of a 4x4 transform (metres): ``child`` in ``parent``."""
    x, y, z = (float(v) for v in matrix_m[:3, 3])
    qx, qy, qz, qw = quaternion(matrix_m[:3, :3])
    return msgs.TransformStamped(
        header=msgs.Header(stamp=stamp, frame_id=parent),
        child_frame_id=child,
        transform=msgs.Transform(msgs.Vector3(x, y, z), msgs.Quaternion(qx, qy, qz, qw)),
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
    #: STATUS not published again: the copy of one that came on the robot's other link, or
    #: the second link's greeting of the state already announced
    statuses_repeated: int = 0
    commands: int = 0
    replies: int = 0
    commands_refused: int = 0
    publish_errors: int = 0
    #: poses and joint states not published because of the ROS-side rate (--rate)
    rate_skipped: int = 0
    #: move_jp/move_cp received, started running (the bridge's KeyframeAck), left waiting for
    #: an operator's KeyframeAck; refusals are in commands_refused
    moves: int = 0
    moves_running: int = 0
    moves_waiting: int = 0
    forces: int = 0
    forces_refused: int = 0
    #: TipForce received in header version 1 (no metadata, so no force_n): the daemon answers
    #: in v1 until it has read the bridge's v2 greeting, so the first one or two after a
    #: connect come this way; a v1-only daemon sends nothing else (logged once)
    forces_v1: int = 0
    #: servo_cf wrenches forwarded to the daemon (SENSOR ServoCF), refused (frame, not
    #: finite, no operator link)
    servo_cf: int = 0
    servo_cf_refused: int = 0


@dataclass
class _Move:
    """A move_jp/move_cp in progress: the daemon commands still to send, one after the other."""

    kind: str
    steps: list[tuple[str, dict[str, str]]]
    started: float
    plan: int | None = None
    ack_tries: int = 0
    #: the request id its replies carry (the goal's stamp)
    rid: str = ""


@dataclass
class _Word:
    """A CRTK word forwarded as one or more of the daemon's commands, one after the other."""

    word: str
    rid: str
    steps: list[str]
    #: "<Command>: <the daemon's answer>" of each command answered so far
    answers: list[str] = field(default_factory=list)


@dataclass
class _Pending:
    """A command sent to a daemon, waiting for its answer: the user's (published on
    command_reply), a move's step, or the bridge's own look at a running plan (``probe``)."""

    robot: Robot
    name: str
    move: _Move | None = None
    probe: bool = False
    #: the client's request id (echoed in the reply), the CRTK word this command is a step of
    rid: str = ""
    word: _Word | None = None


@dataclass
class Robot:
    """One daemon as seen by the bridge: its namespace, its links, its DDS endpoints."""

    ns: str
    leaf: str
    viewer: TCPClient | None = None
    operator: TCPClient | None = None
    base_m: np.ndarray | None = None
    state: str | None = None
    #: the name and text of the daemon's last state STATUS ("RUNNING -> STOPPED: <why>")
    status_state: str | None = None
    #: state STATUS messages taken, and their count when a link last asked GetState on
    #: connect: that answer is older than any STATUS taken since (another link's may come
    #: first) and must not undo it
    state_statuses: int = 0
    state_asked_at: int = 0
    state_text: str = ""
    #: the daemon is STOPPED by this bridge's ``pause`` (and no alarm since): CRTK's
    #: ``resume`` and ``enable`` may Run it again; any other stop is the daemon's Run's
    paused_by_bridge: bool = False
    #: the links (viewer, operator) whose greeting STATUS is still to come, and the stamped
    #: STATUS messages lately seen with the link they came on: the daemon sends its STATUS to
    #: every link, the bridge publishes each once
    greeting_due: set[str] = field(default_factory=set)
    recent_status: OrderedDict[tuple[Any, ...], str] = field(default_factory=OrderedDict)
    status_lock: threading.Lock = field(default_factory=threading.Lock)
    #: CRTK's is_busy: a keyframe plan runs (module docstring)
    busy: bool = False
    #: the last Tip (world, metres) and measured joints (names, positions): a move's start
    tip_m: np.ndarray | None = None
    joints: tuple[list[str], list[float]] | None = None
    move: _Move | None = None
    #: until this (monotonic) time operating_state waits for the answer to the bridge's
    #: GetStats on connecting (is a plan running?), so that a bridge started mid-run does
    #: not say "not busy" first
    probing_until: float = 0.0
    writers: dict[str, DataWriter] = field(default_factory=dict)
    readers: list[tuple[DataReader[Any], Callable[[Any], None]]] = field(default_factory=list)
    counters: _Counters = field(default_factory=_Counters)
    #: per published leaf: the monotonic time its next sample is due (the --rate cap)
    last_pub: dict[str, float] = field(default_factory=dict)

    @property
    def base_frame(self) -> str:
        return f"{self.leaf}_base"

    @property
    def tip_frame(self) -> str:
        return f"{self.leaf}_tip"


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
        rate_hz: float = 0.0,
        tf: bool = True,
        ack_moves: bool = False,
        move_joint_speed: float = MOVE_JOINT_SPEED,
        move_tip_speed: float = MOVE_TIP_SPEED,
    ) -> None:
        if not 0.0 <= rate_hz <= MAX_RATE_HZ:
            raise ValueError(f"rate must be 0 (as the daemon sends) .. {MAX_RATE_HZ:g} Hz")
        if not (move_joint_speed > 0.0 and move_tip_speed > 0.0):
            raise ValueError("move speeds must be > 0")
        #: send KeyframeAck for the plans of move_jp/move_cp (--ack-moves; module docstring)
        self.ack_moves = ack_moves
        self.move_joint_speed = move_joint_speed
        self.move_tip_speed = move_tip_speed
        self.domain_id = domain_id
        self.world_frame = world_frame
        #: the minimum interval between two samples of one pose topic (0: every one)
        self.min_interval = 0.0 if rate_hz == 0.0 else 1.0 / rate_hz
        # Domain() applies the configuration to this domain id in this process; it must exist
        # before the participant and live as long as it
        self._domain = Domain(domain_id, config) if config is not None else None
        self.participant = DomainParticipant(domain_id)
        self.robots: dict[str, Robot] = {}
        self.latency_us = Histogram()
        self._lock = threading.Lock()
        self._cmd_id = 0
        # command id -> what was sent; bounded: a daemon that never answers must not grow it
        self._pending: OrderedDict[int, _Pending] = OrderedDict()
        self._stopping = threading.Event()
        self._stop = GuardCondition(self.participant)
        self._waitset = WaitSet(self.participant)
        self._waitset.attach(self._stop)
        self._thread: threading.Thread | None = None
        dp = self.participant
        self._tf: DataWriter | None = None
        self._tf_static: DataWriter | None = None
        if tf:
            self._tf = DataWriter(
                dp, Topic(dp, "rt/tf", msgs.TFMessage), typed_qos(QOS_TF, msgs.TFMessage)
            )
            self._tf_static = DataWriter(
                dp,
                Topic(dp, "rt/tf_static", msgs.TFMessage),
                typed_qos(QOS_TF_STATIC, msgs.TFMessage),
            )
        #: the fixed frames on /tf_static: (parent, child) -> transform; all in one message
        self._static: dict[tuple[str, str], msgs.TransformStamped] = {}
        for host, port, ns in viewers:
            robot = self._robot(ns)
            robot.viewer = self._client(robot, host, port, "viewer")
        for host, port, ns in operators:
            robot = self._robot(ns)
            robot.operator = self._client(robot, host, port, "operator")

    # ------------------------------------------------------------------ setup
    def _writer(self, robot: Robot, leaf: str, cls: type[Any], qos: Qos) -> DataWriter:
        dp = self.participant
        w = DataWriter(dp, Topic(dp, topic_name(robot.ns, leaf), cls), typed_qos(qos, cls))
        robot.writers[leaf] = w
        return w

    def _robot(self, ns: str) -> Robot:
        if ns in self.robots:
            return self.robots[ns]
        leaf = ns.strip("/").rsplit("/", 1)[-1]
        robot = Robot(ns=ns, leaf=leaf)
        dp = self.participant
        outputs: tuple[tuple[str, type[Any], Qos], ...] = (
            ("measured_cp", msgs.PoseStamped, QOS_DEFAULT),
            ("local/measured_cp", msgs.PoseStamped, QOS_DEFAULT),
            ("base/measured_cp", msgs.PoseStamped, QOS_DEFAULT),
            ("measured_js", msgs.JointState, QOS_DEFAULT),
            ("operating_state", msgs.OperatingState, QOS_LATCHED),
            ("state", msgs.String, QOS_LATCHED),
            ("status", msgs.String, QOS_DEFAULT),
            ("command_reply", msgs.String, QOS_DEFAULT),
        )
        for leaf_name, cls, qos in outputs:
            self._writer(robot, leaf_name, cls, qos)
        inputs: tuple[tuple[str, type[Any], Callable[[Any], None]], ...] = (
            ("state_command", msgs.StringStamped, lambda s: self.command(ns, str(s.string))),
            ("command", msgs.String, lambda s: self.command(ns, str(s.data))),
            ("move_jp", msgs.JointState, lambda s: self.move(ns, "move_jp", s)),
            ("move_cp", msgs.PoseStamped, lambda s: self.move(ns, "move_cp", s)),
            ("servo_cf", msgs.WrenchStamped, lambda s: self.servo_cf(ns, s)),
        )
        for leaf_name, rcls, handle in inputs:
            reader: DataReader[Any] = DataReader(
                dp, Topic(dp, topic_name(ns, leaf_name), rcls), typed_qos(QOS_DEFAULT, rcls)
            )
            self._waitset.attach(ReadCondition(reader, SampleState.NotRead))
            robot.readers.append((reader, handle))
        self.robots[ns] = robot
        return robot

    def _client(self, robot: Robot, host: str, port: int, role: str) -> TCPClient:
        client: TCPClient

        def on_connect(peer: Any) -> None:
            with robot.status_lock:
                robot.greeting_due.add(role)
            # as 3D Slicer does: a v2 STATUS first, so the daemon answers in header version 2;
            # then ask the state (a late joiner must not wait for the next change)
            client.send(igtl.StatusMessage(header_version=2, metadata={"dummy": "dummy"}))
            if role == "operator":
                # a keyframe plan may be running already (is_busy): the controller's
                # statistics say so (every daemon answers GetStats); operating_state waits
                # for the answer (a second at most)
                robot.probing_until = time.monotonic() + PROBE_WAIT_S
                self._send_command(robot, client, "GetStats", probe=True)
            with robot.status_lock:
                robot.state_asked_at = robot.state_statuses
            self._send_command(robot, client, "GetState", quiet=True)

        client = TCPClient(
            host,
            port,
            on_message=lambda peer, msg: self._on_igtl(robot, msg, role),
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

    def _due(self, robot: Robot, leaf: str) -> bool:
        """The ROS-side rate cap: True when ``leaf`` may be published now (and noted so)."""
        if self.min_interval == 0.0:
            return True
        now = time.monotonic()
        interval = self.min_interval
        # a schedule, not the time since the last sample: a sample may come up to a quarter of
        # the interval early (the daemon's TCP stream arrives in bursts after a stall of either
        # side), and the next is due one interval after the later of its due time and one
        # interval ago; so the average never exceeds the cap, and a source at the cap's rate
        # is not thinned by its own jitter (measured: 79 Hz of a 100 Hz source under load with
        # a cap on the time since the last sample)
        due = robot.last_pub.get(leaf, -math.inf)
        if now < due - 0.25 * interval:
            robot.counters.rate_skipped += 1
            return False
        robot.last_pub[leaf] = max(due, now - interval) + interval
        return True

    def _lazy_writer(self, robot: Robot, leaf: str, cls: type[Any]) -> None:
        """Topics the daemon may or may not send (setpoints): created when the first sample
        comes, so a daemon that sends none shows no silent topic."""
        if leaf not in robot.writers:
            self._writer(robot, leaf, cls, QOS_DEFAULT)

    def _on_igtl(self, robot: Robot, msg: Message, link: str = "viewer") -> None:
        t_in = time.perf_counter()
        mtype = msg.message_type
        stamp = msgs.Time.from_seconds(msg.timestamp if msg.timestamp > 0.0 else time.time())
        if mtype == "TRANSFORM":
            if self._on_transform(robot, msg, stamp):
                self.latency_us.add((time.perf_counter() - t_in) * 1e6)
        elif mtype in ("SENSOR", "NDARRAY") and msg.device_name == "Force":
            self._on_force(robot, msg, stamp)
        elif mtype == "NDARRAY" and msg.device_name in ("Joints", "Setpoints"):
            self._on_joints(robot, msg, stamp)
        elif mtype == "STATUS":
            self._on_status(robot, msg, stamp, link)
        elif mtype == "RTS_COMMAND":
            self._on_reply(robot, msg, stamp)

    def _on_transform(self, robot: Robot, msg: Message, stamp: msgs.Time) -> bool:
        """TRANSFORM ``Base``, ``Tip``, ``SetpointTip`` or ``TipForce`` (translation in mm, made
        m here). True when a pose was taken in (its latency is counted), False when the
        message was dropped, thinned or is ``TipForce``."""
        m = msg.matrix  # type: ignore[attr-defined]
        m[:3, 3] *= MM
        name = msg.device_name
        if name == "Base":
            robot.counters.bases += 1
            changed = robot.base_m is None or not np.allclose(robot.base_m, m, atol=1e-9)
            robot.base_m = m
            if changed:
                self._publish_static(robot, m, stamp)
            if self._due(robot, "base/measured_cp"):
                self._publish(robot, "base/measured_cp", pose_stamped(m, stamp, self.world_frame))
            return True
        if name in ("Tip", "SetpointTip"):
            return self._on_tip(robot, name, m, stamp)
        if name == "TipForce":
            self._on_tip_force(robot, msg, stamp)
        return False

    def _on_tip(self, robot: Robot, name: str, m: np.ndarray, stamp: msgs.Time) -> bool:
        """``Tip`` -> ``measured_cp``, ``local/measured_cp`` (Base^-1 . Tip) and /tf;
        ``SetpointTip`` -> ``setpoint_cp`` and ``local/setpoint_cp``. False when there is no
        base yet or the rate cap skips it."""
        if name == "Tip":
            robot.tip_m = m  # a move_cp's start
        if robot.base_m is None:
            # the daemon sends Tip before Base each period: the very first Tip has no
            # base to be expressed in yet
            robot.counters.tips_without_base += 1
            return False
        kind = "measured" if name == "Tip" else "setpoint"
        if not self._due(robot, f"{kind}_cp"):
            return False
        if kind == "setpoint":
            self._lazy_writer(robot, "setpoint_cp", msgs.PoseStamped)
            self._lazy_writer(robot, "local/setpoint_cp", msgs.PoseStamped)
        local = np.linalg.solve(robot.base_m, m)  # Base^-1 . Tip
        if kind == "measured":
            robot.counters.tips += 1
        self._publish(robot, f"{kind}_cp", pose_stamped(m, stamp, self.world_frame))
        self._publish(robot, f"local/{kind}_cp", pose_stamped(local, stamp, robot.base_frame))
        if kind == "measured" and self._tf is not None:
            tf = msgs.TFMessage(
                transforms=[transform_stamped(local, stamp, robot.base_frame, robot.tip_frame)]
            )
            try:
                self._tf.write(tf)
            except Exception as err:  # noqa: BLE001 - as _publish
                robot.counters.publish_errors += 1
                log.warning("%s: publishing /tf failed: %s", robot.ns, err)
        return True

    def _on_joints(self, robot: Robot, msg: Message, stamp: msgs.Time) -> None:
        """NDARRAY ``Joints`` -> ``measured_js``, ``Setpoints`` -> ``setpoint_js`` (the joint
        names from the metadata ``joints``, else joint0, joint1, ...)."""
        leaf = "measured_js" if msg.device_name == "Joints" else "setpoint_js"
        values = [float(v) for v in np.asarray(msg.array).ravel()]  # type: ignore[attr-defined]
        names = msg.metadata.get("joints", "")
        joint_names = names.split(",") if names else [f"joint{i}" for i in range(len(values))]
        if len(joint_names) != len(values):
            joint_names = [f"joint{i}" for i in range(len(values))]
        if leaf == "measured_js":
            robot.joints = (joint_names, values)  # a move_jp's start
        if not self._due(robot, leaf):
            return
        if leaf == "setpoint_js":
            self._lazy_writer(robot, leaf, msgs.JointState)
        self._publish(
            robot,
            leaf,
            msgs.JointState(
                header=msgs.Header(stamp=stamp, frame_id=robot.leaf),
                name=joint_names,
                position=values,
            ),
        )

    def _on_status(
        self, robot: Robot, msg: Message, stamp: msgs.Time, link: str = "viewer"
    ) -> None:
        """STATUS -> ``status`` ("name: text"), and the operating state or busy flag when its
        name is one of CRTK's states or the keyframe plan's running/ended; once, whichever of
        the robot's links it came on (:meth:`_first_copy`)."""
        robot.counters.statuses += 1
        name = getattr(msg, "error_name", "")
        text = getattr(msg, "status_message", "")
        if name == "" and text == "":
            return  # a keep-alive or greeting, nothing to say
        # one STATUS at a time, whichever link it came on: the copy on the other link is
        # judged once the first is published and its state set
        with robot.status_lock:
            if not self._first_copy(robot, msg, name, text, link):
                robot.counters.statuses_repeated += 1
                return
            if name in ALARMS:
                robot.paused_by_bridge = False  # an alarm while paused: not ours to resume
            self._publish(robot, "status", msgs.String(data=f"{name}: {text}"))
            if name in CRTK_STATE:
                robot.state_text = text
                robot.status_state = name
                robot.state_statuses += 1
                self._set_state(robot, name, stamp)
            elif name in (KEYFRAME_RUNNING, KEYFRAME_ENDED):
                self._set_busy(robot, name == KEYFRAME_RUNNING, stamp)

    def _first_copy(self, robot: Robot, msg: Message, name: str, text: str, link: str) -> bool:
        """Whether a STATUS is news, with ``robot.status_lock`` held. A bridge with a viewer and
        an operator link to one daemon gets each of its broadcasts twice (the daemon sends its
        STATUS to every client) and a greeting on each link: a stamped STATUS equal to one
        lately seen on the *other* link is its copy; a link's greeting that names the state
        the other (connected) link has announced already (its last state STATUS) says
        nothing new. Unstamped STATUS
        cannot be told apart: each is news."""
        greeting = link in robot.greeting_due
        robot.greeting_due.discard(link)
        others = [
            client
            for role, client in (("viewer", robot.viewer), ("operator", robot.operator))
            if role != link and client is not None
        ]
        if greeting and name == robot.status_state and any(c.connected for c in others):
            return False
        if msg.timestamp <= 0.0:
            return True
        key = (name, text, int(getattr(msg, "code", 0)), msg.timestamp)
        seen_on = robot.recent_status.get(key)
        if seen_on is not None and seen_on != link:
            del robot.recent_status[key]  # each broadcast comes once per link
            return False
        robot.recent_status[key] = link
        while len(robot.recent_status) > STATUS_MEMORY:
            robot.recent_status.popitem(last=False)
        return True

    def _on_force(self, robot: Robot, msg: Message, stamp: msgs.Time) -> None:
        """SENSOR or NDARRAY ``Force`` (N: a master's displayed force; 3 values, or 6 with a
        torque in N m) -> ``measured_cf``, in the robot's base frame (the world frame when its
        metadata says ``frame=patient``: a slave's ``force`` output sent as SENSOR)."""
        if msg.message_type == "SENSOR":
            values = [float(v) for v in msg.data]  # type: ignore[attr-defined]
            unit = str(msg.unit)  # type: ignore[attr-defined]
        else:
            values = [float(v) for v in np.asarray(msg.array).ravel()]  # type: ignore[attr-defined]
            unit = msg.metadata.get("unit", "N")
        if (
            len(values) not in (3, 6)
            or unit not in ("N", "")
            or not all(map(math.isfinite, values))
        ):
            robot.counters.forces_refused += 1
            if robot.counters.forces_refused == 1:
                log.warning(
                    "%s: %s Force not published: %d values in %r (3 or 6, N)",
                    robot.ns, msg.message_type, len(values), unit,
                )  # fmt: skip
            return
        if not self._due(robot, "measured_cf"):
            return
        self._lazy_writer(robot, "measured_cf", msgs.WrenchStamped)
        torque = values[3:] or [0.0, 0.0, 0.0]
        robot.counters.forces += 1
        # a slave's force output sent as SENSOR says it is in the patient frame (the world)
        patient = msg.metadata.get("frame") == "patient"
        self._publish(
            robot,
            "measured_cf",
            msgs.WrenchStamped(
                header=msgs.Header(
                    stamp=stamp, frame_id=self.world_frame if patient else robot.base_frame
                ),
                wrench=msgs.Wrench(msgs.Vector3(*values[:3]), msgs.Vector3(*torque)),
            ),
        )

    def servo_cf(self, ns: str, goal: Any) -> None:
        """CRTK ``servo_cf`` (geometry_msgs/WrenchStamped, N, frame_id ``<leaf>_base`` or empty:
        the frame of ``measured_cf``, the master's axes): a force for the daemon to display,
        sent as SENSOR ``ServoCF`` (unit N, the force's three values) on the operator link.
        The daemon shows it for its ``external_force_timeout_ms`` (a client streams it);
        torque is not displayed by the 3-DOF masters and not sent."""
        robot = self.robots[ns]
        f = goal.wrench.force
        values = (float(f.x), float(f.y), float(f.z))
        why = ""
        if goal.header.frame_id not in ("", robot.base_frame):
            why = f"frame {goal.header.frame_id!r} (takes {robot.base_frame!r})"
        elif not all(map(math.isfinite, values)):
            why = f"not a force: {values}"
        elif robot.operator is None:
            why = f"no operator interface for {ns} (occ-ros2 --operator)"
        if not why:
            msg = igtl.SensorMessage(
                values, NEWTON, device_name="ServoCF", header_version=2, timestamp=time.time()
            )
            if robot.operator is not None and robot.operator.send(msg) == 1:
                robot.counters.servo_cf += 1
                return
            why = "operator interface not connected"
        robot.counters.servo_cf_refused += 1
        if robot.counters.servo_cf_refused == 1 or robot.counters.servo_cf_refused % 1000 == 0:
            log.warning(
                "%s/servo_cf refused (%d so far): %s", ns, robot.counters.servo_cf_refused, why
            )

    def _on_tip_force(self, robot: Robot, msg: Message, stamp: msgs.Time) -> None:
        """TRANSFORM ``TipForce`` (a slave's contact force, its output source ``force``:
        occ/haptics/forceviz.py) -> ``measured_cf``: metadata ``force_n`` (N, the patient frame,
        which is the world of ``measured_cp``), frame_id the world frame. One in header version 1
        (no metadata: sent before the daemon read the v2 greeting) is counted in ``forces_v1``;
        a v2 one without a readable ``force_n`` or in another frame in ``forces_refused``."""
        if msg.header_version == 1:
            robot.counters.forces_v1 += 1
            if robot.counters.forces_v1 == 3:  # past a connect's gap: the daemon speaks v1 only
                log.warning(
                    "%s: TipForce arrives in header version 1 (no metadata, no force_n): "
                    "measured_cf needs a daemon that answers in v2", robot.ns,
                )  # fmt: skip
            return
        f = parse_force(msg.metadata.get("force_n"))
        if f is None or msg.metadata.get("frame", "patient") != "patient":
            robot.counters.forces_refused += 1
            if robot.counters.forces_refused == 1:
                log.warning(
                    "%s: TipForce not published: metadata force_n %r, frame %r (a v2 "
                    "connection and force_n in the patient frame are needed)",
                    robot.ns, msg.metadata.get("force_n"), msg.metadata.get("frame"),
                )  # fmt: skip
            return
        if not self._due(robot, "measured_cf"):
            return
        self._lazy_writer(robot, "measured_cf", msgs.WrenchStamped)
        robot.counters.forces += 1
        self._publish(
            robot,
            "measured_cf",
            msgs.WrenchStamped(
                header=msgs.Header(stamp=stamp, frame_id=self.world_frame),
                wrench=msgs.Wrench(msgs.Vector3(*f), msgs.Vector3(0.0, 0.0, 0.0)),
            ),
        )

    def _publish_static(self, robot: Robot, base_m: np.ndarray, stamp: msgs.Time) -> None:
        """world -> <leaf>_base on /tf_static: one message with every robot's fixed frame
        (a latched topic keeps one message per publisher)."""
        if self._tf_static is None:
            return
        with self._lock:
            self._static[(self.world_frame, robot.base_frame)] = transform_stamped(
                base_m, stamp, self.world_frame, robot.base_frame
            )
            sample = msgs.TFMessage(transforms=list(self._static.values()))
        try:
            self._tf_static.write(sample)
        except Exception as err:  # noqa: BLE001 - as _publish
            robot.counters.publish_errors += 1
            log.warning("%s: publishing /tf_static failed: %s", robot.ns, err)

    def _operating_state(self, robot: Robot, stamp: msgs.Time | None = None) -> None:
        """CRTK's operating_state of the robot's current state (a fresh stamp when none)."""
        state = robot.state
        if state is None or time.monotonic() < robot.probing_until:
            return
        if stamp is None:
            stamp = msgs.Time.from_seconds(time.time())
        self._publish(
            robot,
            "operating_state",
            msgs.OperatingState(
                header=msgs.Header(stamp=stamp, frame_id=""),
                state=CRTK_STATE[state],
                is_homed=state not in ("INIT", "SHUTDOWN"),
                is_busy=robot.busy,
            ),
        )

    def _set_state(self, robot: Robot, state: str, stamp: msgs.Time) -> None:
        if state == robot.state:
            return
        robot.state = state
        if state != "STOPPED":
            robot.paused_by_bridge = False
        if state != "RUNNING":
            robot.busy = False  # a plan runs only while RUNNING (the daemon drops it otherwise)
        self._publish(robot, "state", msgs.String(data=state))
        self._operating_state(robot, stamp)

    def _set_busy(self, robot: Robot, busy: bool, stamp: msgs.Time | None = None) -> None:
        if busy != robot.busy:
            robot.busy = busy
            self._operating_state(robot, stamp)

    def _on_reply(self, robot: Robot, msg: Message, stamp: msgs.Time) -> None:
        cid = int(getattr(msg, "command_id", 0))
        with self._lock:
            pending = self._pending.pop(cid, None)
        status = msg.metadata.get("Status", "?")
        text = msg.metadata.get("Message", "")
        name = pending.name if pending is not None else getattr(msg, "command_name", "")
        if name == "GetState" and status == "SUCCESS":
            # "state=RUNNING; alert=...": the state, whoever asked; the answer to our own
            # question on connect only while no state STATUS came since it was asked
            for part in text.split(";"):
                key, _, value = part.strip().partition("=")
                if key == "state" and value in CRTK_STATE:
                    with robot.status_lock:
                        if pending is not None or robot.state_statuses == robot.state_asked_at:
                            self._set_state(robot, value, stamp)
        if pending is None:
            return  # our own GetState on connect
        if pending.probe:
            robot.probing_until = 0.0
            robot.busy = status == "SUCCESS" and plan_running(text)
            self._operating_state(robot)
            return
        if pending.move is not None:
            self._move_reply(robot, pending.move, name, status == "SUCCESS", text)
            return
        if pending.word is not None:
            self._word_reply(robot, pending.word, name, status == "SUCCESS", text)
            return
        robot.counters.replies += 1
        reply = f"{_named(pending.rid)}{name} {status}: {text}"
        self._publish(robot, "command_reply", msgs.String(data=reply))
        if name in ("Enable", "Disable", "Stop", "Run", "Hold"):
            # a CRTK client waits for an operating_state after its command, changed or not
            self._operating_state(robot)

    def _word_reply(self, robot: Robot, word: _Word, name: str, ok: bool, text: str) -> None:
        """The daemon's answer to one of a CRTK word's commands: the next one, or the word's
        reply (``enable SUCCESS: Enable: READY -> ENABLED; Run: ENABLED -> RUNNING``)."""
        word.answers.append(f"{name}: {text}")
        if ok and name == "Stop" and word.word == "pause" and text.startswith("RUNNING -> STOPPED"):
            robot.paused_by_bridge = True
        if ok and word.steps:
            self._word_next(robot, word)
            return
        robot.counters.replies += 1
        status = "SUCCESS" if ok else "FAIL"
        reply = f"{_named(word.rid)}{word.word} {status}: {'; '.join(word.answers)}"
        self._publish(robot, "command_reply", msgs.String(data=reply))
        self._operating_state(robot)  # CRTK's client waits for one after its command

    def _word_next(self, robot: Robot, word: _Word) -> None:
        name = word.steps.pop(0)
        client = robot.operator
        if client is None or not self._send_command(robot, client, name, word=word):
            why = f"{name}: operator interface not connected"
            self._refuse(robot, word.word, "; ".join([*word.answers, why]), word.rid)

    # ------------------------------------------------------------------ DDS -> IGTL
    def _command_loop(self) -> None:
        while not self._stopping.is_set():
            self._waitset.wait(duration(milliseconds=500))
            for robot in self.robots.values():
                for reader, handle in robot.readers:
                    for sample in reader.take(N=16):
                        # a publisher gone (a ROS 2 node that exits deletes its writers) comes
                        # as a sample without data: nothing to forward
                        if not isinstance(sample, InvalidSample):
                            handle(sample)

    def command(self, ns: str, text: str) -> None:
        """Forward one command to the daemon of ``ns`` (what the DDS subscriptions do): a CRTK
        word through :data:`CRTK_TABLE`, any other word as the daemon's own command; either
        may begin with a request id (``[ID] word``), which its reply echoes."""
        robot = self.robots[ns]
        robot.counters.commands += 1
        try:
            rid, word = split_request(text)
        except ValueError as err:
            self._refuse(robot, "(request)", str(err))
            return
        if word in CRTK_WORDS and robot.operator is not None:
            self._crtk(robot, word, rid)
            return
        self._forward(robot, word, rid)  # without an operator port: refused, saying so

    def _forward(self, robot: Robot, name: str, rid: str = "") -> None:
        if not name or not name.replace("_", "").isalnum():
            self._refuse(robot, name or "(empty)", "not a command name", rid)
        elif robot.operator is None:
            why = f"no operator interface for {robot.ns} (occ-ros2 --operator)"
            self._refuse(robot, name, why, rid)
        elif not self._send_command(robot, robot.operator, name, rid=rid):
            self._refuse(robot, name, "operator interface not connected", rid)

    def _crtk(self, robot: Robot, word: str, rid: str = "") -> None:
        """CRTK's state table (module docstring, :data:`CRTK_TABLE`)."""
        state = robot.state
        if state is None:
            self._refuse(robot, word, "the daemon's state is not known yet (not connected)", rid)
            return
        meta = CRTK_STATE[state]
        action: str
        what: str | tuple[str, ...]
        if state in ("INIT", "SHUTDOWN"):
            action, what = "fail", f"the daemon is in {state}"
        else:
            action, what = CRTK_TABLE.get((word, state), ("fail", f"not valid in {meta}"))
        if action == "send" and state == "STOPPED" and "Run" in what and not robot.paused_by_bridge:
            why = robot.state_text or "a stop"
            action, what = "fail", HELD.format(why=why, word=word)
        if action == "send":
            assert isinstance(what, tuple)
            self._word_next(robot, _Word(word, rid, list(what)))
            return
        assert isinstance(what, str)
        robot.counters.replies += 1
        if action == "fail":
            robot.counters.commands_refused += 1
        status = "SUCCESS" if action == "ok" else "FAIL"
        text = what.format(state=state)
        reply = f"{_named(rid)}{word} {status}: {text}"
        self._publish(robot, "command_reply", msgs.String(data=reply))
        self._operating_state(robot)

    # ------------------------------------------------------------------ moves
    def move(self, ns: str, kind: str, goal: Any) -> None:
        """A ``move_jp`` (JointState) or ``move_cp`` (PoseStamped) goal: the daemon's keyframe
        commands, one after the other as each is answered (module docstring)."""
        robot = self.robots[ns]
        robot.counters.moves += 1
        rid = stamp_request(goal.header)
        try:
            if robot.operator is None:
                raise ValueError(f"no operator interface for {robot.ns} (occ-ros2 --operator)")
            current = robot.move
            if current is not None and time.monotonic() - current.started < MOVE_TIMEOUT_S:
                raise ValueError(
                    f"the last {current.kind} is still being planned; wait for its reply"
                )
            if kind == "move_jp":
                space, pose, t = self._joint_goal(robot, goal)
            else:
                space, pose, t = self._tip_goal(robot, goal)
        except ValueError as err:
            self._refuse(robot, kind, str(err), rid)
            return
        move = _Move(
            kind,
            [
                ("KeyframeClear", {}),
                ("KeyframeAdd", {"T": f"{t:.3f}", "Pose": pose, "Space": space, "Label": kind}),
                ("KeyframePlan", {"Interpolation": "linear", "Mode": "stop"}),
            ],
            time.monotonic(),
            rid=rid,
        )
        robot.move = move
        self._move_next(robot, move)

    def _joint_goal(self, robot: Robot, goal: Any) -> tuple[str, str, float]:
        if robot.joints is None:
            raise ValueError("the daemon's joint positions are not known yet (its NDARRAY Joints)")
        names, here = robot.joints
        positions = [float(v) for v in goal.position]
        if goal.name:
            if len(goal.name) != len(positions):
                raise ValueError(f"{len(goal.name)} names but {len(positions)} positions")
            target = list(here)
            for joint, value in zip(goal.name, positions, strict=True):
                if joint not in names:
                    raise ValueError(f"no joint {joint!r} (the daemon's: {', '.join(names)})")
                target[names.index(joint)] = value
        elif len(positions) != len(names):
            raise ValueError(
                f"{len(positions)} positions for {len(names)} joints ({', '.join(names)}); "
                "give all, or name them"
            )
        else:
            target = positions
        if not all(math.isfinite(v) for v in target):
            raise ValueError("a position is not a finite number")
        distance = max((abs(a - b) for a, b in zip(target, here, strict=True)), default=0.0)
        pose = " ".join(f"{v:.9g}" for v in target)
        return "joint", pose, move_time(distance, self.move_joint_speed)

    def _tip_goal(self, robot: Robot, goal: Any) -> tuple[str, str, float]:
        p = goal.pose.position
        point = np.array([p.x, p.y, p.z], dtype=float)
        frame = goal.header.frame_id or self.world_frame
        if frame == robot.base_frame:
            if robot.base_m is None:
                raise ValueError(f"the base is not known yet (frame {frame!r})")
            point = robot.base_m[:3, :3] @ point + robot.base_m[:3, 3]
        elif frame != self.world_frame:
            raise ValueError(
                f"frame_id {frame!r}: a goal is in {self.world_frame!r} (as measured_cp) or "
                f"{robot.base_frame!r} (as local/measured_cp)"
            )
        if not np.all(np.isfinite(point)):
            raise ValueError("the position is not finite")
        if robot.tip_m is None:
            raise ValueError("the tip is not known yet (the daemon's TRANSFORM Tip)")
        distance = float(np.linalg.norm(point - robot.tip_m[:3, 3]))
        pose = " ".join(f"{v / MM:.6f}" for v in point)  # the daemon's world frame, mm
        return "cartesian", pose, move_time(distance, self.move_tip_speed)

    def _move_next(self, robot: Robot, move: _Move) -> None:
        name, args = move.steps.pop(0)
        self._move_send(robot, move, name, args)

    def _move_send(self, robot: Robot, move: _Move, name: str, args: dict[str, str]) -> None:
        client = robot.operator
        if robot.move is not move:
            return  # given up (timed out) meanwhile
        if client is None or not self._send_command(robot, client, name, args=args, move=move):
            robot.move = None
            self._refuse(robot, move.kind, "operator interface not connected", move.rid)

    def _ack(self, robot: Robot, move: _Move) -> None:
        self._move_send(robot, move, "KeyframeAck", {"Plan": str(move.plan)})

    def _move_reply(self, robot: Robot, move: _Move, name: str, ok: bool, text: str) -> None:
        """The daemon's answer to one of a move's commands (IGTL client thread)."""
        if robot.move is not move:
            return
        kind = move.kind
        if not ok:
            if (
                name == "KeyframeAck"
                and "not been previewed" in text
                and move.ack_tries < ACK_RETRIES
            ):
                # the preview goes out with the daemon's next keyframe-path output: ask again
                move.ack_tries += 1
                timer = threading.Timer(ACK_RETRY_S, self._ack, (robot, move))
                timer.daemon = True
                timer.start()
                return
            robot.move = None
            why = text if text.startswith(name) else f"{name}: {text}"
            self._refuse(robot, kind, why, move.rid)
            return
        if name == "KeyframePlan":
            found = re.match(r"plan (\d+):", text)
            if found is None:
                robot.move = None
                why = f"KeyframePlan answered {text!r}: no plan number"
                self._refuse(robot, kind, why, move.rid)
                return
            move.plan = int(found.group(1))
            if self.ack_moves:
                self._ack(robot, move)
                return
            robot.move = None
            robot.counters.moves_waiting += 1
            robot.counters.replies += 1
            waits = (
                f"plan {move.plan} waits for an operator's KeyframeAck Plan={move.plan} "
                "(occ-ros2 runs without --ack-moves)"
            )
            self._publish(robot, "status", msgs.String(data=f"KEYFRAME_WAITING: {waits}"))
            reply = f"{_named(move.rid)}{kind} WAITING: {waits}: {text}"
            self._publish(robot, "command_reply", msgs.String(data=reply))
            return
        if name == "KeyframeAck":
            robot.move = None
            robot.counters.moves_running += 1
            robot.counters.replies += 1
            reply = f"{_named(move.rid)}{kind} SUCCESS: {text}"
            self._publish(robot, "command_reply", msgs.String(data=reply))
            return
        self._move_next(robot, move)  # KeyframeClear, KeyframeAdd done: the next

    def _refuse(self, robot: Robot, name: str, why: str, rid: str = "") -> None:
        robot.counters.commands_refused += 1
        reply = f"{_named(rid)}{name} FAIL: {why}"
        self._publish(robot, "command_reply", msgs.String(data=reply))

    def _send_command(
        self,
        robot: Robot,
        client: TCPClient,
        name: str,
        quiet: bool = False,
        *,
        args: dict[str, str] | None = None,
        move: _Move | None = None,
        probe: bool = False,
        rid: str = "",
        word: _Word | None = None,
    ) -> bool:
        """Send the daemon's command ``name`` (``args``: its XML attributes, as 3D Slicer
        sends them); ``quiet``: its answer is not waited for."""
        with self._lock:
            self._cmd_id = (self._cmd_id + 1) & 0xFFFFFFFF
            cid = self._cmd_id
            if not quiet:
                self._pending[cid] = _Pending(robot, name, move, probe, rid, word)
                while len(self._pending) > 256:
                    self._pending.popitem(last=False)
        text = ""
        if args:
            attrs = "".join(f" {k}={quoteattr(v)}" for k, v in args.items())
            text = f"<Command Name={quoteattr(name)}{attrs}/>"
        cmd = igtl.CommandMessage(
            command_id=cid,
            command_name=name,
            command=text,
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
