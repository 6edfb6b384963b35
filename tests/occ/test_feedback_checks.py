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


class KnownNoise(ScriptedFeedback):
    """A backend that knows its encoders' noise at rest (1 mrad a joint)."""

    def _default_noise(self) -> Sequence[float] | None:
        return [0.001] * len(self.joints)


@pytest.mark.req("SR-HW-9")
def test_the_backends_own_noise_widens_the_reach_unless_feedback_noise_is_configured() -> None:
    # 2 x 2 rad/s over 1 ms is 0.004 rad; twice the backend's 1 mrad makes it 0.006
    d = KnownNoise([revolute(velocity=2.0)], heartbeat_ms=0)
    d.configure()
    d.activate()
    d.read(0.0)
    d.feedback = [0.0059]
    d.read(0.001)
    assert d.state is DriverState.ACTIVE
    d.feedback = [0.0059 + 0.0061]
    with pytest.raises(DriverError, match=r"at most 0\.006: .* plus twice the noise 0\.001\)"):
        d.read(0.002)
    # a configured feedback_noise is the backend's word no more
    d = KnownNoise([revolute(velocity=2.0)], heartbeat_ms=0, feedback_noise=0.0)
    d.configure()
    d.activate()
    d.read(0.0)
    d.feedback = [0.0059]
    with pytest.raises(DriverError, match=r"at most 0\.004: .* plus twice the noise 0\)"):
        d.read(0.001)


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
    d.read(5.0)  # however long (a window of its own would still fault here)
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
    h.read(5.0)
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


# ------------------------------------------------------- issue 36: range, dither, following
@pytest.mark.req("SR-HW-22")
def test_a_reading_outside_the_limits_by_more_than_the_margin_faults_in_every_state() -> None:
    for powered in (False, True):
        j = prismatic(velocity=10.0)  # limits [-0.5, 0.5]; default margin 2 mm
        d = ScriptedFeedback([j], heartbeat_ms=0)
        d.configure()
        if powered:
            d.activate()
        d.feedback = [0.5019]
        d.read(0.0)  # within the margin: a joint at its stop, an encoder's quantum
        assert d.state is not DriverState.FAULT and j.position == 0.5019
        d.feedback = [0.5021]
        with pytest.raises(
            DriverError,
            match=r"joint p: measured position 0\.5021 outside its "
            r"limits \[-0\.5, 0\.5\] by more than 0\.002 \(limit_margin\)",
        ):
            d.read(0.001)
        assert j.position == 0.5019  # not believed: the last reading stays


def test_the_limit_margin_is_configurable_per_joint() -> None:
    a, b = prismatic("a", 10.0), prismatic("b", 10.0)
    d = ScriptedFeedback([a, b], heartbeat_ms=0, limit_margin={"a": 0.0, "b": 0.01})
    d.configure()
    d.feedback = [0.5, 0.509]
    d.read(0.0)
    d.feedback = [0.50001, 0.509]
    with pytest.raises(DriverError, match="joint a: measured position"):
        d.read(0.001)
    with pytest.raises(ValueError, match=r"limit_margin names joints .* \(missing: \['b'\]\)"):
        ScriptedFeedback([a, b], limit_margin={"a": 0.0})


@pytest.mark.req("SR-HW-8")
def test_a_stale_reading_that_dithers_by_a_count_is_still_frozen() -> None:
    # a CAN node whose stale position toggles by one count: on today's main never frozen
    j = prismatic(velocity=10.0)
    d = active(j, feedback_noise=1e-6)
    d.feedback = [0.0]
    d.read(0.0)
    d.write([0.001], 0.0)
    for k in range(1, 50):
        d.feedback = [1e-6 * (k % 2)]
        d.read(k * 0.001)
    assert d.state is DriverState.ACTIVE
    d.feedback = [1e-6]
    with pytest.raises(
        DriverError,
        match=r"joint p: feedback frozen at 1e-06 for 51 ms .*"
        r"no move beyond its noise, 1e-06",
    ):
        d.read(0.051)


def fe_drive(joint: Joint, **fe: Any) -> ScriptedFeedback:
    d = active(joint, frozen_feedback_ms=0, feedback_jump=0, following_error=fe)
    d.feedback = [0.0]
    d.read(0.0)
    return d


