"""What the drives are told each tick, by the robot's state (occ/core/motion.py), the policy alone
on real joints, robot data and controllers: while RUNNING the controllers' targets, held
while the stream in control is late and re-joined at half the velocity limits (never a jump);
the held setpoint while ENABLED or STOPPED; nothing while the drives are off; for a haptic
master its efforts while RUNNING and zero otherwise. Through the whole robot in simulated
time: test_robot_sim.py, test_teleop.py, test_haptic_master.py."""

from __future__ import annotations

from collections.abc import Sequence

import pytest

from occ.clock import SimClock
from occ.controllers import Controller, ControllerContext, ControllerSet
from occ.core.data import RobotData
from occ.core.hardware import HardwareSet
from occ.core.motion import POWERED, Motion
from occ.core.safety import RobotState as S
from occ.drivers.sim import SimDriver
from occ.errors import ConfigError
from occ.joint import Joint, JointLimits
from occ.kinematics.frame import Frame

PERIOD = 0.001
VMAX = (1.0, 0.5, 2.0)  # rad/s: half of it a tick is 0.5, 0.25 and 1 mrad
STEP = tuple(0.5 * v * PERIOD for v in VMAX)


class Scripted(Controller):
    """Returns the targets it is given (None: hold), counting its calls; commands positions
    or, with ``effort``, efforts; ``drives=False``: a hand-moved device (commands nothing)."""

    def __init__(
        self, effort: bool = False, drives: bool = True, joints: Sequence[int] | None = None
    ) -> None:
        super().__init__()
        self.effort = effort
        self.drives_joints = drives
        self.joints = joints  # the joints it commands (None: all)
        self.target: Sequence[float] | None = None
        self.calls: list[float] = []
        #: each ``hold`` call's time and the held setpoint as it was given
        self.holds: list[tuple[float, list[float]]] = []
        #: moved into the held setpoint by ``hold`` (a slave letting go of the tissue)
        self.release: Sequence[float] | None = None

    def command_interfaces(self) -> tuple[str, ...]:
        assert self.data is not None
        if not self.drives_joints:
            return ()
        kind = "effort" if self.effort else "position"
        names = self.data.joint_names
        idx = range(len(names)) if self.joints is None else self.joints
        return tuple(f"{names[i]}/{kind}" for i in idx)

    def update(self, now: float) -> Sequence[float] | None:
        self.calls.append(now)
        return None if self.target is None else list(self.target)

    def hold(self, now: float, setpoint: list[float]) -> None:
        self.holds.append((now, list(setpoint)))
        if self.release is not None:
            setpoint[:] = self.release


class MotionRig:
    def __init__(self, effort: bool = False, drives: bool = True, split: bool = False) -> None:
        self.joints = [
            Joint(f"j{i}", limits=JointLimits(-3.0, 3.0, velocity=v)) for i, v in enumerate(VMAX)
        ]
        clock = SimClock()
        frame = Frame.builtin("occ_slave")
        self.data = RobotData("r", [j.name for j in self.joints], (0.1, 0.2, 0.3), frame, clock)
        self.ctl = Scripted(effort, drives, [0] if split else None)
        #: with ``split``, a second controller commands the other two joints
        self.other = Scripted(effort, drives, [1, 2])
        self.set = ControllerSet([self.ctl, self.other] if split else [self.ctl])
        ctx = ControllerContext(
            clock=clock, frame=frame, rate_hz=1.0 / PERIOD, interfaces=(),
            loop_t0=lambda: 0.0, period_s=PERIOD, shift=lambda s: None,
        )  # fmt: skip
        self.set.configure(self.data, ctx)
        if effort:
            self.data.effort_command = [0.0] * 3
        self.writes: list[tuple[list[float], float, bool]] = []
        self.motion = Motion(self.data, self.set, self.joints, PERIOD, self.write)

    def write(self, values: Sequence[float], now: float, effort: bool) -> None:
        self.writes.append((list(values), now, effort))

    def enter(self, *states: S) -> None:
        """The transitions through ``states`` from INIT, as the robot makes them."""
        old = self.data.state
        for new in states:
            self.data.state = new
            self.motion.on_state(old, new)
            old = new

    def tick(self, state: S, now: float, holding: bool = False) -> list[float] | None:
        n = len(self.writes)
        self.motion.control(state, now, holding)
        assert len(self.writes) - n <= 1
        return self.writes[-1][0] if len(self.writes) > n else None


