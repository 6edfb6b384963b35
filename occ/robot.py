"""The Robot: one InterfaceManager, one Frame, its Joints and Drivers, and the control loop.

This is the Open Core Control structure (Arata et al., IJCARS 2010): network I/O in the
InterfaceManager (reusable on any robot), kinematics in the Frame, hardware behind Drivers; here
assembled from a validated YAML configuration instead of C++ ``main()``.

Lifecycle (ros2_control): ``configure()`` builds and configures everything (state READY, servos
off), ``activate()`` starts the interfaces, ``run()`` runs the loop until stopped,
``shutdown()`` stops drivers safely and closes everything (safe twice).

Each tick (:meth:`Robot.tick`, on the loop thread):

1. read drivers (joint measured state) and compute the tip pose (FK);
2. drain stream queues (every sample: loss monitor, controller) and the command queue;
3. update safety monitors (loss monitor deadline) and the controller;
4. write drivers: the controller's setpoints while RUNNING, the held position while
   ENABLED/STOPPED, nothing while READY/FAULT/ESTOP (drivers inactive);
5. send the outputs that are due (each at its own rate; sends only queue, never block).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

import igtl
from igtl.messages.base import Message
from igtl.transport import UDPEndpoint

from .clock import Clock, RealClock
from .commands import Request, error_reply, parse_request, success_reply
from .config import DaemonConfig
from .controllers import Controller
from .drivers import create_driver
from .drivers.base import Driver, DriverState
from .errors import CommandError, OCCError, StateError
from .frame import Frame
from .interfaces import Inbound, Interface, InterfaceManager
from .joint import Joint, JointLimits, PIDGains
from .loop import ControlLoop
from .safety import LossMonitor, RobotState, StateMachine, Watchdog
from .stats import LoopStats

log = logging.getLogger(__name__)

M_TO_MM = 1000.0

#: STATUS code sent with each state (operators see why, not just what).
STATE_STATUS_CODE = {
    RobotState.INIT: igtl.StatusCode.NOT_READY,
    RobotState.READY: igtl.StatusCode.OK,
    RobotState.ENABLED: igtl.StatusCode.OK,
    RobotState.RUNNING: igtl.StatusCode.OK,
    RobotState.STOPPED: igtl.StatusCode.DISABLED,
    RobotState.FAULT: igtl.StatusCode.HARDWARE_FAILURE,
    RobotState.ESTOP: igtl.StatusCode.PANICK_MODE,
    RobotState.SHUTDOWN: igtl.StatusCode.SHUT_DOWN,
}

#: Operator command -> state-machine event.
COMMAND_EVENTS = {
    "enable": "enable",
    "disable": "disable",
    "run": "run",
    "stop": "stop",
    "estop": "estop",
    "reset": "reset",
    "hold": "hold",
}

#: States in which drivers are ACTIVE (servos on).
POWERED = frozenset({RobotState.ENABLED, RobotState.RUNNING, RobotState.STOPPED})


@dataclass
class Output:
    """One periodic output: a message type built from a named source, every ``every`` ticks."""

    interface: Interface
    type: str
    device: str
    source: str
    every: int
    header_version: int
    seq: int = 0


SourceFn = Callable[[Output, float], Message | None]


def pose_to_message(
    pose: np.ndarray, mtype: str, device: str, header_version: int, timestamp: float
) -> Message:
    """A TRANSFORM or POSITION (mm) from a 4x4 pose in metres."""
    if mtype == "TRANSFORM":
        m = pose.copy()
        m[:3, 3] *= M_TO_MM
        return igtl.TransformMessage.from_matrix(
            m, device_name=device, timestamp=timestamp, header_version=header_version
        )
    if mtype == "POSITION":
        x, y, z = (pose[:3, 3] * M_TO_MM).tolist()
        return igtl.PositionMessage(
            (x, y, z),
            rotation_to_quaternion(pose[:3, :3]),
            device_name=device,
            timestamp=timestamp,
            header_version=header_version,
        )
    raise OCCError(f"output type {mtype} cannot carry a pose")


def rotation_to_quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix, w >= 0 (Shepperd's method, numerically stable)."""
    m = r.tolist()
    t = m[0][0] + m[1][1] + m[2][2]
    if t > 0.0:
        s = math.sqrt(t + 1.0) * 2.0
        q = ((m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s, 0.25 * s)
    elif m[0][0] > m[1][1] and m[0][0] > m[2][2]:
        s = math.sqrt(1.0 + m[0][0] - m[1][1] - m[2][2]) * 2.0
        q = (0.25 * s, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s, (m[2][1] - m[1][2]) / s)
    elif m[1][1] > m[2][2]:
        s = math.sqrt(1.0 + m[1][1] - m[0][0] - m[2][2]) * 2.0
        q = ((m[0][1] + m[1][0]) / s, 0.25 * s, (m[1][2] + m[2][1]) / s, (m[0][2] - m[2][0]) / s)
    else:
        s = math.sqrt(1.0 + m[2][2] - m[0][0] - m[1][1]) * 2.0
        q = ((m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, 0.25 * s, (m[1][0] - m[0][1]) / s)
    if q[3] < 0.0:
        q = (-q[0], -q[1], -q[2], -q[3])
    return q


def quaternion_to_rotation(q: Sequence[float]) -> np.ndarray:
    x, y, z, w = q
    n = math.sqrt(x * x + y * y + z * z + w * w) or 1.0
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


class Robot:
    """A robot daemon assembled from a :class:`~occ.config.DaemonConfig`."""

    def __init__(
        self,
        config: DaemonConfig,
        *,
        clock: Clock | None = None,
        controller: Controller | None = None,
        recorder: Any | None = None,
    ) -> None:
        self.config = config
        rc = config.robot
        self.name = rc.name
        self.clock: Clock = clock if clock is not None else RealClock(spin_us=rc.realtime.spin_us)
        self.rate_hz = rc.rate_hz
        self.period = 1.0 / rc.rate_hz
        self.state_machine = StateMachine(clock=self.clock)
        self.state_machine.add_listener(self._on_transition)
        self.recorder = recorder

        # --- Joints, Frame, Drivers (hardware-dependent parts)
        self.joints: list[Joint] = []
        for jc in rc.joints:
            gains = None
            if jc.pid is not None:
                gains = PIDGains(
                    kp=jc.pid.kp,
                    ki=jc.pid.ki,
                    kd=jc.pid.kd,
                    i_limit=jc.pid.i_limit if jc.pid.i_limit is not None else math.inf,
                    out_limit=(
                        jc.pid.out_limit
                        if jc.pid.out_limit is not None
                        else (jc.limits.effort or math.inf)
                    ),
                )
            limits = JointLimits(
                jc.limits.min,
                jc.limits.max,
                jc.limits.velocity,
                jc.limits.effort if jc.limits.effort is not None else math.inf,
            )
            self.joints.append(Joint(jc.name, jc.type, limits, jc.home, gains))
        self.joint_index = {j.name: i for i, j in enumerate(self.joints)}
        fc = rc.frame
        if fc.model is not None:
            self.frame = Frame.builtin(fc.model)
        else:
            assert fc.tip_link is not None  # the schema requires it with urdf
            self.frame = Frame.from_urdf(str(fc.urdf), fc.tip_link, fc.base_link)
        # The configured joints are the kinematic model's, in its order: FK and IK index them.
        if list(self.frame.joint_names) != [j.name for j in self.joints]:
            raise OCCError(
                f"robot.joints {[j.name for j in self.joints]} do not match the joints of the "
                f"kinematic model {self.frame.name!r} {list(self.frame.joint_names)} (same names, "
                "same order)"
            )
        self.drivers: list[tuple[Driver, list[int]]] = []
        for dc in rc.drivers:
            idx = [self.joint_index[n] for n in dc.joints]
            drv = create_driver(
                dc.plugin,
                dc.name,
                [self.joints[i] for i in idx],
                dict(dc.params),
                on_limit=dc.on_limit,
            )
            self.drivers.append((drv, idx))

        # --- Interfaces
        self.interfaces = InterfaceManager(config.interfaces, clock_now=self.clock.now)
        self.interfaces.on_connect(self._on_peer_connect)
        self._pollers = [
            iface.transport.poll
            for iface in self.interfaces.interfaces.values()
            if iface.streams and isinstance(iface.transport, UDPEndpoint)
        ]

        # --- Safety
        sc = config.safety
        wd = sc.watchdog
        self.watchdog = Watchdog(
            wd.budget_us * 1e-6,
            alert_run=wd.alert_run,
            stop_run=wd.stop_run,
            hard_gap_s=wd.hard_gap_ms * 1e-3,
            policy=wd.policy,
            on_alert=self._on_watchdog_alert,
            on_stop=self._on_watchdog_stop,
            period_limit_s=max(2.0 * self.period, wd.budget_us * 1e-6),
        )
        ls = sc.loss
        self.loss_monitor: LossMonitor | None = None
        self.loss_input: str | None = None
        self.loss_policy = ls.policy
        if ls.enabled and ls.input is not None:
            self.loss_monitor = LossMonitor(
                ls.period_ms * 1e-3,
                ls.max_consecutive,
                ls.deadline_ms * 1e-3 if ls.deadline_ms is not None else None,
            )
            self.loss_input = ls.input
        self.last_alert = ""

        # --- State shared with controllers and outputs
        n = len(self.joints)
        self.q = [j.home for j in self.joints]
        self.hold_setpoint = list(self.q)
        self.setpoint = list(self.q)
        self.tip = np.eye(4)
        self.base = np.eye(4)
        self.sources: dict[str, SourceFn] = {
            "tip": self._source_tip,
            "base": self._source_base,
            "status": self._source_status,
            "joints": self._source_joints,
        }
        self._slices = [(drv, idx, [0.0] * len(idx)) for drv, idx in self.drivers]
        self._n = n
        self.ticks = 0
        self.commands_handled = 0
        self.commands_refused = 0

        # --- Loop and statistics
        self.stats = LoopStats(self.rate_hz, budget_s=wd.budget_us * 1e-6)
        for name, iface in self.interfaces.interfaces.items():
            self.stats.interfaces[name] = iface.stats
        self.loop = ControlLoop(
            self.rate_hz,
            self.tick,
            clock=self.clock,
            stats=self.stats,
            watchdog=self.watchdog,
            realtime={
                "fifo_priority": rc.realtime.fifo_priority,
                "cpu": rc.realtime.cpu,
                "gc": rc.realtime.gc,
                "switch_interval_s": (
                    rc.realtime.switch_interval_us * 1e-6
                    if rc.realtime.switch_interval_us is not None
                    else None
                ),
            },
        )

        # --- Controller and outputs
        self.controller = controller if controller is not None else Controller()
        self.outputs: list[Output] = []
        for iface in self.interfaces.interfaces.values():
            for oc in iface.cfg.outputs:
                every = max(1, round(self.rate_hz / oc.rate_hz))
                self.outputs.append(
                    Output(iface, oc.type, oc.device, oc.source, every, iface.cfg.header_version)
                )
        self.controller.bind(self)
        for out in self.outputs:
            if out.source not in self.sources:
                raise OCCError(
                    f"interface {out.interface.name}: output source {out.source!r} unknown; "
                    f"known: {', '.join(sorted(self.sources))}"
                )
        self._shutdown_done = False

    # ================================================================== lifecycle
    @property
    def state(self) -> RobotState:
        return self.state_machine.state

    def configure(self) -> None:
        """Configure drivers (servos off), read the initial state: INIT -> READY."""
        for drv, _ in self.drivers:
            drv.configure()
        now = self.clock.now()
        self._read(now)
        self.hold_setpoint = list(self.q)
        self.state_machine.request("configure", "configured")

    def activate(self) -> None:
        """Start the network interfaces.

        When the loop runs SCHED_FIFO, the interface threads get SCHED_FIFO one priority below
        it: otherwise a busy machine can leave a datagram in the socket buffer for milliseconds
        (measured here: 7 ms gaps under load), which the loss monitor rightly calls a loss.
        """
        self.interfaces.start()
        prio = self.config.robot.realtime.fifo_priority
        if prio:
            report = self.interfaces.set_thread_priority(max(1, prio - 1))
            log.info("interface threads: %s", report)

    def run(self, duration: float | None = None, ticks: int | None = None) -> LoopStats:
        return self.loop.run(duration=duration, ticks=ticks)

    def stop_loop(self) -> None:
        self.loop.stop()

    def shutdown(self) -> None:
        """Stop drivers safely, close interfaces. Safe to call twice."""
        if self._shutdown_done:
            return
        self._shutdown_done = True
        self.state_machine.try_request("shutdown", "daemon shutting down")
        for drv, _ in self.drivers:
            try:
                drv.shutdown()
            except Exception:  # noqa: BLE001 - every driver must get its shutdown
                log.exception("driver %s: shutdown failed", drv.name)
        self.interfaces.stop()

    def __enter__(self) -> Robot:
        self.configure()
        self.activate()
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    # ================================================================== the tick
    def tick(self, now: float, k: int) -> None:
        self.ticks += 1
        state = self.state_machine.state
        try:
            self._read(now)
        except OCCError as err:
            self._fault(f"driver read failed: {err}")
            state = self.state_machine.state
        # streams: every sample, in order. UDP stream sockets are polled here first: a datagram
        # that arrived while this thread held the interpreter (the clock's spin) is used now,
        # not one tick later.
        for poll in self._pollers:
            poll()
        for iface in self.interfaces.interfaces.values():
            for q in iface.streams.values():
                if not len(q):
                    continue
                for item in q.drain():
                    if self.loss_monitor is not None and item.interface == self.loss_input:
                        ts = item.msg.timestamp if item.msg.header_version == 1 else None
                        seq = item.msg.message_id if item.msg.header_version == 2 else None
                        self.loss_monitor.on_packet(seq, ts, now)
                    if self.recorder is not None:
                        self.recorder.record_message(item.msg, "in", item.interface, now)
                    self.controller.on_sample(item, now)
        # commands, bounded per tick so a flood cannot stall the loop
        if len(self.interfaces.commands):
            for item in self.interfaces.commands.drain(limit=16):
                self._handle(item, now)
        # safety monitors
        if self.loss_monitor is not None:
            event = self.loss_monitor.check(now)
            if event is not None:
                self._safety_stop(
                    f"packet loss on {self.loss_input}: {event.cause}", self.loss_policy
                )
        state = self.state_machine.state
        # controller and drivers
        if not self.controller.drives_joints:
            if state is RobotState.RUNNING:
                self.controller.update(now)
        elif state is RobotState.RUNNING:
            target = self.controller.update(now)
            sp = self.setpoint
            if target is not None:
                for i in range(self._n):
                    sp[i] = target[i]
            else:
                sp[:] = self.hold_setpoint
            self._write(sp, now)
        elif state in POWERED:
            self._write(self.hold_setpoint, now)
        # outputs due this tick
        for out in self.outputs:
            if k % out.every == 0:
                msg = self.sources[out.source](out, now)
                if msg is not None:
                    out.interface.send(msg)
                    if self.recorder is not None:
                        self.recorder.record_message(msg, "out", out.interface.name, now)
        if self.recorder is not None:
            self.recorder.record_state(self, now)

    def _read(self, now: float) -> None:
        for drv, _idx in self.drivers:
            if drv.state is DriverState.UNCONFIGURED or drv.state is DriverState.SHUTDOWN:
                continue
            drv.read(now)
        q = self.q
        for i, j in enumerate(self.joints):
            q[i] = j.position
        self.tip = self.frame.fk(q)

    def _write(self, setpoints: Sequence[float], now: float) -> None:
        for drv, idx, buf in self._slices:
            if drv.state is not DriverState.ACTIVE:
                continue
            for n, i in enumerate(idx):
                buf[n] = setpoints[i]
            try:
                drv.write(buf, now)
            except OCCError as err:
                self._fault(f"driver {drv.name}: {err}")
                return

    # ================================================================== state changes
    def _on_transition(
        self, old: RobotState, new: RobotState, event: str, reason: str, t: float
    ) -> None:
        stopped = (RobotState.FAULT, RobotState.ESTOP, RobotState.STOPPED)
        level = logging.WARNING if new in stopped else logging.INFO
        log.log(
            level,
            "state %s -> %s (%s)%s",
            old.value,
            new.value,
            event,
            f": {reason}" if reason else "",
        )
        # drivers follow the state: powered in ENABLED/RUNNING/STOPPED, off elsewhere
        if new in POWERED and old not in POWERED:
            self.hold_setpoint = list(self.q)
            for drv, _ in self.drivers:
                if drv.state is DriverState.INACTIVE:
                    drv.activate()
        elif new not in POWERED and old in POWERED:
            for drv, _ in self.drivers:
                if drv.state is DriverState.ACTIVE:
                    drv.deactivate()
        if new is RobotState.READY and old in (RobotState.FAULT, RobotState.ESTOP):
            for drv, _ in self.drivers:
                if drv.state is DriverState.FAULT:
                    drv.reset()
        if new is RobotState.STOPPED or (new is RobotState.ENABLED and old is RobotState.RUNNING):
            self.hold_setpoint = list(self.q)
        if new is RobotState.RUNNING and self.loss_monitor is not None:
            # Armed by the first packet after (re)starting: a slave waiting for its master holds
            # still (no target), and a master that vanishes afterwards trips the deadline.
            self.loss_monitor.reset(None)
        self.controller.on_state(old, new, self.clock.now())
        text = f"{old.value} -> {new.value}" + (f": {reason}" if reason else "")
        status = igtl.StatusMessage(
            code=int(STATE_STATUS_CODE[new]),
            subcode=0,
            error_name=new.value,
            status_message=text,
            device_name=self.name[:20],
            timestamp=t,
        )
        self.interfaces.broadcast_operators(status)
        if self.recorder is not None:
            self.recorder.record_message(status, "out", "*", self.clock.now())

    def _safety_stop(self, reason: str, policy: str) -> None:
        self.last_alert = reason
        log.error("SAFETY STOP: %s", reason)
        if policy == "fault":
            self._fault(reason)
        elif self.state_machine.state in (RobotState.RUNNING, RobotState.ENABLED):
            self.state_machine.try_request("stop", reason)
        else:
            # not moving: still tell the operators why
            self.interfaces.broadcast_operators(
                igtl.StatusMessage(
                    code=int(igtl.StatusCode.TIME_OUT),
                    error_name="ALERT",
                    status_message=reason,
                    device_name=self.name[:20],
                    timestamp=self.clock.wall_time(),
                )
            )

    def _fault(self, reason: str) -> None:
        self.last_alert = reason
        log.error("FAULT: %s", reason)
        self.state_machine.try_request("fault", reason)

    def _on_watchdog_alert(self, reason: str, overruns: int) -> None:
        log.warning("watchdog: %s (%d overruns so far)", reason, overruns)
        self.interfaces.broadcast_operators(
            igtl.StatusMessage(
                code=int(igtl.StatusCode.TIME_OUT),
                error_name="WATCHDOG",
                status_message=f"watchdog: {reason}",
                device_name=self.name[:20],
                timestamp=self.clock.wall_time(),
            )
        )

    def _on_watchdog_stop(self, reason: str, policy: str) -> None:
        self._safety_stop(f"watchdog: {reason}", policy)

    def _on_peer_connect(self, iface: Interface, peer: Any) -> None:
        # runs on the interface thread: only queue a STATUS with the current state
        if iface.commands:
            st = self.state_machine.state
            iface.send_to_peer(
                igtl.StatusMessage(
                    code=int(STATE_STATUS_CODE[st]),
                    error_name=st.value,
                    status_message=f"{self.name} is {st.value}",
                    device_name=self.name[:20],
                    timestamp=self.clock.wall_time(),
                ),
                peer,
            )

    # ================================================================== operator requests
    def _handle(self, item: Inbound, now: float) -> None:
        msg = item.msg
        if self.recorder is not None:
            self.recorder.record_message(msg, "in", item.interface, now)
        wall = self.clock.wall_time()
        try:
            if msg.message_type not in ("COMMAND", "STRING") and not msg.message_type.startswith(
                ("GET_", "STT_", "STP_")
            ):
                # a discrete input routed to the command queue (e.g. VFIXTURE)
                self.controller.on_sample(item, now)
                return
            req = parse_request(msg)
            if req.kind == "query":
                reply = self._answer_query(req, wall)
            else:
                text = self._execute(req, now)
                reply = success_reply(req, text, timestamp=wall)
            self.commands_handled += 1
        except (CommandError, StateError) as err:
            self.commands_refused += 1
            log.warning(
                "%s: refused %s from %s:%s: %s",
                item.interface,
                msg.message_type,
                *item.peer.address[:2],
                err,
            )
            reply = error_reply(
                msg, str(err), code=igtl.StatusCode.ILLEGAL_INSTRUCTION, timestamp=wall
            )
        self.interfaces.reply(item, reply)
        if self.recorder is not None:
            self.recorder.record_message(reply, "out", item.interface, now)

    def _execute(self, req: Request, now: float) -> str:
        key = req.name.strip().lower()
        event = COMMAND_EVENTS.get(key)
        if event is not None:
            reason = f"operator {req.name}"
            if event == "reset":
                self.watchdog.reset()
                if self.loss_monitor is not None:
                    self.loss_monitor.reset(None)
                if self.state_machine.state is RobotState.STOPPED:
                    self.last_alert = ""
                    return "STOPPED: alerts cleared; send Run to resume"
            tr = self.state_machine.request(event, reason)
            return f"{tr.old.value} -> {tr.new.value}"
        if key == "getstate":
            return self.describe_state()
        if key == "getstats":
            import json

            return json.dumps(self.snapshot(), separators=(",", ":"))
        return self.controller.on_command(req, now) or "OK"

    def _answer_query(self, req: Request, wall: float) -> Message:
        msg = req.msg
        assert msg is not None
        name = req.name
        if name == "GET_STATUS":
            st = self.state_machine.state
            return igtl.StatusMessage(
                code=int(STATE_STATUS_CODE[st]),
                error_name=st.value,
                status_message=self.describe_state(),
                device_name=msg.device_name or self.name[:20],
                header_version=msg.header_version,
                timestamp=wall,
            )
        if name == "GET_CAPABIL":
            types = [
                "TRANSFORM",
                "POSITION",
                "STATUS",
                "STRING",
                "COMMAND",
                "CAPABILITY",
                "GET_STATUS",
                "GET_CAPABIL",
                "GET_TRANS",
            ]
            return igtl.CapabilityMessage(
                types=tuple(types),
                device_name=msg.device_name,
                header_version=msg.header_version,
                timestamp=wall,
            )
        if name in ("GET_TRANS", "GET_TRANSFOR"):
            want = msg.device_name or "Tip"
            pose = self.base if want.lower() == "base" else self.world_tip()
            return pose_to_message(pose, "TRANSFORM", want, msg.header_version, wall)
        raise CommandError(f"{name} is not supported by {self.name}")

    def describe_state(self) -> str:
        st = self.state_machine.state
        parts = [f"state={st.value}"]
        if self.last_alert:
            parts.append(f"alert={self.last_alert}")
        if self.state_machine.last_reason:
            parts.append(f"reason={self.state_machine.last_reason}")
        return "; ".join(parts)

    # ================================================================== output sources
    def _source_tip(self, out: Output, now: float) -> Message:
        # in world coordinates, as Slicer shows it: the base pose (config or tracker) x the FK
        return pose_to_message(
            self.world_tip(), out.type, out.device, out.header_version, self.clock.wall_time()
        )

    def world_tip(self) -> np.ndarray:
        """The tip pose in world coordinates (base pose x forward kinematics), metres."""
        return self.base @ self.tip

    def _source_base(self, out: Output, now: float) -> Message:
        return pose_to_message(
            self.base, out.type, out.device, out.header_version, self.clock.wall_time()
        )

    def _source_status(self, out: Output, now: float) -> Message:
        st = self.state_machine.state
        return igtl.StatusMessage(
            code=int(STATE_STATUS_CODE[st]),
            error_name=st.value,
            status_message=self.describe_state(),
            device_name=out.device,
            header_version=out.header_version,
            timestamp=self.clock.wall_time(),
        )

    def _source_joints(self, out: Output, now: float) -> Message:
        arr = np.array(self.q, dtype=np.float64)
        return igtl.NDArrayMessage(
            array=arr,
            device_name=out.device,
            header_version=out.header_version,
            timestamp=self.clock.wall_time(),
        )

    # ================================================================== reporting
    def snapshot(self) -> dict[str, Any]:
        snap = self.stats.snapshot()
        snap["robot"] = self.name
        snap["state"] = self.state_machine.state.value
        snap["commands"] = {"handled": self.commands_handled, "refused": self.commands_refused}
        snap["watchdog"] = self.watchdog.counters()
        if self.loss_monitor is not None:
            snap["loss"] = self.loss_monitor.counters()
        snap["controller"] = self.controller.stats()
        snap["drivers"] = {drv.name: drv.stats() for drv, _ in self.drivers}
        snap["realtime"] = self.loop.realtime_report
        return snap


def build_robot(
    config: DaemonConfig, *, clock: Clock | None = None, recorder: Any | None = None
) -> Robot:
    """Build a robot with the controller its config asks for (teleop master/slave or hold)."""
    controller: Controller | None = None
    if config.teleop:
        from .controllers.teleop import make_teleop_controller

        controller = make_teleop_controller(config.teleop.model_dump())
    return Robot(config, clock=clock, controller=controller, recorder=recorder)