@pytest.mark.req("SR-HW-14")
def test_the_following_error_faults_after_its_time_outside_the_window() -> None:
    j = prismatic(velocity=0.1)
    d = fe_drive(j, window=0.001, time_ms=3, lag_ms=0)
    for k in range(1, 20):  # the command still; the reading runs away at 0.1 mm a tick
        d.write([0.0], (k - 1) * 0.001)
        d.feedback = [1e-4 * k]
        if 1e-4 * k <= 0.001 + 1e-12 or k < 14:
            d.read(k * 0.001)  # inside the window, then outside it for less than 3 ms
            assert d.state is DriverState.ACTIVE, k
        else:
            with pytest.raises(
                DriverError,
                match=r"joint p: following error 0\.0014 beyond "
                r"its window 0\.001 for 3 ms",
            ):
                d.read(k * 0.001)
            break
    assert d.state is DriverState.FAULT


def test_back_inside_the_window_restarts_the_time() -> None:
    j = prismatic(velocity=0.1)
    d = fe_drive(j, window=0.001, time_ms=3, lag_ms=0)
    d.write([0.0], 0.0)
    for k, x in enumerate([0.002, 0.002, 0.0, 0.002, 0.002, 0.002], start=1):
        d.feedback = [x]
        d.read(k * 0.001)  # never outside for 3 ms in a row
    assert d.state is DriverState.ACTIVE


def test_the_window_widens_with_the_commanded_speed_and_the_load() -> None:
    # 20 ms of lag at 0.1 m/s widen a 0.5 mm window by 2 mm; 10 N on a 1e4 N/m servo by 1 mm
    j = prismatic(velocity=0.1)
    d = fe_drive(j, window=0.0005, time_ms=0, lag_ms=20, stiffness=1.0e4)
    for k in range(1, 200):  # a ramp at the velocity limit; the servo falls 2.4 mm behind
        x = 1e-4 * k
        d.write([x], k * 0.001)
        d.feedback = [x - 0.0024 * (1.0 - math.exp(-k / 20.0))]
        d.read(k * 0.001 + 0.0005)
    assert d.state is DriverState.ACTIVE
    d.feedback = [0.0199 - 0.0027]  # more than the window allows (0.5 + ~2 mm)
    with pytest.raises(DriverError, match="following error"):
        d.read(0.2)


def test_a_loaded_servo_is_allowed_its_give() -> None:
    class Loaded(ScriptedFeedback):
        def _read(self, now: float) -> tuple[Sequence[float], Sequence[float], Sequence[float]]:
            return list(self.feedback), [0.0], [10.0]  # 10 N pushing back

    j = prismatic(velocity=10.0)
    d = Loaded(
        [j],
        heartbeat_ms=0,
        frozen_feedback_ms=0,
        following_error={"window": 0.0005, "time_ms": 0, "stiffness": 1.0e4},
    )
    d.configure()
    d.activate()
    d.feedback = [0.0]
    d.read(0.0)
    d.write([0.0014], 0.001)
    d.read(0.5)  # 1.4 mm off: 0.5 + 10 N / 1e4 N/m = 1.5 mm allowed
    assert d.state is DriverState.ACTIVE


def test_following_error_off_and_bad_settings() -> None:
    for off in (None, False):
        d = active(prismatic(velocity=0.1), frozen_feedback_ms=0, following_error=off)
        d.feedback = [0.0]
        d.read(0.0)
        d.write([0.0], 0.0)
        d.feedback = [0.3]
        d.read(5.0)
        assert d.state is DriverState.ACTIVE
    for bad, text in [
        ({"windw": 1}, r"following_error: unknown keys \['windw'\]"),
        ({"window": 0}, r"following_error.window must be a finite number > 0"),
        ({"time_ms": -1}, r"following_error.time_ms must be a finite number >= 0"),
        ("tight", r"following_error must be a mapping"),
    ]:
        with pytest.raises(ValueError, match=text):
            ScriptedFeedback([prismatic()], following_error=bad)


def test_an_effort_drive_is_not_judged_by_a_following_error() -> None:
    gains = PIDGains(kp=1.0, ki=0.0, kd=0.0)
    e = Joint("e", "revolute", JointLimits(-3.0, 3.0, 100.0, 50.0), gains=gains)
    h = active(e, command_interface="effort", frozen_feedback_ms=0)
    h.feedback = [0.0]
    h.read(0.0)
    h.write([0.05], 0.0)
    h.read(1.0)  # the hand holds it 50 mrad away (ten windows): not the drive's error
    assert h.state is DriverState.ACTIVE


