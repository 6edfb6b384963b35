"""Kinematics of one serial chain, on pinocchio: forward, Jacobian, inverse, RCM.

A :class:`Frame` wraps a pinocchio model and one tip frame, expressed in a base frame
(the model root by default). Poses are 4x4 homogeneous numpy arrays in metres.

Inverse kinematics
------------------
Both shipped robots are 3-DOF and position-only, so a target is a 3-vector (or a 4x4 whose
orientation is ignored when the chain has fewer than 6 DOF). The solver:

1. tries an *analytic* solver registered for the model's name (``occ_slave``: RCM geometry,
   ``master3``: Cartesian stage). A factory inspects the model and checks its closed form
   numerically against pinocchio at load time; if the URDF was edited into a shape the
   closed form does not describe, the factory declines and DLS is used, so a wrong closed
   form can never silently drive a robot;
2. otherwise runs damped least squares (Levenberg-Marquardt style,
   ``dq = J^T (J J^T + lambda^2 I)^-1 e``) with every iterate projected onto the joint limits.

Joint limits: by default a target that needs a joint outside its limits raises
:class:`~occ.errors.KinematicsError` (naming joint, value and limit). With ``clamp=True`` the
solution is clamped and :class:`IKResult` reports which joints were clamped and the remaining
Cartesian error, so a teleoperation controller can hold the workspace boundary.

Performance: ``fk`` reuses one ``pin.Data`` and updates only the tip frame
(``forwardKinematics`` + ``updateFramePlacement``); a Frame is therefore not thread-safe: use
one per thread (``Frame.copy()``). See ``benchmarks/bench_frame.py`` for timings.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pinocchio as pin

from occ.errors import KinematicsError, caused

__all__ = [
    "Frame",
    "IKResult",
    "AnalyticIK",
    "BUILTIN_MODELS",
    "register_analytic_ik",
    "robots_dir",
]

FloatArray = npt.NDArray[np.float64]
#: An analytic solver: (target position (x, y, z) in the base frame, seed q0 as nq floats) ->
#: candidate solutions, each a sequence of nq floats. Plain floats, no numpy: the
#: teleoperation tick solves at the master's rate, where small-array numpy costs more than the
#: arithmetic.
AnalyticSolver = Callable[[tuple[float, float, float], list[float]], Sequence[Sequence[float]]]
#: A closed-form tip position (base frame, metres) for q, used for the residual instead of a
#: full forward-kinematics pass.
ClosedFK = Callable[[Sequence[float]], Sequence[float]]
#: A rotation as three rows of three floats.
Rows = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
#: A closed-form tip pose (base frame, metres) for q: (rotation rows, position).
ClosedPose = Callable[[Sequence[float]], tuple[Rows, tuple[float, float, float]]]


@dataclass(frozen=True, slots=True)
class AnalyticIK:
    """What an analytic factory returns: the solver, and optionally its closed-form tip
    position (checked against pinocchio when the model loads) for a cheap residual."""

    solve: AnalyticSolver
    position: ClosedFK | None = None
    #: the closed-form tip pose, when the factory has one (checked at load like ``position``)
    pose: ClosedPose | None = None


#: A factory builds a solver for one Frame, or returns None if the model does not fit.
AnalyticFactory = Callable[["Frame"], "AnalyticIK | AnalyticSolver | None"]

#: Shipped models: name -> (URDF file name, tip link).
BUILTIN_MODELS: dict[str, tuple[str, str]] = {
    "occ_slave": ("occ_slave.urdf", "tool_tip"),
    "master3": ("master3.urdf", "handle"),
}

_ANALYTIC: dict[str, AnalyticFactory] = {}
_LIMIT_TOL = 1e-12  # a solution this close past a limit is on the limit
_CHECK_TOL = 1e-9  # metres; closed form vs pinocchio at load time


def robots_dir() -> Path:
    """Directory of the shipped URDFs: the package data ``occ/robots`` (installed with the
    package, found through :mod:`importlib.resources`, so a wheel finds them as a checkout
    does); ``$OCC_ROBOTS_DIR`` overrides it."""
    env = os.environ.get("OCC_ROBOTS_DIR")
    if env:
        return Path(env)
    # a directory on the file system (pinocchio reads files by name): the package is installed
    # unpacked (setuptools' wheels are), never imported from a zip
    return Path(str(resources.files("occ").joinpath("robots")))


def register_analytic_ik(model_name: str, factory: AnalyticFactory) -> None:
    """Register an analytic IK factory for models whose URDF ``<robot name>`` is ``model_name``."""
    _ANALYTIC[model_name] = factory


@dataclass(frozen=True, slots=True)
class IKResult:
    """What :meth:`Frame.solve_ik` found.

    ``error`` is the Cartesian residual (metres for a position task; the norm of the 6-D
    log error for a pose task) at ``q``; ``clamped`` names the joints held at a limit because
    the target needed them beyond it (only non-empty with ``clamp=True``).
    """

    q: FloatArray
    method: str
    iterations: int
    error: float
    clamped: tuple[str, ...]


class Frame:
    """Kinematics of the chain from ``base_link`` to ``tip_link`` of a pinocchio model.

    DLS settings: ``damping`` (lambda, in the task's units), ``max_iterations``,
    ``tolerance`` (Cartesian residual that counts as converged, metres).
    """

    def __init__(
        self,
        model: pin.Model,
        tip_link: str,
        base_link: str | None = None,
        *,
        damping: float = 1e-3,
        max_iterations: int = 100,
        tolerance: float = 1e-8,
    ) -> None:
        if model.nq != model.nv:
            raise KinematicsError(
                f"model {model.name!r}: only revolute/prismatic joints are supported "
                f"(nq={model.nq} != nv={model.nv})"
            )
        if not model.existFrame(tip_link):
            raise KinematicsError(f"model {model.name!r} has no link {tip_link!r}")
        if damping < 0.0 or max_iterations < 1 or tolerance <= 0.0:
            raise ValueError("damping >= 0, max_iterations >= 1 and tolerance > 0 required")
        self.model: pin.Model = model
        self.data: pin.Data = model.createData()
        self.name: str = model.name
        self.tip_link: str = tip_link
        self.base_link: str | None = base_link
        self.damping = float(damping)
        self.max_iterations = int(max_iterations)
        self.tolerance = float(tolerance)
        self._tip_id: int = model.getFrameId(tip_link)
        self._damping_eye3: FloatArray = self.damping**2 * np.eye(3)
        self._damping_eye6: FloatArray = self.damping**2 * np.eye(6)
        self.nq: int = model.nq
        self.joint_names: tuple[str, ...] = tuple(model.names[1:])
        self.lower: FloatArray = np.array(model.lowerPositionLimit, dtype=np.float64)
        self.upper: FloatArray = np.array(model.upperPositionLimit, dtype=np.float64)
        # Plain-float copies: for 3-6 joints, Python comparisons beat numpy's call overhead.
        self._lo: list[float] = self.lower.tolist()
        self._hi: list[float] = self.upper.tolist()
        self._neutral: FloatArray = self._clip(np.zeros(model.nq))

        # The base must be rigidly attached to the root, so base <- root is a constant.
        self._base_inv, self._base_rot_t = _fixed_base(model, base_link)

        self._rcm: FloatArray | None = None
        if model.existFrame("rcm"):
            rcm_frame = model.frames[model.getFrameId("rcm")]
            if rcm_frame.parentJoint == 0:
                self._rcm = self._to_base_point(np.array(rcm_frame.placement.translation))

        self._analytic: AnalyticSolver | None = None
        self._analytic_fk: ClosedFK | None = None
        self._analytic_pose: ClosedPose | None = None
        factory = _ANALYTIC.get(self.name)
        if factory is not None:
            made = factory(self)
            if isinstance(made, AnalyticIK):
                self._analytic, self._analytic_fk = made.solve, made.position
                if made.pose is not None and _check_closed_pose(self, made.pose):
                    self._analytic_pose = made.pose
            else:
                self._analytic = made
        self._lo_hi = list(zip(self._lo, self._hi, strict=True))
        self._neutral_list: list[float] = self._neutral.tolist()

    def set_limits(self, lower: Sequence[float], upper: Sequence[float]) -> None:
        """Narrow the model's joint limits to the robot's configured ones (the intersection
        with the URDF's): every IK (analytic, DLS, clamping) and limit check then keeps to what
        the drivers accept. ValueError when they do not overlap."""
        lo = np.maximum(self.lower, np.asarray(lower, dtype=np.float64))
        hi = np.minimum(self.upper, np.asarray(upper, dtype=np.float64))
        bad = [self.joint_names[i] for i in range(self.nq) if lo[i] > hi[i]]
        if bad:
            raise ValueError(f"{self.name}: configured limits outside the URDF's for {bad}")
        self.model.lowerPositionLimit = lo
        self.model.upperPositionLimit = hi
        self.lower, self.upper = lo, hi
        self._lo, self._hi = lo.tolist(), hi.tolist()
        self._lo_hi = list(zip(self._lo, self._hi, strict=True))
        self._neutral = self._clip(np.zeros(self.nq))
        self._neutral_list = self._neutral.tolist()

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_urdf(
        cls, path: str | os.PathLike[str], tip_link: str, base_link: str | None = None, **kw: Any
    ) -> Frame:
        """Load a URDF (pinocchio's parser) and build the chain to ``tip_link``."""
        path = Path(path)
        if not path.is_file():
            raise KinematicsError(f"URDF not found: {path}")
        try:
            model = pin.buildModelFromUrdf(str(path))
        except (RuntimeError, ValueError) as err:
            raise caused(KinematicsError(f"cannot load URDF {path}: {err}"), err) from err
        return cls(model, tip_link, base_link, **kw)

    @classmethod
    def builtin(cls, name: str, **kw: Any) -> Frame:
        """One of the shipped robots: ``'occ_slave'`` (tip ``tool_tip``) or ``'master3'``
        (tip ``handle``)."""
        try:
            file_name, tip = BUILTIN_MODELS[name]
        except KeyError as err:
            raise caused(
                KinematicsError(
                    f"unknown built-in model {name!r}; known: {', '.join(sorted(BUILTIN_MODELS))}"
                ),
                err,
            ) from err
        # base_link passed positionally: mypyc (2.4.1) passes an empty **kw as the optional
        # positional base_link through ``cls.from_urdf(...)`` ("str or None expected; got dict")
        base_link = kw.pop("base_link", None)
        return cls.from_urdf(robots_dir() / file_name, tip, base_link, **kw)

    def copy(self) -> Frame:
        """An independent Frame on the same model (its own ``pin.Data``), for another thread."""
        return Frame(
            self.model,
            self.tip_link,
            self.base_link,
            damping=self.damping,
            max_iterations=self.max_iterations,
            tolerance=self.tolerance,
        )

    def __repr__(self) -> str:
        return (
            f"Frame({self.name!r}, tip={self.tip_link!r}, joints={list(self.joint_names)}, "
            f"analytic_ik={self.has_analytic_ik})"
        )

    # ------------------------------------------------------------------ queries
    @property
    def has_analytic_ik(self) -> bool:
        """True when a registered closed form matched this model at load time."""
        return self._analytic is not None

    @property
    def rcm(self) -> FloatArray | None:
        """Remote centre of motion in the base frame, or None.

        Taken from the URDF's fixed ``rcm`` link, else from the RCM analytic solver.
        """
        return None if self._rcm is None else self._rcm.copy()

    @property
    def neutral(self) -> FloatArray:
        """The zero configuration clamped into the limits: the default IK seed."""
        return self._neutral.copy()

    def within_limits(self, q: Sequence[float] | FloatArray) -> bool:
        """True when every joint of ``q`` is inside its limits."""
        values = q.tolist() if isinstance(q, np.ndarray) else list(q)
        for v, lo, hi in zip(values, self._lo, self._hi, strict=True):
            if not (lo - _LIMIT_TOL <= v <= hi + _LIMIT_TOL):
                return False
        return True

    def _clip(self, q: FloatArray) -> FloatArray:
        # np.minimum(np.maximum()) is about 3x faster than np.clip on tiny arrays.
        return np.minimum(np.maximum(q, self.lower), self.upper)

    # ------------------------------------------------------------------ forward
    def _q(self, q: Sequence[float] | FloatArray) -> FloatArray:
        qa = np.asarray(q, dtype=np.float64)
        if qa.shape != (self.nq,):
            raise ValueError(f"{self.name}: q must have shape ({self.nq},), got {qa.shape}")
        return qa

    def _placement(self, q: FloatArray) -> pin.SE3:
        pin.forwardKinematics(self.model, self.data, q)
        placement = pin.updateFramePlacement(self.model, self.data, self._tip_id)
        if self._base_inv is not None:
            return self._base_inv * placement
        return placement

    def fk(self, q: Sequence[float] | FloatArray) -> FloatArray:
        """Tip pose in the base frame, 4x4 homogeneous (metres)."""
        return self._placement(self._q(q)).homogeneous

    def position(self, q: Sequence[float] | FloatArray) -> FloatArray:
        """Tip position in the base frame (3,), metres; a little cheaper than ``fk``."""
        return np.array(self._placement(self._q(q)).translation)

    def tip_position(self, q: Sequence[float] | FloatArray) -> tuple[float, float, float]:
        """Tip position in the base frame as three floats, metres: the analytic model's closed
        form when it has one (checked against pinocchio when the model loaded), else
        :meth:`position`. The per-tick variant (no numpy on the way)."""
        closed = self._analytic_fk
        if closed is not None:
            x, y, z = closed(q.tolist() if isinstance(q, np.ndarray) else q)
            return (float(x), float(y), float(z))
        x, y, z = self.position(q).tolist()
        return (x, y, z)

    def tip_pose(self, q: Sequence[float]) -> tuple[Rows, tuple[float, float, float]]:
        """Tip pose in the base frame as plain floats: (rotation rows, position in metres).
        The analytic model's closed form when it has one (checked against pinocchio when the
        model loaded), else :meth:`fk`. The per-sample variant (a slave's return channel at
        500 Hz): no numpy on the way."""
        closed = self._analytic_pose
        if closed is not None:
            return closed(q)
        m = self.fk(q).tolist()
        r0, r1, r2 = m[0], m[1], m[2]
        return (
            ((r0[0], r0[1], r0[2]), (r1[0], r1[1], r1[2]), (r2[0], r2[1], r2[2])),
            (r0[3], r1[3], r2[3]),
        )

    def jacobian(self, q: Sequence[float] | FloatArray) -> FloatArray:
        """6 x nq Jacobian of the tip: rows 0-2 linear velocity of the tip point, rows 3-5
        angular velocity, both expressed in base-frame axes."""
        qa = self._q(q)
        jac = pin.computeFrameJacobian(
            self.model, self.data, qa, self._tip_id, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
        )
        if self._base_rot_t is not None:
            jac = np.vstack((self._base_rot_t @ jac[:3], self._base_rot_t @ jac[3:]))
        return np.asarray(jac)

    def _to_base_point(self, p_root: FloatArray) -> FloatArray:
        if self._base_inv is None:
            return p_root
        return np.asarray(self._base_inv.act(p_root), dtype=np.float64)

    # ------------------------------------------------------------------ inverse
    def ik(
        self,
        target: Sequence[float] | FloatArray,
        q0: Sequence[float] | FloatArray | None = None,
        *,
        clamp: bool = False,
        method: str = "auto",
    ) -> FloatArray:
        """Joint positions that put the tip at ``target`` (see :meth:`solve_ik`)."""
        return self.solve_ik(target, q0, clamp=clamp, method=method).q

    def solve_ik(
        self,
        target: Sequence[float] | FloatArray,
        q0: Sequence[float] | FloatArray | None = None,
        *,
        clamp: bool = False,
        method: str = "auto",
    ) -> IKResult:
        """Inverse kinematics with a report.

        ``target``: a 3-vector tip position or a 4x4 pose (orientation used only when the
        chain has 6 or more DOF). ``q0``: seed and tie-breaker (closest analytic branch);
        default :attr:`neutral`. ``method``: ``'auto'`` (analytic if available), ``'analytic'``
        or ``'dls'``. Raises :class:`KinematicsError` if the target is unreachable within the
        limits (unless ``clamp``), or if DLS does not converge.
        """
        if method not in ("auto", "analytic", "dls"):
            raise ValueError(f"method must be 'auto', 'analytic' or 'dls', got {method!r}")
        pose: pin.SE3 | None = None
        if isinstance(target, (tuple, list)) and len(target) == 3:
            xyz = (float(target[0]), float(target[1]), float(target[2]))  # no numpy: cheapest
        else:
            tgt = np.asarray(target, dtype=np.float64)
            if tgt.shape == (4, 4):
                if not all(math.isfinite(v) for v in tgt.flat):
                    raise ValueError("target must be finite")
                if self.nq >= 6:
                    pose = pin.SE3(tgt)
                xyz = tuple(tgt[:3, 3].tolist())
            elif tgt.shape == (3,):
                xyz = tuple(tgt.tolist())
            else:
                raise ValueError(f"target must be a 3-vector or a 4x4 pose, got shape {tgt.shape}")
        if not (math.isfinite(xyz[0]) and math.isfinite(xyz[1]) and math.isfinite(xyz[2])):
            raise ValueError("target must be finite")
        if q0 is None:
            seed = self._neutral_list
        else:
            seed = q0.tolist() if isinstance(q0, np.ndarray) else [float(v) for v in q0]
            if len(seed) != self.nq:
                raise ValueError(f"{self.name}: q must have shape ({self.nq},), got ({len(seed)},)")

        if pose is None and method != "dls" and self._analytic is not None:
            return self._solve_analytic(xyz, seed, clamp)
        if method == "analytic":
            raise KinematicsError(f"model {self.name!r}: no analytic IK for this target")
        return self._solve_dls(
            np.array(xyz, dtype=np.float64), pose, np.array(seed, dtype=np.float64), clamp
        )

    def ik_clamped(
        self, position: tuple[float, float, float], seed: list[float]
    ) -> tuple[list[float], bool]:
        """``solve_ik(position, seed, clamp=True)`` as ``(q, clamped)`` in plain floats.

        The same answer (a test compares them), without the report's residual and arrays:
        teleoperation calls this at the master's rate on the control loop. Raises ValueError
        for a target that is not finite, KinematicsError as :meth:`solve_ik`.
        """
        x, y, z = position
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            raise ValueError("target must be finite")
        analytic = self._analytic
        if analytic is not None:
            tol = _LIMIT_TOL
            lo_hi = self._lo_hi
            best: Sequence[float] | None = None
            best_d = math.inf
            # plain loops, no generators: this runs every tick (a generator per candidate cost
            # more than the arithmetic, tools/stability.py's profile)
            for q in analytic(position, seed):
                inside = True
                d = 0.0
                for i, (lo, hi) in enumerate(lo_hi):
                    v = q[i]
                    if not lo - tol <= v <= hi + tol:  # NaN too
                        inside = False
                        break
                    if i < len(seed):
                        e = v - seed[i]
                        d += e * e
                if inside and (best is None or d < best_d):
                    best, best_d = q, d
            if best is not None:
                out = []
                for i, (lo, hi) in enumerate(lo_hi):
                    v = best[i]
                    out.append(lo if v < lo else hi if v > hi else v)
                return out, False
        res = self.solve_ik(position, seed, clamp=True)
        return res.q.tolist(), bool(res.clamped)

    def _solve_analytic(
        self, position: tuple[float, float, float], seed: list[float], clamp: bool
    ) -> IKResult:
        # Plain floats throughout: this runs on the control loop at the master's rate, where
        # each small-array numpy call costs more than the arithmetic it does.
        assert self._analytic is not None
        candidates = self._analytic(position, seed)
        tol = _LIMIT_TOL
        lo_hi = self._lo_hi
        inside = [
            q
            for q in candidates
            if all(lo - tol <= v <= hi + tol for v, (lo, hi) in zip(q, lo_hi, strict=True))
        ]
        if inside:
            if len(inside) == 1:
                best = inside[0]
            else:
                best = min(
                    inside,
                    key=lambda q: sum((a - b) ** 2 for a, b in zip(q, seed, strict=False)),
                )
            q = [
                lo if v < lo else hi if v > hi else v
                for v, (lo, hi) in zip(best, lo_hi, strict=True)
            ]
            return IKResult(
                np.array(q, dtype=np.float64), "analytic", 0, self._residual(q, position), ()
            )
        if not candidates:
            raise KinematicsError(f"{self.name}: no solution for target {list(position)}")
        arrays = [np.asarray(q, dtype=np.float64) for q in candidates]
        best_a = min(arrays, key=lambda q: _violation(self, q))
        if not clamp:
            raise KinematicsError(
                f"{self.name}: target {[round(v, 6) for v in position]} unreachable within "
                f"limits: {_describe_violation(self, best_a)}"
            )
        clamped = _clamped_names(self, best_a)
        qa = self._clip(best_a)
        return IKResult(qa, "analytic", 0, self._residual(qa, position), clamped)

    def dls_step(
        self, q: Sequence[float] | FloatArray, target: Sequence[float] | FloatArray
    ) -> FloatArray:
        """One damped-least-squares step toward a 3-vector ``target`` (projected on limits)."""
        qa = self._q(q)
        tgt = np.asarray(target, dtype=np.float64)
        err = tgt - self._placement(qa).translation
        return self._dls_update(qa, err, None)

    def _dls_update(self, q: FloatArray, err: FloatArray, pose_task: bool | None) -> FloatArray:
        if pose_task:
            jac = pin.computeFrameJacobian(
                self.model, self.data, q, self._tip_id, pin.ReferenceFrame.LOCAL
            )
        else:
            jac = pin.computeFrameJacobian(
                self.model, self.data, q, self._tip_id, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
            )[:3]
            if self._base_rot_t is not None:
                jac = self._base_rot_t @ jac
        jjt = jac @ jac.T
        jjt += self._damping_eye6 if pose_task else self._damping_eye3
        dq = jac.T @ np.linalg.solve(jjt, err)
        return self._clip(q + dq)

    def _solve_dls(
        self, position: FloatArray, pose: pin.SE3 | None, seed: FloatArray, clamp: bool
    ) -> IKResult:
        q = self._clip(seed)
        error = math.inf
        iterations = 0
        stalled = False
        for iterations in range(1, self.max_iterations + 1):
            placement = self._placement(q)
            if pose is None:
                err = position - placement.translation
            else:
                err = pin.log6(placement.actInv(pose)).vector
            error = math.sqrt(float(err @ err))
            if error < self.tolerance:
                return IKResult(q, "dls", iterations - 1, error, ())
            q_next = self._dls_update(q, err, pose is not None)
            if float(np.max(np.abs(q_next - q))) < 1e-14:
                stalled = True
                break
            q = q_next
        at_limit = _at_limit_names(self, q)
        if stalled and at_limit:
            if clamp:
                return IKResult(q, "dls", iterations, error, at_limit)
            raise KinematicsError(
                f"{self.name}: target unreachable within limits (DLS stopped at joints "
                f"{list(at_limit)} on their limits, residual {error:.3g})"
            )
        raise KinematicsError(
            f"{self.name}: DLS did not converge in {iterations} iterations "
            f"(residual {error:.3g}, tolerance {self.tolerance:.3g})"
        )

    # ------------------------------------------------------------------ helpers
    def _residual(
        self, q: Sequence[float] | FloatArray, position: Sequence[float] | FloatArray
    ) -> float:
        closed = self._analytic_fk
        if closed is not None:
            x, y, z = closed(q.tolist() if isinstance(q, np.ndarray) else q)
            px, py, pz = position
            return math.sqrt((x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2)
        d = self._placement(np.asarray(q, dtype=np.float64)).translation - np.asarray(position)
        return math.sqrt(float(d @ d))


# ---------------------------------------------------------------------- the base
def _fixed_base(
    model: pin.Model, base_link: str | None
) -> tuple[pin.SE3 | None, FloatArray | None]:
    """``base_link``'s placement on the root, inverted, and its rotation transposed (None,
    None: no base link, or one at the root's origin); KinematicsError for a base link that is
    missing or moves with a joint."""
    if base_link is None:
        return None, None
    if not model.existFrame(base_link):
        raise KinematicsError(f"model {model.name!r} has no link {base_link!r}")
    base_frame = model.frames[model.getFrameId(base_link)]
    if base_frame.parentJoint != 0:
        raise KinematicsError(
            f"base link {base_link!r} moves with joint "
            f"{model.names[base_frame.parentJoint]!r}; it must be fixed to the root"
        )
    if base_frame.placement.isIdentity():
        return None, None
    return base_frame.placement.inverse(), np.ascontiguousarray(base_frame.placement.rotation.T)


# ---------------------------------------------------------------------- limit reports
def _violation(frame: Frame, q: FloatArray) -> float:
    """How far ``q`` is outside ``frame``'s joint limits, summed over the joints."""
    return float(np.sum(np.maximum(frame.lower - q, 0.0) + np.maximum(q - frame.upper, 0.0)))


def _clamped_names(frame: Frame, q: FloatArray) -> tuple[str, ...]:
    """The joints of ``q`` outside ``frame``'s limits (a clip moves them)."""
    return tuple(
        name
        for name, v, lo, hi in zip(frame.joint_names, q, frame.lower, frame.upper, strict=True)
        if v < lo - _LIMIT_TOL or v > hi + _LIMIT_TOL
    )


def _at_limit_names(frame: Frame, q: FloatArray) -> tuple[str, ...]:
    """The joints of ``q`` on (or beyond) one of ``frame``'s limits."""
    return tuple(
        name
        for name, v, lo, hi in zip(frame.joint_names, q, frame.lower, frame.upper, strict=True)
        if v <= lo + _LIMIT_TOL or v >= hi - _LIMIT_TOL
    )


def _describe_violation(frame: Frame, q: FloatArray) -> str:
    """Each joint of ``q`` outside ``frame``'s limits, with what it needs, in words."""
    parts = []
    for name, v, lo, hi in zip(frame.joint_names, q, frame.lower, frame.upper, strict=True):
        if v < lo - _LIMIT_TOL or v > hi + _LIMIT_TOL:
            parts.append(f"joint {name} needs {v:.6g}, limits [{lo:.6g}, {hi:.6g}]")
    return "; ".join(parts)


# ---------------------------------------------------------------------- analytic solvers
def _check_configs(frame: Frame, seed: int) -> list[FloatArray]:
    """Eight fixed pseudo-random configurations in the frame's limits (±1 where unlimited),
    where a closed form is compared with pinocchio."""
    rng = np.random.default_rng(seed)
    lo = np.where(np.isfinite(frame.lower), frame.lower, -1.0)
    hi = np.where(np.isfinite(frame.upper), frame.upper, 1.0)
    return [rng.uniform(lo, hi) for _ in range(8)]


def _check_closed_form(frame: Frame, closed: ClosedFK) -> bool:
    """Compare a closed-form tip position with pinocchio at fixed pseudo-random configurations."""
    return all(
        np.max(np.abs(frame.position(q) - np.asarray(closed(q.tolist())))) <= _CHECK_TOL
        for q in _check_configs(frame, 12345)
    )


def _check_closed_pose(frame: Frame, closed: ClosedPose) -> bool:
    """Compare a closed-form tip pose with pinocchio at fixed pseudo-random configurations."""
    for q in _check_configs(frame, 54321):
        rows, pos = closed(q.tolist())
        want = frame.fk(q)
        got = np.array([[*rows[i], pos[i]] for i in range(3)])
        if np.max(np.abs(got - want[:3])) > _CHECK_TOL:
            return False
    return True


def _rows(m: FloatArray) -> Rows:
    r = m.tolist()
    return (
        (float(r[0][0]), float(r[0][1]), float(r[0][2])),
        (float(r[1][0]), float(r[1][1]), float(r[1][2])),
        (float(r[2][0]), float(r[2][1]), float(r[2][2])),
    )


def _rcm_factory(frame: Frame) -> AnalyticIK | None:
    """Closed form of a yaw(z) / pitch(x) / insertion(-z) chain through an RCM point.

    tip = rcm + (d0 + q2) * (-sin q0 sin q1, cos q0 sin q1, -cos q1), where ``rcm`` is the
    origin of the first joint and ``d0`` the tip's distance past the RCM at zero insertion.
    Two branches, (yaw, pitch) and (yaw - pi, -pitch); the caller keeps the one in limits.
    """
    if frame.nq != 3:
        return None
    model = frame.model
    rcm = frame._to_base_point(np.array(model.jointPlacements[1].translation))
    tip0 = frame.position(np.zeros(3))
    d0 = float(rcm[2] - tip0[2])

    rx, ry, rz = rcm.tolist()

    def closed(q: Sequence[float]) -> tuple[float, float, float]:
        d = d0 + q[2]
        s1 = math.sin(q[1])
        return (rx - d * math.sin(q[0]) * s1, ry + d * math.cos(q[0]) * s1, rz - d * math.cos(q[1]))

    if not _check_closed_form(frame, closed):
        return None
    if frame._rcm is None:
        frame._rcm = rcm

    def solve(target: tuple[float, float, float], q0: list[float]) -> list[tuple[float, ...]]:
        tx, ty, tz = target
        wx, wy, wz = tx - rx, ty - ry, tz - rz
        dist = math.sqrt(wx * wx + wy * wy + wz * wz)
        if dist < 1e-9:
            raise KinematicsError(f"{frame.name}: target at the RCM point: direction undefined")
        insertion = dist - d0
        radial = math.hypot(wx, wy)
        if radial < 1e-12 * dist:
            # On the vertical axis: yaw is free, keep the seed's.
            pitch = math.atan2(0.0, -wz)
            return [(float(q0[0]), pitch, insertion)]
        pitch = math.atan2(radial, -wz)
        yaw = math.atan2(-wx, wy)
        yaw_b = yaw - math.pi if yaw > 0.0 else yaw + math.pi
        return [(yaw, pitch, insertion), (yaw_b, -pitch, insertion)]

    # the tip's rotation: yaw about z, then pitch about x, then the tool's rotation at zero
    # (what the position's closed form says too: the tool axis is Rz(q0) Rx(q1) (0, 0, -1))
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = _rows(frame.fk(np.zeros(3))[:3, :3])

    def pose(q: Sequence[float]) -> tuple[Rows, tuple[float, float, float]]:
        c0, s0 = math.cos(q[0]), math.sin(q[0])
        c1, s1 = math.cos(q[1]), math.sin(q[1])
        d = d0 + q[2]
        # Rz(q0) Rx(q1) = [[c0, -s0 c1, s0 s1], [s0, c0 c1, -c0 s1], [0, s1, c1]]
        b00, b01, b02 = c0, -s0 * c1, s0 * s1
        b10, b11, b12 = s0, c0 * c1, -c0 * s1
        b21, b22 = s1, c1
        return (
            (
                (
                    b00 * a00 + b01 * a10 + b02 * a20,
                    b00 * a01 + b01 * a11 + b02 * a21,
                    b00 * a02 + b01 * a12 + b02 * a22,
                ),
                (
                    b10 * a00 + b11 * a10 + b12 * a20,
                    b10 * a01 + b11 * a11 + b12 * a21,
                    b10 * a02 + b11 * a12 + b12 * a22,
                ),
                (b21 * a10 + b22 * a20, b21 * a11 + b22 * a21, b21 * a12 + b22 * a22),
            ),
            (rx - d * s0 * s1, ry + d * c0 * s1, rz - d * c1),
        )

    return AnalyticIK(solve, closed, pose)


def _cartesian_factory(frame: Frame) -> AnalyticIK | None:
    """Closed form of a chain of prismatic joints: tip = p0 + A q, A constant and invertible."""
    if frame.nq != 3:
        return None
    p0 = frame.position(np.zeros(3))
    axes = np.column_stack([frame.position(np.eye(3)[i]) - p0 for i in range(3)])
    if abs(np.linalg.det(axes)) < 1e-12:
        return None
    inverse = np.linalg.inv(axes)

    p = p0.tolist()
    a = axes.tolist()
    inv = inverse.tolist()

    def closed(q: Sequence[float]) -> tuple[float, float, float]:
        q0, q1, q2 = q
        return (
            p[0] + a[0][0] * q0 + a[0][1] * q1 + a[0][2] * q2,
            p[1] + a[1][0] * q0 + a[1][1] * q1 + a[1][2] * q2,
            p[2] + a[2][0] * q0 + a[2][1] * q1 + a[2][2] * q2,
        )

    if not _check_closed_form(frame, closed):
        return None

    def solve(target: tuple[float, float, float], q0: list[float]) -> list[tuple[float, ...]]:
        tx, ty, tz = target
        dx, dy, dz = tx - p[0], ty - p[1], tz - p[2]
        return [
            (
                inv[0][0] * dx + inv[0][1] * dy + inv[0][2] * dz,
                inv[1][0] * dx + inv[1][1] * dy + inv[1][2] * dz,
                inv[2][0] * dx + inv[2][1] * dy + inv[2][2] * dz,
            )
        ]

    rotation = _rows(frame.fk(np.zeros(3))[:3, :3])  # prismatic joints: it never changes

    def pose(q: Sequence[float]) -> tuple[Rows, tuple[float, float, float]]:
        return rotation, closed(q)

    return AnalyticIK(solve, closed, pose)


register_analytic_ik("occ_slave", _rcm_factory)
register_analytic_ik("master3", _cartesian_factory)


def chain_hash(frame: Frame) -> str:
    """A short hash of ``frame``'s kinematic chain: each joint's name, type (its axis with it)
    and placement in its parent (to 1 um / 1 urad), the tip and base links. Two daemons that
    agree on it agree on where an arm is for the same joint positions (a cell member's
    heartbeat carries it, occ/net/celllink.py)."""
    import hashlib

    model = frame.model
    h = hashlib.sha256()
    for i in range(1, model.njoints):
        m = model.jointPlacements[i]
        numbers = np.round(np.concatenate([m.rotation.ravel(), m.translation]), 6) + 0.0
        h.update(f"{model.names[i]}|{model.joints[i].shortname()}|".encode())
        h.update(",".join(f"{v:.6f}" for v in numbers).encode())
    h.update(f"|{frame.tip_link}|{frame.base_link}".encode())
    return h.hexdigest()[:16]
