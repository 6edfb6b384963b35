"""occ.kinematics.trajectory: the promises mutation testing found unchecked (issue 29).

Each test states a behaviour the planner documents (module docstring of occ/kinematics/trajectory.py) and
checks it against an independent computation: the natural cubic spline solved here as a dense
linear system, Shoemake's squad written here with quaternions as (w, v) pairs, the turn of a
quaternion measured as an angle. docs/VERIFICATION.md ("occ/kinematics/trajectory.py") lists what each
one kills.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import pytest

from occ.kinematics.trajectory import Keyframe, _slerp, plan, ramp_integral

# --------------------------------------------------------------------------- helpers


def _quat(axis: Sequence[float], angle: float) -> tuple[float, float, float, float]:
    n = math.sqrt(sum(a * a for a in axis))
    s = math.sin(angle / 2.0)
    return (axis[0] / n * s, axis[1] / n * s, axis[2] / n * s, math.cos(angle / 2.0))


def _turn(a: Any, b: Any) -> float:
    """The rotation angle from a to b (radians), precise for tiny angles too: from the vector
    part of a^-1 b, not from an arc cosine."""
    w1, v1 = a[3], np.asarray(a[:3], dtype=float)
    w2, v2 = b[3], np.asarray(b[:3], dtype=float)
    # conj(a) * b as (w, v)
    w = w1 * w2 + float(v1 @ v2)
    v = w1 * v2 - w2 * v1 - np.cross(v1, v2)
    return 2.0 * math.atan2(float(np.linalg.norm(v)), abs(w))


# quaternions as (w, v): an implementation of its own, not the module's (x, y, z, w) helpers
def _wv(q: Any) -> tuple[float, np.ndarray]:
    return float(q[3]), np.asarray(q[:3], dtype=float)


def _xyzw(w: float, v: np.ndarray) -> np.ndarray:
    return np.array([v[0], v[1], v[2], w])


def _mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    wa, va = _wv(a)
    wb, vb = _wv(b)
    return _xyzw(wa * wb - float(va @ vb), wa * vb + wb * va + np.cross(va, vb))


def _inv(q: np.ndarray) -> np.ndarray:
    w, v = _wv(q)
    return _xyzw(w, -v)


def _log(q: np.ndarray) -> np.ndarray:
    w, v = _wv(q)
    s = float(np.linalg.norm(v))
    if s == 0.0:
        return np.zeros(3)
    return v / s * math.acos(max(-1.0, min(1.0, w)))


def _exp(v: np.ndarray) -> np.ndarray:
    a = float(np.linalg.norm(v))
    if a == 0.0:
        return _xyzw(1.0, np.zeros(3))
    return _xyzw(math.cos(a), v / a * math.sin(a))


def _power(q: np.ndarray, u: float) -> np.ndarray:
    return _exp(u * _log(q))


def _ref_slerp(a: np.ndarray, b: np.ndarray, u: float) -> np.ndarray:
    if float(a @ b) < 0.0:
        b = -b
    return _mul(a, _power(_mul(_inv(a), b), u))


def _ref_squad(qs: list[np.ndarray], i: int, u: float) -> np.ndarray:
    """Shoemake's squad on segment i at share u, control points from their definition."""

    def control(k: int) -> np.ndarray:
        if k in (0, len(qs) - 1):
            return qs[k]
        inv = _inv(qs[k])
        tangent = _log(_mul(inv, qs[k + 1])) + _log(_mul(inv, qs[k - 1]))
        return _mul(qs[k], _exp(-tangent / 4.0))

    return _ref_slerp(
        _ref_slerp(qs[i], qs[i + 1], u),
        _ref_slerp(control(i), control(i + 1), u),
        2.0 * u * (1.0 - u),
    )


def _aligned(rots: Sequence[Any]) -> list[np.ndarray]:
    """Each quaternion the same sign as the one before (as the planner documents)."""
    qs: list[np.ndarray] = []
    for r in rots:
        q = np.array(r, dtype=float)
        qs.append(-q if qs and float(q @ qs[-1]) < 0.0 else q)
    return qs


