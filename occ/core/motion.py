"""What the drives are told each tick, by the robot's state: the controllers' targets while
RUNNING (held while the stream in control is late, then re-joined without a jump), the held
setpoint while ENABLED or STOPPED, nothing while the drives are off; or, for a robot whose
controllers command efforts (a haptic master), their efforts while RUNNING and zero otherwise.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from occ.controllers import ControllerSet
from occ.core.data import RobotData
from occ.core.hardware import HardwareSet
from occ.core.safety import RobotState
from occ.errors import ConfigError
from occ.joint import Joint, step_together

#: States in which drivers are ACTIVE (servos on).
POWERED = frozenset({RobotState.ENABLED, RobotState.RUNNING, RobotState.STOPPED})

#: ``write(values, now, effort)``: every drive its slice, or a FAULT (occ/core/robot.py)
Write = Callable[[Sequence[float], float, bool], None]


class Motion:
    """The robot's motion policy (see the module docstring)."""

    def __init__(
        self,
        data: RobotData,
        controller: ControllerSet,
        joints: Sequence[Joint],
        period: float,
        write: Write,
    ) -> None:
        self.data = data
        self.controller = controller
        self._write = write
        # after a hold, the setpoint re-joins the controllers' target at half the joint
        # velocity limits (no jump, whatever the master did meanwhile)
        self._reentry_step = [0.5 * j.limits.velocity * period for j in joints]
        #: re-joining: the next targets are approached at half the velocity limits
        self.reentry = False
        self.reentries = 0
        #: may this setpoint be written? (the collision guard's ``admit``: a setpoint no
        #: verdict covers is not written, the previous one is held and re-joined after)
        self.admit: Callable[[Sequence[float], float], bool] | None = None
        self._prev = [0.0] * len(joints)
        self.refused = 0

    @staticmethod
    def check_command_kinds(controller: ControllerSet, hardware: HardwareSet) -> None:
        """Efforts go to effort drivers only, and a driver needing a PID for positions has
        its gains: a configuration mistake is a ConfigError at build, not a FAULT at run."""
        effort = controller.commands_effort
        for drv in hardware.drivers:
            if effort and drv.command_interface != "effort":
                raise ConfigError(
                    f"driver {drv.name!r}: the controller commands efforts, but the driver "
                    f"takes {drv.command_interface} commands (set command_interface: effort)"
                )
            if not effort and controller.drives_joints and drv.missing_gains:
                raise ConfigError(
                    f"driver {drv.name!r}: effort interface needs PID gains on joints "
                    f"{drv.missing_gains} (the controller commands positions)"
                )

    def on_state(self, old: RobotState, new: RobotState) -> None:
        """What a state change means for the setpoints (the drives were powered or not by
        the robot's effector before it): the held setpoint is where the joints are on power-up
        and what the drives were last told on a stop; RUNNING starts from it and joins the
        controllers' first targets at half the velocity limits (a controller whose target is
        elsewhere, an absolute tracker input, moves there smoothly, not at the limits)."""
        data = self.data
        if new in POWERED and old not in POWERED:
            data.hold_setpoint = list(data.q)
        if new is RobotState.STOPPED or (new is RobotState.ENABLED and old is RobotState.RUNNING):
            # the last safe setpoint: what the drivers were last told (not where they lag)
            data.hold_setpoint = list(data.setpoint if old is RobotState.RUNNING else data.q)
        if new is RobotState.RUNNING:
            data.setpoint[:] = data.hold_setpoint
            self.reentry = True

    def control(self, state: RobotState, now: float, holding: bool) -> None:
        """Controllers and drivers for one tick (see the module docstring)."""
        data = self.data
        controller = self.controller
        if controller.commands_effort:
            self._control_effort(state, now, holding)
            return
        if not controller.drives_joints:
            if state is RobotState.RUNNING and not holding:
                controller.update(now, data.setpoint)
            return
        if state is RobotState.RUNNING:
            sp = data.setpoint
            if holding:
                self.reentry = True
            else:
                target = controller.update(now, sp)
                if target is not None:
                    admit = self.admit
                    if admit is not None:
                        self._prev[:] = sp
                    if self.reentry:
                        self.reentry = self._rejoin(sp, target)
                    else:
                        sp[:] = target
                    if admit is not None and not admit(sp, now):
                        sp[:] = self._prev
                        self.reentry = True
                        self.refused += 1
            self._write(sp, now, False)
        elif state in POWERED:
            if state is RobotState.STOPPED:
                # a stop in contact lets go of the tissue: the controllers may move the held
                # setpoint out of it (teleop-slave's release, issue 37)
                controller.hold(now, data.hold_setpoint)
            self._write(data.hold_setpoint, now, False)

    def _control_effort(self, state: RobotState, now: float, holding: bool) -> None:
        """Efforts while RUNNING, zero effort (the device free in the operator's hand) while
        ENABLED/STOPPED or while a watched stream is late, nothing while the drivers are off.
        Written every tick while powered, which also feeds the drives' heartbeat."""
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
        self._write(eff, now, True)

    def _rejoin(self, sp: list[float], target: Sequence[float]) -> bool:
        """Move ``sp`` toward ``target`` by at most half the velocity limits, every joint
        together along the straight line (a 6-DOF tool through a port keeps its axis there);
        True while away."""
        away = step_together(sp, target, self._reentry_step)
        if not away:
            self.reentries += 1
        return away