def test_the_drives_are_powered_in_enabled_running_and_stopped_only() -> None:
    assert POWERED == {S.ENABLED, S.RUNNING, S.STOPPED}


# ------------------------------------------------------------------ positions
def test_nothing_is_written_while_the_drives_are_off() -> None:
    rig = MotionRig()
    rig.ctl.target = (1.0, 1.0, 1.0)
    for state in (S.INIT, S.READY, S.FAULT, S.ESTOP, S.SHUTDOWN):
        assert rig.tick(state, 0.0) is None
    assert rig.writes == [] and rig.ctl.calls == []


def test_enabled_holds_where_the_joints_were_at_power_up() -> None:
    rig = MotionRig()
    rig.data.q[:] = [0.5, -0.5, 1.0]
    rig.enter(S.READY, S.ENABLED)
    rig.data.q[:] = [0.6, -0.4, 1.1]  # the joints sag: the hold is where they were
    rig.ctl.target = (2.0, 2.0, 2.0)
    assert rig.tick(S.ENABLED, 0.001) == [0.5, -0.5, 1.0]
    assert rig.writes[-1] == ([0.5, -0.5, 1.0], 0.001, False)
    assert rig.ctl.calls == []  # the controllers are not asked outside RUNNING


def test_running_starts_from_the_hold_and_rejoins_the_target_at_half_the_velocity_limits() -> None:
    rig = MotionRig()
    rig.enter(S.READY, S.ENABLED)
    sp = rig.data.setpoint
    rig.enter(S.RUNNING)
    assert rig.data.setpoint is sp and sp == [0.1, 0.2, 0.3] and rig.motion.reentry
    # the target 0.7, 1.5 and 2.5 steps away: every joint moves together along the straight
    # line, as fast as the farthest (2.5 steps: 0.4 of the way a tick) allows; all arrive in
    # the third tick, as the farthest would alone
    rig.ctl.target = (0.1 + 0.7 * STEP[0], 0.2 - 1.5 * STEP[1], 0.3 + 2.5 * STEP[2])
    out = rig.tick(S.RUNNING, 0.001)
    assert out == pytest.approx(
        [0.1 + 0.28 * STEP[0], 0.2 - 0.6 * STEP[1], 0.3 + STEP[2]], abs=1e-15
    )
    assert rig.motion.reentry and rig.motion.reentries == 0
    out = rig.tick(S.RUNNING, 0.002)
    assert out == pytest.approx(
        [0.1 + 0.56 * STEP[0], 0.2 - 1.2 * STEP[1], 0.3 + 2 * STEP[2]], abs=1e-15
    )
    assert rig.motion.reentry
    out = rig.tick(S.RUNNING, 0.003)
    assert out == list(rig.ctl.target)  # there: exactly the target
    assert not rig.motion.reentry and rig.motion.reentries == 1
    # joined: the targets are followed as given, a jump too (the drivers limit it)
    rig.ctl.target = (1.0, -1.0, 2.0)
    assert rig.tick(S.RUNNING, 0.004) == [1.0, -1.0, 2.0]
    assert rig.writes[-1] == ([1.0, -1.0, 2.0], 0.004, False)
    assert rig.motion.reentries == 1 and rig.ctl.calls == [0.001, 0.002, 0.003, 0.004]