def _gauss(f: Callable[[float], float], a: float, b: float, pieces: int = 2000) -> float:
    x, w = np.polynomial.legendre.leggauss(5)
    edges = np.linspace(a, b, pieces + 1)
    mids, half = 0.5 * (edges[:-1] + edges[1:]), 0.5 * np.diff(edges)
    pts = mids[:, None] + half[:, None] * x[None, :]
    vals = np.vectorize(f)(pts)
    return float(np.sum(half * (vals @ w)))


def _natural_spline(times: list[float], points: np.ndarray) -> tuple[Callable, Callable]:
    """C(t) and C'(t) of the natural cubic spline through ``points``, from the textbook
    second-derivative form, solved as one dense system (not the module's Thomas sweep)."""
    n = len(times)
    h = np.diff(times)
    a = np.zeros((n, n))
    rhs = np.zeros((n, points.shape[1]))
    a[0, 0] = a[-1, -1] = 1.0  # natural: C'' = 0 at both ends
    for i in range(1, n - 1):
        a[i, i - 1], a[i, i], a[i, i + 1] = h[i - 1], 2.0 * (h[i - 1] + h[i]), h[i]
        rhs[i] = 6.0 * ((points[i + 1] - points[i]) / h[i] - (points[i] - points[i - 1]) / h[i - 1])
    m = np.linalg.solve(a, rhs)

    def seg(t: float) -> int:
        return min(max(int(np.searchsorted(times, t, side="right")) - 1, 0), n - 2)

    def c(t: float) -> np.ndarray:
        i = seg(t)
        t0, t1, hh = times[i], times[i + 1], h[i]
        return (
            m[i] * (t1 - t) ** 3 / (6 * hh)
            + m[i + 1] * (t - t0) ** 3 / (6 * hh)
            + (points[i] / hh - m[i] * hh / 6) * (t1 - t)
            + (points[i + 1] / hh - m[i + 1] * hh / 6) * (t - t0)
        )

    def dc(t: float) -> np.ndarray:
        i = seg(t)
        t0, t1, hh = times[i], times[i + 1], h[i]
        return (
            -m[i] * (t1 - t) ** 2 / (2 * hh)
            + m[i + 1] * (t - t0) ** 2 / (2 * hh)
            - (points[i] / hh - m[i] * hh / 6)
            + (points[i + 1] / hh - m[i + 1] * hh / 6)
        )

    return c, dc


# --------------------------------------------------------------------------- keyframes


def test_a_rotation_is_stored_normalised_and_a_nan_one_is_refused() -> None:
    # within the 1e-3 tolerance: accepted and made unit, every component divided by the norm
    k = Keyframe(0.0, [0.0], [0.5 * 1.0008, 0.5 * 1.0008, 0.5 * 1.0008, 0.5 * 1.0008])
    assert k.rotation == pytest.approx((0.5, 0.5, 0.5, 0.5), abs=1e-15)
    k = Keyframe(0.0, [0.0], [0.6 * 0.9995, 0.0, 0.0, 0.8 * 0.9995])
    assert k.rotation == pytest.approx((0.6, 0.0, 0.0, 0.8), abs=1e-15)
    # a quaternion as a column (a 4x1 array) is the same quaternion
    assert Keyframe(0.0, [0.0], np.array([[0.0], [0.0], [0.0], [1.0]])).rotation == (
        0.0,
        0.0,
        0.0,
        1.0,
    )
    for bad in ((math.nan, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0, math.nan), (0.0, 0.0, 1.0)):
        with pytest.raises(ValueError, match="unit quaternion"):
            Keyframe(0.0, [0.0], bad)


# --------------------------------------------------------------------------- the ramp


