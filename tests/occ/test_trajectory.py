"""occ.kinematics.trajectory: keyframes met at their times, rest where promised, continuous velocity, and the
German Heart Center sigmoid (normalised) with its half-speed point and area rule."""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from occ.kinematics.trajectory import Keyframe, Trajectory, plan, ramp_integral, ramp_speed

COMBOS = list(itertools.product(("linear", "spline"), ("stop", "continuous")))

# a corner, a long and a short segment, a start later than 0: the awkward cases together
KEYFRAMES = [
    Keyframe(t=0.5, pose=[0.0, 0.0, 0.0]),
    Keyframe(t=1.5, pose=[0.10, 0.0, 0.02]),
    Keyframe(t=4.0, pose=[0.10, 0.20, 0.02]),
    Keyframe(t=4.6, pose=[-0.05, 0.15, 0.0]),
    Keyframe(t=5.0, pose=[-0.05, 0.15, 0.01]),
]


def _numeric_integral(f, a: float, b: float, pieces: int = 400) -> float:
    """Composite 5-point Gauss-Legendre: independent of the closed forms under test."""
    x, w = np.polynomial.legendre.leggauss(5)
    edges = np.linspace(a, b, pieces + 1)
    total = 0.0
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        total += half * sum(wi * f(mid + half * xi) for xi, wi in zip(x, w, strict=True))
    return total


# --------------------------------------------------------------------------- the sigmoid


@pytest.mark.parametrize("n", [0.01, 1.0, 6.0, 12.0, 60.0])
@pytest.mark.parametrize("t_a", [0.2, 1.0, 3.7])
def test_sigmoid_ends_half_point_and_area(n: float, t_a: float) -> None:
    assert ramp_speed(0.0, t_a, n) == 0.0
    assert ramp_speed(t_a, t_a, n) == 1.0
    assert ramp_speed(t_a / 2, t_a, n) == pytest.approx(0.5, abs=1e-12)
    # point symmetry about (t_a/2, 1/2): what makes the area exactly half
    for frac in (0.1, 0.3, 0.45):
        t = frac * t_a
        assert ramp_speed(t, t_a, n) + ramp_speed(t_a - t, t_a, n) == pytest.approx(1.0, abs=1e-12)
    area = _numeric_integral(lambda t: ramp_speed(t, t_a, n), 0.0, t_a)
    assert area == pytest.approx(t_a / 2, rel=1e-9)
    assert ramp_integral(t_a, t_a, n) == pytest.approx(t_a / 2, rel=1e-12)


@pytest.mark.parametrize("n", [0.01, 1.0, 6.0, 12.0, 60.0])
def test_sigmoid_closed_form_integral_matches_numeric(n: float) -> None:
    t_a = 1.3
    for t in np.linspace(0.0, t_a, 14)[1:]:
        numeric = _numeric_integral(lambda u: ramp_speed(u, t_a, n), 0.0, float(t), pieces=200)
        assert ramp_integral(float(t), t_a, n) == pytest.approx(numeric, rel=1e-9, abs=1e-12)


def test_sigmoid_monotone_and_steepness_changes_shape() -> None:
    xs = np.linspace(0.0, 1.0, 101)
    for n in (0.5, 6.0, 30.0):
        s = [ramp_speed(float(x), 1.0, n) for x in xs]
        assert all(b >= a for a, b in itertools.pairwise(s))
    # steeper: slower at first, faster through the middle; n -> 0 tends to a straight ramp
    q = [ramp_speed(0.25, 1.0, n) for n in (0.01, 2.0, 6.0, 20.0)]
    assert q[0] == pytest.approx(0.25, abs=1e-4)
    assert q[0] > q[1] > q[2] > q[3] > 0.0
    # the raw (unnormalised) logistic would start at 1/(1 + e^n): normalising removes that step
    assert 1.0 / (1.0 + math.exp(6.0)) > 2e-3


def test_bad_steepness_refused() -> None:
    for n in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="steepness"):
            ramp_speed(0.1, 1.0, n)
        with pytest.raises(ValueError, match="steepness"):
            plan(KEYFRAMES, steepness=n)


# --------------------------------------------------------------------------- keyframes and rest


