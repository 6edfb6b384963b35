"""Joint, JointLimits and the PID servo law."""

from __future__ import annotations

import math

import pytest

from occ.joint import Joint, JointLimits, PIDGains, step_together


def make_joint(**gains: float) -> Joint:
    return Joint(
        "j1",
        "revolute",
        JointLimits(-1.0, 1.0, velocity=2.0, effort=5.0),
        home=0.0,
        gains=PIDGains(**gains) if gains else None,
    )


@pytest.mark.req("SR-LIM-1")
def test_limits_validate_and_clamp() -> None:
    lim = JointLimits(-0.5, 0.5, 1.0, 2.0)
    assert lim.clamp(0.7) == 0.5 and lim.clamp(-0.7) == -0.5 and lim.clamp(0.1) == 0.1
    assert lim.contains(0.5) and not lim.contains(math.nan)
    with pytest.raises(ValueError):
        JointLimits(1.0, -1.0)
    with pytest.raises(ValueError):
        JointLimits(-1.0, 1.0, velocity=0.0)
    with pytest.raises(ValueError):
        PIDGains(kp=-1.0)


def test_joint_construction_and_state() -> None:
    j = Joint("ins", "prismatic", JointLimits(0.0, 0.15), home=0.05)
    assert j.position == 0.05 and not j.measured and math.isnan(j.command_position)
    j.set_measured(0.06, 0.01, 1.5, now=2.0)
    assert (j.position, j.velocity, j.effort, j.measured, j.stamp) == (0.06, 0.01, 1.5, True, 2.0)
    with pytest.raises(ValueError):
        Joint("bad", "spherical")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        Joint("x", "prismatic", JointLimits(0.0, 0.1), home=0.2)


def test_servo_without_gains_is_a_configuration_error() -> None:
    with pytest.raises(ValueError, match="no PID gains"):
        make_joint().servo(0.1, 0.001)


def test_proportional_and_output_limit() -> None:
    j = make_joint(kp=10.0)
    assert j.servo(0.1, 0.001) == pytest.approx(1.0)
    # Output is bounded by the joint's effort limit (5) even if out_limit is larger.
    assert j.servo(1.0, 0.001) == pytest.approx(5.0)
    j2 = make_joint(kp=10.0, out_limit=2.0)
    assert j2.servo(-1.0, 0.001) == pytest.approx(-2.0)


def test_derivative_on_measurement_has_no_setpoint_kick() -> None:
    j = make_joint(kp=0.0, kd=1.0)
    j.position = 0.0
    assert j.servo(0.0, 0.001) == 0.0  # first call: no previous measurement
    # A setpoint step with the joint standing still gives no derivative action...
    assert j.servo(0.5, 0.001) == 0.0
    # ...but motion of the joint is damped: d/dt(position) = 0.001/0.001 = 1 -> -kd * 1.
    j.position = 0.001
    assert j.servo(0.5, 0.001) == pytest.approx(-1.0)


def test_integral_limit_and_conditional_integration() -> None:
    j = make_joint(kp=0.0, ki=100.0, i_limit=0.3)
    for _ in range(100):
        out = j.servo(0.1, 0.001)
    assert out == pytest.approx(0.3)  # integral term clamped to i_limit

    # Saturated output: the integrator must not wind up while saturated.
    j = make_joint(kp=100.0, ki=100.0)  # kp * 1.0 = 100 >> effort limit 5
    for _ in range(1000):
        assert j.servo(1.0, 0.001) == pytest.approx(5.0)
    assert j._integral == 0.0  # frozen while saturated in the error's direction
    # Once the error reverses, the output leaves saturation immediately.
    assert j.servo(-0.01, 0.001) < 0.0


def test_reset_servo_clears_memory() -> None:
    j = make_joint(kp=0.0, ki=10.0, kd=1.0)
    for _ in range(10):
        j.servo(0.2, 0.01)
    assert j._integral > 0.0
    j.reset_servo()
    assert j._integral == 0.0 and math.isnan(j.command_effort)
    assert j.servo(0.0, 0.01) == 0.0