@pytest.mark.parametrize("n", [0.01, 1.0, 6.0])
def test_the_ramp_integral_is_exact_at_its_ends_and_linear_after_it(n: float) -> None:
    t_a = 1.3
    assert ramp_integral(0.0, t_a, n) == 0.0
    assert ramp_integral(-0.4, t_a, n) == 0.0  # before the ramp: nothing travelled
    # I(1) = 1/2 exactly (the closed form alone rounds to 0.500000000000089 for n = 0.01)
    assert ramp_integral(t_a, t_a, n) == t_a * 0.5
    # after the ramp the speed is 1 (v0): the distance grows by the time past t_a
    for t in (1.5 * t_a, 1.99 * t_a, 2.0 * t_a, 3.0 * t_a):
        assert ramp_integral(t, t_a, n) == pytest.approx(t_a * 0.5 + (t - t_a), rel=1e-12)


# --------------------------------------------------------------------------- the plan itself


def test_a_trajectory_reports_how_it_was_planned() -> None:
    frames = [Keyframe(0.5, [0.0, 0.0]), Keyframe(2.0, [0.1, 0.0]), Keyframe(3.0, [0.1, 0.2])]
    traj = plan(frames, "spline", "continuous", steepness=7.5, ramp=0.3)
    assert traj.keyframes == tuple(frames)
    assert (traj.interpolation, traj.mode, traj.steepness, traj.ramp) == (
        "spline",
        "continuous",
        7.5,
        0.3,
    )
    assert (traj.start, traj.end, traj.duration, traj.dim) == (0.5, 3.0, 2.5, 2)
    assert repr(traj) == (
        "Trajectory(3 keyframes, spline, continuous, steepness=7.5, ramp=0.3, 0.5..3.0 s)"
    )


def test_sample_takes_one_time_or_many() -> None:
    traj = plan([Keyframe(0.0, [0.0, 1.0]), Keyframe(2.0, [1.0, 3.0])])
    pos, vel = traj.sample(0.7)
    assert pos.shape == vel.shape == (1, 2)
    np.testing.assert_array_equal(pos[0], traj.position(0.7))
    np.testing.assert_array_equal(vel[0], traj.velocity(0.7))
    pos, vel = traj.sample([[0.2, 0.9], [1.1, 1.8]])  # any shape: flattened, in order
    assert pos.shape == (4, 2)
    np.testing.assert_array_equal(pos[3], traj.position(1.8))


def test_progress_is_zero_before_the_start_and_one_at_and_after_the_end() -> None:
    frames = [Keyframe(1.0, [0.0]), Keyframe(2.0, [1.0]), Keyframe(4.0, [1.5])]
    for mode in ("stop", "continuous"):
        traj = plan(frames, "linear", mode)  # type: ignore[arg-type]
        assert traj.progress(0.0) == (0, 0.0)
        assert traj.progress(1.0) == (0, 0.0)
        assert traj.progress(2.0) == (1, 0.0)
        assert traj.progress(4.0) == (1, 1.0)
        assert traj.progress(9.0) == (1, 1.0)
        i, u = traj.progress(3.0)
        assert i == 1 and u == pytest.approx((traj.position(3.0)[0] - 1.0) / 0.5, rel=1e-12)


def test_continuous_linear_passes_a_keyframe_at_the_smaller_average_speed() -> None:
    """v_k = min(D_k / T_k, D_k+1 / T_k+1), the documented speed through keyframe k."""
    frames = [
        Keyframe(0.5, [0.0, 0.0, 0.0]),
        Keyframe(1.5, [0.10, 0.0, 0.02]),
        Keyframe(4.0, [0.10, 0.20, 0.02]),
        Keyframe(4.6, [-0.05, 0.15, 0.0]),
        Keyframe(5.0, [-0.05, 0.15, 0.01]),
    ]
    traj = plan(frames, "linear", "continuous")
    avg = [
        float(np.linalg.norm(np.subtract(b.pose, a.pose))) / (b.t - a.t)
        for a, b in zip(frames[:-1], frames[1:], strict=True)
    ]
    for k in range(1, len(frames) - 1):
        want = min(avg[k - 1], avg[k])
        assert traj.speed(frames[k].t) == pytest.approx(want, rel=1e-12), k
        assert traj.speed(frames[k].t - 1e-9) == pytest.approx(want, rel=1e-6), k


