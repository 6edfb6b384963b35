"""The Robot: one InterfaceManager, one Frame, its Joints and Drivers, and the control loop.

This is the Open Core Control structure (Arata et al., IJCARS 2010): network I/O in the
InterfaceManager (reusable on any robot), kinematics in the Frame, hardware behind Drivers; here
assembled from a validated YAML configuration instead of C++ ``main()``. The Robot keeps
assembly, lifecycle, the tick and what its state means for its drivers; others see its
:class:`~occ.core.data.RobotData`; requests, outputs and motion are the :mod:`~occ.net.operators`
desk's, the :mod:`~occ.net.outputs` scheduler's and the controller plugins'.

Lifecycle (ros2_control): ``configure()`` configures the drivers (state READY, servos off),
``activate()`` starts the interfaces and the supervisor, ``run()`` runs the loop until stopped,
``shutdown()`` stops drivers safely and closes everything (safe twice).

Each tick (:meth:`Robot.tick`, on the loop thread): read every drive (:mod:`occ.core.hardware`);
the stream samples, judged (:mod:`occ.net.streams`), and at most 16 operator requests; the cell
(:mod:`occ.core.cell`); the loss monitors' events; the controllers and the drive writes
(:mod:`occ.core.motion`); the outputs due; the recording, the State Data Table and the black
box (:mod:`occ.recording.blackbox`)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import igtl
from occ.clock import Clock, RealClock
from occ.config import DaemonConfig
from occ.controllers import Controller, create_controller
from occ.core import wiring
from occ.core.hardware import describe
from occ.core.safety import RobotState, StateMachine
from occ.core.statetable import table_for
from occ.core.stats import LoopStats
from occ.core.supervision import SupervisorThread, Worker
from occ.recording.record import writer_priority

log = logging.getLogger(__name__)

#: How long configure() waits, on the real clock, for every joint's first measurement.
MEASURE_WAIT_S = 1.0


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
        self.config, rc = config, config.robot
        self.name, self.rate_hz, self.period = rc.name, rc.rate_hz, 1.0 / rc.rate_hz
        self.clock: Clock = clock if clock is not None else RealClock(spin_us=rc.realtime.spin_us)
        self.state_machine = StateMachine(clock=self.clock)
        self.recorder = recorder
        # --- Joints, Frame, Drivers: the drives as one unit (occ/core/hardware.py); the data
        self.joints, self.frame, self.hardware, self.data, env = wiring.build_drives(self)
        # whole-arm collision checking (occ/kinematics/collision.py): plans and, at run time,
        # a worker
        self.collision = wiring.build_collision(self)
        # --- Interfaces, and the streams among them (polled, judged, one in control)
        self.interfaces, self.collab, self.streams = wiring.build_inputs(config, self.clock)
        # --- Safety: alarms, loop watchdog, supervisor (occ/core/alarms.py, occ/core/safety.py)
        self.alarms, self.watchdog, self.supervisor = wiring.build_safety(self, recorder)
        self.cell = wiring.build_cell(self)  # several arms, one stop (occ/core/cell.py)
        self.black_box = wiring.build_black_box(self, controllers)  # occ/recording/blackbox.py
        self.supervisor_thread: SupervisorThread | None = None
        self._supervisor_handled = False
        #: jobs the loop must not pay for (GetStats); the worker sends the reply itself
        self.worker = Worker(f"occ-{self.name}-report", fifo_priority=writer_priority(config))
        self.ticks = 0
        #: the State Data Table (``state_table.seconds``), written once a tick
        seconds = config.state_table.seconds
        self.state_table = table_for(seconds, self.joints, self.rate_hz, self.frame)
        self._owner_code = float(self.collab.code()) if self.collab is not None else -1.0
        # --- Loop and statistics
        self.stats, self.loop = wiring.build_loop(self)
        # --- Controllers and motion; what a state change means (occ/core/transitions.py)
        self.controller, self.motion = wiring.build_motion(self, controllers, env)
        self.effects = wiring.build_effects(self)  # the state machine's guard, effector, listener
        # --- Operators and outputs
        self.operators = wiring.build_desk(self)
        self.streams.bind(
            self.controller.on_sample, self.controller.on_input, self.operators.refuse_input
        )
        self.interfaces.on_connect(self.operators.greet)
        self.outputs = wiring.build_outputs(self)
        self.set_recorder(recorder)
        self.services = [p for p in (self.collision, self.cell, self.black_box) if p is not None]
        self._shutdown_done = False

    def set_recorder(self, recorder: Any | None) -> None:
        """Attach a recorder (from any thread: the loop sees it from its next read) or detach
        it (None; on the loop thread only, so the loop never loses it between a check and a
        call). Run-time recording, occ/recording/control.py."""
        self.recorder = self.alarms.watch_recording(recorder)  # its failure: an alert
        self._record_out = self.black_box.outputs_tap(recorder)  # the outputs sent: to both

    # ================================================================== lifecycle
    @property
    def state(self) -> RobotState:
        return self.state_machine.state

    def configure(self) -> None:
        """Configure drivers (servos off): INIT -> READY, or FAULT with an alert naming each
        drive that failed (``Reset`` configures again). On the real clock it waits up to
        ``MEASURE_WAIT_S`` for every joint's first measurement; a joint still unmeasured keeps
        the robot from being enabled (``StateEffects.may_power``, occ/core/transitions.py)."""
        failures = self.hardware.configure()
        if failures:
            self.alarms.fault(f"configure failed: {describe(failures)}")
            return
        real = isinstance(self.clock, RealClock)
        self.hardware.await_measured(self.joints, self._read, self.clock.now, MEASURE_WAIT_S, real)
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
        for part in self.services:  # the collision worker, the cell link
            part.start()
        self.supervisor_thread = self.supervisor_thread or SupervisorThread.build(
            self.config.safety.supervisor, self.supervisor, self.clock, prio
        )

    def run(self, duration: float | None = None, ticks: int | None = None) -> LoopStats:
        # a run's end disarms the supervisor (the loop's on_end, occ/core/wiring.py)
        return self.loop.run(duration=duration, ticks=ticks)

    def start_in(self, *events: str) -> None:
        """Transitions for the loop's first tick (``occd --start``): Enable writes to the
        drives to prove them (issue 36), and a drive's heartbeat runs from its first command,
        so power comes on inside the run of ticks that goes on commanding it, never before
        the loop has started (which can take longer than the heartbeat)."""
        self.effects.start_in(events)

    def stop_loop(self) -> None:
        self.loop.stop()

    def __enter__(self) -> Robot:
        self.configure()
        self.activate()
        return self

    def shutdown(self) -> None:
        """Stop drivers safely, close interfaces. Safe to call twice."""
        if self._shutdown_done:
            return
        self._shutdown_done = True
        self.supervisor.disarm()
        if self.supervisor_thread is not None:
            self.supervisor_thread.stop()
        self.state_machine.try_request("shutdown", "daemon shutting down")
        self.effects.finish(timeout=2.0)  # a power-up under way: stopped, waited for
        self.controller.shutdown()
        self.hardware.shutdown()
        self.interfaces.stop()
        self.worker.stop()
        for part in self.services:
            part.stop()
        self.operators.recording.close_all()  # recordings started at run time

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def reset_monitors(self) -> None:
        """An operator's Reset: watchdog, supervisor and loss monitor cleared, and every
        ephemeral stream owner forgotten (a restarted master may send from a new port)."""
        self.watchdog.reset()
        self.supervisor.reset()
        self._supervisor_handled = False
        self.streams.reset()
        for iface in self.interfaces.interfaces.values():
            iface.release_stream()

    # ================================================================== the tick
    def tick(self, now: float, k: int) -> None:
        """One control cycle. Nothing a peer sends and no plugin error ends it: an exception
        from a driver, a controller or a handler puts the robot in FAULT with an alert
        naming it, and the daemon goes on serving operators."""
        self.ticks += 1
        self.effects.tick_now = now
        sup = self.supervisor
        sup.last_beat = now
        if not sup.armed:  # the first tick of a run: the black box learns the loop thread
            sup.arm(now)
            self.black_box.on_loop()
        elif sup.tripped and not self._supervisor_handled:  # back after a hung tick
            self._supervisor_handled = self.alarms.supervisor_back(sup)
        self._read(now)
        if self.effects.powerup is not None:
            self.effects.land()  # a power-up off the loop thread that has ended: completed
        try:
            self.streams.drain(now, self.recorder)
        except Exception as err:  # noqa: BLE001
            self.alarms.plugin_error(f"controller {self.controller.name}: on_sample", err)
        if self.effects.pending_start and not self.effects.powering_up:
            self.effects.start_events()  # commands next: at most 16 a tick, parsed already
        commands = self.interfaces.commands
        if commands.pending:
            for item in commands.drain(limit=16):
                self.operators.handle(item, now)
        if self.cell is not None:  # the other arms' heartbeats: a hold in this tick
            self.cell.tick(now)
        state = self.state_machine.state
        for name, mon, event in self.streams.events(now):
            if name == self.streams.input:
                self.alarms.loss_event(event, state)
            else:  # a master not in control: an alert, the robot keeps its owner
                self.alarms.bystander_loss(name, mon, event, state)
            state = self.state_machine.state
        try:
            self.motion.control(state, now, self.streams.holding)
        except Exception as err:  # noqa: BLE001
            self.alarms.plugin_error(f"controller {self.controller.name}: update", err)
        guard = self.collision  # a link inside its margin: an ALERT and the safety stop
        if guard is not None and (why := guard.after_control(state, self.data, now)):
            self.alarms.collision_stop(why, guard.policy)
        try:
            self.outputs.send_due(now, k, self._record_out)
        except Exception as err:  # noqa: BLE001
            self.alarms.plugin_error("output", err)
        if self.recorder is not None:
            self.recorder.record_state(self.data, now)
        if self.state_table is not None:
            self.state_table.write_data(now, self._owner_code, self.data, self.joints)
        self.black_box.end_tick(now, k)  # what this tick read and did (black_box)

    def _read(self, now: float) -> None:
        """Every drive read (a failed one latches FAULT naming it; the others still read)."""
        failures = self.hardware.read(now)
        self.data.measured_from(self.joints)
        if failures is not None:
            self.alarms.hardware_fault(failures)

    def write(self, values: Sequence[float], now: float, effort: bool = False) -> None:
        """Every drive its slice of ``values`` (position setpoints, or efforts), or none:
        a drive that is not ACTIVE or whose write fails latches FAULT, which powers every
        drive off in this tick."""
        failure = self.hardware.write(values, now, effort)
        if failure is not None:
            self.alarms.hardware_fault([failure])

    # ================================================================== collaboration
    def handover(self, to: str, interface: str, now: float) -> str:
        """Give the motion to master ``to`` (:meth:`StreamInputs.handover` checks and
        switches), the new target re-joined without a jump (the controller re-indexes on its
        first sample as well); a STATUS ``HANDOVER`` to every operator. CommandError when
        refused (nothing changes)."""
        running = self.state_machine.state is RobotState.RUNNING
        old, by = self.streams.handover(to, interface, now, running)
        if old == to:
            return f"{to} already has control"
        assert self.collab is not None  # the streams refused the handover otherwise
        self._owner_code = float(self.collab.code())
        self.motion.reentry = True
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
        """Every statistic (GetStats, ``occd --stats``): every part's, registered at build."""
        return self.operators.report()


def build_robot(
    config: DaemonConfig, *, clock: Clock | None = None, recorder: Any | None = None
) -> Robot:
    """Build a robot with the controller plugins its config names (``hold`` when none)."""
    controllers = [create_controller(c.plugin, c.params) for c in config.controllers]
    return Robot(config, clock=clock, controllers=controllers, recorder=recorder)
