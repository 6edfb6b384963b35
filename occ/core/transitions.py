"""What a change of the robot's state means for its drives and its parts.

:class:`StateEffects` is given to the robot's state machine (occ/core/safety.py ``StateMachine``) as
its three hooks:

- the guard (:meth:`StateEffects.may_power`): servos go on only when every joint was measured;
- the effector (:meth:`StateEffects.effect`): the drives powered all or nothing on entering a
  powered state, and proven by a checked read and a write; off on leaving it; reset out of
  FAULT/ESTOP (a failure vetoes the transition, named);
- the requests (:meth:`StateEffects.request`): an Enable whose drives' activation waits is
  powered up off the loop thread (occ/core/powerup.py) and completed by the loop when it has
  ended (:meth:`StateEffects.land`, every tick); a Disable or a Stop meanwhile cancels it, any
  other transition (EStop, Fault, shutdown) stops it;
- the listener (:meth:`StateEffects.on_transition`): the held setpoints, the streams, the
  controllers, the STATUS to every operator, and a FAULT for a drive still powered after a
  switch-off that failed.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import igtl
from occ.clock import Clock
from occ.controllers import ControllerSet
from occ.core.alarms import Alarms
from occ.core.data import RobotData
from occ.core.hardware import HardwareFailure, HardwareSet, describe
from occ.core.motion import POWERED, Motion
from occ.core.powerup import PowerUp
from occ.core.safety import TRANSITIONS, RobotState, StateMachine
from occ.drivers.base import DriverState
from occ.errors import StateError
from occ.joint import Joint
from occ.net.commands import Deferred
from occ.net.outputs import STATE_STATUS_CODE
from occ.net.streams import StreamInputs

log = logging.getLogger("occ.core.robot")
#: the states whose entry switches every drive still ACTIVE off, whatever the state before
_STOPS = frozenset({RobotState.FAULT, RobotState.ESTOP})


class StateEffects:
    """The state machine's guard, effector and listener for one robot (module docstring)."""

    def __init__(
        self,
        hardware: HardwareSet,
        joints: Sequence[Joint],
        clock: Clock,
        data: RobotData,
        controller: ControllerSet,
        motion: Motion,
        streams: StreamInputs,
        alarms: Alarms,
    ) -> None:
        self.hardware = hardware
        self.joints = joints
        self.clock = clock
        self.data = data
        self.controller = controller
        self.motion = motion
        self.streams = streams
        self.alarms = alarms
        #: the tick under way (its `now`): what a transition's reads and writes happen at
        self.tick_now: float | None = None
        #: the robot's state machine (set by occ/core/wiring.py ``build_effects``)
        self.states: StateMachine | None = None
        #: the power-up under way off the loop thread (None: none)
        self.powerup: PowerUp | None = None
        #: while the loop completes a power-up: what failed of it (the effector's input)
        self._landed: list[HardwareFailure] | None = None
        #: power-ups started, and the wall-clock time of the last one (GetStats ``power_up``)
        self.powerups = 0
        self.last_powerup_ms: float | None = None
        #: ``occd --start``'s transitions not yet asked (start_in; the tick checks it, a
        #: plain attribute: the loop looks every tick)
        self.pending_start: list[str] = []

    # ------------------------------------------------------------------ requests
    def request(self, event: str, reason: str) -> str | Deferred:
        """A state-machine event from an operator (occ/net/operators.py) or ``--start``, on the
        loop thread: the transition's text, or a :class:`Deferred` answered when a power-up
        off the loop thread is done (module docstring). StateError when refused."""
        states = self.states
        assert states is not None
        name = event.strip().lower()
        pu = self.powerup
        if pu is not None:
            if name == "enable":
                raise StateError(
                    f"'enable' refused in state {states.state.value}: the drives are powering "
                    f"up ({pu.reason}{'; cancelled: ' + pu.cancelled if pu.cancelled else ''})"
                )
            if name == "reset":
                raise StateError(
                    f"'reset' refused in state {states.state.value}: the drives are still "
                    f"working ({pu.action}, {pu.reason})"
                )
            if name in ("disable", "stop") and states.state is RobotState.READY:
                pu.cancel(f"{reason} ({name})", stop=False)  # idempotent
                return "READY: the power-up is cancelled; its drives go off as it ends"
            # estop, fault, shutdown: through the state machine, whose effector stops it
        elif name == "enable":
            old = states.state
            new = TRANSITIONS.get((old, name))
            waiting = self.hardware.waiting()
            if new in POWERED and old not in POWERED and waiting:
                states.check(name)  # its table and its guards, as request would
                answer = Deferred()
                self.hardware.hold(waiting)
                self.powerup = PowerUp(waiting, reason, answer).start()
                self.powerups += 1
                log.info(
                    "enable: powering up %s off the loop thread (%s)",
                    ", ".join(d.name for d in waiting),
                    reason,
                )
                return answer
        elif name == "reset" and states.state in (RobotState.FAULT, RobotState.ESTOP):
            waiting = self.hardware.waiting(DriverState.FAULT)
            if waiting:  # their fault resets wait too: on threads of their own
                states.check(name)
                answer = Deferred()
                self.hardware.hold(waiting)
                self.powerup = PowerUp(waiting, reason, answer, action="reset").start()
                return answer
        tr = states.request(name, reason)
        return f"{tr.old.value} -> {tr.new.value}"

    @property
    def powering_up(self) -> bool:
        """A power-up is under way off the loop thread (or ended and not yet collected)."""
        return self.powerup is not None

    def land(self) -> None:
        """Every tick, on the loop thread: a power-up whose activations have all ended is
        collected. Its drives are the loop's again; cancelled, whatever came up is switched
        off; else the loop completes the Enable (the HardwareSet's rule, verify, ENABLED) and
        answers the operator."""
        pu = self.powerup
        if pu is None or not pu.done:
            return
        self.powerup = None
        self.hardware.release(pu.drivers)
        if pu.took_s is not None:
            self.last_powerup_ms = round(pu.took_s * 1e3, 3)
        if pu.cancelled is not None:
            if pu.action == "reset":
                return  # the resets' result is discarded: the robot stays where it went
            for d in pu.leftovers():
                if pu.stopped:
                    d.safe_stop(pu.cancelled)  # came up before the stop reached it
            if stopped := self.hardware.deactivate():
                self.alarms.hardware_alert(stopped)
            return
        states = self.states
        assert states is not None
        self._landed = pu.failures()
        event = "reset" if pu.action == "reset" else "enable"
        try:
            tr = states.request(event, pu.reason)
        except StateError as err:  # refused or vetoed (TransitionFailed): FAULT latched
            if pu.answer is not None:
                pu.answer.fail(str(err))
            log.error("%s: %s", event, err)
        except Exception as err:  # noqa: BLE001 - a failing part is a FAULT, not a crash
            if pu.answer is not None:
                pu.answer.fail(f"{event} failed: {err}")
            self.alarms.plugin_error(f"{event} (off the loop thread)", err)
        else:
            if pu.answer is not None:
                pu.answer.resolve(f"{tr.old.value} -> {tr.new.value}")
        finally:
            self._landed = None

    def finish(self, timeout: float) -> None:
        """At shutdown: a power-up under way is stopped, waited for (at most ``timeout``)
        and collected, so no thread is left powering a drive the robot closes."""
        pu = self.powerup
        if pu is None:
            return
        pu.cancel("shutdown", stop=True)
        if not pu.wait(timeout):
            log.error("shutdown: power-up of %s did not end", [d.name for d in pu.drivers])
            return
        self.land()

    # -- occd --start: transitions for the loop's first ticks ------------------------------
    #: ``gate(event)``: why ``--start``'s ``event`` must wait a tick ('' to go now); the cell's
    #: ``start_wait`` (a Run waits until every member has been heard)
    start_gate: Callable[[str], str] | None = None

    def start_in(self, events: tuple[str, ...] | list[str]) -> None:
        """``--start``'s transitions, asked in the loop's first tick (Robot.start_in)."""
        self.pending_start = list(events)

    def start_events(self) -> None:
        """``--start``'s transitions, in order; one that powers drives up off the loop thread
        leaves the rest for the tick after it has landed."""
        while self.pending_start:
            ev = self.pending_start[0]
            gate = self.start_gate
            if gate is not None and gate(ev):
                return  # asked again next tick (a cell not complete yet: occ/core/cell.py)
            self.pending_start.pop(0)
            try:
                answer = self.request(ev, "--start")
            except StateError as err:  # a refusal or a failure is alerted by the state machine
                log.error("--start: %s refused or failed (%s)", ev, err)
                self.pending_start = []
                return
            if isinstance(answer, Deferred):
                answer.bind(self._started)  # the rest once it has landed
                return

    def _started(self, ok: bool, text: str) -> None:
        """A power-up asked by ``--start`` has landed: the remaining events go on, unless it
        failed."""
        if not ok:
            log.error("--start: enable refused or failed (%s)", text)
            self.pending_start = []

    def await_power_up(self, timeout: float) -> bool:
        """Wait (wall clock, at most ``timeout``) until the activations of a power-up under way
        have all ended, without ticking (the next tick completes it); True when they have or
        none was under way. For tests and tools in simulated time."""
        pu = self.powerup
        return True if pu is None else pu.wait(timeout)

    def _now(self) -> float:
        return self.tick_now if self.tick_now is not None else self.clock.now()

    def may_power(self, state: RobotState, event: str) -> str:
        """Servos go on only when every joint has been measured: the held setpoint is where
        the joints are, never a default the hardware did not report."""
        missing = self.hardware.unmeasured(self.joints) if event == "enable" else ""
        if not missing:
            return ""
        why = f"no measurement yet from {missing} (are the drives on and answering?)"
        self.alarms.broadcast("ALERT", f"enable refused: {why}", igtl.StatusCode.NOT_READY)
        return why

    def effect(self, old: RobotState, new: RobotState, event: str) -> str:
        """The state machine's effector: every drive powered on entering POWERED, all or
        nothing (a failure vetoes); off on leaving it (never refused, a drive that fails to stop
        is named in an alert); reset and configured out of FAULT/ESTOP, or vetoed."""
        failures: list[HardwareFailure] = []
        hw = self.hardware
        landed, self._landed = self._landed, None
        pu = self.powerup
        if pu is not None and landed is None:
            # any other transition while the drives power up (EStop, Fault, shutdown) wins:
            # every drive coming up is stopped, the Enable answered with a refusal
            pu.cancel(f"{event}: {old.value} -> {new.value}", stop=True)
        if new in POWERED and old not in POWERED:
            # landed: the power-up off the loop thread ended (its drives ACTIVE, or failed)
            failures = hw.activate(landed or ())
            if not failures:  # up: proven by a checked read and a write before it is said
                failures = hw.verify(self.joints, self._now(), self.controller.commands_effort)
                if failures:
                    failures += hw.deactivate()
                elif landed is not None:
                    # the drives powered up off the loop were not read meanwhile: the held
                    # setpoint starts from verify's fresh reading, not the one before
                    self.data.measured_from(self.joints)
        elif (old in POWERED or new in _STOPS) and new not in POWERED:
            # off on leaving POWERED; and on entering FAULT or ESTOP from any state, every drive
            # still ACTIVE (one powered by a transition that raised after activate: the robot
            # never became ENABLED, yet its drives are on)
            if stopped := hw.deactivate():
                self.alarms.hardware_alert(stopped)
        if new is RobotState.READY and old in (RobotState.FAULT, RobotState.ESTOP):
            failures = hw.reset(self._now(), landed or ())
        return describe(failures)

    def on_transition(
        self, old: RobotState, new: RobotState, event: str, reason: str, t: float
    ) -> None:
        self.data.state = new
        stopped = new in (RobotState.FAULT, RobotState.ESTOP, RobotState.STOPPED)
        why = f": {reason}" if reason else ""
        level = logging.WARNING if stopped else logging.INFO
        log.log(level, "state %s -> %s (%s)%s", old.value, new.value, event, why)
        self.motion.on_state(old, new)  # held and first setpoints (the drives: effect)
        if new is RobotState.RUNNING:
            # Armed by the first packet after (re)starting: a slave waiting for its master
            # holds still (no target), and a master that vanishes afterwards is caught.
            self.streams.reset()
        self.controller.on_state(old, new, self._now())  # the tick's time, as replayed
        text = f"{old.value} -> {new.value}{why}"
        self.alarms.broadcast(new.value, text, STATE_STATUS_CODE[new], timestamp=t)
        if old in (RobotState.FAULT, RobotState.ESTOP) and new is RobotState.READY:
            self.alarms.cleared()
        # a drive whose switch-off failed (Disable, a roll-back) may still be powered: the
        # robot may not look merely off, it latches FAULT naming it (issue 36)
        if new is RobotState.READY and (unsafe := self.hardware.unsafe()):
            self.alarms.fault(f"switch-off failed: {describe(unsafe)}")
