"""Keyframe plans: what a plan is made from (:class:`PlanRequest`), the planning and the check
of every tick of it as it would run (:func:`build_plan`, on the planner thread), and what
passed (:class:`CheckedPlan`). The checks are listed in :mod:`occ.controllers.keyframe`'s
docstring, "Plan, check and preview"."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Literal, NoReturn, Protocol

import numpy as np

from occ.config import Vec3
from occ.controllers.keyframe.pacer import Pacer
from occ.controllers.keyframe.sets import KeyframeSet, PlanSettings, Space
from occ.errors import CommandError, KinematicsError
from occ.joint import JointLimits
from occ.kinematics.cellpaths import ArmPath, path_digest
from occ.kinematics.port import (
    SHAFT_BOUND_M,
    PortMismatch,
    PortTrajectory,
    ShaftWatch,
    keyframes_through_port,
    port_in_base,
    port_plan,
    shaft_offset,
)
from occ.kinematics.trajectory import Keyframe, Trajectory, plan
from occ.samples import quaternion_to_rotation, rotation_to_quaternion

if TYPE_CHECKING:
    from occ.controllers import ControllerContext
    from occ.controllers.keyframe.params import KeyframeParams
    from occ.core.data import RobotData
    from occ.kinematics.frame import Frame

MM = 1e-3
#: most samples of a cell set's part: an NDARRAY's dimension is at most 65535
MAX_CELL_SAMPLES = 65535


class ForbiddenCheck(Protocol):
    """Whether a tip position (metres, robot base frame) is forbidden: a false value when it
    is free, True or a short description of what it hits when it is not."""

    def __call__(self, point: tuple[float, float, float], /) -> str | bool | None: ...


class PathCheck(Protocol):
    """A whole-arm check of a plan's joint path (occ/kinematics/collision.py ``PathCheck``): given
    the plan's samples (one per loop period, joint values), the base pose (world <- base) and
    the pacer, None when clear, else (the first sample that fails, what it hits)."""

    def check_path(
        self,
        qs: Sequence[Sequence[float]],
        base: np.ndarray,
        pace: Callable[[], None] | None,
        /,
    ) -> tuple[int, str] | None: ...


class PlanRefused(Exception):
    """A plan that failed its checks (the message names the keyframe and the limit)."""


@dataclass(frozen=True)
class PlanRequest:
    """Everything a plan is made from, snapshot on the loop thread when it is asked for."""

    id: int
    kset: KeyframeSet
    q_start: tuple[float, ...]
    base: np.ndarray  # world <- base, metres
    interpolation: Literal["linear", "spline"]
    mode: Literal["stop", "continuous"]
    steepness: float
    ramp: float
    period: float
    joint_names: tuple[str, ...]
    limits: tuple[JointLimits, ...]
    velocity_scale: float
    start_tolerance: float
    start_tolerance_mm: float
    workspace: tuple[Vec3, Vec3] | None  # metres, base frame
    forbidden: tuple[ForbiddenCheck, ...]
    max_duration_s: float
    preview_points: int
    #: Cartesian with orientation: how far keyframe 0 may be turned from the tool (rad)
    start_tolerance_rad: float = 0.0087
    #: called between samples: gives the interpreter back to the loop (None: never)
    pace: Pacer | None = None
    #: whole-arm checks of the sampled joint path (after the per-tick checks)
    path_checks: tuple[PathCheck, ...] = ()
    #: a laparoscopic tool's port (base frame, metres; None: no port) and its rules: how far a
    #: keyframe's given axis may be from the port's (rad), the tip's least depth beyond it (m)
    port: np.ndarray | None = None
    port_tolerance_rad: float = 0.0087
    port_min_depth: float = 0.01
    #: a part of a cell set: this member's name; the plan keeps its sampled joint path and
    #: its digest (they are exchanged with the other members). None: not kept
    cell_member: str | None = None


@dataclass(frozen=True)
class CheckedPlan:
    """A plan that passed every check, with what is needed to run and preview it."""

    id: int
    space: Space
    traj: Trajectory  # joint SI, or the tip in the base frame (metres)
    labels: tuple[str, ...]  # of the plan's keyframes (the implicit start included)
    point_names: tuple[str, ...]  # short names for the previewed points
    q_start: tuple[float, ...]
    q_end: tuple[float, ...]
    path_mm: np.ndarray  # (n, 3) tip path, world mm (decimated)
    keys_mm: np.ndarray  # (k, 3) keyframe tip positions, world mm
    peak: tuple[str, float]  # the joint closest to its velocity limit, and the share used
    summary: str
    ticks: int
    #: the set it was planned from, and how (what KeyframeSave stores once it is acknowledged)
    kset: KeyframeSet | None = None
    settings: PlanSettings | None = None
    #: the base pose it was planned with (world <- base, m) and the period it was sampled at
    base: np.ndarray | None = None
    period: float = 0.0
    #: the joints commanded at each loop period from t = 0 (samples x joints) and their
    #: digest (occ/kinematics/cellpaths.py): kept for a part of a cell set, else None and ''
    qs: np.ndarray | None = None
    digest: str = ""


def rotation_to_quaternion_np(r: np.ndarray) -> np.ndarray:
    return np.array(rotation_to_quaternion(np.asarray(r)), dtype=float)


def pose_ik(
    frame: Frame, traj: Trajectory, t: float, seed: Sequence[float]
) -> tuple[list[float], bool]:
    """The joints for the plan's full pose at ``t`` (position and orientation, base frame):
    damped least squares from ``seed`` (the previous tick), the limits held; ``clamped`` when
    a joint had to stop at a limit. KinematicsError when the pose is not reached (residual over
    1e-6: a position in metres and an angle in radians)."""
    pose = np.eye(4)
    pose[:3, :3] = (
        traj.rotation(t)
        if isinstance(traj, PortTrajectory)
        else quaternion_to_rotation(traj.orientation(t).tolist())
    )
    pose[:3, 3] = traj.position(t)
    res = frame.solve_ik(pose, list(seed), clamp=True, method="dls")
    if res.error > 1e-6 and not res.clamped:
        raise KinematicsError(f"the pose is not reached (residual {res.error:.3g})")
    return res.q.tolist(), bool(res.clamped)


def _where(t: float, times: Sequence[float], labels: Sequence[str], period: float) -> str:
    """Which keyframe (or segment between two) time ``t`` falls on, for a refusal."""
    for i, tk in enumerate(times):
        if abs(t - tk) <= 0.5 * period:
            return f"at {labels[i]}"
    for i in range(len(times) - 1):
        if times[i] < t < times[i + 1]:
            return f"at t={t:.3f} s, between {labels[i]} and {labels[i + 1]}"
    return f"at t={t:.3f} s"


@dataclass
class _Timeline:
    """The keyframes a plan goes through, in the units it is planned in (joint SI, or the tip
    in the base frame, metres), the start joined to where the robot is."""

    frames: list[Keyframe]
    labels: list[str]  # for refusals (the implicit start included)
    short: list[str]  # the previewed points' names
    cart: bool
    oriented: bool  # Cartesian with the tool's orientation
    notes: list[str] = field(default_factory=list)  # said in the plan's summary
    #: a joint set planned through a port: its keyframes' joints (the arm must reach them)
    joint_keys: list[tuple[float, ...]] | None = None


def build_plan(req: PlanRequest, frame: Frame) -> CheckedPlan:
    """Plan ``req`` and check every tick of it (see the package docstring); PlanRefused with
    the reason otherwise. Runs on the planner thread with a Frame of its own."""
    if req.pace is not None:
        req.pace.begin()
    tl = _timeline(req, frame)
    try:
        if req.port is not None:
            traj: Trajectory = port_plan(
                tl.frames, req.port, req.interpolation, req.mode, req.steepness, req.ramp
            )
        else:
            traj = plan(tl.frames, req.interpolation, req.mode, req.steepness, req.ramp)
    except ValueError as err:
        raise PlanRefused(f"cannot plan: {err}") from err
    ticks = math.ceil(traj.end / req.period - 1e-9)
    checks = _TickChecks(req, [k.t for k in tl.frames], tl.labels)
    watch = ShaftWatch(req.port) if req.port is not None else None
    path, qs = _sample(req, frame, traj, tl, checks, ticks, watch)
    if watch is not None:
        _port_verdict(req, tl, checks, watch, qs)
    for path_check in req.path_checks:
        crossing = path_check.check_path(qs, req.base, req.pace)
        if crossing is not None:
            t = min(crossing[0] * req.period, traj.end)
            raise PlanRefused(f"{crossing[1]} {checks.where(t)}")
    checked = _checked(req, frame, traj, tl, checks, path, qs[-1], ticks)
    if req.cell_member is not None:
        if len(qs) > MAX_CELL_SAMPLES:
            raise PlanRefused(
                f"a part of a cell set is exchanged as an NDARRAY of at most "
                f"{MAX_CELL_SAMPLES} samples; this plan has {len(qs)} ({traj.end:.1f} s)"
            )
        arr = np.array(qs, dtype=float)
        digest = path_digest(ArmPath(req.cell_member, arr, req.base, req.period))
        checked = replace(checked, qs=arr, digest=digest)
    return checked


def _timeline(req: PlanRequest, frame: Frame) -> _Timeline:
    """The set's keyframes in the plan's units, starting where the robot is (an implicit
    keyframe at t = 0, or keyframe 0 replaced by the robot's pose when within tolerance);
    PlanRefused when keyframe 0 is too far from it or the plan too long."""
    kset = req.kset
    cart = kset.space == "cartesian"
    here: tuple[float, ...] = (
        tuple(float(v) for v in frame.tip_position(list(req.q_start))) if cart else req.q_start
    )
    oriented = cart and kset.keyframes[0].rotation is not None
    if oriented and frame.nq < 6:
        raise PlanRefused(
            f"the keyframes have orientations, but {frame.name!r} has {frame.nq} joints: "
            "orientation needs a 6-DOF arm"
        )
    here_rot = (
        rotation_to_quaternion_np(np.asarray(frame.fk(list(req.q_start)))[:3, :3])
        if oriented
        else None
    )
    tl = _Timeline(
        frames=_base_frames(req) if cart else list(kset.keyframes),
        labels=[kset.label(i) for i in range(len(kset.keyframes))],
        short=[f"{kset.names[i] or f'K{i}'} t={k.t:g}s" for i, k in enumerate(kset.keyframes)],
        cart=cart,
        oriented=oriented,
    )
    _join_start(req, tl, here, here_rot)
    if req.port is not None:
        _onto_port(req, frame, tl)
    if tl.frames[-1].t > req.max_duration_s:
        raise PlanRefused(
            f"{tl.labels[-1]}: the plan would last {tl.frames[-1].t:g} s, more than "
            f"max_duration_s ({req.max_duration_s:g})"
        )
    return tl


def _base_frames(req: PlanRequest) -> list[Keyframe]:
    """A Cartesian set's keyframes in the robot's base frame (metres; from world mm)."""
    r_t = req.base[:3, :3].T
    origin = req.base[:3, 3]

    def to_base(p_mm: Sequence[float]) -> np.ndarray:
        return np.asarray(r_t @ (np.asarray(p_mm, dtype=float) * MM - origin), dtype=float)

    def to_base_rotation(q: Sequence[float] | None) -> np.ndarray | None:
        if q is None:
            return None
        return rotation_to_quaternion_np(r_t @ quaternion_to_rotation(q))

    return [
        Keyframe(k.t, to_base(k.pose), to_base_rotation(k.rotation)) for k in req.kset.keyframes
    ]


def _join_start(
    req: PlanRequest, tl: _Timeline, here: tuple[float, ...], here_rot: np.ndarray | None
) -> None:
    """Make the timeline start at the robot's pose ``here`` (and turn ``here_rot``)."""
    first = tl.frames[0]
    gap = float(np.linalg.norm(np.subtract(first.pose, here)))
    if tl.oriented and first.t == 0.0:
        assert first.rotation is not None and here_rot is not None
        turn = 2.0 * math.acos(min(1.0, abs(float(np.dot(first.rotation, here_rot)))))
        if turn > req.start_tolerance_rad:
            raise PlanRefused(
                f"{tl.labels[0]} is turned {math.degrees(turn):.3g} deg from the tool (tolerance "
                f"{math.degrees(req.start_tolerance_rad):g} deg): give keyframe 0 a later time "
                "so the robot turns there, or turn it"
            )
    if first.t > 0.0:
        tl.frames.insert(0, Keyframe(0.0, here, here_rot))
        tl.labels.insert(0, "the start (the robot's pose)")
        tl.short.insert(0, "start t=0s")
        return
    cart = tl.cart
    tol = req.start_tolerance_mm * MM if cart else req.start_tolerance
    if gap > tol:
        unit, scale = ("mm", 1 / MM) if cart else ("rad/m", 1.0)
        raise PlanRefused(
            f"{tl.labels[0]} is {gap * scale:.4g} {unit} from where the robot is (tolerance "
            f"{tol * scale:g}): a run starts where the robot is; give keyframe 0 a later "
            "time so the robot moves there, or move it"
        )
    tl.frames[0] = Keyframe(0.0, here, here_rot)
    if gap > 0.0:
        unit = "mm" if cart else "rad/m"
        tl.notes.append(
            f"keyframe 0 replaced by the robot's pose ({gap / (MM if cart else 1):.3g} {unit} away)"
        )


#: how far (rad) a joint may be, at a keyframe of a joint set planned through a port, from the
#: keyframe's value: the same tool pose reached by another arm configuration is further apart
CONFIGURATION_TOLERANCE_RAD = 0.1


def _onto_port(req: PlanRequest, frame: Frame, tl: _Timeline) -> None:
    """A plan through the port (``req.port``): the tool through it where the plan starts, a
    joint set turned into the tool's poses (tip and axis, by FK), every keyframe's orientation
    the port's (:func:`~occ.kinematics.port.keyframes_through_port`); PlanRefused naming the
    keyframe otherwise."""
    port = req.port
    assert port is not None
    if frame.nq < 6:
        raise PlanRefused(
            f"a plan through a port (rcm_mm) turns the tool about it, but {frame.name!r} has "
            f"{frame.nq} joints: it needs a 6-DOF arm"
        )
    start = np.asarray(frame.fk(list(req.q_start)))
    off, _ = shaft_offset(start, port)
    if off > SHAFT_BOUND_M:
        raise PlanRefused(
            f"the tool's shaft is {off / MM:.4g} mm from the port (rcm_mm) where the plan starts "
            f"(bound {SHAFT_BOUND_M / MM:g} mm): bring the tool through the port first"
        )
    start_rot = rotation_to_quaternion_np(start[:3, :3])
    if not tl.cart:
        tl.joint_keys = [tuple(float(v) for v in k.pose) for k in tl.frames]
        poses = [np.asarray(frame.fk(list(k.pose))) for k in tl.frames]
        tl.frames = [
            Keyframe(k.t, p[:3, 3], rotation_to_quaternion_np(p[:3, :3]))
            for k, p in zip(tl.frames, poses, strict=True)
        ]
        tl.cart = True
        tl.notes.append("joint keyframes planned through the port as the tool's poses")
    if tl.frames[0].rotation is None:
        tl.frames[0] = Keyframe(0.0, tl.frames[0].pose, start_rot)
    for i, k in enumerate(tl.frames):
        d = float(np.linalg.norm(np.subtract(k.pose, port)))
        if d < req.port_min_depth:
            raise PlanRefused(
                f"{tl.labels[i]}: the tip is {d / MM:.3g} mm beyond the port, less "
                f"than rcm_min_depth_mm ({req.port_min_depth / MM:g})"
            )
    try:
        tl.frames, turns = keyframes_through_port(tl.frames, port, req.port_tolerance_rad)
    except PortMismatch as err:
        raise PlanRefused(
            f"{tl.labels[err.index]} contradicts the port: its tool axis is "
            f"{math.degrees(err.angle):.3g} deg from the axis through the port and its tip "
            f"(rcm_tolerance_deg {math.degrees(req.port_tolerance_rad):g})"
        ) from err
    except ValueError as err:
        raise PlanRefused(f"cannot keep the port: {err}") from err
    tl.oriented = True
    turned = max(turns[1:], default=0.0)
    if turned > 0.0:
        tl.notes.append(
            f"keyframe orientations turned onto the port's axis (at most "
            f"{math.degrees(turned):.3g} deg)"
        )


def _port_verdict(
    req: PlanRequest,
    tl: _Timeline,
    checks: _TickChecks,
    watch: ShaftWatch,
    qs: Sequence[Sequence[float]],
) -> None:
    """After the samples: the shaft within :data:`SHAFT_BOUND_M` of the port at every one
    (else refused naming the worst), and a joint set's keyframes reached with the arm in their
    own configuration."""
    if watch.worst > SHAFT_BOUND_M:
        t = min(watch.worst_at * req.period, tl.frames[-1].t)
        raise PlanRefused(
            f"the tool's shaft passes {watch.worst / MM:.4g} mm from the port {checks.where(t)} "
            f"(sample {watch.worst_at}, the worst of {watch.seen}; bound "
            f"{SHAFT_BOUND_M / MM:g} mm)"
        )
    tl.notes.append(
        f"the tool's shaft within {watch.worst / MM:.2g} mm of the port at every sample"
    )
    if tl.joint_keys is None:
        return
    for i in range(1, len(tl.frames)):
        j = min(round(tl.frames[i].t / req.period), len(qs) - 1)
        gaps = [abs(a - b) for a, b in zip(qs[j], tl.joint_keys[i], strict=True)]
        worst = max(range(len(gaps)), key=gaps.__getitem__)
        if gaps[worst] > CONFIGURATION_TOLERANCE_RAD:
            raise PlanRefused(
                f"{tl.labels[i]}: through the port the arm reaches its tool pose in another "
                f"configuration (joint {req.joint_names[worst]!r} {gaps[worst]:.3g} rad from the "
                "keyframe's): give these keyframes in Cartesian space"
            )


class _TickChecks:
    """The checks of one tick of a plan, as the drivers and the loop will see it: joint
    limits, the step over one period against the velocity limits (the peak kept for the
    summary), the workspace box and the forbidden regions."""

    def __init__(self, req: PlanRequest, times: list[float], labels: list[str]) -> None:
        self.req = req
        self.times = times
        self.labels = labels
        self.names = req.joint_names
        self.lo = [lim.min for lim in req.limits]
        self.hi = [lim.max for lim in req.limits]
        self.vmax = [lim.velocity * req.velocity_scale for lim in req.limits]
        self.peak_share, self.peak_joint = 0.0, 0
        self.port = None if req.port is None else tuple(float(v) for v in req.port)

    def where(self, t: float) -> str:
        return _where(t, self.times, self.labels, self.req.period)

    def joints(self, t: float, q: list[float]) -> None:
        """A joint plan's sample within the joints' position limits."""
        lo, hi = self.lo, self.hi
        for i, v in enumerate(q):
            if v < lo[i] - 1e-12 or v > hi[i] + 1e-12:
                raise PlanRefused(
                    f"joint {self.names[i]!r} position {v:.6g} is outside its limits "
                    f"[{lo[i]:g}, {hi[i]:g}] {self.where(t)}"
                )

    def clamped(self, t: float, tip: tuple[float, float, float], q: list[float]) -> NoReturn:
        """A Cartesian sample whose IK stopped at a joint limit: refused, naming the joints."""
        lo, hi = self.lo, self.hi
        at = [self.names[i] for i, v in enumerate(q) if v <= lo[i] + 1e-12 or v >= hi[i] - 1e-12]
        raise PlanRefused(
            f"the tip leaves the workspace {self.where(t)}: "
            f"({tip[0] / MM:.2f}, {tip[1] / MM:.2f}, {tip[2] / MM:.2f}) mm needs joint "
            f"{', '.join(at) or '?'} beyond its limits"
        )

    def step(self, t: float, q: list[float], q_prev: list[float]) -> None:
        """Each joint's step over one period, as the drivers check it (the first one too: from
        the held pose to the plan's first sample)."""
        req = self.req
        for i, v in enumerate(q):
            speed = abs(v - q_prev[i]) / req.period
            share = speed / req.limits[i].velocity
            if share > self.peak_share:
                self.peak_share, self.peak_joint = share, i
            if speed > self.vmax[i] * (1.0 + 1e-9):
                scaled = (
                    f" (velocity_scale {req.velocity_scale:g} of {req.limits[i].velocity:g})"
                    if req.velocity_scale < 1.0
                    else ""
                )
                raise PlanRefused(
                    f"joint {self.names[i]!r} velocity {speed:.4g} exceeds its limit "
                    f"{self.vmax[i]:.4g}{scaled} {self.where(t)}; give that segment more time"
                )

    def depth(self, t: float, tip: tuple[float, float, float]) -> None:
        """Through a port: the tip at least ``port_min_depth`` from it (before the IK, which
        the port's axis does not define at the port)."""
        port = self.port
        if port is not None:
            d = math.dist(tip, port)
            if d < self.req.port_min_depth:
                raise PlanRefused(
                    f"the tip comes {d / MM:.6g} mm from the port {self.where(t)}, closer than "
                    f"rcm_min_depth_mm ({self.req.port_min_depth / MM:g})"
                )

    def tip(self, t: float, tip: tuple[float, float, float]) -> None:
        """The tip inside the workspace box and outside every forbidden region."""
        box = self.req.workspace
        if box is not None:
            (x0, y0, z0), (x1, y1, z1) = box
            if not (x0 <= tip[0] <= x1 and y0 <= tip[1] <= y1 and z0 <= tip[2] <= z1):
                raise PlanRefused(
                    f"the tip leaves workspace_mm {self.where(t)}: "
                    f"({tip[0] / MM:.2f}, {tip[1] / MM:.2f}, {tip[2] / MM:.2f}) mm"
                )
        for check in self.req.forbidden:
            hit = check(tip)
            if hit:
                what = f" ({hit})" if isinstance(hit, str) else ""
                raise PlanRefused(
                    f"the tip enters a forbidden region{what} "
                    f"{self.where(t)}: ({tip[0] / MM:.2f}, {tip[1] / MM:.2f}, "
                    f"{tip[2] / MM:.2f}) mm"
                )


def _sample(
    req: PlanRequest,
    frame: Frame,
    traj: Trajectory,
    tl: _Timeline,
    checks: _TickChecks,
    ticks: int,
    watch: ShaftWatch | None = None,
) -> tuple[list[tuple[float, float, float]], list[list[float]]]:
    """Every tick of the plan sampled as the loop will (Cartesian ones through the same IK,
    seeded with the previous tick) and checked: (the decimated tip path, base frame metres;
    the joint samples). ``watch`` sees the tool's pose (FK of the joints) at every sample."""
    period = req.period
    pace = req.pace if req.pace is not None else (lambda: None)
    q_prev = list(req.q_start)
    stride = max(1, math.ceil((ticks + 1) / (req.preview_points - 1)))
    path: list[tuple[float, float, float]] = []
    qs: list[list[float]] = []
    for j in range(ticks + 1):
        pace()
        t = min(j * period, traj.end)
        pos = traj.position(t)
        if tl.cart:
            tip = (float(pos[0]), float(pos[1]), float(pos[2]))
            checks.depth(t, tip)
            try:
                if tl.oriented:
                    q, clamped = pose_ik(frame, traj, t, q_prev)
                else:
                    q, clamped = frame.ik_clamped(tip, q_prev)
            except (KinematicsError, ValueError) as err:
                raise PlanRefused(f"the tip is unreachable {checks.where(t)}: {err}") from err
            if clamped:
                checks.clamped(t, tip, q)
        else:
            q = pos.tolist()
            checks.joints(t, q)
            tip = frame.tip_position(q)
        checks.step(t, q, q_prev)
        checks.tip(t, tip)
        if watch is not None:
            watch.see(j, np.asarray(frame.fk(q)))
        if j % stride == 0 or j == ticks:
            path.append(tip)
        q_prev = list(q)
        qs.append(q_prev)
    return path, qs


def _checked(
    req: PlanRequest,
    frame: Frame,
    traj: Trajectory,
    tl: _Timeline,
    checks: _TickChecks,
    path: list[tuple[float, float, float]],
    q_end: list[float],
    ticks: int,
) -> CheckedPlan:
    """The plan that passed, with its preview (world mm) and summary."""
    kset = req.kset
    rot = req.base[:3, :3]
    origin = req.base[:3, 3]

    def to_world_mm(p: Sequence[float]) -> np.ndarray:
        return np.asarray((rot @ np.asarray(p) + origin) / MM, dtype=float)

    keys = [k.pose if tl.cart else frame.tip_position(list(k.pose)) for k in tl.frames]
    peak_share = checks.peak_share
    peak = (req.joint_names[checks.peak_joint], peak_share)
    summary = (
        f"plan {req.id}: {len(kset.keyframes)} keyframes ({kset.space}, {traj.interpolation}, "
        f"{traj.mode}), {traj.duration:.3f} s; peak joint speed {peak_share:.0%} of the limit "
        f"({peak[0]})"
        + (f"; {'; '.join(tl.notes)}" if tl.notes else "")
        + f"; preview on its way to the viewers; acknowledge with KeyframeAck Plan={req.id}"
    )
    return CheckedPlan(
        id=req.id,
        space="cartesian" if tl.cart else "joint",
        traj=traj,
        labels=tuple(tl.labels),
        point_names=tuple(tl.short),
        q_start=tuple(req.q_start),
        q_end=tuple(q_end),
        path_mm=np.array([to_world_mm(p) for p in path]),
        keys_mm=np.array([to_world_mm(p) for p in keys]),
        peak=peak,
        summary=summary,
        ticks=ticks,
        kset=kset,
        settings=PlanSettings(req.interpolation, req.mode, req.steepness, req.ramp),
        base=req.base,
        period=req.period,
    )


def run_tick(
    frame: Frame, run: CheckedPlan, t: float, q_last: list[float]
) -> tuple[list[float], tuple[str, str, str | None] | None]:
    """Tick ``t`` of the running plan ``run``, sampled as it was checked (joint plans directly,
    Cartesian ones through the same IK seeded with ``q_last``): (the joints, None), or
    (``q_last``, why the run must stop: (its counter, the reason for its status, the error to
    keep or None)): the tip unreachable (``ik_failures``), or the tool's shaft off the port by
    more than :data:`SHAFT_BOUND_M` (``port_stops``). On the loop thread."""
    traj = run.traj
    pos = traj.position(t)
    if run.space == "joint":
        return pos.tolist(), None
    try:
        if traj.has_rotation:
            q, clamped = pose_ik(frame, traj, t, q_last)
        else:
            q, clamped = frame.ik_clamped((float(pos[0]), float(pos[1]), float(pos[2])), q_last)
    except (KinematicsError, ValueError) as err:
        error = f"plan {run.id}: IK failed at t={t:.3f} s: {err}"
        return q_last, ("ik_failures", "tip unreachable", error)
    if clamped:
        return q_last, ("ik_failures", "tip unreachable", None)
    if isinstance(traj, PortTrajectory):
        off, _ = shaft_offset(np.asarray(frame.fk(q)), traj.port)
        if off > SHAFT_BOUND_M:
            bound = SHAFT_BOUND_M / MM
            why = f"the tool's shaft {off / MM:.4g} mm from the port (bound {bound:g} mm)"
            return q_last, ("port_stops", why, f"plan {run.id}: {why} at t={t:.3f} s")
    return q, None


def ack_ready(plan: CheckedPlan, data: RobotData, unseen: bool) -> None:
    """KeyframeAck's checks that ``plan`` may start now: seen (``unseen``: its preview has not
    gone out yet), the robot RUNNING and still where the plan starts; CommandError saying why
    not."""
    if unseen:
        raise CommandError(
            f"KeyframeAck: plan {plan.id} has not been previewed yet (its preview goes out "
            "with the next keyframe-path output); look at it, then acknowledge"
        )
    if data.state.value != "RUNNING":
        raise CommandError(
            f"KeyframeAck: the robot is {data.state.value}; send Run first (it holds "
            "until a plan is acknowledged)"
        )
    away = max(abs(a - b) for a, b in zip(data.setpoint, plan.q_start, strict=True))
    if away > 1e-9:
        raise CommandError(
            f"KeyframeAck: the robot moved since plan {plan.id} was checked "
            f"({away:.3g} rad/m); plan again"
        )


def plan_settings(args: dict[str, str], given: PlanSettings) -> PlanSettings:
    """KeyframePlan's ``Interpolation``, ``Mode``, ``Steepness`` and ``Ramp`` (``args``, keys
    in lower case), each defaulting to ``given``; CommandError naming a bad one."""
    interpolation = args.get("interpolation", given.interpolation).strip().lower()
    mode = args.get("mode", given.mode).strip().lower()
    if interpolation not in ("linear", "spline"):
        raise CommandError(f"Interpolation must be linear or spline, got {interpolation!r}")
    if mode not in ("stop", "continuous"):
        raise CommandError(f"Mode must be stop or continuous, got {mode!r}")
    try:
        steepness = float(args.get("steepness", given.steepness))
        ramp = float(args.get("ramp", given.ramp))
    except ValueError as err:
        raise CommandError(f"KeyframePlan: {err}") from None
    if not (math.isfinite(steepness) and steepness > 0):
        raise CommandError(f"Steepness must be > 0, got {steepness:g}")
    if not 0 < ramp <= 0.5:
        raise CommandError(f"Ramp must be in (0, 0.5], got {ramp:g}")
    return PlanSettings(interpolation, mode, steepness, ramp)  # type: ignore[arg-type]


def plan_request(
    plan_id: int,
    kset: KeyframeSet,
    st: PlanSettings,
    p: KeyframeParams,
    data: RobotData,
    ctx: ControllerContext,
    limits: Sequence[JointLimits],
    checks: tuple[tuple[ForbiddenCheck, ...], tuple[PathCheck, ...]],
) -> PlanRequest:
    """What plan ``plan_id`` of ``kset`` is made from, snapshot on the loop thread: the
    robot's commanded pose and base, the limits, the params' checks, the tip ``checks`` and
    whole-arm ones, and a Pacer on the loop's clock."""
    box = p.workspace_mm
    return PlanRequest(
        id=plan_id,
        kset=kset,
        q_start=tuple(data.commanded()),
        base=np.array(data.base, dtype=float),
        interpolation=st.interpolation,
        mode=st.mode,
        steepness=st.steepness,
        ramp=st.ramp,
        period=ctx.period_s,
        joint_names=data.joint_names,
        limits=tuple(limits),
        velocity_scale=p.velocity_scale,
        start_tolerance=p.start_tolerance,
        start_tolerance_mm=p.start_tolerance_mm,
        start_tolerance_rad=math.radians(p.start_tolerance_deg),
        workspace=(
            (
                tuple(v * MM for v in box.min_mm),  # type: ignore[arg-type]
                tuple(v * MM for v in box.max_mm),
            )
            if box is not None
            else None
        ),
        forbidden=checks[0],
        path_checks=checks[1],
        port=None if p.rcm_mm is None else port_in_base(p.rcm_mm, np.asarray(data.base)),
        port_tolerance_rad=math.radians(p.rcm_tolerance_deg),
        port_min_depth=p.rcm_min_depth_mm * MM,
        max_duration_s=p.max_duration_s,
        preview_points=p.preview_points,
        pace=Pacer(time.perf_counter, ctx.loop_t0, ctx.period_s),
    )