@pytest.mark.req("SR-LOSS-2")
def test_a_late_stream_holds_the_setpoint_and_the_resumed_one_rejoins_without_a_jump() -> None:
    rig = MotionRig()
    rig.enter(S.READY, S.ENABLED, S.RUNNING)
    rig.ctl.target = (0.1, 0.2, 0.3)
    rig.tick(S.RUNNING, 0.001)
    assert not rig.motion.reentry and rig.motion.reentries == 1
    # late: the setpoint is held (written every tick), the controllers are not asked
    rig.ctl.target = (0.9, 0.9, 0.9)
    for k in range(2, 6):
        assert rig.tick(S.RUNNING, k * 0.001, holding=True) == [0.1, 0.2, 0.3]
    assert rig.ctl.calls == [0.001] and rig.motion.reentry
    # back: the master moved meanwhile; the robot goes there at half the limits, every joint
    # along the straight line (0.8, 0.7, 0.6 away: the second joint, 0.7 / STEP[1] steps
    # away, is the farthest and sets the pace)
    out = rig.tick(S.RUNNING, 0.006)
    f = STEP[1] / 0.7
    assert out == pytest.approx([0.1 + 0.8 * f, 0.2 + STEP[1], 0.3 + 0.6 * f], abs=1e-15)
    assert rig.motion.reentry and rig.motion.reentries == 1


def test_a_controller_that_holds_leaves_the_setpoint_where_it_is() -> None:
    rig = MotionRig()
    rig.enter(S.READY, S.ENABLED, S.RUNNING)
    rig.ctl.target = None
    assert rig.tick(S.RUNNING, 0.001) == [0.1, 0.2, 0.3]
    assert rig.motion.reentry  # still to re-join when a target comes


def test_a_stop_holds_what_the_drives_were_last_told_not_where_they_lag() -> None:
    rig = MotionRig()
    rig.enter(S.READY, S.ENABLED, S.RUNNING)
    rig.ctl.target = (0.1, 0.2, 0.3)
    rig.tick(S.RUNNING, 0.001)
    rig.ctl.target = (0.4, 0.5, 0.6)
    rig.tick(S.RUNNING, 0.002)
    rig.data.q[:] = [0.35, 0.45, 0.55]  # lagging behind the setpoint
    rig.enter(S.STOPPED)
    assert rig.data.hold_setpoint == [0.4, 0.5, 0.6]
    assert rig.data.hold_setpoint is not rig.data.setpoint
    assert rig.tick(S.STOPPED, 0.003) == [0.4, 0.5, 0.6]
    rig.data.setpoint[:] = [9.0, 9.0, 9.0]  # a copy: what the setpoint becomes is not held
    assert rig.tick(S.STOPPED, 0.004) == [0.4, 0.5, 0.6]
    # Run again: from the hold, re-joining the controllers' target at half the limits
    rig.enter(S.RUNNING)
    assert rig.data.setpoint == [0.4, 0.5, 0.6] and rig.motion.reentry
    rig.ctl.target = (0.0, 0.0, 0.0)
    out = rig.tick(S.RUNNING, 0.005)
    f = STEP[1] / 0.5  # the farthest in steps: the second joint
    assert out == pytest.approx([0.4 - 0.4 * f, 0.5 - STEP[1], 0.6 - 0.6 * f], abs=1e-15)