@pytest.mark.parametrize(("interpolation", "mode"), COMBOS)
def test_every_keyframe_met_at_its_time(interpolation: str, mode: str) -> None:
    traj = plan(KEYFRAMES, interpolation, mode)  # type: ignore[arg-type]
    for k in KEYFRAMES:
        np.testing.assert_allclose(traj.position(k.t), k.pose, rtol=0, atol=1e-6)
        # reached from the segment before as well (its formula evaluated at its very end)
        before = math.nextafter(k.t, -math.inf)
        np.testing.assert_allclose(traj.position(before), k.pose, rtol=0, atol=1e-6)
    assert traj.start == 0.5 and traj.end == 5.0 and traj.duration == 4.5


@pytest.mark.parametrize(("interpolation", "mode"), COMBOS)
def test_rest_at_start_and_end_and_holds_outside(interpolation: str, mode: str) -> None:
    traj = plan(KEYFRAMES, interpolation, mode)  # type: ignore[arg-type]
    first, last = KEYFRAMES[0], KEYFRAMES[-1]
    for t in (first.t - 1.0, 0.0, first.t):
        np.testing.assert_array_equal(traj.position(t), first.pose)
        np.testing.assert_array_equal(traj.velocity(t), np.zeros(3))
    for t in (last.t, last.t + 10.0):
        np.testing.assert_array_equal(traj.position(t), last.pose)
        np.testing.assert_array_equal(traj.velocity(t), np.zeros(3))
    # starts and ends from rest continuously (not with a step in speed)
    assert traj.speed(first.t + 1e-6) < 1e-6
    assert traj.speed(math.nextafter(last.t, -math.inf)) < 1e-9


@pytest.mark.parametrize("interpolation", ["linear", "spline"])
def test_stop_mode_rests_at_every_keyframe(interpolation: str) -> None:
    traj = plan(KEYFRAMES, interpolation, "stop")  # type: ignore[arg-type]
    for k in KEYFRAMES:
        assert traj.speed(k.t) == 0.0
        assert traj.speed(math.nextafter(k.t, -math.inf)) < 1e-9
        assert traj.speed(k.t + 1e-7) < 1e-6


@pytest.mark.parametrize("interpolation", ["linear", "spline"])
def test_continuous_mode_moves_through_interior_keyframes(interpolation: str) -> None:
    traj = plan(KEYFRAMES, interpolation, "continuous")  # type: ignore[arg-type]
    for k in KEYFRAMES[1:-1]:
        assert traj.speed(k.t) > 1e-3


# --------------------------------------------------------------------------- continuity