@pytest.mark.req("SR-HW-14")
def test_a_step_after_a_stall_enters_the_average_in_full_once_then_decays() -> None:
    """The commanded speed is an average over the servo's lag (5 ms here): a step after a stall
    of 7.5 ms (longer than the lag) counts in full (S / period: the window widens by lag x that,
    5 S), never more, and then decays by dt / lag a write. A joint left 10 mm from its command
    is judged outside the window exactly when 0.5 mm + 50 mm x 0.8^k falls under 10 mm: k = 8."""
    j = prismatic(velocity=10.0)
    d = fe_drive(j, window=0.0005, time_ms=0, lag_ms=5)
    d.write([0.0], 0.0)
    t = 0.0075
    d.write([0.01], t)
    d.read(t + 0.0005)  # 10 mm off, window 0.5 + 50 mm: a step the servo has yet to follow
    for k in range(1, 8):
        d.write([0.01], t + k * 0.001)
        d.read(t + k * 0.001 + 0.0005)
        assert d.state is DriverState.ACTIVE, k
    d.write([0.01], t + 0.008)
    with pytest.raises(DriverError, match=r"following error 0\.01 beyond its window 0\.00888"):
        d.read(t + 0.0085)


@pytest.mark.req("SR-HW-9")
def test_a_late_ticks_step_shown_by_a_reading_that_comes_soon_after_is_no_jump() -> None:
    """On the real clock a late tick commands the velocity limit over its longer interval
    (0.21 mm in 2.1 ms at 0.1 m/s); a drive that follows at once shows that step in the next
    reading, which may come 1 ms later or sooner: the step commanded is plausible, a slip of
    more than twice it is not (a CI run faulted a keyframe plan on the first)."""
    j = prismatic(velocity=0.1)
    d = active(j, frozen_feedback_ms=0, following_error=None)
    x = 0.0

    def tick(now: float, command: float, shown: float | None = None) -> None:
        nonlocal x
        d.feedback = [x if shown is None else shown]  # the drive has followed the last command
        d.read(now)
        d.write([command], now)
        x = command

    tick(0.0, 0.0)
    tick(0.001, 0.0001)
    tick(0.0031, 0.00031)  # late by 1.1 ms: 0.21 mm at the limit over 2.1 ms
    tick(0.004, 0.0004)  # on time: the reading shows the 0.21 mm in 0.9 ms
    tick(0.005, 0.0005)
    assert d.state is DriverState.ACTIVE
    with pytest.raises(DriverError, match="feedback jump of 0.00035 in 1 ms"):
        tick(0.006, 0.0006, shown=0.0004 + 0.00035)  # 0.35 mm for a 0.1 mm command: a slip


# ------------------------------------- what the fresh mutation run of 2026-11-29 found unchecked
@pytest.mark.req("SR-HW-9")
def test_a_jump_factor_under_one_still_judges_steps() -> None:
    # feedback_jump 0.5 x 2 rad/s over 1 ms: 1 mrad a tick; 1.5 mrad is a jump
    d = active(revolute(velocity=2.0), feedback_jump=0.5)
    d.read(0.0)
    d.feedback = [0.001]
    d.read(0.001)
    assert d.state is DriverState.ACTIVE
    d.feedback = [0.0025]
    with pytest.raises(DriverError, match=r"feedback jump of 0\.0015 in 1 ms \(at most 0\.001:"):
        d.read(0.002)


@pytest.mark.req("SR-HW-22")
def test_a_reading_exactly_at_the_limit_plus_the_margin_is_believed() -> None:
    j = prismatic(velocity=10.0)  # limits [-0.5, 0.5], margin 2 mm
    d = ScriptedFeedback([j], heartbeat_ms=0)
    d.configure()
    for x in (-0.5 - 0.002, 0.5 + 0.002):
        d.feedback = [x]
        d.read(0.0)
        assert d.state is DriverState.INACTIVE and j.position == x


@pytest.mark.req("SR-HW-9", "SR-HW-22")
def test_the_joints_after_a_failed_one_are_still_read() -> None:
    # a fault names the first joint that failed, but every joint's believable reading is taken
    for bad in (9.0, 0.5):  # out of range, then a jump
        a, b = revolute("a", velocity=2.0), revolute("b", velocity=2.0)
        d = active(a, b)
        d.read(0.0)
        d.feedback = [bad, 0.001]
        with pytest.raises(DriverError, match="joint a: "):
            d.read(0.001)
        assert a.position == 0.0 and b.position == 0.001 and b.stamp == 0.001