# --------------------------------------------------------------------------- the spline


@pytest.mark.parametrize("count", [3, 4, 6])
def test_the_spline_is_the_natural_cubic_spline_through_the_keyframes(count: int) -> None:
    rng = np.random.default_rng(count)
    times = np.cumsum(rng.uniform(0.4, 2.0, count)).tolist()
    points = rng.uniform(-0.1, 0.1, (count, 3))
    frames = [Keyframe(t, p) for t, p in zip(times, points, strict=True)]
    c, dc = _natural_spline(times, points)
    # stop mode plays each segment along its arc length: the lengths are the curve's
    stop = plan(frames, "spline", "stop")
    for i in range(count - 1):
        length = _gauss(lambda t: float(np.linalg.norm(dc(t))), times[i], times[i + 1])
        assert stop.lengths[i] == pytest.approx(length, rel=1e-10), i
    # continuous mode plays the curve in its own time on the interior segments
    cont = plan(frames, "spline", "continuous")
    for i in range(1, count - 2):
        for u in (0.1, 0.5, 0.9):
            t = times[i] + u * (times[i + 1] - times[i])
            np.testing.assert_allclose(cont.position(t), c(t), rtol=0, atol=1e-12)
            np.testing.assert_allclose(cont.velocity(t), dc(t), rtol=0, atol=1e-12)


def test_spline_stop_speed_stays_near_the_profile_through_a_cusp() -> None:
    """Out and back along one line: the curve's tangent vanishes at the middle keyframe (a
    true cusp), where the arc-length inverse has an infinite slope. The commanded speed still
    follows the profile: within 0.075 % of the profile's peak speed everywhere, never more
    than twice the profile's speed (measured: 0.049 % and 1.70 times, in the first and last
    few milliseconds next to the cusp; elsewhere to the table's accuracy)."""
    frames = [Keyframe(0.0, [0.0]), Keyframe(1.0, [1.0]), Keyframe(2.0, [0.0])]
    traj = plan(frames, "spline", "stop")
    near = np.geomspace(1e-6, 0.03, 400)
    taus = np.unique(np.concatenate([np.linspace(1e-6, 1 - 1e-6, 1001), near, 1.0 - near]))
    for seg in (0, 1):
        prof = traj._profiles[seg]
        peak = prof.c
        for tau in taus.tolist():
            want = prof.speed(tau, traj._r)
            got = traj.speed(frames[seg].t + tau)
            assert abs(got - want) <= 7.5e-4 * peak, (seg, tau, got, want)
            assert got <= 2.0 * want, (seg, tau, got, want)
            if 0.05 <= tau <= 0.95:
                assert got == pytest.approx(want, rel=2e-4), (seg, tau)


def test_a_spline_that_stands_still_plans_without_warnings() -> None:
    """Equal poses: the curve's speed is zero everywhere; the arc-length table must divide
    by nothing (no RuntimeWarning in the daemon's log) and the pose is held exactly."""
    frames = [Keyframe(0.0, [0.2, -0.1]), Keyframe(1.0, [0.2, -0.1]), Keyframe(3.0, [0.2, -0.1])]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for mode in ("stop", "continuous"):
            traj = plan(frames, "spline", mode)  # type: ignore[arg-type]
            for t in np.linspace(-0.5, 3.5, 41).tolist():
                np.testing.assert_array_equal(traj.position(t), [0.2, -0.1])
                np.testing.assert_array_equal(traj.velocity(t), [0.0, 0.0])


# --------------------------------------------------------------------------- orientation