def _dense(traj: Trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ts = np.linspace(traj.start - 0.1, traj.end + 0.1, 6001)
    pos, vel = traj.sample(ts)
    return ts, pos, vel


@pytest.mark.parametrize(("interpolation", "mode"), COMBOS)
def test_velocity_is_the_derivative_of_position(interpolation: str, mode: str) -> None:
    traj = plan(KEYFRAMES, interpolation, mode)  # type: ignore[arg-type]
    h = 1e-6
    corners = {k.t for k in KEYFRAMES[1:-1]} if (interpolation, mode) == COMBOS[1] else set()
    vmax = max(traj.speed(float(t)) for t in np.linspace(traj.start, traj.end, 200))
    for t in np.linspace(traj.start + 2 * h, traj.end - 2 * h, 997).tolist():
        if any(abs(t - c) < 2 * h for c in corners):
            continue
        numeric = (traj.position(t + h) - traj.position(t - h)) / (2 * h)
        np.testing.assert_allclose(traj.velocity(t), numeric, rtol=0, atol=1e-6 * vmax)


@pytest.mark.parametrize(("interpolation", "mode"), COMBOS)
def test_velocity_has_no_jumps(interpolation: str, mode: str) -> None:
    traj = plan(KEYFRAMES, interpolation, mode)  # type: ignore[arg-type]
    ts, _, vel = _dense(traj)
    dt = ts[1] - ts[0]
    speed = np.linalg.norm(vel, axis=1)
    # the speed never jumps: bounded steps (the peak acceleration times dt, with margin)
    acc = np.abs(np.diff(speed)) / dt
    assert acc.max() < 50.0
    jumps = np.linalg.norm(np.diff(vel, axis=0), axis=1) / dt
    if (interpolation, mode) != ("linear", "continuous"):
        assert jumps.max() < 50.0
    else:
        # the documented corner: direction changes at interior keyframes only, speed does not
        big = ts[1:][jumps > 50.0]
        assert len(big) > 0
        for t in big:
            assert min(abs(t - k.t) for k in KEYFRAMES[1:-1]) <= dt


def test_linear_continuous_corner_keeps_speed_changes_direction() -> None:
    traj = plan(KEYFRAMES, "linear", "continuous")
    k = KEYFRAMES[1]
    before, after = traj.velocity(k.t - 1e-9), traj.velocity(k.t)
    assert np.linalg.norm(before) == pytest.approx(np.linalg.norm(after), rel=1e-6)
    d_in = np.subtract(KEYFRAMES[1].pose, KEYFRAMES[0].pose)
    d_out = np.subtract(KEYFRAMES[2].pose, KEYFRAMES[1].pose)
    cos_in = before @ d_in / (np.linalg.norm(before) * np.linalg.norm(d_in))
    cos_out = after @ d_out / (np.linalg.norm(after) * np.linalg.norm(d_out))
    assert cos_in == pytest.approx(1.0) and cos_out == pytest.approx(1.0)


@pytest.mark.parametrize("mode", ["stop", "continuous"])
def test_closed_form_position_is_the_integral_of_velocity(mode: str) -> None:
    traj = plan(KEYFRAMES, "linear", mode)  # type: ignore[arg-type]
    # the acceleration steps where a ramp starts or ends (the normalised sigmoid's residual
    # slope): integrate piecewise between those instants so the quadrature stays exact
    breaks = set()
    for a, b in itertools.pairwise(k.t for k in KEYFRAMES):
        breaks |= {a, a + traj.ramp * (b - a), b - traj.ramp * (b - a), b}
    for t in (0.7, 1.2, 2.0, 3.9, 4.55, 4.9):
        edges = sorted(x for x in breaks | {t} if x <= t)
        for axis in range(3):
            moved = sum(
                _numeric_integral(lambda u, a=axis: traj.velocity(u)[a], lo, hi, pieces=40)
                for lo, hi in itertools.pairwise(edges)
            )
            assert traj.position(t)[axis] - KEYFRAMES[0].pose[axis] == pytest.approx(
                moved, abs=1e-12
            )


def test_stop_profile_is_the_papers_ramp_cruise_ramp() -> None:
    # one segment of length 2 in 4 s, ramps of 1 s: v0 = L / (T - t_a/2 - t_b/2) = 2 / 3
    traj = plan([Keyframe(0.0, [0.0]), Keyframe(4.0, [2.0])], "linear", "stop", steepness=8.0)
    v0 = 2.0 / 3.0
    assert traj.velocity(0.5)[0] == pytest.approx(v0 / 2, rel=1e-12)  # half speed at t_a/2
    assert traj.velocity(1.0)[0] == pytest.approx(v0, rel=1e-12)
    assert traj.velocity(2.0)[0] == pytest.approx(v0, rel=1e-12)
    assert traj.velocity(3.5)[0] == pytest.approx(v0 / 2, rel=1e-12)
    assert traj.position(1.0)[0] == pytest.approx(v0 * 0.5, rel=1e-12)  # area t_a v0 / 2
    assert traj.velocity(0.25)[0] == pytest.approx(v0 * ramp_speed(0.25, 1.0, 8.0), rel=1e-12)


def test_spline_continuous_interior_is_the_spline_in_time() -> None:
    # more keyframes than segments with ramps: the middle segments play the natural spline as is
    frames = [Keyframe(float(i), [math.sin(i), math.cos(i)]) for i in range(6)]
    traj = plan(frames, "spline", "continuous")
    ts, pos, vel = _dense(traj)
    acc = np.diff(vel, axis=0) / (ts[1] - ts[0])
    inner = (ts[1:] > 1.1) & (ts[1:] < 3.9)
    # C2 inside: acceleration itself continuous (no step larger than jerk * dt)
    assert np.abs(np.diff(acc[inner], axis=0)).max() < 0.05


def test_arc_length_spline_stop_has_profile_speed() -> None:
    # in stop mode a spline segment is played at the profile's speed along its arc length
    traj = plan(KEYFRAMES, "spline", "stop")
    seg = 1
    length = traj.lengths[seg]
    T = KEYFRAMES[seg + 1].t - KEYFRAMES[seg].t
    v0 = length / (T - 0.25 * T)
    mid = 0.5 * (KEYFRAMES[seg].t + KEYFRAMES[seg + 1].t)
    # to the arc-length table's accuracy (velocity is the derivative of the commanded position)
    assert traj.speed(mid) == pytest.approx(v0, rel=1e-5)
    worst = max(
        abs(traj.speed(t) - v0) / v0
        for t in np.linspace(KEYFRAMES[seg].t + 0.25 * T, KEYFRAMES[seg + 1].t - 0.25 * T, 500)
    )
    assert worst < 1e-5
    travelled = _numeric_integral(traj.speed, KEYFRAMES[seg].t, KEYFRAMES[seg + 1].t, pieces=200)
    assert travelled == pytest.approx(length, rel=1e-5)


# --------------------------------------------------------------------------- validation


def test_invalid_input_raises_value_error() -> None:
    ok = [Keyframe(0.0, [0.0, 0.0]), Keyframe(1.0, [1.0, 0.0])]
    with pytest.raises(ValueError, match="at least 2"):
        plan(ok[:1])
    with pytest.raises(ValueError, match="at least 2"):
        plan([])
    with pytest.raises(ValueError, match="strictly increasing"):
        plan([ok[0], Keyframe(0.0, [1.0, 1.0])])
    with pytest.raises(ValueError, match="strictly increasing"):
        plan([ok[1], ok[0]])
    with pytest.raises(ValueError, match="dimension"):
        plan([ok[0], Keyframe(1.0, [1.0, 0.0, 0.0])])
    with pytest.raises(ValueError, match="finite"):
        Keyframe(math.nan, [0.0])
    with pytest.raises(ValueError, match="finite"):
        Keyframe(0.0, [0.0, math.inf])
    with pytest.raises(ValueError, match="non-empty vector"):
        Keyframe(0.0, [])
    with pytest.raises(ValueError, match="non-empty vector"):
        Keyframe(0.0, [[0.0, 1.0]])
    with pytest.raises(ValueError, match="numeric"):
        Keyframe(0.0, ["a"])
    with pytest.raises(ValueError, match="interpolation"):
        plan(ok, interpolation="cubic")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="mode"):
        plan(ok, mode="pause")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="ramp"):
        plan(ok, ramp=0.6)
    with pytest.raises(ValueError, match="ramp"):
        plan(ok, ramp=0.0)
    with pytest.raises(ValueError, match="not a Keyframe"):
        plan([ok[0], (1.0, [0.0, 0.0])])  # type: ignore[list-item]