def test_a_first_reading_is_believed_wherever_it_is_even_when_already_stamped() -> None:
    # a CiA 402 drive stamps each reading with its sample time, so a joint not yet measured
    # may carry a stamp; its first reading is still not a jump from where it never was
    j = revolute(velocity=2.0)
    d = active(j)
    j.stamp = 0.0
    d.feedback = [2.5]
    d.read(0.001)
    assert d.state is DriverState.ACTIVE and j.measured and j.position == 2.5


@pytest.mark.req("SR-HW-9")
def test_a_servo_catching_up_after_a_stall_may_move_at_the_commanded_speed() -> None:
    # a 5 mm step after 50 ms without a write is 5 m/s over a period (the 20 ms lag's average
    # takes it in full); three writes later (no step, 5 % decay each) the servo may still move
    # 2 x 4.3 m/s x 1 ms = 8.6 mm a reading, though 2 x its 0.1 m/s allows 0.2 mm
    j = prismatic(velocity=0.1)
    d = active(j, frozen_feedback_ms=0)
    d.feedback = [0.0]
    d.read(0.0)
    d.write([0.0], 0.0)
    d.write([0.005], 0.05)
    for k in range(1, 4):
        d.write([0.005], 0.05 + 0.001 * k)
    d.read(0.053)
    d.feedback = [0.004]
    d.read(0.054)
    assert d.state is DriverState.ACTIVE and j.position == 0.004
    d.feedback = [0.0135]
    with pytest.raises(DriverError, match="feedback jump of 0.0095 in 1 ms"):
        d.read(0.055)


def test_a_jump_after_a_pause_names_its_time_in_ms() -> None:
    d = active(revolute(velocity=1.0))
    d.read(0.0)
    d.feedback = [2.5]
    with pytest.raises(DriverError, match=r"feedback jump of 2\.5 in 999 ms \(at most 1\.998:"):
        d.read(0.999)


@pytest.mark.req("SR-HW-14")
def test_a_load_either_way_widens_the_window_alike() -> None:
    class Pushed(ScriptedFeedback):
        def _read(self, now: float) -> tuple[Sequence[float], Sequence[float], Sequence[float]]:
            return list(self.feedback), [0.0], [-10.0]  # 10 N pulling

    j = prismatic(velocity=10.0)
    d = Pushed(
        [j],
        heartbeat_ms=0,
        frozen_feedback_ms=0,
        following_error={"window": 0.0005, "time_ms": 0, "stiffness": 1.0e4},
    )
    d.configure()
    d.activate()
    d.feedback = [0.0]
    d.read(0.0)
    d.write([0.0014], 0.001)
    d.read(0.5)  # 1.4 mm off: 0.5 + |-10 N| / 1e4 N/m = 1.5 mm allowed
    assert d.state is DriverState.ACTIVE


@pytest.mark.req("SR-HW-14")
def test_the_following_error_fault_says_how_long_and_its_time_ms() -> None:
    j = prismatic(velocity=0.1)
    d = fe_drive(j, window=0.001, time_ms=7, lag_ms=0)
    d.write([0.0], 0.0)
    d.feedback = [0.002]
    d.read(0.001)
    with pytest.raises(DriverError) as info:
        d.read(0.0085)
    assert str(info.value) == (
        "driver 'drive': joint p: following error 0.002 beyond its window 0.001 for 7.5 ms "
        "(following_error: measured 0.002, commanded 0, time_ms 7)"
    )


@pytest.mark.req("SR-HW-14")
def test_the_default_window_is_half_a_millimetre_or_5_mrad_by_joint_type() -> None:
    for joint, inside, outside in (
        (prismatic(velocity=0.1), 0.0005, 0.0006),
        (revolute(velocity=2.0), 0.005, 0.0051),
    ):
        d = fe_drive(joint, time_ms=0)
        d.write([0.0], 0.0)
        d.feedback = [inside]
        d.read(0.001)
        assert d.state is DriverState.ACTIVE
        d.feedback = [outside]
        with pytest.raises(DriverError, match="following error"):
            d.read(0.002)


class KnownServo(ScriptedFeedback):
    """A backend that knows its servo: no lag behind a moving command, 1e4 N/m stiff."""

    def _following_model(self) -> tuple[Sequence[float], Sequence[float | None]] | None:
        return [0.0] * len(self.joints), [1.0e4] * len(self.joints)


@pytest.mark.req("SR-HW-14")
def test_the_backends_servo_model_sets_the_lag() -> None:
    # no lag: a moving command widens nothing, so 1 mm behind a 0.5 mm window faults
    j = prismatic(velocity=0.1)
    d = KnownServo(
        [j], heartbeat_ms=0, frozen_feedback_ms=0, following_error={"window": 0.0005, "time_ms": 0}
    )
    d.configure()
    d.activate()
    d.feedback = [0.0]
    d.read(0.0)
    for k in range(1, 11):
        d.write([1e-4 * k], 0.001 * k)
    with pytest.raises(DriverError, match=r"beyond its window 0\.0005 "):
        d.read(0.0105)