def test_while_stopped_the_controllers_may_move_the_held_setpoint_and_that_is_written() -> None:
    """STOPPED asks the controllers' ``hold`` each tick with its time and the held setpoint
    (a slave in contact lets go of the tissue); what they leave there is what the drives are
    told. ENABLED holds without asking them."""
    rig = MotionRig()
    rig.data.q[:] = [0.1, 0.2, 0.3]
    rig.enter(S.READY, S.ENABLED)
    assert rig.tick(S.ENABLED, 0.001) == [0.1, 0.2, 0.3]
    assert rig.ctl.holds == []  # not asked while ENABLED
    rig.enter(S.STOPPED)
    assert rig.tick(S.STOPPED, 0.002) == [0.1, 0.2, 0.3]
    assert rig.ctl.holds == [(0.002, [0.1, 0.2, 0.3])]
    rig.ctl.release = (0.1, 0.15, 0.3)  # backs off along the second joint
    assert rig.tick(S.STOPPED, 0.003) == [0.1, 0.15, 0.3]
    assert rig.ctl.holds[-1] == (0.003, [0.1, 0.2, 0.3])
    assert rig.data.hold_setpoint == [0.1, 0.15, 0.3]  # moved in place: kept on Run
    rig.ctl.release = None
    assert rig.tick(S.STOPPED, 0.004) == [0.1, 0.15, 0.3]
    assert rig.ctl.holds[-1] == (0.004, [0.1, 0.15, 0.3])


def test_running_back_to_enabled_holds_the_last_setpoint() -> None:
    rig = MotionRig()
    rig.enter(S.READY, S.ENABLED, S.RUNNING)
    rig.ctl.target = (0.1, 0.2, 0.3)
    rig.tick(S.RUNNING, 0.001)
    rig.ctl.target = (0.2, 0.3, 0.4)
    rig.tick(S.RUNNING, 0.002)
    rig.data.q[:] = [0.0, 0.0, 0.0]
    rig.enter(S.ENABLED)
    assert rig.data.hold_setpoint == [0.2, 0.3, 0.4]
    assert rig.tick(S.ENABLED, 0.003) == [0.2, 0.3, 0.4]


def test_a_stop_from_enabled_holds_where_the_joints_are() -> None:
    """ENABLED -> STOPPED (a stop before Run): nothing was told while RUNNING, the hold is
    the measured position; STOPPED -> ENABLED (Reset) keeps it."""
    rig = MotionRig()
    rig.enter(S.READY, S.ENABLED)
    rig.data.setpoint[:] = [7.0, 7.0, 7.0]
    rig.data.q[:] = [0.3, 0.2, 0.1]
    rig.enter(S.STOPPED)
    assert rig.data.hold_setpoint == [0.3, 0.2, 0.1]
    rig.data.q[:] = [0.0, 0.0, 0.0]
    rig.enter(S.ENABLED)
    assert rig.data.hold_setpoint == [0.3, 0.2, 0.1]
    assert rig.tick(S.ENABLED, 0.001) == [0.3, 0.2, 0.1]


def test_powering_up_again_after_a_fault_holds_where_the_joints_are_then() -> None:
    rig = MotionRig()
    rig.enter(S.READY, S.ENABLED, S.RUNNING)
    rig.ctl.target = (0.1, 0.2, 0.3)
    rig.tick(S.RUNNING, 0.001)
    rig.enter(S.FAULT, S.READY)
    rig.data.q[:] = [1.0, 1.5, 2.0]
    rig.enter(S.ENABLED)
    assert rig.data.hold_setpoint == [1.0, 1.5, 2.0]
    rig.data.q[:] = [0.0, 0.0, 0.0]  # a copy of q, not q
    assert rig.tick(S.ENABLED, 0.002) == [1.0, 1.5, 2.0]


