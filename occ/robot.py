"""The Robot: one InterfaceManager, one Frame, its Joints and Drivers, and the control loop.

This is the Open Core Control structure (Arata et al., IJCARS 2010): network I/O in the
InterfaceManager (reusable on any robot), kinematics in the Frame, hardware behind Drivers; here
assembled from a validated YAML configuration instead of C++ ``main()``. The Robot keeps
assembly, lifecycle, the tick and what the robot's state means for its drivers; the state that
others see is its :class:`~occ.data.RobotData`, operator requests are the
:class:`~occ.operators.OperatorDesk`'s, periodic outputs the
:class:`~occ.outputs.OutputScheduler`'s, and what it does while RUNNING its controller plugins'.

Lifecycle (ros2_control): ``configure()`` configures the drivers (state READY, servos off),
``activate()`` starts the interfaces and the supervisor, ``run()`` runs the loop until stopped,
``shutdown()`` stops drivers safely and closes everything (safe twice).

Each tick (:meth:`Robot.tick`, on the loop thread):

1. read drivers (joint measured state; forward kinematics only when the tip is asked for);
2. read the UDP stream sockets, drain the stream queues (every sample judged by the loss
   monitor; accepted ones to the controllers) and at most 16 operator requests;
3. act on the loss monitor (hold, resume, latch) and update the controllers;
4. write drivers: the controllers' setpoints while RUNNING (the last one while a stream is
   late, then a rate-limited re-entry), the held position while ENABLED/STOPPED, nothing while
   READY/FAULT/ESTOP (drivers inactive);
5. send the outputs that are due (each at its own rate; sends only queue, never block).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from typing import Any

import igtl
from igtl.transport import UDPEndpoint

from .alarms import Alarms
from .assembly import build_hardware, build_loss_monitors, build_watchdog, realtime_settings
from .clock import Clock, RealClock
from .collab import Collaboration
from .config import DaemonConfig
from .controllers import Controller, ControllerContext, ControllerSet, create_controller
from .data import RobotData
from .drivers.base import DriverState
from .errors import CommandError, ConfigError, OCCError
from .interfaces import Inbound, InterfaceManager
from .loop import ControlLoop
from .operators import OperatorDesk
from .outputs import STATE_STATUS_CODE, BuiltinSources, OutputScheduler
from .record import STATE_CODES
from .safety import LossMonitor, RobotState, StateMachine, Supervisor, Verdict
from .statetable import StateTable, capacity_for
from .stats import LoopStats
from .supervision import SupervisorThread, Worker

log = logging.getLogger(__name__)

#: Datagrams a tick reads from each UDP stream socket (a 500 Hz stream brings one every other
#: tick); beyond that a flood waits in the socket buffer, which overflows: the tick's cost stays
#: bounded, and a master drowned in a flood is a failed link (hold, then the latched stop).
POLL_LIMIT = 4

#: How long configure() waits, on the real clock, for every joint's first measurement.
MEASURE_WAIT_S = 1.0

#: States in which drivers are ACTIVE (servos on).
POWERED = frozenset({RobotState.ENABLED, RobotState.RUNNING, RobotState.STOPPED})

#: a state's number in the recording and the State Data Table
STATE_NUMBER = {st: float(STATE_CODES.get(st.value, -1)) for st in RobotState}


def judge(
    monitor: LossMonitor, item: Inbound, now: float, to_wall: float, since: float = -math.inf
) -> Verdict:
    """The loss monitor's verdict on one stream sample (sequence number from a v2 header).

    ``since`` is the previous tick's start: a sample taken in this tick arrived after it, or
    was stamped when read (a polled socket), so its earliest arrival for the timestamp
    check is ``min(t_rx, since)``: a stall of our own loop never makes samples stale."""
    msg = item.msg
    seq = msg.message_id if msg.header_version == 2 else None
    rx = item.t_rx
    return monitor.on_packet(
        seq, msg.timestamp, now, rx + to_wall, (rx if rx < since else since) + to_wall
    )


class Robot:
    """A robot daemon assembled from a :class:`~occ.config.DaemonConfig`."""

    def __init__(
        self,
        config: DaemonConfig,
        *,
        clock: Clock | None = None,
        controllers: Sequence[Controller] = (),
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
        self.state_machine.add_guard(self._may_power)
        self.recorder = recorder

        # --- Joints, Frame, Drivers (hardware-dependent parts)
        self.joints, self.frame, self.drivers = build_hardware(rc)
        self.joint_index = {j.name: i for i, j in enumerate(self.joints)}
        names = [j.name for j in self.joints]
        self._slices = [(drv, idx, [0.0] * len(idx)) for drv, idx in self.drivers]
        self.data = RobotData(
            self.name, names, [j.home for j in self.joints], self.frame, self.clock
        )

        # --- Interfaces. UDP stream sockets are read by the loop itself, at most POLL_LIMIT
        # datagrams a tick: a 500 Hz stream then costs no thread wake-up per datagram, and a
        # flood costs the tick a bounded amount (the socket buffer overflows instead).
        self.interfaces = InterfaceManager(
            config.interfaces, clock_now=self.clock.now, poll_streams=rc.realtime.poll_streams
        )
        self._pollers = [
            iface.transport.poll
            for iface in self.interfaces.interfaces.values()
            if isinstance(iface.transport, UDPEndpoint) and iface.transport.polled
        ]
        # --- Collaboration: several masters, one owner (occ/collab.py)
        co = config.collaboration
        self.collab: Collaboration | None = Collaboration(co) if co is not None else None

        # --- Safety
        sc = config.safety
        wd = sc.watchdog
        self.watchdog = build_watchdog(
            wd,
            self.period,
            on_alert=lambda reason, n: self.alarms.watchdog_alert(reason, n),
            on_stop=lambda reason, policy: self.alarms.safety_stop(f"watchdog: {reason}", policy),
        )
        ls = sc.loss
        #: every watched stream's monitor (one per master when collaborating)
        self.loss_monitors: dict[str, LossMonitor] = build_loss_monitors(
            ls, self.collab.masters if self.collab is not None else None
        )
        self._monitor_list = list(self.loss_monitors.items())
        #: the monitor of the stream that moves the robot (the owner's) and its interface
        self.loss_input: str | None = self.collab.owner if self.collab is not None else ls.input
        self.loss_monitor: LossMonitor | None = self.loss_monitors.get(self.loss_input or "")
        if self.loss_monitor is None:
            self.loss_input = None
        self.loss_policy = ls.policy
        masters = self.collab.masters if self.collab is not None else ()
        #: (interface, queue, its loss monitor or None, a master's stream) for each stream
        #: input, looked up once here, not per sample
        self._stream_queues = [
            (iface.name, q, self.loss_monitors.get(iface.name), iface.name in masters)
            for iface in self.interfaces.interfaces.values()
            for q in iface.streams.values()
        ]
        self.alarms = Alarms(self)
        sv = sc.supervisor
        self.supervisor = Supervisor(
            sv.timeout_ms * 1e-3, on_trip=lambda reason: self.alarms.supervisor_trip(reason)
        )
        self._supervisor_cfg = sv
        self.supervisor_thread: SupervisorThread | None = None
        self._supervisor_handled = False
        #: jobs the loop must not pay for (GetStats); the worker sends the reply itself
        self.worker = Worker(f"occ-{self.name}-report")
        # after a hold, the setpoint re-joins the controllers' target at half the joint
        # velocity limits (no jump, whatever the master did meanwhile)
        self._reentry_step = [0.5 * j.limits.velocity * self.period for j in self.joints]
        self._reentry = False
        self._prev_tick = -math.inf  # the previous tick's start (earliest arrival of samples)
        self.reentries = 0
        self.ticks = 0
        #: the State Data Table (``state_table.seconds``), written once a tick
        st = config.state_table
        self.state_table: StateTable | None = (
            StateTable(
                [j.name for j in self.joints], capacity_for(st.seconds, self.rate_hz), self.frame
            )
            if st.seconds is not None
            else None
        )
        self._owner_code = float(self.collab.code()) if self.collab is not None else -1.0

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
            realtime=realtime_settings(rc.realtime),
        )

        # --- Controllers, operators, outputs
        self.controller = ControllerSet(controllers)
        self.controller.configure(
            self.data,
            ControllerContext(
                clock=self.clock,
                frame=self.frame,
                rate_hz=self.rate_hz,
                interfaces=tuple(self.interfaces.interfaces),
                loop_t0=lambda: self.loop.t0,
                period_s=self.loop.period_s,
                shift=self.loop.shift,
                joint_limits=tuple(j.limits for j in self.joints),
            ),
        )
        self._check_command_kinds()
        if self.controller.commands_effort:
            self.data.effort_command = [0.0] * len(self.joints)
        self.operators = OperatorDesk(self)
        self.interfaces.on_connect(self.operators.greet)
        sources = {
            **BuiltinSources(self.data, self.operators.describe_state).table(),
            **self.controller.outputs(),
        }
        self.outputs = OutputScheduler.for_interfaces(
            self.interfaces.interfaces.values(), self.rate_hz, sources
        )
        self._record_out = (
            (lambda msg, iface, now: recorder.record_message(msg, "out", iface, now))
            if recorder is not None
            else None
        )
        self._shutdown_done = False

    def set_recorder(self, recorder: Any | None) -> None:
        """Attach a recorder (from any thread: the loop sees it from its next read) or detach
        it (None; on the loop thread only, so the loop never loses it between a check and a
        call). Run-time recording, occ/reccontrol.py."""
        if recorder is None:
            self._record_out = None
            self.recorder = None
            return
        self.recorder = recorder
        self._record_out = lambda msg, iface, now: recorder.record_message(msg, "out", iface, now)

    # ================================================================== lifecycle
    @property
    def state(self) -> RobotState:
        return self.state_machine.state

    def configure(self) -> None:
        """Configure drivers (servos off), read the initial state: INIT -> READY.

        On the real clock it waits up to ``MEASURE_WAIT_S`` for every joint's first
        measurement (drives report once asked); a joint still unmeasured then keeps the robot
        from being enabled (:meth:`_may_power`), never held at a position nobody reported."""
        for drv, _ in self.drivers:
            drv.configure()
        self._read(self.clock.now())
        if isinstance(self.clock, RealClock):
            give_up = self.clock.now() + MEASURE_WAIT_S
            while not all(j.measured for j in self.joints) and self.clock.now() < give_up:
                time.sleep(0.005)
                self._read(self.clock.now())
        self.data.hold_setpoint = list(self.data.q)
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
        if sv.enabled and isinstance(self.clock, RealClock) and self.supervisor_thread is None:
            sup_prio = sv.fifo_priority or (min(99, prio + 1) if prio else None)
            self.supervisor_thread = SupervisorThread(
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
        if self.supervisor_thread is not None:
            self.supervisor_thread.stop()
        self.state_machine.try_request("shutdown", "daemon shutting down")
        self.controller.shutdown()
        for drv, _ in self.drivers:
            try:
                drv.shutdown()
            except Exception:  # noqa: BLE001 - every driver must get its shutdown
                log.exception("driver %s: shutdown failed", drv.name)
        self.interfaces.stop()
        self.worker.stop()
        self.operators.recording.close_all()  # recordings started at run time

    def __enter__(self) -> Robot:
        self.configure()
        self.activate()
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def _may_power(self, state: RobotState, event: str) -> str:
        """Servos go on only when every joint has been measured: the held setpoint is where
        the joints are, never a default the hardware did not report."""
        if event != "enable":
            return ""
        missing = [j.name for j in self.joints if not j.measured]
        if missing:
            return f"no measurement yet from joints {missing} (are the drives on and answering?)"
        return ""

    def reset_monitors(self) -> None:
        """An operator's Reset: watchdog, supervisor and loss monitor cleared, and every
        ephemeral stream owner forgotten (a restarted master may send from a new port)."""
        self.watchdog.reset()
        self.supervisor.reset()
        self._supervisor_handled = False
        for monitor in self.loss_monitors.values():
            monitor.reset(None)
        for iface in self.interfaces.interfaces.values():
            iface.release_stream()

    # ================================================================== the tick
    def tick(self, now: float, k: int) -> None:
        """One control cycle. Nothing a peer sends and no plugin error ends it: an exception
        from a driver, a controller or a handler puts the robot in FAULT with an alert
        naming it, and the daemon goes on serving operators."""
        self.ticks += 1
        sup = self.supervisor
        sup.last_beat = now
        if not sup.armed:
            sup.arm(now)
        elif sup.tripped and not self._supervisor_handled:
            self._supervisor_handled = True
            self.alarms.fault(f"supervisor: {sup.reason}")
        try:
            self._read(now)
        except Exception as err:  # noqa: BLE001 - a driver error is a FAULT, not a crash
            self.alarms.plugin_error("driver read", err)
        try:
            self._streams(now)
        except Exception as err:  # noqa: BLE001
            self.alarms.plugin_error(f"controller {self.controller.name}: on_sample", err)
        # commands, bounded per tick so a flood cannot stall the loop (parsed already)
        commands = self.interfaces.commands
        if commands.pending:
            for item in commands.drain(limit=16):
                self.operators.handle(item, now)
        state = self.state_machine.state
        for name, mon in self._monitor_list:
            event = mon.check(now)
            if event is not None:
                if name == self.loss_input:
                    self.alarms.loss_event(event, state)
                else:  # a master not in control: an alert, the robot keeps its owner
                    self.alarms.bystander_loss(name, mon, event, state)
                state = self.state_machine.state
        monitor = self.loss_monitor
        try:
            self._control(state, now, monitor is not None and monitor.holding)
        except Exception as err:  # noqa: BLE001
            self.alarms.plugin_error(f"controller {self.controller.name}: update", err)
        try:
            self.outputs.send_due(now, k, self._record_out)
        except Exception as err:  # noqa: BLE001
            self.alarms.plugin_error("output", err)
        if self.recorder is not None:
            self.recorder.record_state(self.data, now)
        table = self.state_table
        if table is not None:
            data = self.data
            table.write(
                now,
                STATE_NUMBER[data.state],
                self._owner_code,
                data.q,
                data.commanded(),
                self.joints,
            )

    def _streams(self, now: float) -> None:
        """Every stream sample, in order, judged by the loss monitor; only accepted samples
        reach the controllers. Polled UDP stream sockets are read here first, at most
        ``POLL_LIMIT`` datagrams each."""
        for poll in self._pollers:
            poll(POLL_LIMIT)
        since = self._prev_tick
        self._prev_tick = now
        to_wall = 0.0
        walled = False
        for name, q, monitor, master in self._stream_queues:
            if not q.pending and not q.evicted:
                continue  # most ticks: nothing arrived (checked without a call)
            if monitor is not None:
                if not walled:
                    walled = True
                    # reception times on the wall clock, to compare with header timestamps
                    to_wall = self.clock.wall_time() - now
                if q.evicted:
                    # samples the loop could not take in time: seen, never called lost
                    for item in q.drain_overflow():
                        judge(monitor, item, now, to_wall, since)
            recorder = self.recorder
            on_sample = self.controller.on_sample
            # a master not in control is judged and counted, and moves nothing
            follow = not master or name == self.loss_input
            for item in q.drain():
                if recorder is not None:
                    recorder.record_message(item.msg, "in", name, now)
                if monitor is not None:
                    if judge(monitor, item, now, to_wall, since) is not Verdict.ACCEPT:
                        continue
                if follow:
                    try:
                        on_sample(item, now)
                    except CommandError as err:
                        # a discrete input on a stream queue (a VFIXTURE) that the controller
                        # refused: an answer to its sender, not a FAULT
                        self.operators.refuse_input(item, err)

    def _control(self, state: RobotState, now: float, holding: bool) -> None:
        """Controllers and drivers: follow while RUNNING (hold the last setpoint while the
        watched stream is overdue, then re-join the target without a jump), hold while
        ENABLED/STOPPED, nothing while the drivers are off."""
        data = self.data
        if self.controller.commands_effort:
            self._control_effort(state, now, holding)
            return
        if not self.controller.drives_joints:
            if state is RobotState.RUNNING and not holding:
                self.controller.update(now, data.setpoint)
            return
        if state is RobotState.RUNNING:
            sp = data.setpoint
            if holding:
                self._reentry = True
            else:
                target = self.controller.update(now, sp)
                if target is not None:
                    if self._reentry:
                        self._reentry = self._rejoin(sp, target)
                    else:
                        sp[:] = target
            self._write(sp, now)
        elif state in POWERED:
            self._write(data.hold_setpoint, now)

    def _control_effort(self, state: RobotState, now: float, holding: bool) -> None:
        """A robot whose controllers command efforts (a haptic master): their efforts while
        RUNNING, zero effort (the device free in the operator's hand) while ENABLED/STOPPED or
        while a watched stream is late, nothing while the drivers are off. Written every tick
        while powered, which also feeds the drives' heartbeat."""
        if state not in POWERED:
            return
        eff = self.data.effort_command
        assert eff is not None  # set at build when the controllers command efforts
        target = None
        if state is RobotState.RUNNING and not holding:
            target = self.controller.update(now, eff)
        if target is None:
            for i in range(len(eff)):
                eff[i] = 0.0
        else:
            eff[:] = target
        self._write(eff, now, effort=True)

    def _check_command_kinds(self) -> None:
        """Efforts go to effort drivers only, and a driver needing a PID for positions has
        its gains: a configuration mistake is a ConfigError at build, not a FAULT at run."""
        effort = self.controller.commands_effort
        for drv, _idx in self.drivers:
            if effort and drv.command_interface != "effort":
                raise ConfigError(
                    f"driver {drv.name!r}: the controller commands efforts, but the driver "
                    f"takes {drv.command_interface} commands (set command_interface: effort)"
                )
            if not effort and self.controller.drives_joints and drv.missing_gains:
                raise ConfigError(
                    f"driver {drv.name!r}: effort interface needs PID gains on joints "
                    f"{drv.missing_gains} (the controller commands positions)"
                )

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

    def _read(self, now: float) -> None:
        for drv, _idx in self.drivers:
            if drv.state is DriverState.UNCONFIGURED or drv.state is DriverState.SHUTDOWN:
                continue
            drv.read(now)
        self.data.measured_from(self.joints)

    def _write(self, values: Sequence[float], now: float, effort: bool = False) -> None:
        """Each active driver its slice of ``values``: position setpoints, or efforts."""
        for drv, idx, buf in self._slices:
            if drv.state is not DriverState.ACTIVE:
                continue
            for n, i in enumerate(idx):
                buf[n] = values[i]
            try:
                (drv.write_effort if effort else drv.write)(buf, now)
            except OCCError as err:
                self.alarms.fault(f"driver {drv.name}: {err}")
                return

    # ================================================================== state changes
    def _on_transition(
        self, old: RobotState, new: RobotState, event: str, reason: str, t: float
    ) -> None:
        data = self.data
        data.state = new
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
            data.hold_setpoint = list(data.q)
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
            data.hold_setpoint = list(data.setpoint if old is RobotState.RUNNING else data.q)
        if new is RobotState.RUNNING:
            data.setpoint[:] = data.hold_setpoint
            # from the held setpoint, the controllers' first targets are joined at half the
            # velocity limits: a controller whose target is elsewhere (an absolute tracker
            # input) moves there smoothly instead of at the drives' limits
            self._reentry = True
            # Armed by the first packet after (re)starting: a slave waiting for its master
            # holds still (no target), and a master that vanishes afterwards is caught.
            for monitor in self.loss_monitors.values():
                monitor.reset(None)
        self.controller.on_state(old, new, self.clock.now())
        text = f"{old.value} -> {new.value}" + (f": {reason}" if reason else "")
        self.alarms.broadcast(new.value, text, STATE_STATUS_CODE[new], timestamp=t)

    # ================================================================== collaboration
    def handover(self, to: str, interface: str, now: float) -> str:
        """Give the motion to master ``to`` (an operator's ``Handover`` that arrived on
        ``interface``): policy checked, the new owner's stream live while RUNNING, its loss
        monitor now the one acted on, the new target re-joined without a jump; a STATUS
        ``HANDOVER`` to every operator. CommandError when refused (nothing changes)."""
        co = self.collab
        if co is None:
            raise CommandError("Handover: no collaboration configured (this slave has one master)")
        try:
            if not to:
                raise CommandError('Handover needs To="MASTER INTERFACE"')
            by = co.authorize(interface, to)
            if to == co.owner:
                return f"{to} already has control"
            monitor = self.loss_monitors.get(to)
            if self.state_machine.state is RobotState.RUNNING and monitor is not None:
                if monitor.tripped or monitor.holding or monitor.last_good is None:
                    why = (
                        "latched lost"
                        if monitor.tripped
                        else "late"
                        if monitor.holding
                        else "silent since Run"
                    )
                    raise CommandError(
                        f"{to}'s stream is not live ({why}): control stays with {co.owner}"
                    )
        except CommandError:
            co.refused += 1
            raise
        old = co.switch(to, by, now)
        self.loss_input = to
        self.loss_monitor = monitor
        self._owner_code = float(co.code())
        # the new owner's first target is joined at half the velocity limits (the controller
        # re-indexes on its first sample as well): the slave never jumps
        self._reentry = True
        text = f"control {old} -> {to} (by {by})"
        log.warning("handover: %s", text)
        self.alarms.broadcast("HANDOVER", text, igtl.StatusCode.OK)
        return text

    # ================================================================== reporting
    @property
    def last_alert(self) -> str:
        """Why the robot last stopped or faulted ('' once an operator cleared it)."""
        return self.alarms.last_alert

    def describe_state(self) -> str:
        return self.operators.describe_state()

    def snapshot(self) -> dict[str, Any]:
        """Every statistic (GetStats, ``occd --stats``): built by the operator desk."""
        return self.operators.report()


def build_robot(
    config: DaemonConfig, *, clock: Clock | None = None, recorder: Any | None = None
) -> Robot:
    """Build a robot with the controller plugins its config names (``hold`` when none)."""
    controllers = [create_controller(c.plugin, c.params) for c in config.controllers]
    return Robot(config, clock=clock, controllers=controllers, recorder=recorder)
