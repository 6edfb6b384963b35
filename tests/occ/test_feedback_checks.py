"""The driver base's feedback checks, at their edges (docs/SAFETY.md SR-HW: feedback lost, a
jump no joint can make, an encoder frozen while the drive is told to move).

The fault matrix (test_fault_matrix.py) shows each fault stops the shipped slave; these tests
pin where each check starts and stops, on a drive whose feedback the test writes itself, so
that a check made weaker or stricter (a threshold, a unit, a comparison) fails here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import pytest

from occ.drivers import Driver, DriverState
from occ.errors import DriverError
from occ.joint import Joint, JointLimits, PIDGains


class ScriptedFeedback(Driver):
    """A drive whose encoders report what the test sets in ``feedback`` (one per joint)."""

    supported_interfaces = ("position", "effort")

    def __init__(self, joints: Sequence[Joint], **params: Any) -> None:
        interface = params.pop("command_interface", None)
        super().__init__("drive", joints, params, "fault", interface)
        self.feedback = [j.home for j in joints]

    def _read(self, now: float) -> tuple[Sequence[float], Sequence[float], Sequence[float]]:
        n = len(self.feedback)
        return list(self.feedback), [0.0] * n, [0.0] * n

    def _write(self, values: Sequence[float], now: float) -> None:
        pass


def revolute(name: str = "r", velocity: float = 2.0) -> Joint:
    return Joint(name, "revolute", JointLimits(-3.0, 3.0, velocity, 50.0))


def prismatic(name: str = "p", velocity: float = 0.1) -> Joint:
    return Joint(name, "prismatic", JointLimits(-0.5, 0.5, velocity, 50.0))


def active(*joints: Joint, **params: Any) -> ScriptedFeedback:
    d = ScriptedFeedback(list(joints), heartbeat_ms=0, **params)
    d.configure()
    d.activate()
    return d


# ------------------------------------------------------------------------- feedback lost
def test_a_joint_never_measured_stays_unmeasured_and_the_others_are_read() -> None:
    a, b = revolute("a"), revolute("b")
    d = active(a, b)
    d.feedback = [math.nan, 0.25]
    d.read(0.0)  # no fault: a joint that never reported is not "lost", it is not there yet
    assert d.state is DriverState.ACTIVE
    assert (a.measured, b.measured, b.position) == (False, True, 0.25)


def test_a_measured_joint_that_reports_nan_or_inf_faults_naming_it() -> None:
    for bad in (math.nan, math.inf, -math.inf):
        a, b = revolute("a"), revolute("b")
        d = active(a, b)
        d.read(0.0)
        d.feedback = [0.0, bad]
        with pytest.raises(DriverError, match=r"joint b: feedback lost"):
            d.read(0.001)
        assert d.state is DriverState.FAULT
        assert "joint b: feedback lost" in (d.fault_reason or "")
        assert d.stats()["errors"] == 1


# ------------------------------------------------------------------------------- jumps
def test_a_step_of_exactly_the_plausible_reach_passes_and_just_over_it_faults() -> None:
    # feedback_jump 2 x 2 rad/s over one period (1 ms): 0.004 rad in a tick (issue 36: a real
    # slip exceeds it; 10 x let a 5 x slip through)
    for sign in (1.0, -1.0):
        j = revolute(velocity=2.0)
        d = active(j)
        d.read(0.0)
        reach = 2.0 * 2.0 * 0.001
        d.feedback = [sign * reach]
        d.read(0.001)
        assert d.state is DriverState.ACTIVE  # exactly the reach: plausible
        d.feedback = [sign * (2.0 * reach + 1e-6)]
        with pytest.raises(DriverError, match=r"joint r: feedback jump of 0\.004001 in 1 ms"):
            d.read(0.002)


def test_the_reach_grows_with_the_time_since_the_last_reading_never_under_a_period() -> None:
    j = revolute(velocity=2.0)
    d = active(j)
    d.read(0.0)
    d.feedback = [0.039]  # 2 x 2 rad/s x 10 ms = 0.04 rad: plausible after 10 ms
    d.read(0.010)
    assert d.state is DriverState.ACTIVE
    # two readings 0.1 ms apart: judged over a whole period (0.004 rad), not 0.1 ms (0.0004)
    d.feedback = [0.039 + 0.003]
    d.read(0.0101)
    assert d.state is DriverState.ACTIVE
    d.feedback = [0.039 + 0.003 + 0.0041]
    with pytest.raises(DriverError, match="feedback jump"):
        d.read(0.0102)


def test_a_slow_joint_is_judged_by_its_own_velocity_limit() -> None:
    # a prismatic joint at 0.1 m/s: 0.2 mm in a tick is plausible, 0.22 mm is not (its jump
    # speed, 0.2 m/s, is not over 1: a check switched on only above 1 would miss it)
    j = prismatic(velocity=0.1)
    d = active(j)
    d.read(0.0)
    d.feedback = [0.0002]
    d.read(0.001)
    assert d.state is DriverState.ACTIVE
    d.feedback = [0.00042]
    with pytest.raises(DriverError, match="joint p: feedback jump"):
        d.read(0.002)


def test_feedback_jump_zero_or_none_switches_the_check_off() -> None:
    for off in (0, None, "0"):
        j = revolute()
        d = active(j, feedback_jump=off)
        d.read(0.0)
        d.feedback = [2.5]
        d.read(0.001)
        assert d.state is DriverState.ACTIVE


@pytest.mark.parametrize("bad", [-1.0, "ten", math.nan, [1.0]])
def test_a_feedback_check_that_is_no_number_is_refused(bad: object) -> None:
    for key in ("feedback_jump", "frozen_feedback_ms"):
        with pytest.raises(ValueError, match=f"{key} must be a number >= 0"):
            ScriptedFeedback([revolute()], **{key: bad})


# ------------------------------------------------------------------------------ frozen
def frozen_drive(joint: Joint, command: float, **params: Any) -> ScriptedFeedback:
    """A drive told to go to ``command`` whose encoder stays at 0 from t = 0 on."""
    d = active(joint, **params)
    d.feedback = [0.0]
    d.read(0.0)
    d.read(0.0)  # the same reading again: the encoder has not moved since t = 0
    d.write([command], 0.0)
    return d


def test_a_frozen_encoder_faults_once_it_has_not_moved_for_longer_than_the_window() -> None:
    d = frozen_drive(revolute(velocity=100.0), 0.05)
    d.read(50 * 1e-3)  # exactly the window (50 ms) since it last moved: not yet
    assert d.state is DriverState.ACTIVE
    with pytest.raises(DriverError, match=r"joint r: feedback frozen at 0 for 50 ms"):
        d.read(0.050 + 1e-6)
    assert d.state is DriverState.FAULT
    assert "commanded +0.05 away" in (d.fault_reason or "")


@pytest.mark.parametrize("command", [0.0051, -0.0051])
def test_frozen_either_side_of_the_command(command: float) -> None:
    d = frozen_drive(revolute(velocity=100.0), command)
    with pytest.raises(DriverError, match="feedback frozen"):
        d.read(0.051)


@pytest.mark.parametrize("command", [0.005, -0.005])
def test_a_joint_held_within_5_mrad_of_its_command_is_not_frozen(command: float) -> None:
    d = frozen_drive(revolute(velocity=100.0), command)
    d.read(1.0)
    assert d.state is DriverState.ACTIVE


def test_a_prismatic_joint_is_frozen_half_a_millimetre_from_its_command() -> None:
    d = frozen_drive(prismatic(velocity=10.0), 0.0005)
    d.read(1.0)
    assert d.state is DriverState.ACTIVE  # 0.5 mm away: a servo's lag, not frozen
    d = frozen_drive(prismatic(velocity=10.0), 0.001)
    with pytest.raises(DriverError, match="joint p: feedback frozen"):
        d.read(1.0)


def test_the_frozen_window_is_configured_in_milliseconds() -> None:
    d = frozen_drive(revolute(velocity=100.0), 0.05, frozen_feedback_ms=200)
    d.read(0.2)
    assert d.state is DriverState.ACTIVE
    with pytest.raises(DriverError, match="for 201 ms"):
        d.read(0.201)


def test_a_moving_encoder_restarts_the_window() -> None:
    d = frozen_drive(revolute(velocity=100.0), 0.05)
    d.read(0.040)
    d.feedback = [0.0001]  # it moved: the window starts again from here
    d.read(0.041)
    d.read(0.090)
    assert d.state is DriverState.ACTIVE
    with pytest.raises(DriverError, match="feedback frozen at 0.0001 for 50 ms"):
        d.read(0.0911)


def test_frozen_is_not_judged_while_inactive_or_on_an_effort_drive() -> None:
    j = revolute(velocity=100.0)
    d = active(j)
    d.feedback = [0.0]
    d.read(0.0)
    d.read(0.0)
    d.write([0.05], 0.0)
    d.deactivate()  # powered off: nothing moves the joint, so nothing is frozen
    d.read(1.0)
    assert d.state is DriverState.INACTIVE
    gains = PIDGains(kp=1.0, ki=0.0, kd=0.0)
    e = Joint("e", "revolute", JointLimits(-3.0, 3.0, 100.0, 50.0), gains=gains)
    h = active(e, command_interface="effort")  # a haptic handle: the hand moves it
    h.feedback = [0.0]
    h.read(0.0)
    h.read(0.0)
    h.write([0.05], 0.0)  # a position through its PID: still the hand's to move
    assert e.command_position == 0.05
    h.read(1.0)
    assert h.state is DriverState.ACTIVE


def test_frozen_feedback_ms_zero_switches_the_check_off() -> None:
    d = frozen_drive(revolute(velocity=100.0), 0.05, frozen_feedback_ms=0)
    d.read(10.0)
    assert d.state is DriverState.ACTIVE


# ----------------------------------------------------------------- the counts and the limit
def test_every_feedback_fault_is_counted() -> None:
    d = active(revolute())
    d.read(0.0)
    for k in range(3):
        d.feedback = [math.nan]
        with pytest.raises(DriverError, match="feedback lost"):
            d.read(0.001 * (2 * k + 1))
        d.reset()
        d.activate()
        d.feedback = [0.0]
        d.read(0.001 * (2 * k + 2))
    assert d.stats()["errors"] == 3


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_a_setpoint_step_of_exactly_the_velocity_reach_is_taken_on_a_faulting_drive(
    sign: float,
) -> None:
    # on_limit "fault": one period (1 ms) at 2 rad/s (and the 1e-9 relative slack for float
    # rounding) is the largest step; it must be taken, not faulted
    j = revolute(velocity=2.0)
    d = active(j)
    d.read(0.0)
    reach = 2.0 * (1.0 + 1e-9) * 0.001
    d.write([sign * reach], 0.001)
    assert d.state is DriverState.ACTIVE and j.command_position == sign * reach


def test_a_powered_off_joint_moved_by_hand_is_read_where_it_is() -> None:
    # configured, not active: operators still see the arm, and nothing is judged frozen
    j = revolute(velocity=2.0)
    d = ScriptedFeedback([j], heartbeat_ms=0)
    d.configure()
    d.read(0.0)
    for k in range(1, 4):
        d.feedback = [0.01 * k]  # pushed by hand, 10 mrad a tick: 5 x its velocity limit
        d.read(0.001 * k)
    assert d.state is DriverState.INACTIVE and j.position == pytest.approx(0.03)


def test_the_faults_say_how_far_in_how_long_and_the_limit() -> None:
    j = revolute(velocity=2.0)
    d = active(j)
    d.read(0.0)
    d.feedback = [0.5]
    with pytest.raises(DriverError) as jumped:
        d.read(0.005)  # 0.5 rad in 5 ms: at most 2 x 2 rad/s x 5 ms = 0.02 rad
    assert str(jumped.value) == (
        "driver 'drive': joint r: feedback jump of 0.5 in 5 ms (at most 0.02: feedback_jump "
        "2 x 2/s, the speed it may have, plus twice the noise 0)"
    )
    d = frozen_drive(revolute(velocity=100.0), 0.05)
    with pytest.raises(DriverError) as frozen:
        d.read(0.9)
    assert str(frozen.value) == (
        "driver 'drive': joint r: feedback frozen at 0 for 900 ms while commanded +0.05 away "
        "(no move beyond its noise, 0)"
    )