def test_keyframe_pose_is_an_immutable_float_tuple() -> None:
    k = Keyframe(t=1, pose=np.array([1, 2, 3]))
    assert k.t == 1.0 and k.pose == (1.0, 2.0, 3.0)
    with pytest.raises(AttributeError):
        k.t = 2.0  # type: ignore[misc]


def test_standing_still_between_equal_poses() -> None:
    frames = [Keyframe(0.0, [1.0]), Keyframe(1.0, [1.0]), Keyframe(2.0, [2.0])]
    for interpolation, mode in COMBOS:
        traj = plan(frames, interpolation, mode)  # type: ignore[arg-type]
        for k in frames:
            np.testing.assert_allclose(traj.position(k.t), k.pose, atol=1e-6)
        _, pos, vel = _dense(traj)
        assert np.isfinite(pos).all() and np.isfinite(vel).all()


# --------------------------------------------------------------------------- property


@st.composite
def keyframe_sets(draw: st.DrawFn) -> list[Keyframe]:
    count = draw(st.integers(2, 6))
    dim = draw(st.integers(1, 4))
    t = draw(st.floats(0.0, 10.0))
    coords = st.floats(-1.0, 1.0, allow_nan=False)
    frames = []
    for _ in range(count):
        frames.append(Keyframe(t, draw(st.lists(coords, min_size=dim, max_size=dim))))
        t += draw(st.floats(0.05, 5.0))
    return frames


@settings(max_examples=60, deadline=None)
@given(
    frames=keyframe_sets(),
    combo=st.sampled_from(COMBOS),
    steepness=st.floats(0.1, 40.0),
    ramp=st.floats(0.05, 0.5),
)
def test_property_keyframes_met_and_speeds_finite(
    frames: list[Keyframe], combo: tuple[str, str], steepness: float, ramp: float
) -> None:
    interpolation, mode = combo
    traj = plan(frames, interpolation, mode, steepness=steepness, ramp=ramp)  # type: ignore[arg-type]
    for k in frames:
        np.testing.assert_allclose(traj.position(k.t), k.pose, rtol=0, atol=1e-6)
        before = math.nextafter(k.t, -math.inf)
        np.testing.assert_allclose(traj.position(before), k.pose, rtol=0, atol=1e-6)
        if mode == "stop":
            assert traj.speed(k.t) == 0.0
    ts = np.linspace(traj.start, traj.end, 301)
    pos, vel = traj.sample(ts)
    assert np.isfinite(pos).all() and np.isfinite(vel).all()
    assert traj.speed(traj.start) == 0.0 and traj.speed(traj.end) == 0.0