def test_a_keyframe_given_with_the_other_sign_turns_the_short_way() -> None:
    q1 = np.negative(_quat((0, 0, 1), 0.6))  # the same rotation as +q, written with -q
    frames = [
        Keyframe(0.0, [0.0, 0.0, 0.0], _quat((0, 0, 1), 0.0)),
        Keyframe(1.0, [0.1, 0.0, 0.0], q1),
        Keyframe(2.0, [0.1, 0.1, 0.0], _quat((0, 0, 1), 0.2)),
    ]
    for interpolation in ("linear", "spline"):
        traj = plan(frames, interpolation, "stop")  # type: ignore[arg-type]
        # slerp stays on the short arc; squad may overshoot a keyframe a little (measured
        # 8e-6 rad here), the long way round would be 5.7 rad
        slack = 1e-9 if interpolation == "linear" else 0.01
        if interpolation == "linear":  # half way in time and turn (a symmetric profile)
            assert _turn(traj.orientation(0.5), frames[0].rotation) == pytest.approx(0.3)
        assert _turn(traj.orientation(1.0), q1) < 1e-12
        for t in np.linspace(0.0, 2.0, 81).tolist():
            q = traj.orientation(t)
            assert abs(float(np.linalg.norm(q)) - 1.0) < 1e-12
            # the short way: never farther than 0.6 rad from the start, nor 0.4 from the end
            assert _turn(q, frames[0].rotation) <= 0.6 + slack
            assert _turn(q, frames[2].rotation) <= 0.4 + slack


def test_slerp_takes_the_short_way_whatever_the_sign_of_its_end() -> None:
    q0 = np.array(_quat((1, 2, 3), 0.3))
    q1 = np.array(_quat((-1, 0, 2), 1.1))
    whole = _turn(q0, q1)
    for u in (0.25, 0.5, 0.8):
        a, b = _slerp(q0, q1, u), _slerp(q0, np.negative(q1), u)
        assert _turn(a, b) < 1e-12
        assert _turn(q0, b) == pytest.approx(u * whole, rel=1e-9)
        assert _turn(b, q1) == pytest.approx((1 - u) * whole, rel=1e-9)


def test_a_tiny_turn_is_played_with_the_same_timing_and_stays_unit() -> None:
    """A turn of 2 microradians (the chord branch of slerp: the quaternions nearly equal)."""
    angle = 2e-6
    frames = [
        Keyframe(0.0, [0.0, 0.0, 0.0], _quat((0.3, -0.2, 1.0), 0.4)),
        Keyframe(1.0, [0.1, 0.0, 0.0], _quat((0.3, -0.2, 1.0), 0.4 + angle)),
    ]
    traj = plan(frames, "linear", "stop")
    for t in (0.1, 0.3, 0.5, 0.7, 0.95):
        q = traj.orientation(t)
        assert abs(float(np.linalg.norm(q)) - 1.0) < 2e-16 * 8
        share_path = float(traj.position(t)[0]) / 0.1
        assert _turn(frames[0].rotation, q) == pytest.approx(share_path * angle, rel=1e-6)
        assert _turn(q, frames[1].rotation) == pytest.approx((1 - share_path) * angle, rel=1e-6)


def test_orientation_shares_the_positions_progress_in_continuous_mode() -> None:
    """Continuous linear: the segment's speeds at its keyframes are not zero, and the turn
    follows the position's own profile (distance over length), not a resting one."""
    frames = [
        Keyframe(0.0, [0.0, 0.0, 0.0], _quat((0, 0, 1), 0.0)),
        Keyframe(2.0, [0.1, 0.0, 0.0], _quat((0, 0, 1), 1.2)),
        Keyframe(3.0, [0.1, 0.05, 0.0], _quat((0, 0, 1), 1.5)),
    ]
    traj = plan(frames, "linear", "continuous")
    assert traj.speed(2.0) > 0.04  # moving through keyframe 1
    for t in (0.3, 1.0, 1.7, 1.99):
        share_path = float(traj.position(t)[0]) / 0.1
        assert _turn(frames[0].rotation, traj.orientation(t)) == pytest.approx(
            share_path * 1.2, rel=1e-9
        )


