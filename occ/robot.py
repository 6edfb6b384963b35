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

import json
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

import igtl
from igtl.messages.base import Message
from igtl.transport import UDPEndpoint
from igtl.transport.common import RateLimit

from .clock import Clock, RealClock
from .commands import Request, error_reply, parse_request, safe_name, success_reply
from .config import DaemonConfig
from .controllers import Controller
from .drivers import create_driver
from .drivers.base import Driver, DriverState
from .errors import CommandError, OCCError, StateError
from .frame import Frame
from .interfaces import Inbound, Interface, InterfaceManager, is_operator_request
from .joint import Joint, JointLimits, PIDGains
from .loop import ControlLoop
from .safety import LossEvent, LossMonitor, RobotState, StateMachine, Supervisor, Verdict, Watchdog
from .stats import LoopStats
from .supervision import SupervisorThread, Worker

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

#: Datagrams a tick reads from each UDP stream socket (a 500 Hz stream brings one every other
#: tick); beyond that a flood waits in the socket buffer, which overflows: the tick's cost stays
#: bounded, and a master drowned in a flood is a failed link (hold, then the latched stop).
POLL_LIMIT = 4

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


#: statistics a viewer is not shown: what it would take to forge the master stream (the next
#: sequence number, the stream's source port)
VIEWER_HIDDEN = frozenset({"seq", "last_seq", "stream_owner"})


def redact_for_viewer(value: Any) -> Any:
    """``value`` (a statistics snapshot) without the keys in :data:`VIEWER_HIDDEN`."""
    if isinstance(value, dict):
        return {k: redact_for_viewer(v) for k, v in value.items() if k not in VIEWER_HIDDEN}
    if isinstance(value, list):
        return [redact_for_viewer(v) for v in value]
    return value