def test_a_setpoint_the_collision_guard_does_not_admit_is_not_written() -> None:
    rig = MotionRig()
    seen: list[list[float]] = []
    allow = [True]

    times: list[float] = []

    def admit(sp: Sequence[float], now: float) -> bool:
        seen.append(list(sp))
        times.append(now)
        return allow[0]

    rig.motion.admit = admit
    rig.enter(S.READY, S.ENABLED, S.RUNNING)
    rig.ctl.target = (0.1, 0.2, 0.3)
    assert rig.tick(S.RUNNING, 0.001) == [0.1, 0.2, 0.3]
    rig.ctl.target = (0.2, 0.3, 0.4)
    assert rig.tick(S.RUNNING, 0.002) == [0.2, 0.3, 0.4]
    assert rig.motion.refused == 0 and not rig.motion.reentry
    assert times == [0.001, 0.002]  # each setpoint asked about at the tick's time
    # refused: the previous setpoint held, counted, and the next admitted one re-joined
    allow[0] = False
    rig.ctl.target = (1.0, 1.0, 1.0)
    assert rig.tick(S.RUNNING, 0.003) == [0.2, 0.3, 0.4]
    assert seen[-1] == [1.0, 1.0, 1.0]  # what was asked is what was refused
    assert rig.motion.refused == 1 and rig.motion.reentry
    assert rig.tick(S.RUNNING, 0.004) == [0.2, 0.3, 0.4]
    assert rig.motion.refused == 2
    allow[0] = True
    out = rig.tick(S.RUNNING, 0.005)
    f = STEP[1] / 0.7  # the farthest in steps: the second joint
    assert out == pytest.approx([0.2 + 0.8 * f, 0.3 + STEP[1], 0.4 + 0.6 * f], abs=1e-15)
    assert seen[-1] == out and rig.motion.refused == 2
    # a hold asks the guard nothing
    n = len(seen)
    rig.tick(S.RUNNING, 0.006, holding=True)
    assert len(seen) == n


def test_a_hand_moved_device_is_never_written_its_controllers_run_while_following() -> None:
    rig = MotionRig(drives=False)
    assert not rig.set.drives_joints
    rig.enter(S.READY, S.ENABLED, S.RUNNING)
    rig.ctl.target = (1.0, 1.0, 1.0)
    assert rig.tick(S.RUNNING, 0.001) is None
    assert rig.ctl.calls == [0.001]
    assert rig.tick(S.RUNNING, 0.002, holding=True) is None  # late: not asked
    assert rig.tick(S.ENABLED, 0.003) is None and rig.tick(S.STOPPED, 0.004) is None
    assert rig.ctl.calls == [0.001] and rig.writes == []


def test_joints_a_controller_holds_keep_their_setpoint_while_the_others_follow() -> None:
    """Two controllers, each commanding its own joints: one that holds (None) leaves its
    joints where the robot last told them."""
    rig = MotionRig(split=True)
    rig.enter(S.READY, S.ENABLED, S.RUNNING)
    rig.ctl.target = (0.1, 9.0, 9.0)  # only its joint 0 is taken
    rig.other.target = None
    assert rig.tick(S.RUNNING, 0.001) == [0.1, 0.2, 0.3]
    rig.ctl.target = (0.1 + STEP[0], 9.0, 9.0)
    rig.tick(S.RUNNING, 0.002)
    rig.other.target = (9.0, 0.2, 0.3)
    rig.ctl.target = None
    assert rig.tick(S.RUNNING, 0.003) == pytest.approx([0.1 + STEP[0], 0.2, 0.3], abs=1e-15)


# ------------------------------------------------------------------ efforts
def test_a_haptic_master_gets_its_efforts_while_running_and_zero_otherwise() -> None:
    rig = MotionRig(effort=True)
    assert rig.set.commands_effort
    eff = rig.data.effort_command
    assert eff is not None
    rig.ctl.target = (0.5, -0.25, 1.0)
    for state in (S.INIT, S.READY, S.FAULT, S.ESTOP):  # drives off: nothing
        assert rig.tick(state, 0.0) is None
    assert rig.ctl.calls == []
    rig.enter(S.READY, S.ENABLED)
    eff[:] = [3.0, 3.0, 3.0]
    assert rig.tick(S.ENABLED, 0.001) == [0.0, 0.0, 0.0]  # free in the operator's hand
    assert rig.writes[-1] == ([0.0, 0.0, 0.0], 0.001, True)
    rig.enter(S.RUNNING)
    assert rig.tick(S.RUNNING, 0.002) == [0.5, -0.25, 1.0]  # no re-entry ramp for forces
    assert rig.writes[-1] == ([0.5, -0.25, 1.0], 0.002, True) and eff == [0.5, -0.25, 1.0]
    assert rig.tick(S.RUNNING, 0.003, holding=True) == [0.0, 0.0, 0.0]  # late: no force
    assert rig.ctl.calls == [0.002]
    rig.ctl.target = None
    eff[:] = [3.0, 3.0, 3.0]
    assert rig.tick(S.RUNNING, 0.004) == [0.0, 0.0, 0.0]  # a controller with none: zero
    rig.ctl.target = (0.1, 0.1, 0.1)
    rig.tick(S.RUNNING, 0.005)
    rig.enter(S.STOPPED)
    assert rig.tick(S.STOPPED, 0.006) == [0.0, 0.0, 0.0]
    assert all(w[2] for w in rig.writes)  # every write an effort