# ------------------------------------------------------------------ orientation (issue 28)
def _quat(axis: tuple[float, float, float], angle: float) -> tuple[float, float, float, float]:
    n = math.sqrt(sum(a * a for a in axis))
    s = math.sin(angle / 2.0)
    return (axis[0] / n * s, axis[1] / n * s, axis[2] / n * s, math.cos(angle / 2.0))


def _angle(a: Any, b: Any) -> float:
    d = abs(float(np.dot(a, b)))
    return 2.0 * math.acos(min(1.0, d))


ORIENTED = [
    Keyframe(0.0, [0.0, 0.0, 0.0], _quat((0, 0, 1), 0.0)),
    Keyframe(2.0, [0.1, 0.0, 0.0], _quat((0, 0, 1), 1.2)),
    Keyframe(3.0, [0.1, 0.0, 0.0], _quat((1, 0, 0), 0.8)),  # a turn in place
    Keyframe(5.0, [0.1, 0.05, 0.02], _quat((0, 1, 1), -0.5)),
]


@pytest.mark.parametrize("interpolation", ["linear", "spline"])
@pytest.mark.parametrize("mode", ["stop", "continuous"])
def test_orientation_is_met_exactly_at_every_keyframe(interpolation: str, mode: str) -> None:
    traj = plan(ORIENTED, interpolation=interpolation, mode=mode)  # type: ignore[arg-type]
    for k in ORIENTED:
        q = traj.orientation(k.t)
        assert _angle(q, k.rotation) < 1e-9, (k.t, q, k.rotation)
        assert abs(float(np.linalg.norm(q)) - 1.0) < 1e-12
    # and just before each: the approach is continuous (no jump into the keyframe)
    for k in ORIENTED[1:]:
        assert _angle(traj.orientation(k.t - 1e-6), k.rotation) < 1e-4


def test_orientation_turns_with_the_positions_sigmoid_timing() -> None:
    """On a stop segment the turned share of the angle is the travelled share of the path: the
    same sigmoid ramps, at rest at both keyframes."""
    traj = plan(ORIENTED[:2], interpolation="linear", mode="stop")
    for t in (0.1, 0.5, 1.0, 1.5, 1.9):
        share_path = float(traj.position(t)[0]) / 0.1
        share_angle = _angle(traj.orientation(t), ORIENTED[0].rotation) / 1.2
        assert share_angle == pytest.approx(share_path, abs=1e-9)
    # a turn in place (no path): its own resting profile, symmetric, half way at mid time
    traj_turn = plan(ORIENTED[1:3])
    mid = _angle(traj_turn.orientation(2.5), ORIENTED[1].rotation)
    assert mid == pytest.approx(_angle(ORIENTED[1].rotation, ORIENTED[2].rotation) / 2, rel=1e-9)
    assert traj_turn.orientation(2.0) == pytest.approx(np.array(ORIENTED[1].rotation))


def test_squad_has_no_angular_velocity_step_at_an_interior_keyframe() -> None:
    """Spline + continuous: the angular velocity just before and just after an interior
    keyframe agree (slerp's would step: it is piecewise geodesic)."""
    frames = [ORIENTED[0], ORIENTED[1], Keyframe(4.0, [0.2, 0.0, 0.0], _quat((0, 0, 1), 2.0))]
    h = 1e-5

    def omega(traj: Any, t: float) -> float:
        return _angle(traj.orientation(t + h), traj.orientation(t - h)) / (2 * h)

    sq = plan(frames, interpolation="spline", mode="continuous")
    assert omega(sq, 2.0 - 1e-3) == pytest.approx(omega(sq, 2.0 + 1e-3), rel=0.02)


def test_orientation_all_or_none_and_unit() -> None:
    with pytest.raises(ValueError, match="keyframe 1 has no rotation"):
        plan([ORIENTED[0], Keyframe(1.0, [0.0, 0.0, 0.0])])
    with pytest.raises(ValueError, match="unit quaternion"):
        Keyframe(0.0, [0.0], (0.0, 0.0, 0.0, 2.0))
    with pytest.raises(ValueError, match="no orientation"):
        plan([Keyframe(0.0, [0.0]), Keyframe(1.0, [1.0])]).orientation(0.5)