def judge(monitor: LossMonitor, item: Inbound, now: float, to_wall: float) -> Verdict:
    """The loss monitor's verdict on one stream sample (sequence number from a v2 header)."""
    msg = item.msg
    seq = msg.message_id if msg.header_version == 2 else None
    return monitor.on_packet(seq, msg.timestamp, now, item.t_rx + to_wall)


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
        # UDP stream sockets are read by the loop itself, at most POLL_LIMIT datagrams a tick:
        # a 500 Hz stream then costs no thread wake-up per datagram (on this VM each wake-up
        # and interpreter-lock hand-over costs more than decoding the datagram), and a flood
        # costs the tick a bounded amount (the socket buffer overflows instead).
        self.interfaces = InterfaceManager(
            config.interfaces, clock_now=self.clock.now, poll_streams=rc.realtime.poll_streams
        )
        self.interfaces.on_connect(self._on_peer_connect)
        self._pollers = [
            iface.transport.poll
            for iface in self.interfaces.interfaces.values()
            if isinstance(iface.transport, UDPEndpoint) and iface.transport.polled
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
                grace_s=ls.grace_ms * 1e-3,
                strict=ls.strict,
                timestamp_tolerance_s=(
                    ls.timestamp_tolerance_ms * 1e-3
                    if ls.timestamp_tolerance_ms is not None
                    else None
                ),
            )
            self.loss_input = ls.input
        self.last_alert = ""
        sv = sc.supervisor
        self.supervisor = Supervisor(sv.timeout_ms * 1e-3, on_trip=self._on_supervisor_trip)
        self._supervisor_cfg = sv
        self._supervisor_thread: SupervisorThread | None = None
        self._supervisor_handled = False
        #: jobs the loop must not pay for (GetStats); the worker sends the reply itself
        self.worker = Worker(f"occ-{self.name}-report")
        self._errors_logged = 0
        self._refusal_log = RateLimit(5)

        # --- State shared with controllers and outputs
        n = len(self.joints)
        self.q = [j.home for j in self.joints]
        self.hold_setpoint = list(self.q)
        self.setpoint = list(self.q)
        self._tip = np.eye(4)
        self._tip_stale = False
        self.base = np.eye(4)
        self.sources: dict[str, SourceFn] = {
            "tip": self._source_tip,
            "base": self._source_base,
            "status": self._source_status,
            "joints": self._source_joints,
        }
        self._slices = [(drv, idx, [0.0] * len(idx)) for drv, idx in self.drivers]
        # after a hold, the setpoint re-joins the controller's target at half the joint
        # velocity limits (no jump, whatever the master did meanwhile)
        self._reentry_step = [0.5 * j.limits.velocity * self.period for j in self.joints]
        self._reentry = False
        self.reentries = 0
        self._stream_queues = [
            (iface.name, q)
            for iface in self.interfaces.interfaces.values()
            for q in iface.streams.values()
        ]
        self._n = n
        self.ticks = 0
        self.commands_handled = 0
        self.commands_refused = 0
        self.reply_errors = 0

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
        """Start the network interfaces and, on the real clock, the supervisor thread.

        When the loop runs SCHED_FIFO, the interface threads get SCHED_FIFO one priority below
        it: otherwise a busy machine can leave a datagram in the socket buffer for milliseconds
        (measured here: 7 ms gaps under load), which the loss monitor rightly calls a loss. The
        supervisor runs one priority above the loop, so a loop that spins cannot starve it.
        """
        self.interfaces.start()
        prio = self.config.robot.realtime.fifo_priority
        if prio:
            report = self.interfaces.set_thread_priority(max(1, prio - 1))
            log.info("interface threads: %s", report)
        self.worker.start()
        sv = self._supervisor_cfg
        if sv.enabled and isinstance(self.clock, RealClock) and self._supervisor_thread is None:
            sup_prio = sv.fifo_priority or (min(99, prio + 1) if prio else None)
            self._supervisor_thread = SupervisorThread(
                self.supervisor, self.clock, fifo_priority=sup_prio
            ).start()

    def run(self, duration: float | None = None, ticks: int | None = None) -> LoopStats:
        try:
            return self.loop.run(duration=duration, ticks=ticks)
        finally:
            self.supervisor.disarm()  # the loop ended on purpose: nothing to watch

    def stop_loop(self) -> None:
        self.loop.stop()

    def shutdown(self) -> None:
        """Stop drivers safely, close interfaces. Safe to call twice."""
        if self._shutdown_done:
            return
        self._shutdown_done = True
        self.supervisor.disarm()
        if self._supervisor_thread is not None:
            self._supervisor_thread.stop()
        self.state_machine.try_request("shutdown", "daemon shutting down")
        for drv, _ in self.drivers:
            try:
                drv.shutdown()
            except Exception:  # noqa: BLE001 - every driver must get its shutdown
                log.exception("driver %s: shutdown failed", drv.name)
        self.interfaces.stop()
        self.worker.stop()

    def __enter__(self) -> Robot:
        self.configure()
        self.activate()
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    # ================================================================== the tick
    def tick(self, now: float, k: int) -> None:
        """One control cycle. Nothing a peer sends and no plugin error ends it: an exception
        from a driver, the controller or a handler puts the robot in FAULT with an alert
        naming it, and the daemon goes on serving operators."""
        self.ticks += 1
        sup = self.supervisor
        sup.last_beat = now
        if not sup.armed:
            sup.arm(now)
        elif sup.tripped and not self._supervisor_handled:
            self._supervisor_handled = True
            self._fault(f"supervisor: {sup.reason}")
        try:
            self._read(now)
        except Exception as err:  # noqa: BLE001 - a driver error is a FAULT, not a crash
            self._plugin_error("driver read", err)
        try:
            self._streams(now)
        except Exception as err:  # noqa: BLE001
            self._plugin_error(f"controller {self.controller.name}: on_sample", err)
        # commands, bounded per tick so a flood cannot stall the loop (parsed already)
        if len(self.interfaces.commands):
            for item in self.interfaces.commands.drain(limit=16):
                self._handle(item, now)
        # safety monitors
        monitor = self.loss_monitor
        state = self.state_machine.state
        if monitor is not None:
            event = monitor.check(now)
            if event is not None:
                self._on_loss_event(event, state)
                state = self.state_machine.state
        try:
            self._control(state, now, monitor is not None and monitor.holding)
        except Exception as err:  # noqa: BLE001
            self._plugin_error(f"controller {self.controller.name}: update", err)
        try:
            self._send_outputs(now, k)
        except Exception as err:  # noqa: BLE001
            self._plugin_error("output", err)
        if self.recorder is not None:
            self.recorder.record_state(self, now)

    def _streams(self, now: float) -> None:
        """Every stream sample, in order, judged by the loss monitor; only accepted samples
        reach the controller. Polled UDP stream sockets are read here first, at most
        ``POLL_LIMIT`` datagrams each."""
        for poll in self._pollers:
            poll(POLL_LIMIT)
        monitor = self.loss_monitor
        watched = self.loss_input
        recorder = self.recorder
        on_sample = self.controller.on_sample
        # reception times on the wall clock, to compare with the peer's header timestamps
        to_wall = self.clock.wall_time() - now if monitor is not None else 0.0
        for name, q in self._stream_queues:
            if monitor is not None and name == watched and q.has_overflow:
                # samples the loop could not take in time: seen, never called lost
                for item in q.drain_overflow():
                    judge(monitor, item, now, to_wall)
            if not len(q):
                continue
            for item in q.drain():
                msg = item.msg
                if recorder is not None:
                    recorder.record_message(msg, "in", name, now)
                if monitor is not None and name == watched:
                    if judge(monitor, item, now, to_wall) is not Verdict.ACCEPT:
                        continue
                on_sample(item, now)

    def _control(self, state: RobotState, now: float, holding: bool) -> None:
        """Controller and drivers: follow while RUNNING (hold the last setpoint while the
        watched stream is overdue, then re-join the target without a jump), hold while
        ENABLED/STOPPED, nothing while the drivers are off."""
        if not self.controller.drives_joints:
            if state is RobotState.RUNNING and not holding:
                self.controller.update(now)
            return
        if state is RobotState.RUNNING:
            sp = self.setpoint
            if holding:
                self._reentry = True
            else:
                target = self.controller.update(now)
                if target is not None:
                    if self._reentry:
                        self._reentry = self._rejoin(sp, target)
                    else:
                        for i in range(self._n):
                            sp[i] = target[i]
            self._write(sp, now)
        elif state in POWERED:
            self._write(self.hold_setpoint, now)

    def _rejoin(self, sp: list[float], target: Sequence[float]) -> bool:
        """Move ``sp`` toward ``target`` by at most half the velocity limit; True while away."""
        away = False
        for i, step in enumerate(self._reentry_step):
            d = target[i] - sp[i]
            if d > step:
                sp[i] += step
                away = True
            elif d < -step:
                sp[i] -= step
                away = True
            else:
                sp[i] = target[i]
        if not away:
            self.reentries += 1
        return away

    def _send_outputs(self, now: float, k: int) -> None:
        for out in self.outputs:
            if k % out.every == 0:
                msg = self.sources[out.source](out, now)
                if msg is not None:
                    out.interface.send(msg)
                    if self.recorder is not None:
                        self.recorder.record_message(msg, "out", out.interface.name, now)

    def _plugin_error(self, where: str, err: BaseException) -> None:
        """An exception from a plugin or handler: FAULT with an alert naming it."""
        reason = f"{where} raised {type(err).__name__}: {err}"
        if self._errors_logged < 20:  # a fault that repeats every tick must not flood the log
            self._errors_logged += 1
            log.error("%s", reason, exc_info=err)
        if self.state_machine.state is not RobotState.FAULT:
            self._fault(reason)

    def _read(self, now: float) -> None:
        for drv, _idx in self.drivers:
            if drv.state is DriverState.UNCONFIGURED or drv.state is DriverState.SHUTDOWN:
                continue
            drv.read(now)
        q = self.q
        for i, j in enumerate(self.joints):
            q[i] = j.position
        self._tip_stale = True  # forward kinematics when someone asks (outputs run at 10 Hz)

    @property
    def tip(self) -> np.ndarray:
        """The tip pose in the base frame (forward kinematics of the last joint read), metres."""
        if self._tip_stale:
            self._tip = self.frame.fk(self.q)
            self._tip_stale = False
        return self._tip

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
            # the last safe setpoint: what the drivers were last told (not where they lag)
            self.hold_setpoint = list(self.setpoint if old is RobotState.RUNNING else self.q)
        if new is RobotState.RUNNING:
            self.setpoint[:] = self.hold_setpoint
            self._reentry = False
            if self.loss_monitor is not None:
                # Armed by the first packet after (re)starting: a slave waiting for its master
                # holds still (no target), and a master that vanishes afterwards is caught.
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

    def _on_loss_event(self, event: LossEvent, state: RobotState) -> None:
        """Act on the loss monitor: only while RUNNING does the stream move the robot, so only
        then is its loss an alert (before Run, or while stopped, it is only counted)."""
        where = f"stream {self.loss_input}"
        if state is not RobotState.RUNNING:
            log.debug("%s: %s (%s, not acted on in %s)", where, event.kind, event.cause, state)
            return
        if event.kind == "latch":
            self._safety_stop(f"packet loss on {self.loss_input}: {event.cause}", self.loss_policy)
        elif event.kind == "hold":
            log.info("%s: %s", where, event.cause)
        else:  # resume, refused: keep following, tell the operators
            log.warning("%s: %s", where, event.cause)
            self._alert("STREAM", f"{where}: {event.cause}", igtl.StatusCode.OK)

    def _alert(self, name: str, text: str, code: int) -> None:
        self.interfaces.broadcast_operators(
            igtl.StatusMessage(
                code=int(code),
                error_name=name,
                status_message=text,
                device_name=self.name[:20],
                timestamp=self.clock.wall_time(),
            )
        )

    def _on_supervisor_trip(self, reason: str) -> None:
        """On the supervisor thread, while the loop is stuck: drivers to their safe state at
        once, operators alerted; the loop latches FAULT when it comes back (:meth:`tick`)."""
        self.last_alert = f"supervisor: {reason}"
        log.error("SUPERVISOR: %s; drivers to their safe state", reason)
        for drv, _ in self.drivers:
            drv.safe_stop(reason)
        self._alert("SUPERVISOR", f"supervisor: {reason}", igtl.StatusCode.HARDWARE_FAILURE)

    def _safety_stop(self, reason: str, policy: str) -> None:
        self.last_alert = reason
        log.error("SAFETY STOP: %s", reason)
        if policy == "fault":
            self._fault(reason)
        elif self.state_machine.state in (RobotState.RUNNING, RobotState.ENABLED):
            self.state_machine.try_request("stop", reason)
        else:
            # not moving: still tell the operators why
            self._alert("ALERT", reason, igtl.StatusCode.TIME_OUT)

    def _fault(self, reason: str) -> None:
        self.last_alert = reason
        log.error("FAULT: %s", reason)
        self.state_machine.try_request("fault", reason)

    def _on_watchdog_alert(self, reason: str, overruns: int) -> None:
        log.warning("watchdog: %s (%d overruns so far)", reason, overruns)
        self._alert("WATCHDOG", f"watchdog: {reason}", igtl.StatusCode.TIME_OUT)

    def _on_watchdog_stop(self, reason: str, policy: str) -> None:
        self._safety_stop(f"watchdog: {reason}", policy)

    def _on_peer_connect(self, iface: Interface, peer: Any) -> None:
        # runs on the interface thread: only queue a STATUS with the current state
        if iface.answers:
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
        req: Request | None = item.request
        if req is None and not is_operator_request(msg):
            # a discrete input routed to the command queue (e.g. VFIXTURE)
            try:
                self.controller.on_sample(item, now)
            except Exception as err:  # noqa: BLE001
                self._plugin_error(f"controller {self.controller.name}: on_sample", err)
            return
        wall = self.clock.wall_time()
        try:
            if req is None:  # not parsed by an interface thread (a test, a replay)
                req = parse_request(msg)
            if req.kind == "query":
                reply = self._answer_query(req, wall)
            elif req.name.strip().lower() == "getstats":
                # statistics are built off the loop thread; the worker replies
                if not self.worker.start().submit(lambda: self._reply_stats(item, req)):
                    raise CommandError("busy: too many statistics requests; try again")
                self.commands_handled += 1
                return
            else:
                text = self._execute(req, now)
                reply = success_reply(req, text, timestamp=wall)
            self.commands_handled += 1
        except (CommandError, StateError) as err:
            self.commands_refused += 1
            if self._refusal_log.allow():  # a flood of bad commands must not flood the log
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
        except Exception as err:  # noqa: BLE001 - a failing handler is a FAULT, not a crash
            self.commands_refused += 1
            name = req.name if req is not None else msg.message_type
            self._plugin_error(f"command {name!r}", err)
            reply = error_reply(
                msg, f"{name} failed: {err}", code=igtl.StatusCode.UNKNOWN_ERROR, timestamp=wall
            )
        self._send_reply(item, reply, now)

    def _send_reply(self, item: Inbound, reply: Message, now: float) -> None:
        try:
            self.interfaces.reply(item, reply)
        except Exception as err:  # noqa: BLE001 - a reply that cannot be sent is counted
            self.reply_errors += 1
            log.warning("%s: reply to %s could not be sent: %s", item.interface, item.peer, err)
            return
        if self.recorder is not None:
            self.recorder.record_message(reply, "out", item.interface, now)

    def _reply_stats(self, item: Inbound, req: Request) -> None:
        """On the worker thread: the snapshot (histogram percentiles, controller statistics)
        costs milliseconds; the loop only handed the request over."""
        snap = self.snapshot()
        if req.args.get("Histogram", "").lower() == "lateness":
            # the raw buckets: a client subtracts two of them into a window's percentiles
            snap["lateness_buckets"] = self.stats.lateness.buckets()
        if item.role != "operator":
            snap = redact_for_viewer(snap)
        text = json.dumps(snap, separators=(",", ":"), default=str)
        reply = success_reply(req, text, timestamp=self.clock.wall_time())
        self.interfaces.reply(item, reply)

    def _execute(self, req: Request, now: float) -> str:
        key = req.name.strip().lower()
        event = COMMAND_EVENTS.get(key)
        if event is not None:
            reason = f"operator {req.name}"
            if event == "reset":
                self.watchdog.reset()
                self.supervisor.reset()
                self._supervisor_handled = False
                if self.loss_monitor is not None:
                    self.loss_monitor.reset(None)
                for iface in self.interfaces.interfaces.values():
                    iface.release_stream()  # a restarted master may send from a new port
                if self.state_machine.state is RobotState.STOPPED:
                    self.last_alert = ""
                    return "STOPPED: alerts cleared; send Run to resume"
            tr = self.state_machine.request(event, reason)
            return f"{tr.old.value} -> {tr.new.value}"
        if key == "getstate":
            return self.describe_state()
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
                device_name=safe_name(msg.device_name or self.name),
                header_version=msg.header_version,
                message_id=msg.message_id,
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
                device_name=safe_name(msg.device_name),
                header_version=msg.header_version,
                message_id=msg.message_id,
                timestamp=wall,
            )
        if name in ("GET_TRANS", "GET_TRANSFOR"):
            want = safe_name(msg.device_name or "Tip")
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
        snap["commands"] = {
            "handled": self.commands_handled,
            "refused": self.commands_refused,
            "reply_errors": self.reply_errors,
            "worker_refused": self.worker.refused,
        }
        snap["watchdog"] = self.watchdog.counters()
        snap["supervisor"] = {
            "timeout_ms": self.supervisor.timeout_s * 1e3,
            "trips": self.supervisor.trips,
            "tripped": self.supervisor.tripped,
            "thread": self._supervisor_thread.report if self._supervisor_thread else None,
        }
        snap["reentries"] = self.reentries
        snap["last_alert"] = self.last_alert
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