def test_a_haptic_master_whose_controllers_share_the_joints_gets_each_ones_efforts() -> None:
    rig = MotionRig(effort=True, split=True)
    rig.enter(S.READY, S.ENABLED, S.RUNNING)
    eff = rig.data.effort_command
    assert eff is not None
    eff[:] = [0.7, 0.8, 0.9]  # the efforts last told
    rig.ctl.target = (1.0, 5.0, 5.0)
    rig.other.target = None
    assert rig.tick(S.RUNNING, 0.001) == [1.0, 0.8, 0.9]  # the other holds what it told
    rig.other.target = (5.0, 2.0, 3.0)
    assert rig.tick(S.RUNNING, 0.002) == [1.0, 2.0, 3.0]


# ------------------------------------------------------------------ the build check
def _drivers(effort_iface: bool, gains: bool) -> HardwareSet:
    from occ.joint import PIDGains

    g = PIDGains(kp=1.0) if gains else None
    joints = [
        Joint(f"j{i}", limits=JointLimits(-3.0, 3.0, velocity=1.0), gains=g) for i in range(3)
    ]
    ok = SimDriver("ok", joints[:1])
    drv = SimDriver("arm", joints[1:], command_interface="effort" if effort_iface else "position")
    return HardwareSet([(ok, [0]), (drv, [1, 2])])


@pytest.mark.parametrize(
    ("effort_ctl", "effort_iface", "gains", "error"),
    [
        (True, False, False, "driver 'ok': the controller commands efforts, but the driver takes "
                             "position commands (set command_interface: effort)"),
        (False, True, False, "driver 'arm': effort interface needs PID gains on joints "
                             "['j1', 'j2'] (the controller commands positions)"),
        (False, True, True, None),
        (False, False, False, None),
    ],
)  # fmt: skip
def test_a_driver_that_cannot_take_the_controllers_commands_is_refused_at_build(
    effort_ctl: bool, effort_iface: bool, gains: bool, error: str | None
) -> None:
    rig = MotionRig(effort=effort_ctl)
    hw = _drivers(effort_iface, gains)
    if error is None:
        Motion.check_command_kinds(rig.set, hw)
    else:
        with pytest.raises(ConfigError) as info:
            Motion.check_command_kinds(rig.set, hw)
        assert str(info.value) == error


def test_a_hand_moved_device_on_effort_drives_without_gains_is_accepted() -> None:
    """It commands nothing: its drives need no PID gains for positions."""
    rig = MotionRig(drives=False)
    Motion.check_command_kinds(rig.set, _drivers(True, False))


def test_efforts_to_effort_drives_need_no_gains() -> None:
    rig = MotionRig(effort=True)
    joints = [Joint(f"j{i}", limits=JointLimits(-3.0, 3.0, velocity=1.0)) for i in range(3)]
    Motion.check_command_kinds(
        rig.set, HardwareSet([(SimDriver("h", joints, command_interface="effort"), [0, 1, 2])])
    )
