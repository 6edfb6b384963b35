"""Alarms: what the robot does when something fails, and how the operators hear of it.

A plugin or handler that raises, a loss-monitor event, the loop watchdog, the supervisor: each
ends here, on the thread that saw it. A stop holds the last setpoint, latched until an
operator's Run; a fault latches until Reset; every one is logged (rate-limited where it can
repeat every tick) and sent to every viewer and operator as a STATUS naming its cause.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import igtl
from occ.core.hardware import HardwareFailure, describe
from occ.core.safety import LossEvent, RobotState

if TYPE_CHECKING:
    from igtl.messages.base import Message
    from occ.clock import Clock
    from occ.core.hardware import HardwareSet
    from occ.core.safety import LossMonitor, StateMachine, Supervisor
    from occ.net.streams import StreamInputs

log = logging.getLogger("occ.core.robot")


class Alarms:
    """The robot's reactions to failures (see the module docstring)."""

    def __init__(
        self,
        name: str,
        states: StateMachine,
        clock: Clock,
        send: Callable[[Message], object],
        hardware: HardwareSet,
        streams: StreamInputs,
        recorder: Any | None = None,
    ) -> None:
        """Narrow ports, not the Robot: the robot's name (STATUS device), its state machine,
        clock, ``send`` (a STATUS to every viewer and operator), its drives (safe stop), its
        streams (which one moves the robot, the loss policy), its recorder."""
        self.name = name
        self.states = states
        self.clock = clock
        self._send = send
        self.hardware = hardware
        self.streams = streams
        self.recorder = recorder
        #: why the robot last stopped or faulted ('' once an operator cleared it)
        self.last_alert = ""
        self._errors_logged = 0
        #: (drive, operation) failures told since the robot last left FAULT/ESTOP
        self._told: set[tuple[str, str]] = set()
        #: True while a safety stop's transition runs (its listeners tell it from an
        #: operator's Stop: occ/core/cell.py)
        self.safety_stopping = False
        #: told on the supervisor's thread when it trips (the cell announces the hung loop)
        self.on_supervisor_trip: Callable[[str], None] | None = None
        #: ``tap(status, "*")``: every STATUS sent, from any thread (the black box), or None
        self.tap: Callable[[Message, str], None] | None = None
        #: ``note(what, obj)``: the facts behind a stop, kept in the black box when it happens
        #: (the loss event with its stream, the drive failures), or None; never per tick
        self.note: Callable[[str, Any], None] | None = None

    def plugin_error(self, where: str, err: BaseException) -> None:
        """An exception from a plugin or handler: FAULT with an alert naming it."""
        reason = f"{where} raised {type(err).__name__}: {err}"
        if self._errors_logged < 20:  # a fault that repeats every tick must not flood the log
            self._errors_logged += 1
            log.error("%s", reason, exc_info=err)
        if self.states.state is not RobotState.FAULT:
            self.fault(reason)

    def hardware_fault(self, failures: Sequence[HardwareFailure]) -> None:
        """A drive failed (read, write, or not ACTIVE when it must be): FAULT naming each
        drive and its cause; the FAULT transition powers every drive off in this tick.

        Already FAULT or ESTOP (no transition, so no state STATUS), a failure not told yet
        since the robot last left FAULT/ESTOP (a drive and an operation) is an ALERT to
        every operator and viewer: a second drive faulting, a read error during an E-stop,
        are heard by whoever is connected, once each, not every tick."""
        reason = describe(failures)
        state = self.states.state
        note = self.note  # which drive, which operation, its words (occ-record why): once each
        if state is RobotState.FAULT or state is RobotState.ESTOP:
            new = [f for f in failures if (f.driver, f.action) not in self._told]
            if new:
                if note is not None:
                    note("drive failure", {"state": state.value, "failures": new})
                self._told.update((f.driver, f.action) for f in new)
                text = f"while {state.value}: {describe(new)}"
                log.error("ALERT: %s", text)
                self.broadcast("ALERT", text, igtl.StatusCode.HARDWARE_FAILURE)
            elif self._errors_logged < 20:  # a drive failing every tick must not flood the log
                self._errors_logged += 1
                log.error("while %s: %s", state.value, reason)
            return
        if note is not None:
            note("drive failure", {"state": state.value, "failures": list(failures)})
        self._told.update((f.driver, f.action) for f in failures)
        self.fault(reason)

    def cleared(self) -> None:
        """The robot left FAULT/ESTOP (a Reset that succeeded): failures are news again."""
        self._told.clear()
        self._errors_logged = 0

    def hardware_alert(self, failures: Sequence[HardwareFailure]) -> None:
        """Drives that failed to stop (latched FAULT by their base): an alert naming them.
        The robot latches FAULT for it once the transition under way is done
        (:meth:`occ.core.robot.Robot._on_transition`: a drive not proven off is never forgotten)."""
        self._told.update((f.driver, f.action) for f in failures)
        text = f"drives failed to stop: {describe(failures)}"
        log.error("ALERT: %s", text)
        self.broadcast("ALERT", text, igtl.StatusCode.HARDWARE_FAILURE)

    def loss_event(self, event: LossEvent, state: RobotState) -> None:
        """Act on the loss monitor: only while RUNNING does the stream move the robot, so only
        then is its loss an alert (before Run, or while stopped, it is only counted)."""
        where = f"stream {self.streams.input}"
        if self.note is not None:  # the event as judged, its numbers and times (occ-record why)
            self.note("loss", {"stream": self.streams.input, "state": state.value, "event": event})
        if state is not RobotState.RUNNING:
            log.debug("%s: %s (%s, not acted on in %s)", where, event.kind, event.cause, state)
            return
        if event.kind == "latch":
            self.safety_stop(
                f"packet loss on {self.streams.input}: {event.cause}", self.streams.policy
            )
        elif event.kind == "hold":
            log.info("%s: %s", where, event.cause)
        else:  # resume, refused: keep following, tell the operators
            log.warning("%s: %s", where, event.cause)
            self.broadcast("STREAM", f"{where}: {event.cause}", igtl.StatusCode.OK)

    def bystander_loss(
        self, name: str, monitor: LossMonitor, event: LossEvent, state: RobotState
    ) -> None:
        """A loss event on the stream of a master that is not in control (collaboration): it
        moves nothing, so it never stops the robot. A latch is an alert to every operator and
        the monitor re-arms (its master may come back and be handed control later); the
        others are logged and, like the owner's, told as a ``STREAM`` warning."""
        owner = self.streams.input
        if self.note is not None:
            self.note(
                "loss", {"stream": name, "state": state.value, "event": event, "owner": owner}
            )
        if state is not RobotState.RUNNING:
            log.debug(
                "stream %s: %s (%s, not acted on in %s)", name, event.kind, event.cause, state
            )
            if event.kind == "latch":
                monitor.reset(None)
            return
        if event.kind == "latch":
            monitor.reset(None)
            text = f"stream {name} (not in control) lost: {event.cause}; following {owner}"
            log.error("ALERT: %s", text)
            self.broadcast("ALERT", text, igtl.StatusCode.TIME_OUT)
        elif event.kind == "hold":
            log.info("stream %s (not in control): %s", name, event.cause)
        else:
            log.warning("stream %s (not in control): %s", name, event.cause)
            self.broadcast("STREAM", f"stream {name}: {event.cause}", igtl.StatusCode.OK)

    def watch_recording(self, recorder: Any | None) -> Any | None:
        """The recorder the alarms write their STATUS to, and whose failure they announce
        (:meth:`recording_failed`); returns it (``Robot.set_recorder``)."""
        self.recorder = recorder
        if recorder is not None:
            recorder.on_failure(self.recording_failed)
        return recorder

    def recording_failed(self, text: str) -> None:
        """A recording that cannot be written (a full disk, its file removed, its writer
        gone): a ``RECORDING`` alert to every operator and viewer, once per recording (the
        recorder tells it once and has logged it). Nothing moves for it: the robot goes on."""
        self.broadcast("RECORDING", text, igtl.StatusCode.RESOURCE_ERROR)

    def broadcast(self, name: str, text: str, code: int, timestamp: float | None = None) -> None:
        """A STATUS to every viewer and operator (and the recording)."""
        status = igtl.StatusMessage(
            code=int(code),
            error_name=name,
            status_message=text,
            device_name=self.name[:20],
            timestamp=self.clock.wall_time() if timestamp is None else timestamp,
        )
        self._send(status)
        recorder = self.recorder  # read once: this may run off the loop thread (supervisor)
        if recorder is not None:
            recorder.record_message(status, "out", "*", self.clock.now())
        if self.tap is not None:
            self.tap(status, "*")

    def black_box_written(self, text: str, ok: bool) -> None:
        """A black box dump written (where, what it holds) or not (why): a ``BLACKBOX``
        STATUS to every operator and viewer, from the dump writer's thread."""
        code = igtl.StatusCode.OK if ok else igtl.StatusCode.RESOURCE_ERROR
        self.broadcast("BLACKBOX", text, code)

    def supervisor_trip(self, reason: str) -> None:
        """On the supervisor thread, while the loop is stuck: operators alerted first, then
        every drive to its safe state at once, in parallel (a drive whose stop hangs delays
        neither the others nor the alert); a drive that did not confirm its stop within the
        bound is a second alert naming it. The loop latches FAULT when it comes back."""
        self.last_alert = f"supervisor: {reason}"
        log.error("SUPERVISOR: %s; drivers to their safe state", reason)
        if (announce := self.on_supervisor_trip) is not None:
            announce(f"supervisor: {reason}")  # the cell's other arms first: they still move
        self.broadcast("SUPERVISOR", f"supervisor: {reason}", igtl.StatusCode.HARDWARE_FAILURE)
        unconfirmed = self.hardware.safe_stop(reason)
        if unconfirmed:
            text = f"supervisor: drives not proven stopped: {describe(unconfirmed)}"
            log.error("ALERT: %s", text)
            self.broadcast("ALERT", text, igtl.StatusCode.HARDWARE_FAILURE)

    def supervisor_back(self, supervisor: Supervisor) -> bool:
        """The loop ticks again after the supervisor tripped: FAULT naming it (True: handled)
        unless the robot was never powered (INIT, READY with every drive safe), where nothing
        moved or could: then an alert, and the supervisor watches again (False). A loaded
        machine that stalls an idle daemon's loop does not latch it (the watchdog alerts the
        same way there)."""
        reason = f"supervisor: {supervisor.reason}"
        idle = self.states.state in (RobotState.INIT, RobotState.READY)
        if idle and not self.hardware.unsafe():
            text = f"{reason}; no drive powered: not latched"
            log.warning("%s", text)
            self.broadcast("SUPERVISOR", text, igtl.StatusCode.OK)
            supervisor.reset()
            return False
        self.fault(reason)
        return True

    def safety_stop(self, reason: str, policy: str) -> None:
        self.last_alert = reason
        log.error("SAFETY STOP: %s", reason)
        if policy == "fault":
            self.fault(reason)
        elif self.states.state in (RobotState.RUNNING, RobotState.ENABLED):
            self.safety_stopping = True
            try:
                self.states.try_request("stop", reason)
            finally:
                self.safety_stopping = False
        else:
            # not moving: still tell the operators why
            self.broadcast("ALERT", reason, igtl.StatusCode.TIME_OUT)

    def fault(self, reason: str) -> None:
        self.last_alert = reason
        log.error("FAULT: %s", reason)
        self.states.try_request("fault", reason)

    def collision_stop(self, why: str, policy: str) -> None:
        """A link inside its margin (occ/kinematics/collision.py's verdict): a ``COLLISION`` ALERT
        naming link and region to every operator and viewer, and the safety stop (held until Run, or
        FAULT with ``policy: fault``)."""
        self.broadcast("COLLISION", why, igtl.StatusCode.ILLEGAL_INSTRUCTION)
        self.safety_stop(why, policy)

    def watchdog_alert(self, reason: str, overruns: int) -> None:
        log.warning("watchdog: %s (%d overruns so far)", reason, overruns)
        self.broadcast("WATCHDOG", f"watchdog: {reason}", igtl.StatusCode.TIME_OUT)
