"""What a change of the robot's state means for its drives and its parts.

:class:`StateEffects` is given to the robot's state machine (occ/core/safety.py ``StateMachine``) as
its three hooks:

- the guard (:meth:`StateEffects.may_power`): servos go on only when every joint was measured;
- the effector (:meth:`StateEffects.effect`): the drives powered all or nothing on entering a
  powered state, and proven by a checked read and a write; off on leaving it; reset out of
  FAULT/ESTOP (a failure vetoes the transition, named);
- the listener (:meth:`StateEffects.on_transition`): the held setpoints, the streams, the
  controllers, the STATUS to every operator, and a FAULT for a drive still powered after a
  switch-off that failed.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import igtl
from occ.clock import Clock
from occ.controllers import ControllerSet
from occ.core.alarms import Alarms
from occ.core.data import RobotData
from occ.core.hardware import HardwareFailure, HardwareSet, describe
from occ.core.motion import POWERED, Motion
from occ.core.safety import RobotState
from occ.joint import Joint
from occ.net.outputs import STATE_STATUS_CODE
from occ.net.streams import StreamInputs

log = logging.getLogger("occ.core.robot")


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
        if new in POWERED and old not in POWERED:
            failures = hw.activate()
            if not failures:  # up: proven by a checked read and a write before it is said
                failures = hw.verify(self.joints, self._now(), self.controller.commands_effort)
                if failures:
                    failures += hw.deactivate()
        elif new not in POWERED and old in POWERED and (stopped := hw.deactivate()):
            self.alarms.hardware_alert(stopped)
        if new is RobotState.READY and old in (RobotState.FAULT, RobotState.ESTOP):
            failures = hw.reset(self._now())
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
        self.controller.on_state(old, new, self.clock.now())
        text = f"{old.value} -> {new.value}{why}"
        self.alarms.broadcast(new.value, text, STATE_STATUS_CODE[new], timestamp=t)
        if old in (RobotState.FAULT, RobotState.ESTOP) and new is RobotState.READY:
            self.alarms.cleared()
        # a drive whose switch-off failed (Disable, a roll-back) may still be powered: the
        # robot may not look merely off, it latches FAULT naming it (issue 36)
        if new is RobotState.READY and (unsafe := self.hardware.unsafe()):
            self.alarms.fault(f"switch-off failed: {describe(unsafe)}")