@pytest.mark.parametrize("mode", ["stop", "continuous"])
def test_spline_orientation_is_shoemakes_squad(mode: str) -> None:
    rots = [
        _quat((1, 2, 3), 0.3),
        _quat((-1, 0.5, 2), 1.1),
        _quat((0.2, -1, 0.4), 0.7),
        _quat((1, 1, -1), 2.0),
        _quat((0, -0.3, 1), -0.9),
    ]
    poses = [
        [0.0, 0.0, 0.0],
        [0.1, 0.02, 0.0],
        [0.1, 0.1, 0.03],
        [0.0, 0.12, 0.05],
        [0.02, 0.0, 0.0],
    ]
    times = [0.0, 1.0, 2.5, 3.0, 4.4]
    frames = [Keyframe(t, p, r) for t, p, r in zip(times, poses, rots, strict=True)]
    traj = plan(frames, "spline", mode)  # type: ignore[arg-type]
    qs = _aligned(rots)
    for t in np.linspace(0.0, 4.4, 89).tolist():
        i, u = traj.progress(t)
        got = traj.orientation(t)
        assert abs(float(np.linalg.norm(got)) - 1.0) < 1e-12
        assert _turn(got, _ref_squad(qs, i, u)) < 1e-9, (t, i, u)


def test_a_tool_that_keeps_its_orientation_keeps_it_exactly() -> None:
    """Spline keyframes with the same orientation (the tool only moves, or pauses turning):
    the squad's tangent is zero there and the tool does not turn at all."""
    q = _quat((0.4, -1.0, 0.3), 0.8)
    poses = [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.1, 0.1, 0.0], [0.0, 0.1, 0.02]]
    frames = [Keyframe(float(i), p, q) for i, p in enumerate(poses)]
    for mode in ("stop", "continuous"):
        traj = plan(frames, "spline", mode)  # type: ignore[arg-type]
        for t in np.linspace(0.0, 3.0, 61).tolist():
            got = traj.orientation(t)
            assert _turn(got, q) < 1e-12 and abs(float(np.linalg.norm(got)) - 1.0) < 1e-12
    # a pause in the turn: two keyframes with one orientation, then a turn
    turned = _quat((0, 0, 1), 0.9)
    frames = [
        Keyframe(0.0, poses[0], q),
        Keyframe(1.0, poses[1], q),
        Keyframe(2.0, poses[2], turned),
        Keyframe(3.0, poses[3], turned),
    ]
    traj = plan(frames, "spline", "stop")
    qs = _aligned([f.rotation for f in frames])
    for t in np.linspace(0.0, 3.0, 61).tolist():
        i, u = traj.progress(t)
        assert _turn(traj.orientation(t), _ref_squad(qs, i, u)) < 1e-9, t


@pytest.mark.parametrize("mode", ["stop", "continuous"])
def test_a_steady_turn_about_one_axis_is_squad_and_slerp_alike(mode: str) -> None:
    """Equal turns about one axis between keyframes: the squad's tangents cancel (its control
    points are the keyframes themselves), so the spline turns as slerp does: about that axis,
    by the share of the segment's progress."""
    step = 0.8
    frames = [
        Keyframe(float(k), [0.05 * k, 0.0, 0.0], _quat((0.0, 0.0, 1.0), step * k)) for k in range(4)
    ]
    traj = plan(frames, "spline", mode)  # type: ignore[arg-type]
    for t in np.linspace(0.0, 3.0, 61).tolist():
        i, u = traj.progress(t)
        want = _quat((0.0, 0.0, 1.0), step * (i + u))
        got = traj.orientation(t)
        assert _turn(got, want) < 1e-9, (t, i, u)
        assert abs(float(np.linalg.norm(got)) - 1.0) < 1e-12