def test_every_per_joint_setting_refused_names_the_driver_the_key_and_the_fault() -> None:
    both = [revolute("r"), revolute("s")]
    for params, text in [
        (
            {"feedback_noise": {"r": 0.1, "x": 0.2}},
            "driver 'drive': feedback_noise names joints ['r', 'x']; its joints are ['r', 's'] "
            "(unknown: ['x']) (missing: ['s'])",
        ),
        (
            {"limit_margin": {"r": 0.1, "s": 0.1, "x": 0.2}},
            "driver 'drive': limit_margin names joints ['r', 's', 'x']; its joints are "
            "['r', 's'] (unknown: ['x'])",
        ),
        (
            {"feedback_noise": {"r": 0.1}},
            "driver 'drive': feedback_noise names joints ['r']; its joints are ['r', 's'] "
            "(missing: ['s'])",
        ),
        (
            {"feedback_noise": {"r": 0.1, "s": "ten"}},
            "driver 'drive': feedback_noise.s must be a finite number >= 0, got 'ten'",
        ),
        (
            {"following_error": {"window": {"r": 0.001, "s": 0}}},
            "driver 'drive': following_error.window.s must be a finite number > 0, got 0",
        ),
        (
            {"following_error": {"window": -1}},
            "driver 'drive': following_error.window must be a finite number > 0, got -1",
        ),
        (
            {"feedback_noise": -1.0},
            "driver 'drive': feedback_noise must be a finite number >= 0, got -1.0",
        ),
        (
            {"feedback_noise": "ten"},
            "driver 'drive': feedback_noise must be a number or {joint: number}, got 'ten'",
        ),
        (
            {"limit_margin": -1},
            "driver 'drive': limit_margin must be a finite number >= 0, got -1",
        ),
        (
            {"feedback_jump": -1},
            "driver 'drive': feedback_jump must be a number >= 0 (0 = off), got -1",
        ),
        (
            {"frozen_feedback_ms": -1},
            "driver 'drive': frozen_feedback_ms must be a number >= 0 (0 = off), got -1",
        ),
        (
            {"following_error": {"time_ms": -1}},
            "driver 'drive': following_error.time_ms must be a finite number >= 0, got -1",
        ),
        (
            {"following_error": {"lag_ms": -1}},
            "driver 'drive': following_error.lag_ms must be a finite number >= 0, got -1",
        ),
        (
            {"following_error": {"stiffness": 0}},
            "driver 'drive': following_error.stiffness must be a finite number > 0, got 0",
        ),
    ]:
        with pytest.raises(ValueError) as info:
            ScriptedFeedback(both, **params)
        assert str(info.value) == text


@pytest.mark.req("SR-HW-14")
def test_the_window_is_widened_by_twice_the_noise_and_the_load_over_the_stiffness() -> None:
    class Loaded(ScriptedFeedback):
        def _read(self, now: float) -> tuple[Sequence[float], Sequence[float], Sequence[float]]:
            return list(self.feedback), [0.0], [10.0]  # 10 N pushing back

    def drive(**fe: Any) -> ScriptedFeedback:
        d = Loaded(
            [prismatic(velocity=10.0)],
            heartbeat_ms=0,
            frozen_feedback_ms=0,
            feedback_jump=0,
            feedback_noise=0.0001,
            following_error={"window": 0.0005, "time_ms": 0, **fe},
        )
        d.configure()
        d.activate()
        d.feedback = [0.0]
        d.read(0.0)
        d.write([0.0], 0.001)
        return d

    # without a stiffness the load widens nothing: 0.5 + 2 x 0.1 mm
    d = drive()
    d.feedback = [0.0007]
    d.read(0.002)
    assert d.state is DriverState.ACTIVE
    d.feedback = [0.00071]
    with pytest.raises(DriverError, match=r"beyond its window 0\.0007 "):
        d.read(0.003)
    # 10 N on 1e4 N/m: 1 mm more, and not a hair beyond it
    d = drive(stiffness=1.0e4)
    d.feedback = [0.0017]
    d.read(0.002)
    assert d.state is DriverState.ACTIVE
    d.feedback = [0.00171]
    with pytest.raises(DriverError, match=r"beyond its window 0\.0017 "):
        d.read(0.003)