def test_zero_dt_uses_p_and_held_integral_only() -> None:
    j = make_joint(kp=2.0, ki=10.0, kd=5.0)
    j.servo(0.1, 0.01)
    held = j._integral
    j.position = 0.05
    out = j.servo(0.1, 0.0)
    assert out == pytest.approx(2.0 * 0.05 + held)


def test_step_together_moves_every_joint_along_the_straight_line() -> None:
    """The farthest joint (in steps) sets the pace; the others move the same fraction of their
    way, so all arrive on the same tick, exactly on the target; none ever steps past its own
    limit, and a joint already there stays."""
    steps = [0.1, 0.2, 0.05, 0.1]
    start = [0.0, 1.0, 2.0, 3.0]
    target = [0.3, 0.2, 2.2, 3.0]  # 3, 4, 4 steps away; the last already there
    values = list(start)
    path = [list(values)]
    for _ in range(10):  # bounded: a broken rate limit must fail here, not hang
        away = step_together(values, target, steps)
        path.append(list(values))
        if not away:
            break
    assert values == target  # exactly, not within rounding
    assert len(path) == 5  # four ticks: the farthest joints' four steps
    for a, b in zip(path, path[1:]):
        assert all(abs(y - x) <= s * (1 + 1e-12) for x, y, s in zip(a, b, steps))
        # on the line: the same fraction of the way for every joint that has a way to go
        fracs = [(y - s0) / (t - s0) for y, s0, t in zip(b, start, target) if t != s0]
        assert max(fracs) - min(fracs) < 1e-12
        assert b[3] == 3.0
    # the snap to the target absorbs rounding only: a joint whose step is 1e-12 of the way
    # short of it (the tolerance's edge) still takes the step, not the target
    step = 1.0 - 1e-12
    values = [0.0]
    assert step_together(values, [1.0], [step]) is True and values == [step]
    # within one step of every joint: there at once
    values = [0.0, 0.0]
    assert not step_together(values, [0.05, -0.2], [0.1, 0.2])
    assert values == [0.05, -0.2]


@pytest.mark.parametrize("field", ["min", "max", "velocity", "effort"])
def test_a_nan_limit_is_refused_by_name(field: str) -> None:
    values = {"min": -1.0, "max": 1.0, "velocity": 1.0, "effort": 1.0, field: math.nan}
    with pytest.raises(ValueError, match=f"JointLimits.{field} must be a number, got nan"):
        JointLimits(**values)


def test_limit_edges_a_locked_joint_and_a_zero_effort() -> None:
    """min == max is a joint locked where it stands (valid); a zero effort limit would let the
    servo give nothing (refused), as a zero velocity limit would let it never move."""
    locked = JointLimits(0.2, 0.2)
    assert locked.contains(0.2) and locked.clamp(0.3) == 0.2
    with pytest.raises(ValueError, match=r"JointLimits.effort must be > 0, got 0.0"):
        JointLimits(-1.0, 1.0, effort=0.0)


@pytest.mark.parametrize("field", ["kp", "ki", "kd", "i_limit", "out_limit"])
def test_a_nan_gain_is_refused_by_name(field: str) -> None:
    values = {"kp": 1.0, field: math.nan}
    with pytest.raises(ValueError, match=f"PIDGains.{field} must be a number >= 0, got nan"):
        PIDGains(**values)


def test_an_unmeasured_joint_reports_rest_and_no_effort_sent() -> None:
    """Before any read the joint stands at home at rest with no effort measured, and no
    effort has been sent (NaN, not a number a viewer could take for one)."""
    j = Joint("yaw", "revolute", JointLimits(-1.0, 1.0), home=0.3)
    assert (j.position, j.velocity, j.effort) == (0.3, 0.0, 0.0)
    assert math.isnan(j.command_effort) and math.isnan(j.stamp)


