"""Keyframe trajectories: poses on a timeline, the motion in between filled in (issue 11).

After the German Heart Center system, which let surgeons program robot motion the way animators
do: put poses on a timeline as *keyframes* and let the planner fill in the motion. This module is
the planner only; it knows nothing about robots, the loop or IGTL (the controller plugin that
plays a plan is `occ/controllers/keyframe/`, see docs/ARCHITECTURE.md).

API::

    from occ.kinematics.trajectory import Keyframe, plan

    traj = plan(
        [Keyframe(t=0.0, pose=[0.0, 0.0]), Keyframe(t=2.0, pose=[0.1, 0.0]),
         Keyframe(t=3.5, pose=[0.1, 0.05])],
        interpolation="spline", mode="continuous", steepness=6.0,
    )
    traj.position(1.0), traj.velocity(1.0)   # numpy arrays, one value per pose coordinate
    traj.start, traj.end, traj.duration      # first and last keyframe time, end - start
    traj.sample(times)                       # (len(times), dim) positions and velocities

**Poses** are plain vectors of any (but one common) dimension: joint positions or a Cartesian
tip position, the caller's choice. The planner is agnostic: it interpolates each coordinate
(linear) or the point in R^dim (spline) and measures path length with the Euclidean norm of the
vector, so mixing units in one pose (metres with radians) weights them as they come.

**Orientation** (a 6-DOF tool, issue 28): keyframes may carry a unit quaternion each (all or
none). It is not a vector and is not mixed into the path length: :meth:`Trajectory.orientation`
turns with the segment's *progress* (the position profile's distance over the segment's length,
so with the same keyframe times and sigmoid ramps; a segment where only the orientation changes
gets a resting profile of its own), by slerp (``linear``) or Shoemake's squad (``spline``:
continuous angular velocity through the keyframes). Each keyframe's orientation is met exactly
at its time.

**Time**: keyframe times are in seconds and strictly increasing; the first keyframe is where the
motion starts (its time may be 0 or later). Before it the plan holds the first pose, after the
last keyframe it holds the last one, at rest. Every keyframe is met exactly at its time (to
rounding: the path parameter reaches the segment's end exactly, see "Exactness").

Speed profile (the paper's sigmoids)
------------------------------------
The German Heart Center paper accelerates and decelerates with logistic sigmoids:

    v_a(t) = v0 / (1 + exp(n (1 - 2t/t_a)))      v_b(t) = v0 / (1 + exp(-n (1 - 2t/t_b)))

with steepness n, whose areas are t_a v0 / 2 (and t_b v0 / 2), so the cruise speed v0 follows
from the path length and the time available. The raw logistic does not start at 0 nor end at v0
(it is v0/(1 + e^n) at t = 0), so it is *normalised* here:

    s(x) = (L(x) - L(0)) / (L(1) - L(0)),   L(x) = 1 / (1 + exp(n (1 - 2x))),   x = t / t_a

which is exactly 0 at x = 0 and exactly 1 at x = 1, and still point-symmetric about
(1/2, 1/2): its area over [0, 1] is exactly 1/2 and the area rule t_a v0 / 2 holds unchanged.
The deceleration is its mirror image (v_b(t) = v0 s((t_b - t)/t_b)), which is the paper's v_b
normalised the same way. Position is the integral of the speed, in closed form: with softplus
sp(z) = log(1 + e^z) (evaluated stably), the integral of L over [0, x] is
(sp(n(2x - 1)) - sp(-n)) / (2n), so

    I(x) = integral of s over [0, x] = [(sp(n(2x-1)) - sp(-n)) / (2n) - L(0) x] / (L(1) - L(0))

and I(1) = 1/2 exactly in exact arithmetic (sp(n) - sp(-n) = n).

Residual acceleration: the normalised ramp's slope at its ends is not zero, it is
2n L(0) L(1) / ((L(1) - L(0)) t_a) v0 ~ 2n e^-n v0 / t_a: with the default n = 6 the
acceleration steps from 0 to about 1 % of the ramp's peak acceleration when a ramp starts or ends
(the raw sigmoid would instead step the *velocity* by v0/(1 + e^n)). A larger n makes the step
smaller and the peak acceleration larger; n -> 0 tends to a linear ramp (constant acceleration).

Every segment between two keyframes (duration T) gets one profile: speed a at its start, a ramp
of duration t_a = ramp * T to the cruise speed c, cruise, a ramp of duration t_b = ramp * T to the
speed b at its end (``ramp`` in (0, 0.5], default 0.25, so the ramps never overlap). Its area
must be the segment's path length D, which fixes c:

    c = (D - (a t_a + b t_b) / 2) / (T - t_a/2 - t_b/2)

(for a = b = 0 this is the paper's v0 = D / (T - t_a/2 - t_b/2)).

Interpolation and mode
----------------------
* ``linear``: straight segments between keyframes, parametrised by arc length.

  - ``stop``: a = b = 0 on every segment: the robot rests at every keyframe.
  - ``continuous``: the robot passes each interior keyframe at the speed
    v_k = min(D_k / T_k, D_k+1 / T_k+1) (the smaller average speed of the two segments it joins),
    ramping between that and each segment's own cruise speed. Choosing the smaller average keeps
    every cruise speed positive (c >= D/(2 (T - t_a/2 - t_b/2)) > 0), so the robot never backs up
    along a segment. **The corner**: at an interior keyframe the *speed* (the velocity's
    magnitude) is continuous but the *direction* changes instantly from one segment's to the
    next: a polyline has a corner there and a straight-line planner cannot round it without
    missing the keyframe. velocity(t_k) reports the outgoing segment's direction. Use
    ``spline`` for motion whose velocity vector is continuous through keyframes.

* ``spline``: one C2 curve through all keyframes, a *natural cubic spline* of the pose with the
  keyframe times as knots (second derivative zero at both ends). The same curve in both modes
  ("same path, stop or fly through").

  - ``continuous``: the curve is played in time, position(t) = C(phi(t)), with phi(t_k) = t_k at
    every keyframe. On interior segments phi(t) = t: the spline in time, C2, so velocity and
    acceleration are continuous (at the first and last interior keyframe, where phi's ramps end,
    the acceleration steps by the ramp's residual described above). On the first and last
    segment phi is a profile of the kind above with D = T, from rest to c then to phi' = 1
    (first), and mirrored (last), so the robot starts and stops with the sigmoid acceleration.
    One segment only: 0 -> c -> 0.
  - ``stop``: each segment of the curve is played from rest to rest with the a = b = 0 profile
    over its *arc length* (numerical: a table of 512 intervals per segment, 5-point
    Gauss-Legendre each, built once by plan(); the curve parameter for a given length is a
    monotone cubic Hermite inverse of the table with slopes 1/|C'|). velocity() is the exact
    time derivative of the position actually commanded (the table's inverse included), so a
    velocity feed-forward agrees with the setpoints; its magnitude is the profile speed to the
    table's accuracy: within 3e-7 relative for 99 % of samples over random keyframe sets, worst
    1.4e-4 where the curve nearly has a cusp (its parametric speed dips to a few percent of its
    mean). Where the curve's tangent vanishes (a true cusp: degenerate keyframe sets, e.g. out
    and back along one line) the direction of motion reverses there with the speed set by the
    profile, so the velocity vector is not continuous at that point.

Exactness: at a keyframe time the path parameter equals the segment's end exactly (the profile
distance at tau = T is D exactly; phi(t_k) = t_k), so a keyframe is met to the rounding of
evaluating the segment's formula at its end (~1e-15 relative).

Cost: ``position(t)`` uses Python floats for the time profile and one small numpy expression for
the pose: a few microseconds a call (docs/BENCHMARKS.md, "occ: trajectory planning").
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["Keyframe", "Trajectory", "plan", "ramp_integral", "ramp_speed"]

Interpolation = Literal["linear", "spline"]
Mode = Literal["stop", "continuous"]
FloatArray = NDArray[np.float64]

DEFAULT_STEEPNESS = 6.0
DEFAULT_RAMP = 0.25
_TABLE_INTERVALS = 512  # arc-length table per spline segment (stop mode)
_GL_X, _GL_W = np.polynomial.legendre.leggauss(5)


@dataclass(frozen=True, slots=True, init=False)
class Keyframe:
    """A pose the motion must pass at time ``t`` (seconds).

    ``pose`` is a vector of any dimension: joint positions, or a Cartesian position, the caller's
    choice (all keyframes of one plan share the dimension). Stored as a tuple of floats.
    """

    t: float
    pose: tuple[float, ...]
    #: the tool's orientation, a unit quaternion (x, y, z, w), or None (position only)
    rotation: tuple[float, float, float, float] | None

    def __init__(self, t: float, pose: ArrayLike, rotation: ArrayLike | None = None) -> None:
        try:
            values = tuple(float(v) for v in np.asarray(pose, dtype=float).reshape(-1))
            time = float(t)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"keyframe needs a number t and a numeric pose vector: {exc}") from exc
        if np.ndim(pose) != 1 or not values:
            raise ValueError(
                f"keyframe pose must be a non-empty vector, got shape {np.shape(pose)}"
            )
        if not math.isfinite(time):
            raise ValueError(f"keyframe time must be finite, got {time}")
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"keyframe pose must be finite, got {values}")
        object.__setattr__(self, "t", time)
        object.__setattr__(self, "pose", values)
        quat: tuple[float, float, float, float] | None = None
        if rotation is not None:
            q = [float(v) for v in np.asarray(rotation, dtype=float).reshape(-1)]
            norm = math.sqrt(sum(v * v for v in q)) if len(q) == 4 else 0.0
            if len(q) != 4 or not all(math.isfinite(v) for v in q) or abs(norm - 1.0) > 1e-3:
                raise ValueError(
                    f"keyframe rotation must be a unit quaternion (x, y, z, w), got {q}"
                )
            quat = (q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm)
        object.__setattr__(self, "rotation", quat)


# --------------------------------------------------------------------------- the ramp


def _sigmoid(z: float) -> float:
    # two branches so exp never overflows, whatever the steepness
    if z >= 0.0:
        return 1.0 / (1.0 + math.exp(-z))
    e = math.exp(z)
    return e / (1.0 + e)


def _softplus(z: float) -> float:
    # log(1 + e^z) without overflow for large z nor loss of the tail for very negative z
    return max(z, 0.0) + math.log1p(math.exp(-abs(z)))


class _Ramp:
    """The normalised sigmoid for one steepness, on the unit interval (precomputed constants)."""

    __slots__ = ("n", "l0", "span", "sp0")

    def __init__(self, n: float) -> None:
        self.n = n
        self.l0 = _sigmoid(-n)  # L(0) = 1 / (1 + e^n)
        # L(1) - L(0) = tanh(n/2): computed directly, 1 - 2 L(0) would cancel for small n
        self.span = math.tanh(n / 2.0)
        self.sp0 = _softplus(-n)

    def speed(self, x: float) -> float:
        """s(x): 0 at x = 0, 1 at x = 1 (exactly), 1/2 at x = 1/2."""
        if x <= 0.0:
            return 0.0
        if x >= 1.0:
            return 1.0
        return (_sigmoid(self.n * (2.0 * x - 1.0)) - self.l0) / self.span

    def integral(self, x: float) -> float:
        """I(x) = integral of s over [0, x]; I(1) = 1/2."""
        if x <= 0.0:
            return 0.0
        if x >= 1.0:
            return 0.5 + (x - 1.0)
        n = self.n
        return ((_softplus(n * (2.0 * x - 1.0)) - self.sp0) / (2.0 * n) - self.l0 * x) / self.span


def ramp_speed(t: float, t_a: float, steepness: float = DEFAULT_STEEPNESS) -> float:
    """The normalised acceleration sigmoid as a fraction of v0: 0 at t = 0, 1 at t = t_a."""
    _check_steepness(steepness)
    return _Ramp(steepness).speed(t / t_a)


def ramp_integral(t: float, t_a: float, steepness: float = DEFAULT_STEEPNESS) -> float:
    """Closed-form integral of :func:`ramp_speed` over [0, t] (seconds x v0); t_a/2 at t = t_a."""
    _check_steepness(steepness)
    return t_a * _Ramp(steepness).integral(t / t_a)


# --------------------------------------------------------------------------- one segment's profile


@dataclass(frozen=True, slots=True)
class _Profile:
    """Speed a -> ramp t_a -> cruise c -> ramp t_b -> speed b over T, covering distance D."""

    T: float
    ta: float
    tb: float
    a: float
    b: float
    c: float
    D: float

    @classmethod
    def make(cls, T: float, D: float, a: float, b: float, ramp: float) -> _Profile:
        ta = tb = ramp * T
        # the area rule: each ramp contributes its duration times the mean of its end speeds
        c = (D - 0.5 * (a * ta + b * tb)) / (T - 0.5 * ta - 0.5 * tb)
        return cls(T, ta, tb, a, b, c, D)

    def distance(self, tau: float, r: _Ramp) -> float:
        if tau <= 0.0:
            return 0.0
        if tau >= self.T:
            return self.D
        if tau < self.ta:
            return self.a * tau + (self.c - self.a) * self.ta * r.integral(tau / self.ta)
        rest = self.T - tau
        if rest < self.tb:
            # the deceleration seen backwards from the end is a ramp from b up to c
            return self.D - self.b * rest - (self.c - self.b) * self.tb * r.integral(rest / self.tb)
        return 0.5 * (self.a + self.c) * self.ta + self.c * (tau - self.ta)

    def speed(self, tau: float, r: _Ramp) -> float:
        if tau <= 0.0:
            return self.a
        if tau >= self.T:
            return self.b
        if tau < self.ta:
            return self.a + (self.c - self.a) * r.speed(tau / self.ta)
        rest = self.T - tau
        if rest < self.tb:
            return self.b + (self.c - self.b) * r.speed(rest / self.tb)
        return self.c


# --------------------------------------------------------------------------- paths


def _natural_spline(times: FloatArray, points: FloatArray) -> FloatArray:
    """Coefficients (segments, 4, dim) of the natural cubic spline through ``points`` at ``times``.

    Segment i: C(u) = k0 + k1 x + k2 x^2 + k3 x^3 with x = u - times[i].
    """
    h = np.diff(times)
    count = len(times)
    m = np.zeros_like(points)  # second derivatives; natural ends: m[0] = m[-1] = 0
    if count > 2:
        # tridiagonal system for the interior second derivatives (Thomas algorithm: diagonally
        # dominant, so no pivoting needed)
        slope = np.diff(points, axis=0) / h[:, None]
        rhs = 6.0 * (slope[1:] - slope[:-1])
        diag = 2.0 * (h[:-1] + h[1:])
        sub = h[1:-1].copy()  # below and above the diagonal (symmetric)
        k = count - 2
        cp = np.zeros(k)
        dp = np.zeros((k, points.shape[1]))
        cp[0] = sub[0] / diag[0] if k > 1 else 0.0
        dp[0] = rhs[0] / diag[0]
        for i in range(1, k):
            den = diag[i] - sub[i - 1] * cp[i - 1]
            cp[i] = sub[i] / den if i < k - 1 else 0.0
            dp[i] = (rhs[i] - sub[i - 1] * dp[i - 1]) / den
        inner = np.zeros_like(dp)
        inner[-1] = dp[-1]
        for i in range(k - 2, -1, -1):
            inner[i] = dp[i] - cp[i] * inner[i + 1]
        m[1:-1] = inner
    dpnt = np.diff(points, axis=0)
    hh = h[:, None]
    coef = np.empty((count - 1, 4, points.shape[1]))
    coef[:, 0] = points[:-1]
    coef[:, 1] = dpnt / hh - hh * (2.0 * m[:-1] + m[1:]) / 6.0
    coef[:, 2] = m[:-1] / 2.0
    coef[:, 3] = (m[1:] - m[:-1]) / (6.0 * hh)
    return coef


def _cubic(k: FloatArray, x: float) -> FloatArray:
    out: FloatArray = ((k[3] * x + k[2]) * x + k[1]) * x + k[0]
    return out


def _cubic_d(k: FloatArray, x: float) -> FloatArray:
    out: FloatArray = (3.0 * k[3] * x + 2.0 * k[2]) * x + k[1]
    return out


class _ArcTable:
    """Arc length of one spline segment, and its inverse (length -> curve parameter x)."""

    __slots__ = ("s", "x", "m0", "m1")

    def __init__(self, k: FloatArray, h: float) -> None:
        nodes = np.linspace(0.0, h, _TABLE_INTERVALS + 1)
        half = 0.5 * (nodes[1] - nodes[0])
        mids = 0.5 * (nodes[:-1] + nodes[1:])
        quad = mids[:, None] + half * _GL_X[None, :]  # (intervals, 5) Gauss-Legendre points
        speed_q = np.linalg.norm(_cubic_d_arr(k, quad.reshape(-1)), axis=1).reshape(quad.shape)
        pieces = half * (speed_q @ _GL_W)
        s = np.concatenate(([0.0], np.cumsum(pieces)))
        speed_n = np.linalg.norm(_cubic_d_arr(k, nodes), axis=1)
        ds = np.diff(s)
        dx = np.diff(nodes)
        # slopes dx/ds = 1/|C'| in each interval's unit coordinates, limited to 3x the secant
        # (Fritsch-Carlson) so the inverse stays monotone, and the secant where |C'| vanishes
        with np.errstate(divide="ignore", invalid="ignore"):
            secant = np.where(ds > 0.0, dx / ds, 0.0)
            inv_l = np.where(speed_n[:-1] > 0.0, 1.0 / speed_n[:-1], np.inf)
            inv_r = np.where(speed_n[1:] > 0.0, 1.0 / speed_n[1:], np.inf)
        m0 = np.minimum(inv_l, 3.0 * secant) * ds
        m1 = np.minimum(inv_r, 3.0 * secant) * ds
        self.s: list[float] = s.tolist()
        self.x: list[float] = nodes.tolist()
        self.x[-1] = h  # the segment's end exactly, so the keyframe is met exactly
        self.m0: list[float] = m0.tolist()
        self.m1: list[float] = m1.tolist()

    @property
    def length(self) -> float:
        return self.s[-1]

    def param(self, d: float) -> tuple[float, float]:
        """The curve parameter x at arc length d, and dx/dd (the inverse's own derivative)."""
        s = self.s
        last = len(s) - 2
        if d <= 0.0:
            return self.x[0], _ratio(self.m0[0], s[1] - s[0])
        if d >= s[-1]:
            return self.x[-1], _ratio(self.m1[last], s[-1] - s[-2])
        j = min(bisect_right(s, d) - 1, last)
        ds = s[j + 1] - s[j]
        if ds <= 0.0:
            return self.x[j], 0.0
        w = (d - s[j]) / ds
        w2 = w * w
        w3 = w2 * w
        x0 = self.x[j]
        x1 = self.x[j + 1]
        m0 = self.m0[j]
        m1 = self.m1[j]
        x = (
            (2.0 * w3 - 3.0 * w2 + 1.0) * x0
            + (w3 - 2.0 * w2 + w) * m0
            + (-2.0 * w3 + 3.0 * w2) * x1
            + (w3 - w2) * m1
        )
        dxdw = (
            (6.0 * w2 - 6.0 * w) * x0
            + (3.0 * w2 - 4.0 * w + 1.0) * m0
            + (6.0 * w - 6.0 * w2) * x1
            + (3.0 * w2 - 2.0 * w) * m1
        )
        return x, dxdw / ds


def _ratio(a: float, b: float) -> float:
    return a / b if b > 0.0 else 0.0


def _cubic_d_arr(k: FloatArray, x: FloatArray) -> FloatArray:
    xs = x[:, None]
    out: FloatArray = (3.0 * k[3] * xs + 2.0 * k[2]) * xs + k[1]
    return out


# --------------------------------------------------------------------------- the plan


class Trajectory:
    """A planned motion: :meth:`position` and :meth:`velocity` at any time (seconds).

    Before the first keyframe the first pose is held, after the last one the last pose, at rest.
    Build it with :func:`plan`.
    """

    def __init__(
        self,
        keyframes: Sequence[Keyframe],
        interpolation: Interpolation,
        mode: Mode,
        steepness: float,
        ramp: float,
    ) -> None:
        self.keyframes: tuple[Keyframe, ...] = tuple(keyframes)
        self.interpolation: Interpolation = interpolation
        self.mode: Mode = mode
        self.steepness = steepness
        self.ramp = ramp
        self._r = _Ramp(steepness)
        self._times: list[float] = [k.t for k in self.keyframes]
        times = np.array(self._times)
        points = np.array([k.pose for k in self.keyframes], dtype=float)
        self._points = points
        self.dim = points.shape[1]
        self.start = self._times[0]
        self.end = self._times[-1]
        self.duration = self.end - self.start
        durations = np.diff(times)
        segs = len(durations)
        self._coef: FloatArray | None = None
        self._tables: list[_ArcTable] = []
        self._delta = np.diff(points, axis=0)

        lengths: list[float]
        if interpolation == "linear":
            lengths = [float(v) for v in np.linalg.norm(self._delta, axis=1)]
        else:
            coef = _natural_spline(times, points)
            self._coef = coef
            if mode == "stop":
                self._tables = [_ArcTable(coef[i], float(durations[i])) for i in range(segs)]
                lengths = [tb.length for tb in self._tables]
            else:
                lengths = [float(h) for h in durations]  # phi's "distance" is curve time
        self.lengths: tuple[float, ...] = tuple(lengths)

        ends = [0.0] * (segs + 1)  # the speed at each keyframe
        if mode == "continuous":
            for k in range(1, segs):
                if interpolation == "linear":
                    ends[k] = min(lengths[k - 1] / durations[k - 1], lengths[k] / durations[k])
                else:
                    ends[k] = 1.0  # phi' = 1: the spline is played in its own time
        self._profiles = [
            _Profile.make(float(durations[i]), lengths[i], ends[i], ends[i + 1], ramp)
            for i in range(segs)
        ]
        # orientation: a quaternion per keyframe, each the same sign as the one before (the
        # short way round); played with the segment's own progress (distance / length), so it
        # turns with the same timing and ramps as the position, or on a resting profile of its
        # own where the position does not move
        self.has_rotation = self.keyframes[0].rotation is not None
        self._quats: list[FloatArray] = []
        self._unit = [_Profile.make(float(durations[i]), 1.0, 0.0, 0.0, ramp) for i in range(segs)]
        self._squad: list[FloatArray] = []
        if self.has_rotation:
            for frame in self.keyframes:
                q: FloatArray = np.array(frame.rotation, dtype=np.float64)
                if self._quats and float(q @ self._quats[-1]) < 0.0:
                    q = np.negative(q)
                self._quats.append(q)
            if interpolation == "spline":
                self._squad = _squad_controls(self._quats)

    # ----------------------------------------------------------------- scalar evaluation

    def _locate(self, t: float) -> tuple[int, float]:
        i = bisect_right(self._times, t) - 1
        i = min(max(i, 0), len(self._profiles) - 1)
        return i, t - self._times[i]

    def position(self, t: float) -> FloatArray:
        """The pose at time ``t`` (a new float64 array of the poses' dimension)."""
        if t <= self.start:
            return self._points[0].copy()
        if t >= self.end:
            return self._points[-1].copy()
        i, tau = self._locate(t)
        d = self._profiles[i].distance(tau, self._r)
        if self._coef is None:
            length = self.lengths[i]
            frac = d / length if length > 0.0 else 0.0
            out: FloatArray = self._points[i] + frac * self._delta[i]
            return out
        if self._tables:
            return _cubic(self._coef[i], self._tables[i].param(d)[0])
        return _cubic(self._coef[i], d)

    def progress(self, t: float) -> tuple[int, float]:
        """The segment at ``t`` and how far along it the motion is, in [0, 1]: the profile's
        distance over the segment's length (exactly 1 at its end keyframe), or, where the
        position does not move, a resting profile of the segment's own."""
        i, tau = self._locate(t)
        length = self.lengths[i]
        if length > 0.0:
            return i, min(1.0, self._profiles[i].distance(tau, self._r) / length)
        return i, min(1.0, self._unit[i].distance(tau, self._r))

    def orientation(self, t: float) -> FloatArray:
        """The tool's orientation at ``t``: a unit quaternion (x, y, z, w); slerp between
        keyframes (``linear``) or squad through them (``spline``: continuous angular velocity at
        the keyframes), with the position's timing. Each keyframe's quaternion exactly at its
        time (up to its sign). ValueError for a plan without orientation."""
        if not self.has_rotation:
            raise ValueError("this plan has no orientation (its keyframes have no rotation)")
        if t <= self.start:
            return self._quats[0].copy()
        if t >= self.end:
            return self._quats[-1].copy()
        i, u = self.progress(t)
        q0, q1 = self._quats[i], self._quats[i + 1]
        if not self._squad:
            return _slerp(q0, q1, u)
        s0, s1 = self._squad[i], self._squad[i + 1]
        return _slerp(_slerp(q0, q1, u), _slerp(s0, s1, u), 2.0 * u * (1.0 - u))

    def velocity(self, t: float) -> FloatArray:
        """The velocity at time ``t`` (pose units per second); zero outside the motion.

        At an interior keyframe of a linear continuous plan (a corner) this is the outgoing
        segment's velocity: the direction changes there, the speed does not.
        """
        if t < self.start or t >= self.end:
            return np.zeros(self.dim)
        i, tau = self._locate(t)
        prof = self._profiles[i]
        v = prof.speed(tau, self._r)
        if self._coef is None:
            length = self.lengths[i]
            if length <= 0.0:
                return np.zeros(self.dim)
            out: FloatArray = (v / length) * self._delta[i]
            return out
        k = self._coef[i]
        if self._tables:
            # the derivative of the position actually commanded (the table's inverse included),
            # so a velocity feed-forward agrees with the positions; its norm is the profile
            # speed to the table's accuracy (~1e-5 relative, tests/occ/test_trajectory.py)
            x, dxdd = self._tables[i].param(prof.distance(tau, self._r))
            out = (v * dxdd) * _cubic_d(k, x)
            return out
        out = v * _cubic_d(k, prof.distance(tau, self._r))
        return out

    def speed(self, t: float) -> float:
        """The magnitude of :meth:`velocity`, pose units per second."""
        return float(np.linalg.norm(self.velocity(t)))

    def sample(self, times: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Positions and velocities at many times: two arrays of shape (len(times), dim).

        For tools, plots and tests; a loop calls :meth:`position` once a tick.
        """
        ts = np.asarray(times, dtype=float).reshape(-1)
        pos = np.empty((len(ts), self.dim))
        vel = np.empty((len(ts), self.dim))
        for j, t in enumerate(ts.tolist()):
            pos[j] = self.position(t)
            vel[j] = self.velocity(t)
        return pos, vel

    def __repr__(self) -> str:
        return (
            f"Trajectory({len(self.keyframes)} keyframes, {self.interpolation}, {self.mode}, "
            f"steepness={self.steepness}, ramp={self.ramp}, {self.start}..{self.end} s)"
        )


# ----------------------------------------------------------------------- quaternions (x, y, z, w)


def _qmul(a: FloatArray, b: FloatArray) -> FloatArray:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ]
    )


def _qconj(q: FloatArray) -> FloatArray:
    return np.array([-q[0], -q[1], -q[2], q[3]])


def _qlog(q: FloatArray) -> FloatArray:
    """The pure quaternion log of a unit quaternion: (axis * half angle, 0)."""
    v = q[:3]
    n = float(np.linalg.norm(v))
    if n < 1e-15:
        return np.zeros(4)
    angle = math.atan2(n, float(q[3]))
    return np.append(v / n * angle, 0.0)


def _qexp(p: FloatArray) -> FloatArray:
    v = p[:3]
    a = float(np.linalg.norm(v))
    if a < 1e-15:
        return np.array([0.0, 0.0, 0.0, 1.0])
    return np.append(v / a * math.sin(a), math.cos(a))


def _slerp(q0: FloatArray, q1: FloatArray, u: float) -> FloatArray:
    """Spherical linear interpolation, exactly ``q0`` at 0 and ``q1`` at 1."""
    if u <= 0.0:
        return q0.copy()
    if u >= 1.0:
        return q1.copy()
    d = float(q0 @ q1)
    if d < 0.0:
        q1, d = -q1, -d
    if d > 1.0 - 1e-12:  # nearly the same: the chord
        q = q0 + u * (q1 - q0)
        return np.asarray(q / np.linalg.norm(q))
    theta = math.acos(d)
    s = math.sin(theta)
    return np.asarray((math.sin((1.0 - u) * theta) / s) * q0 + (math.sin(u * theta) / s) * q1)


def _squad_controls(qs: list[FloatArray]) -> list[FloatArray]:
    """Shoemake's squad control points: ``s_k = q_k exp(-(log(q_k^-1 q_k+1) + log(q_k^-1
    q_k-1)) / 4)`` (the ends their own keyframes)."""
    out = [qs[0].copy()]
    for k in range(1, len(qs) - 1):
        inv = _qconj(qs[k])
        a = _qlog(_qmul(inv, qs[k + 1]))
        b = _qlog(_qmul(inv, qs[k - 1]))
        out.append(_qmul(qs[k], _qexp(-(a + b) / 4.0)))
    out.append(qs[-1].copy())
    return out


def _check_steepness(steepness: float) -> None:
    if not (isinstance(steepness, int | float) and math.isfinite(steepness) and steepness > 0):
        raise ValueError(f"steepness must be a finite number > 0, got {steepness!r}")


def plan(
    keyframes: Sequence[Keyframe],
    interpolation: Interpolation = "linear",
    mode: Mode = "stop",
    steepness: float = DEFAULT_STEEPNESS,
    ramp: float = DEFAULT_RAMP,
) -> Trajectory:
    """Plan the motion through ``keyframes`` (see the module docstring for the design).

    interpolation: ``"linear"`` (straight segments) or ``"spline"`` (natural cubic spline).
    mode: ``"stop"`` (rest at every keyframe) or ``"continuous"`` (rest at the first and last).
    steepness: the sigmoid's n (> 0). ramp: each ramp's share of its segment's time, (0, 0.5].
    Raises ValueError for fewer than 2 keyframes, times not strictly increasing, poses of
    different dimensions, non-finite values or parameters out of range.
    """
    frames = checked_keyframes(keyframes, interpolation, mode, steepness, ramp)
    return Trajectory(frames, interpolation, mode, float(steepness), float(ramp))


def checked_keyframes(
    keyframes: Sequence[Keyframe],
    interpolation: Interpolation,
    mode: Mode,
    steepness: float,
    ramp: float,
) -> list[Keyframe]:
    """The keyframes of a plan and its settings validated as :func:`plan` documents (for a
    :class:`Trajectory` subclass built otherwise, occ/kinematics/port.py); ValueError."""
    if interpolation not in ("linear", "spline"):
        raise ValueError(f"interpolation must be 'linear' or 'spline', got {interpolation!r}")
    if mode not in ("stop", "continuous"):
        raise ValueError(f"mode must be 'stop' or 'continuous', got {mode!r}")
    _check_steepness(steepness)
    if not (isinstance(ramp, int | float) and 0.0 < ramp <= 0.5):
        raise ValueError(f"ramp must be in (0, 0.5] (a share of the segment time), got {ramp!r}")
    frames = list(keyframes)
    if len(frames) < 2:
        raise ValueError(f"a plan needs at least 2 keyframes, got {len(frames)}")
    for i, k in enumerate(frames):
        if not isinstance(k, Keyframe):
            raise ValueError(f"keyframe {i} is not a Keyframe: {k!r}")
    dim = len(frames[0].pose)
    for i, k in enumerate(frames):
        if len(k.pose) != dim:
            raise ValueError(
                f"keyframe {i} has a pose of dimension {len(k.pose)}, keyframe 0 has {dim}"
            )
    with_rotation = [k.rotation is not None for k in frames]
    if any(with_rotation) and not all(with_rotation):
        missing = with_rotation.index(False)
        raise ValueError(
            f"keyframe {missing} has no rotation: in a plan with orientation every keyframe has one"
        )
    for i in range(1, len(frames)):
        if not frames[i].t > frames[i - 1].t:
            raise ValueError(
                f"keyframe times must be strictly increasing: keyframe {i} at "
                f"{frames[i].t} s follows {frames[i - 1].t} s"
            )
    return frames