def test_the_effort_sent_is_the_servo_output() -> None:
    j = make_joint(kp=10.0)
    out = j.servo(0.2, 0.001)
    assert j.command_effort == out == pytest.approx(2.0)


def test_a_clock_that_went_back_changes_no_integral() -> None:
    """dt < 0 (a clock stepped back): the proportional and the held integral act, the
    integrator takes nothing (a negative dt would integrate the error backwards)."""
    j = make_joint(kp=2.0, ki=10.0)
    j.servo(0.1, 0.01)
    held = j.servo(0.1, 0.0)  # dt 0: P plus the held integral
    assert j.servo(0.1, -0.01) == held


def test_a_small_integral_gain_integrates() -> None:
    j = make_joint(kp=0.0, ki=0.5)
    outs = [j.servo(0.2, 0.01) for _ in range(4)]
    assert outs == pytest.approx([0.001, 0.002, 0.003, 0.004])


def test_the_integral_term_is_clamped_both_ways() -> None:
    j = make_joint(kp=0.0, ki=100.0, i_limit=0.3)
    for _ in range(100):
        out = j.servo(-0.1, 0.001)
    assert out == pytest.approx(-0.3)


def test_the_integrator_freezes_when_the_whole_output_would_saturate() -> None:
    """Conditional integration counts the damping too: a joint pushed away from its setpoint
    (derivative term 3.5) with an integral of 1 gives 4.5, under the limit 5; the next
    integral (2.035) would take the sum to 5.535, past it, in the error's direction, so the
    integrator holds and the output is 4.5, not the limit."""
    j = make_joint(kp=0.0, ki=10000.0, kd=1.0)
    j.position = 0.0
    assert j.servo(0.1, 0.001) == pytest.approx(1.0)  # no previous measurement: no D yet
    j.position = -0.0035  # pushed away: D = -kd * (-0.0035 - 0) / 0.001 = 3.5
    assert j.servo(0.1, 0.001) == pytest.approx(4.5)


def test_an_output_exactly_at_the_limit_is_not_saturated() -> None:
    """The integrator freezes only past the limit: a sum of exactly the limit (5 N m, from
    an integral step of exactly 5 with binary-exact gains) is accepted, either way."""
    dt = 2.0**-10
    j = make_joint(kp=0.0, ki=5.0 * 1024)
    assert j.servo(1.0, dt) == 5.0
    j = make_joint(kp=0.0, ki=5.0 * 1024)
    assert j.servo(-1.0, dt) == -5.0


def test_a_saturated_output_unwinds_when_the_error_opposes_it() -> None:
    """Saturated negative by the damping (the joint moving fast toward a setpoint still
    ahead), the error positive: integrating reduces the saturation, so the integrator
    accepts it; once the joint stops, the output is the larger integral."""
    j = make_joint(kp=0.0, ki=10000.0, kd=1.0)
    j.position = 0.0
    j.servo(0.1, 0.001)  # integral 1
    j.position = 0.008  # D = -8: the sum 1.92 - 8 is past -5
    assert j.servo(0.1, 0.001) == -5.0
    out = j.servo(0.1, 0.001)  # the joint stopped: D = 0
    assert out == pytest.approx(1.92 + 0.92)


def test_every_refusal_of_a_joint_says_what_is_wrong() -> None:
    with pytest.raises(ValueError, match=r"^JointLimits: min 1.0 > max -1.0$"):
        JointLimits(1.0, -1.0)
    with pytest.raises(ValueError, match=r"^JointLimits.velocity must be > 0, got 0.0$"):
        JointLimits(-1.0, 1.0, velocity=0.0)
    with pytest.raises(ValueError, match=r"^a joint needs a non-empty name$"):
        Joint("")
    with pytest.raises(
        ValueError,
        match=r"^joint 'b': type must be one of \('revolute', 'prismatic'\), got 'spherical'$",
    ):
        Joint("b", "spherical")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"^joint 'x': home 0.2 outside limits \[0.0, 0.1\]$"):
        Joint("x", "prismatic", JointLimits(0.0, 0.1), home=0.2)
