"""Keyframe trajectories on the robot (issue 11): plan, check, preview, acknowledge, run.

After the German Heart Center system: an operator puts poses on a timeline (keyframes), the
planner (:mod:`occ.trajectory`) fills in the motion, and the plan runs only once it has passed
its checks, been shown in 3D Slicer and been acknowledged. Plugin name ``keyframe``.

Keyframes
    A *keyframe set* is one timeline: times in seconds from the start of the run, and poses
    either in joint space (one value per joint, SI: rad, m) or Cartesian (the tip position in
    mm, in the world frame that the ``tip`` output and 3D Slicer use). The controller keeps one
    set; each source replaces it, ``KeyframeAdd`` inserts into it:

    - the YAML (``params.keyframes``) or a keyframe file (``params.file``), read at start-up;
    - ``KeyframeLoad File=NAME``: a file in ``params.keyframe_dir`` (nothing outside it);
    - a Slicer point list (POINT) or a TRAJ (entry/target points, in that order) on an
      interface that lists the type among its ``inputs`` with ``queue: command``. Cartesian.
      Times come from the v2 metadata ``times`` (seconds, comma-separated, one per point), else
      every ``point_interval_s`` (the first at ``point_interval_s``). Hidden points (alpha 0,
      as Slicer marks them) are left out with their times. A message that cannot be used is
      refused, counted (``inputs_refused``) and logged; the set is then unchanged;
    - ``KeyframeAdd T=SECONDS Pose="a b c" [Label=..] [Space=joint|cartesian]``.

    ``KeyframeList`` lists the set and the plan; ``KeyframeClear`` forgets both.

    The run starts where the robot is: a set whose first keyframe is later than t = 0 gets an
    implicit keyframe at t = 0, the robot's commanded pose (so the robot moves to the first
    keyframe in the time given); a first keyframe at t = 0 must be within
    ``start_tolerance`` / ``start_tolerance_mm`` of it and is then replaced by it exactly.

Plan, check and preview (offline mode, the paper's safety rule)
    ``KeyframePlan [Interpolation=linear|spline] [Mode=stop|continuous] [Steepness=n]
    [Ramp=r]`` plans the set (defaults from the params) and checks every tick of it as it would
    run: each joint within its position limits, each step within ``velocity_scale`` x the
    joint's velocity limit over one period (what the drivers check), the tip inside
    ``workspace_mm`` (base frame) and reachable within the joint limits (Cartesian plans go
    through the Frame's IK, ``ik_clamped``, seeded with the previous tick as at run time), and
    the tip outside every forbidden region (:class:`ForbiddenCheck`, see below). Planning and
    checking run on a planner thread (a spline plan takes milliseconds, a check 30-70 us a
    tick of motion), SCHED_FIFO one below the loop when the loop has it and paced into the
    quiet part of each period (:class:`Pacer`); the command is answered
    when they finish (:class:`~occ.commands.Deferred`): the plan's number and summary, or the
    refusal naming the keyframe (or the segment between two) and the limit. A plan that passed
    is previewed: output source ``keyframe-path`` (POLYDATA: the tip's path as a polyline, world
    mm) and ``keyframe-points`` (POINT: the keyframes), both with v2 metadata
    ``MRMLNodeName`` (the output's device name) so Slicer names its nodes; sent once per new
    plan and again every ``preview_repeat_s`` (a Slicer that connects later sees it too); an
    empty one when the plan is dropped.

Acknowledge and run
    ``KeyframeAck Plan=N`` (the number the plan's reply and ``KeyframeList`` give) starts plan N
    while the robot is RUNNING, if the robot is still where the plan starts (else: replan).
    Each tick the loop samples the plan at ``now - start`` (no thread): joint plans directly,
    Cartesian ones through ``ik_clamped``. At the end the robot rests at the last keyframe and
    the controller holds. A new set or plan never changes a running plan.

    A run is announced to every viewer and operator (the controller context's ``alert``): a
    STATUS named :data:`STATUS_RUNNING` (``KEYFRAME_RUNNING``, code OK) when it starts and
    :data:`STATUS_ENDED` (``KEYFRAME_ENDED``; code OK when it completed, DISABLED when it was
    dropped, below) when it ends, the text saying which plan and how. ROS 2's CRTK
    ``is_busy`` (occ_ros2) is true between the two.

Stop
    An operator's Stop (or anything that takes the robot out of RUNNING: fault, e-stop, Hold)
    during a run *drops* the plan: the robot holds where it was stopped (the robot's own Stop)
    and the run is never resumed mid-way (its timeline would restart at speed, mid-ramp). The
    keyframes stay stored: ``KeyframePlan`` (which now starts from where the robot stopped)
    and ``KeyframeAck`` run them again. The refused, stopped or finished state is in
    ``KeyframeList`` and the statistics.

The trajectory library (issue 28; :mod:`occ.trajlib`, ``params.library``)
    ``KeyframeSave Set=N [Replace=1]`` keeps the stored set in an SQLite file under a name,
    with the settings of the plan that ran it, the robot's name and the hash of its kinematic
    configuration; only a set whose plan was acknowledged (and not changed since) is saved; a
    name taken needs ``Replace=1``. ``KeyframeLibrary`` lists the file's sets (robot, count,
    duration, time saved), ``KeyframeDelete Set=N`` deletes one of this robot's.
    ``KeyframeLoad Set=N`` makes a saved set the stored one, as ``KeyframeLoad File=...``
    does, its plan settings the defaults of the next ``KeyframePlan``; it never runs on load:
    it is planned, checked, previewed and acknowledged again. A set saved by another robot, or
    with another kinematic configuration, is refused with the reason. The file work runs on
    the planner thread, answered by a :class:`~occ.commands.Deferred` like a plan (a request
    while it is busy is refused "busy"). The argument is ``Set``, not ``Name``: in the XML form
    ``Name`` is the command's own name (PlusServer's convention, :mod:`occ.commands`).

Forbidden regions (the collision check)
    :class:`ForbiddenCheck`: any callable taking a tip position (metres, robot base frame) and
    returning something false when it is free, or True / a short description (named in the
    refusal) when it is forbidden. Checks are added with :meth:`KeyframeController.
    add_forbidden_check`, each called for every tick of a plan being checked (on the planner
    thread: it must be thread-safe, e.g. read an immutable snapshot). When the regions change,
    :meth:`KeyframeController.invalidate_plan` makes a checked but unacknowledged plan unusable
    (it must be planned again), as the paper requires of a plan that would now collide.
    A :class:`PathCheck` (anything with ``check_path``, e.g. the whole-arm check of
    ``safety.collision``, occ/collision.py, added at configure) gets the plan's joint samples
    after the per-tick checks and names the first that fails.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import queue
import threading
import time
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, Protocol

import numpy as np
import yaml
from pydantic import BaseModel, BeforeValidator, ConfigDict, DirectoryPath, Field, ValidationError

from ..commands import Deferred
from ..config import (
    Bool,
    DaemonConfig,
    ExistingFile,
    Float,
    Int,
    Name,
    NonNegFloat,
    OutputPath,
    PosFloat,
    Vec3,
    _resolve_path,
)
from ..errors import CommandError, ConfigError, KinematicsError, LibraryError
from ..events import PointsOut, PolylineOut
from ..fixtures import ForbiddenPlane, ForbiddenSphere, forbidden_hit
from ..joint import JointLimits
from ..keyframe_inputs import items_from_event
from ..ratelimit import RateLimit
from ..safety import RobotState
from ..samples import quaternion_to_rotation, rotation_to_quaternion
from ..trajectory import Keyframe, Trajectory, plan
from ..trajlib import Library, SavedSet, check_name, config_hash
from . import Controller, ControllerContext, Problem, SourceFn

if TYPE_CHECKING:
    from ..commands import Request
    from ..data import RobotData
    from ..events import InputEvent
    from ..frame import Frame
    from ..outputs import Output

log = logging.getLogger(__name__)

MM = 1e-3
#: the STATUS names of a run's start and end (module docstring, "Acknowledge and run")
STATUS_RUNNING = "KEYFRAME_RUNNING"
STATUS_ENDED = "KEYFRAME_ENDED"
#: their STATUS codes (igtl StatusCode values; controllers do not import igtl): OK, DISABLED
_CODE_OK = 1
_CODE_DROPPED = 15
Space = Literal["joint", "cartesian"]
ExistingDir = Annotated[DirectoryPath, BeforeValidator(_resolve_path)]

#: largest keyframe file read (bytes): a timeline of keyframes is a few kilobytes
MAX_FILE_BYTES = 1 << 20
#: how the planner thread shares the interpreter with the loop (see :class:`Pacer`)
PACE_WORK_S = 100e-6
PACE_BEFORE_S = 200e-6
PACE_AFTER_S = 350e-6
PACE_HANDBACK_S = 10e-6
PACE_MODE = "phase"
#: most sets KeyframeLibrary lists (a reply is one command message)
MAX_LIBRARY_LINES = 200
_FLAGS = {"1": True, "true": True, "yes": True, "0": False, "false": False, "no": False}


class ForbiddenCheck(Protocol):
    """Whether a tip position (metres, robot base frame) is forbidden: a false value when it
    is free, True or a short description of what it hits when it is not."""

    def __call__(self, point: tuple[float, float, float], /) -> str | bool | None: ...


class PathCheck(Protocol):
    """A whole-arm check of a plan's joint path (occ/collision.py ``PathCheck``): given the
    plan's samples (one per loop period, joint values), the base pose (world <- base) and the
    pacer, None when clear, else (the first sample that fails, what it hits)."""

    def check_path(
        self,
        qs: Sequence[Sequence[float]],
        base: np.ndarray,
        pace: Callable[[], None] | None,
        /,
    ) -> tuple[int, str] | None: ...


# ------------------------------------------------------------------------------ parameters
class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class KeyframeItem(_Model):
    """One keyframe as written in YAML: a time, a pose and an optional name."""

    t: NonNegFloat = Field(description="Time (s) from the start of the run.")
    pose: Annotated[tuple[Float, ...], Field(min_length=1)] = Field(
        description="Joint positions (rad, m; one per joint) or the tip position (mm, world)."
    )
    name: Annotated[str, Field(max_length=64)] | None = Field(None, description="A label.")
    rotation: tuple[Float, Float, Float, Float] | None = Field(
        None,
        description="Cartesian, a 6-DOF arm: the tool's orientation, a unit quaternion (x, y, "
        "z, w) in the world frame (all keyframes of a set, or none).",
    )


class KeyframeFile(_Model):
    """A keyframe file (YAML or JSON): ``{space: ..., keyframes: [{t, pose, name}, ...]}``."""

    space: Space | None = Field(None, description="Overrides `params.space` for this file.")
    keyframes: Annotated[tuple[KeyframeItem, ...], Field(min_length=1)]


class WorkspaceBox(_Model):
    """An axis-aligned box the tip must stay in (mm, robot base frame)."""

    min_mm: Vec3 = Field(description="Lower corner (mm).")
    max_mm: Vec3 = Field(description="Upper corner (mm).")


class ForbiddenSphereItem(_Model):
    """A sphere the tip must not enter (mm, robot base frame)."""

    centre_mm: Vec3 = Field(description="Centre (mm).")
    radius_mm: PosFloat = Field(description="Radius (mm).")
    name: str = Field("", description="Named in a refusal.")


class ForbiddenPlaneItem(_Model):
    """A half-space the tip must not enter: behind ``point_mm`` against ``normal`` (which
    points to the allowed side; mm, robot base frame)."""

    point_mm: Vec3 = Field(description="A point on the plane (mm).")
    normal: Vec3 = Field(description="Normal toward the allowed side (any length > 0).")
    name: str = Field("", description="Named in a refusal.")


class KeyframeParams(_Model):
    """Parameters of ``keyframe``."""

    space: Space = Field(
        "joint",
        description="Space of the keyframes given in YAML, in a file or by KeyframeAdd: "
        "`joint` (one position per joint, rad/m) or `cartesian` (tip position, mm, world "
        "frame). POINT and TRAJ are always Cartesian.",
    )
    keyframes: tuple[KeyframeItem, ...] = Field(
        (), description="Keyframes loaded at start-up: a list of `{t, pose, name}`."
    )
    file: ExistingFile | None = Field(
        None,
        description="A keyframe file loaded at start-up instead (YAML: `space`, `keyframes`); "
        "relative to the config file's folder.",
    )
    keyframe_dir: ExistingDir | None = Field(
        None,
        description="An existing folder KeyframeLoad may read from (names inside it only), "
        "relative to the config file's folder; null = the command is refused.",
    )
    library: OutputPath | None = Field(
        None,
        description="The trajectory library: an SQLite file (created if missing, in an "
        "existing folder; relative to the config file's folder) where KeyframeSave keeps "
        "acknowledged keyframe sets by name for KeyframeLoad Set=...; null = no library, the "
        "library commands are refused.",
    )
    interpolation: Literal["linear", "spline"] = Field(
        "linear", description="Default interpolation of KeyframePlan."
    )
    mode: Literal["stop", "continuous"] = Field(
        "stop", description="Default mode: rest at every keyframe, or move through them."
    )
    steepness: PosFloat = Field(6.0, description="Default steepness n of the sigmoid ramps.")
    ramp: Annotated[Float, Field(gt=0, le=0.5)] = Field(
        0.25, description="Default share of each segment's time spent on each ramp."
    )
    input_interface: Name | None = Field(
        None, description="Interface whose POINT/TRAJ messages are keyframes (null = any)."
    )
    point_interval_s: PosFloat = Field(
        2.0, description="Time between keyframes from POINT/TRAJ without `times` metadata."
    )
    max_keyframes: Annotated[Int, Field(ge=2, le=1000)] = Field(
        100, description="Most keyframes a set may hold."
    )
    max_duration_s: PosFloat = Field(300.0, description="Longest plan accepted (s).")
    velocity_scale: Annotated[Float, Field(gt=0, le=1)] = Field(
        1.0, description="Share of each joint's velocity limit a plan may use."
    )
    start_tolerance: PosFloat = Field(
        1e-3,
        description="Joint space: how far (rad or m) a keyframe at t = 0 may be from the "
        "robot's pose (it is then replaced by it).",
    )
    start_tolerance_mm: PosFloat = Field(
        0.5, description="Cartesian: the same, for the tip position (mm)."
    )
    start_tolerance_deg: PosFloat = Field(
        0.5, description="Cartesian with orientation: the same, for the tool's turn (degrees)."
    )
    workspace_mm: WorkspaceBox | None = Field(
        None, description="Box the tip must stay in (mm, base frame); null = joint limits only."
    )
    forbidden: list[ForbiddenSphereItem | ForbiddenPlaneItem] = Field(
        default_factory=list,
        description="Forbidden regions every plan is checked against, as the virtual "
        "fixtures' forbidden spheres and planes (occ/fixtures.py; mm, base frame): "
        "`{centre_mm, radius_mm, name}` or `{point_mm, normal, name}`.",
    )
    preview_points: Annotated[Int, Field(ge=2, le=10000)] = Field(
        256, description="Most points of the previewed path (the polyline is decimated)."
    )
    preview_repeat_s: PosFloat | None = Field(
        5.0, description="Send the preview again this often (late viewers); null = once."
    )
    preview_required: Bool = Field(
        True,
        description="Refuse a configuration in which no interface sends the preview (an "
        "output with source `keyframe-path`): a plan must be seen before it is acknowledged.",
    )


# ------------------------------------------------------------------------------ keyframe sets
@dataclass(frozen=True)
class PlanSettings:
    """How a set is planned (KeyframePlan's arguments): kept with an acknowledged plan, saved
    with it in the library and the defaults of the next KeyframePlan of the set loaded back."""

    interpolation: Literal["linear", "spline"]
    mode: Literal["stop", "continuous"]
    steepness: float
    ramp: float


@dataclass(frozen=True)
class KeyframeSet:
    """One timeline: keyframes in their own units (joint SI, or Cartesian mm world)."""

    space: Space
    keyframes: tuple[Keyframe, ...]
    names: tuple[str, ...]
    source: str
    #: the plan settings it was saved with (a set from the library), else None: the params'
    settings: PlanSettings | None = None

    def label(self, i: int) -> str:
        name = self.names[i]
        return f"keyframe {i}" + (f" {name!r}" if name else "") + f" (t={self.keyframes[i].t:g} s)"


def make_set(
    space: Space,
    items: Sequence[tuple[float, Sequence[float], str] | tuple[float, Sequence[float], str, Any]],
    source: str,
    *,
    joints: int,
    max_keyframes: int,
) -> KeyframeSet:
    """A validated :class:`KeyframeSet` from ``(t, pose, name)`` triples; ValueError naming the
    keyframe otherwise (dimension, time order, count)."""
    if not items:
        raise ValueError("no keyframes")
    if len(items) > max_keyframes:
        raise ValueError(f"{len(items)} keyframes, more than max_keyframes ({max_keyframes})")
    dim = joints if space == "joint" else 3
    frames: list[Keyframe] = []
    names: list[str] = []
    for i, item in enumerate(items):
        t, pose, name = item[0], item[1], item[2]
        rotation = item[3] if len(item) > 3 else None
        if rotation is not None and space != "cartesian":
            raise ValueError(f"keyframe {i}: a rotation needs Cartesian keyframes")
        try:
            kf = Keyframe(t, pose, rotation)
        except ValueError as err:
            raise ValueError(f"keyframe {i}: {err}") from err
        if frames and (kf.rotation is None) != (frames[-1].rotation is None):
            raise ValueError(f"keyframe {i}: every keyframe of a set has a rotation, or none has")
        if len(kf.pose) != dim:
            what = f"{joints} joint positions" if space == "joint" else "x y z (mm)"
            raise ValueError(f"keyframe {i}: {len(kf.pose)} values, a {space} pose needs {what}")
        if kf.t < 0.0:
            raise ValueError(f"keyframe {i}: time {kf.t:g} s is before the start (t = 0)")
        if frames and not kf.t > frames[-1].t:
            raise ValueError(
                f"keyframe {i}: time {kf.t:g} s does not follow keyframe {i - 1} "
                f"({frames[-1].t:g} s); times must increase"
            )
        frames.append(kf)
        names.append(name)
    return KeyframeSet(space, tuple(frames), tuple(names), source)


def read_keyframe_file(path: Path) -> KeyframeFile:
    """Parse and validate a keyframe file; ValueError with the reason."""
    try:
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise ValueError(f"{path.name}: {size} bytes, more than {MAX_FILE_BYTES}")
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        raise ValueError(f"{path.name}: cannot read: {err}") from err
    if isinstance(data, list):
        data = {"keyframes": data}
    try:
        return KeyframeFile.model_validate(data)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise ValueError(f"{path.name}: {where}: {first['msg']}") from err


def _file_set(kf: KeyframeFile, default: Space, source: str, joints: int, cap: int) -> KeyframeSet:
    return make_set(
        kf.space or default,
        [(k.t, k.pose, k.name or "", k.rotation) for k in kf.keyframes],
        source,
        joints=joints,
        max_keyframes=cap,
    )


# ------------------------------------------------------------------------------ planning
class PlanRefused(Exception):
    """A plan that failed its checks (the message names the keyframe and the limit)."""


class Pacer:
    """Keeps the planner thread off the interpreter lock when the loop needs it.

    One interpreter lock serves every thread: a thread that wants it waits until the holder
    lets go, up to the switch interval. A planner that computed flat out made the loop wait for
    it at most ticks (measured: lateness p50 0.5 ms, p99 6 ms; docs/BENCHMARKS.md). So the
    planner works in slices of ``PACE_WORK_S`` and, while the loop runs, only in the quiet part
    of its period: from ``PACE_AFTER_S`` after a deadline (the tick is done by then) to
    ``PACE_BEFORE_S`` before the next, sleeping through the rest; inside that window it still
    sleeps ``PACE_HANDBACK_S`` between slices. With no loop running (a stepped simulation) it
    only does the latter.
    """

    def __init__(
        self, now: Callable[[], float], loop_t0: Callable[[], float], period: float
    ) -> None:
        self.now = now
        self.loop_t0 = loop_t0
        self.period = period
        self._since = now()
        self.sleeps = 0

    def begin(self) -> None:
        """Wait for the quiet part of the loop's period before the first slice (the thread
        that starts the planner is the loop, mid-tick)."""
        self._since = -math.inf
        self()

    def __call__(self) -> None:
        t = self.now()
        if t - self._since < PACE_WORK_S:
            return
        t0 = self.loop_t0()
        if PACE_MODE == "phase" and t0 == t0:  # not NaN: the loop is running
            period = self.period
            phase = (t - t0) % period
            if phase < PACE_AFTER_S:
                wait = PACE_AFTER_S - phase
            elif phase > period - PACE_BEFORE_S - PACE_WORK_S:
                wait = period - phase + PACE_AFTER_S
            else:
                # a real sleep, however short: a zero one often takes the lock straight back
                # before a waiting loop thread (mid-tick) has woken to take it
                wait = PACE_HANDBACK_S
            self.sleeps += 1
            time.sleep(wait)
        elif PACE_MODE == "rest":
            time.sleep(PACE_WORK_S)
        elif PACE_MODE == "yield":
            time.sleep(0)
        else:
            time.sleep(PACE_HANDBACK_S)
        self._since = self.now()


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
    pose[:3, :3] = quaternion_to_rotation(traj.orientation(t).tolist())
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


def build_plan(req: PlanRequest, frame: Frame) -> CheckedPlan:
    """Plan ``req`` and check every tick of it (see the module docstring); PlanRefused with
    the reason otherwise. Runs on the planner thread with a Frame of its own."""
    kset = req.kset
    cart = kset.space == "cartesian"
    r_t = req.base[:3, :3].T
    origin = req.base[:3, 3]

    def to_base(p_mm: Sequence[float]) -> np.ndarray:
        return np.asarray(r_t @ (np.asarray(p_mm, dtype=float) * MM - origin), dtype=float)

    def to_world_mm(p: Sequence[float]) -> np.ndarray:
        return np.asarray((req.base[:3, :3] @ np.asarray(p) + origin) / MM, dtype=float)

    if req.pace is not None:
        req.pace.begin()
    here: tuple[float, ...] = (
        tuple(float(v) for v in frame.tip_position(list(req.q_start))) if cart else req.q_start
    )
    oriented = cart and kset.keyframes[0].rotation is not None
    if oriented and frame.nq < 6:
        raise PlanRefused(
            f"the keyframes have orientations, but {frame.name!r} has {frame.nq} joints: "
            "orientation needs a 6-DOF arm"
        )

    def to_base_rotation(q: Sequence[float] | None) -> np.ndarray | None:
        if q is None:
            return None
        return rotation_to_quaternion_np(r_t @ quaternion_to_rotation(q))

    frames = [
        Keyframe(k.t, to_base(k.pose), to_base_rotation(k.rotation)) if cart else k
        for k in kset.keyframes
    ]
    here_rot = (
        rotation_to_quaternion_np(np.asarray(frame.fk(list(req.q_start)))[:3, :3])
        if oriented
        else None
    )
    labels = [kset.label(i) for i in range(len(frames))]
    short = [f"{kset.names[i] or f'K{i}'} t={k.t:g}s" for i, k in enumerate(frames)]
    notes: list[str] = []
    first = frames[0]
    gap = float(np.linalg.norm(np.subtract(first.pose, here)))
    if oriented and first.t == 0.0:
        assert first.rotation is not None and here_rot is not None
        turn = 2.0 * math.acos(min(1.0, abs(float(np.dot(first.rotation, here_rot)))))
        if turn > req.start_tolerance_rad:
            raise PlanRefused(
                f"{labels[0]} is turned {math.degrees(turn):.3g} deg from the tool (tolerance "
                f"{math.degrees(req.start_tolerance_rad):g} deg): give keyframe 0 a later time "
                "so the robot turns there, or turn it"
            )
    if first.t > 0.0:
        frames.insert(0, Keyframe(0.0, here, here_rot))
        labels.insert(0, "the start (the robot's pose)")
        short.insert(0, "start t=0s")
    else:
        tol = req.start_tolerance_mm * MM if cart else req.start_tolerance
        if gap > tol:
            unit, scale = ("mm", 1 / MM) if cart else ("rad/m", 1.0)
            raise PlanRefused(
                f"{labels[0]} is {gap * scale:.4g} {unit} from where the robot is (tolerance "
                f"{tol * scale:g}): a run starts where the robot is; give keyframe 0 a later "
                "time so the robot moves there, or move it"
            )
        frames[0] = Keyframe(0.0, here, here_rot)
        if gap > 0.0:
            unit = "mm" if cart else "rad/m"
            notes.append(
                f"keyframe 0 replaced by the robot's pose ({gap / (MM if cart else 1):.3g} {unit} "
                "away)"
            )
    if frames[-1].t > req.max_duration_s:
        raise PlanRefused(
            f"{labels[-1]}: the plan would last {frames[-1].t:g} s, more than max_duration_s "
            f"({req.max_duration_s:g})"
        )
    try:
        traj = plan(frames, req.interpolation, req.mode, req.steepness, req.ramp)
    except ValueError as err:
        raise PlanRefused(f"cannot plan: {err}") from err

    times = [k.t for k in frames]
    period = req.period
    ticks = math.ceil(traj.end / period - 1e-9)
    names = req.joint_names
    lo = [lim.min for lim in req.limits]
    hi = [lim.max for lim in req.limits]
    vmax = [lim.velocity * req.velocity_scale for lim in req.limits]
    box = req.workspace
    forbidden = req.forbidden
    pace = req.pace if req.pace is not None else (lambda: None)
    q_prev = list(req.q_start)
    peak_share, peak_joint = 0.0, 0
    stride = max(1, math.ceil((ticks + 1) / (req.preview_points - 1)))
    path: list[tuple[float, float, float]] = []
    qs: list[list[float]] = []
    for j in range(ticks + 1):
        pace()
        t = min(j * period, traj.end)
        pos = traj.position(t)
        if cart:
            tip = (float(pos[0]), float(pos[1]), float(pos[2]))
            try:
                if oriented:
                    q, clamped = pose_ik(frame, traj, t, q_prev)
                else:
                    q, clamped = frame.ik_clamped(tip, q_prev)
            except (KinematicsError, ValueError) as err:
                raise PlanRefused(
                    f"the tip is unreachable {_where(t, times, labels, period)}: {err}"
                ) from err
            if clamped:
                at = [names[i] for i, v in enumerate(q) if v <= lo[i] + 1e-12 or v >= hi[i] - 1e-12]
                raise PlanRefused(
                    f"the tip leaves the workspace {_where(t, times, labels, period)}: "
                    f"({tip[0] / MM:.2f}, {tip[1] / MM:.2f}, {tip[2] / MM:.2f}) mm needs joint "
                    f"{', '.join(at) or '?'} beyond its limits"
                )
        else:
            q = pos.tolist()
            for i, v in enumerate(q):
                if v < lo[i] - 1e-12 or v > hi[i] + 1e-12:
                    raise PlanRefused(
                        f"joint {names[i]!r} position {v:.6g} is outside its limits "
                        f"[{lo[i]:g}, {hi[i]:g}] {_where(t, times, labels, period)}"
                    )
            tip = frame.tip_position(q)
        # each step over one period, as the drivers check it (the first one too: from the
        # held pose to the plan's first sample)
        for i, v in enumerate(q):
            speed = abs(v - q_prev[i]) / period
            share = speed / req.limits[i].velocity
            if share > peak_share:
                peak_share, peak_joint = share, i
            if speed > vmax[i] * (1.0 + 1e-9):
                scaled = (
                    f" (velocity_scale {req.velocity_scale:g} of {req.limits[i].velocity:g})"
                    if req.velocity_scale < 1.0
                    else ""
                )
                raise PlanRefused(
                    f"joint {names[i]!r} velocity {speed:.4g} exceeds its limit "
                    f"{vmax[i]:.4g}{scaled} {_where(t, times, labels, period)}; give that "
                    "segment more time"
                )
        if box is not None:
            (x0, y0, z0), (x1, y1, z1) = box
            if not (x0 <= tip[0] <= x1 and y0 <= tip[1] <= y1 and z0 <= tip[2] <= z1):
                raise PlanRefused(
                    f"the tip leaves workspace_mm {_where(t, times, labels, period)}: "
                    f"({tip[0] / MM:.2f}, {tip[1] / MM:.2f}, {tip[2] / MM:.2f}) mm"
                )
        for check in forbidden:
            hit = check(tip)
            if hit:
                what = f" ({hit})" if isinstance(hit, str) else ""
                raise PlanRefused(
                    f"the tip enters a forbidden region{what} "
                    f"{_where(t, times, labels, period)}: ({tip[0] / MM:.2f}, {tip[1] / MM:.2f}, "
                    f"{tip[2] / MM:.2f}) mm"
                )
        if j % stride == 0 or j == ticks:
            path.append(tip)
        q_prev = list(q)
        qs.append(q_prev)
    for path_check in req.path_checks:
        crossing = path_check.check_path(qs, req.base, req.pace)
        if crossing is not None:
            t = min(crossing[0] * period, traj.end)
            raise PlanRefused(f"{crossing[1]} {_where(t, times, labels, period)}")

    keys = []
    for k in frames:
        keys.append(k.pose if cart else frame.tip_position(list(k.pose)))
    path_mm = np.array([to_world_mm(p) for p in path])
    keys_mm = np.array([to_world_mm(p) for p in keys])
    peak = (names[peak_joint], peak_share)
    summary = (
        f"plan {req.id}: {len(kset.keyframes)} keyframes ({kset.space}, {traj.interpolation}, "
        f"{traj.mode}), {traj.duration:.3f} s; peak joint speed {peak_share:.0%} of the limit "
        f"({peak[0]})"
        + (f"; {'; '.join(notes)}" if notes else "")
        + f"; preview on its way to the viewers; acknowledge with KeyframeAck Plan={req.id}"
    )
    return CheckedPlan(
        id=req.id,
        space=kset.space,
        traj=traj,
        labels=tuple(labels),
        point_names=tuple(short),
        q_start=tuple(req.q_start),
        q_end=tuple(q_prev),
        path_mm=path_mm,
        keys_mm=keys_mm,
        peak=peak,
        summary=summary,
        ticks=ticks,
        kset=kset,
        settings=PlanSettings(req.interpolation, req.mode, req.steepness, req.ramp),
    )


# ------------------------------------------------------------------------------ controller
def _loop_priority() -> int | None:
    """The calling (loop) thread's SCHED_FIFO priority, None when it is not SCHED_FIFO."""
    try:
        if os.sched_getscheduler(threading.get_native_id()) == os.SCHED_FIFO:
            return int(os.sched_getparam(threading.get_native_id()).sched_priority)
    except (OSError, AttributeError):
        pass
    return None


class _PlannerThread:
    """One daemon thread that runs the planner's jobs, one at a time. The loop only puts a
    job in its queue (microseconds); a job submitted while one is pending is refused."""

    def __init__(self) -> None:
        self._jobs: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self.idle = threading.Event()
        self.idle.set()
        self.fifo: int | None = None  # the thread's SCHED_FIFO priority (None: SCHED_OTHER)
        self.fifo_refused = ""
        self._thread = threading.Thread(target=self._main, name="occ-keyframe-planner", daemon=True)
        self._thread.start()

    def submit(self, job: Callable[[], None], answer: Deferred, fifo: int | None) -> bool:
        """Queue ``job``; False when one is pending. ``fifo``: the loop's SCHED_FIFO priority
        (None: it runs SCHED_OTHER); the job runs one below it, as the interface threads do."""
        with self._lock:
            if not self.idle.is_set():
                return False
            self.idle.clear()

        def run() -> None:
            self._schedule(fifo)
            try:
                job()
            except Exception as err:  # noqa: BLE001 - the operator gets an answer whatever
                log.exception("keyframe planner failed")
                answer.fail(f"planner failed: {err}")

        self._jobs.put(run)
        return True

    def _schedule(self, fifo: int | None) -> None:
        # Below the loop but above ordinary processes, like the interface threads: a planner
        # thread preempted while it holds the interpreter lock (a busy machine) would keep a
        # SCHED_FIFO loop waiting for the lock for as long as the kernel keeps it off the CPU.
        want = None if fifo is None else max(1, fifo - 1)
        if want == self.fifo:
            return
        try:
            if want is None:
                os.sched_setscheduler(threading.get_native_id(), os.SCHED_OTHER, os.sched_param(0))
            else:
                os.sched_setscheduler(
                    threading.get_native_id(), os.SCHED_FIFO, os.sched_param(want)
                )
            self.fifo = want
        except (OSError, AttributeError) as err:
            self.fifo_refused = f"{type(err).__name__}: {err}"

    def stop(self) -> None:
        """Let the thread end once the queued job (if any) is done."""
        self._jobs.put(None)

    def _main(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:
                job()
            finally:
                self.idle.set()


@dataclass
class _PreviewState:
    version: int = 0
    plan: CheckedPlan | None = None
    sent: dict[int, tuple[int, float]] = field(default_factory=dict)  # output -> (version, t)


class KeyframeController(Controller):
    """Keyframe trajectories: stored keyframes planned, checked, previewed in Slicer, run
    after the operator's acknowledgement (issue 11; the module docstring has the details)."""

    name = "keyframe"
    Params = KeyframeParams

    COMMANDS = (
        "KeyframeAdd",
        "KeyframeList",
        "KeyframeClear",
        "KeyframeLoad",
        "KeyframePlan",
        "KeyframeAck",
        "KeyframeSave",
        "KeyframeLibrary",
        "KeyframeDelete",
    )

    def __init__(self, params: BaseModel | dict[str, Any] | None = None) -> None:
        super().__init__(params)
        p = self.params
        assert isinstance(p, KeyframeParams)
        self.p = p
        self.forbidden_checks: list[ForbiddenCheck] = []
        self.path_checks: list[PathCheck] = []
        # shared with the planner thread: every change under the lock; the loop reads the
        # references (atomic) without it
        self._lock = threading.Lock()
        self._generation = 0  # +1 whenever the set changes or a plan is invalidated
        self.kset: KeyframeSet | None = None
        self.plan: CheckedPlan | None = None  # checked, previewed, not yet acknowledged
        self.status = "no keyframes"
        self._next_id = 1
        self._planner: _PlannerThread | None = None
        # the run (loop thread only)
        self.active: CheckedPlan | None = None
        self._t0 = 0.0
        self._q_last: list[float] = []
        self._preview = _PreviewState()
        self._frame_planner: Frame | None = None
        self._log_limit = RateLimit(5)
        # the trajectory library (occ/trajlib.py; used on the planner thread only)
        self.library: Library | None = None
        self.robot_name = ""
        self.config_hash = ""
        #: the last plan acknowledged (loop thread): KeyframeSave stores its set while the
        #: stored keyframes are still that set
        self._acked: CheckedPlan | None = None
        self.counters = {
            "sets": 0,
            "inputs_refused": 0,
            "plans_checked": 0,
            "plans_refused": 0,
            "runs": 0,
            "runs_completed": 0,
            "runs_stopped": 0,
            "ik_failures": 0,
            "library_saved": 0,
            "library_loaded": 0,
            "library_deleted": 0,
            "library_refused": 0,
            # how often the planner waited for the quiet part of the loop's period (Pacer)
            "planner_waits": 0,
        }
        self.last_error = ""

    # ------------------------------------------------------------------ configuration
    @classmethod
    def check(cls, params: Any, config: DaemonConfig) -> list[Problem]:
        from ..config import _did_you_mean

        problems: list[Problem] = []
        names = [i.name for i in config.interfaces]
        ref = params.input_interface
        if ref is not None and ref not in names:
            problems.append(
                (("input_interface",), f"unknown interface '{ref}'" + _did_you_mean(ref, names))
            )
        if params.keyframes and params.file is not None:
            problems.append((("file",), "give `keyframes` or `file`, not both"))
        joints = len(config.robot.joints)
        try:
            if params.keyframes:
                _file_set(
                    KeyframeFile(keyframes=params.keyframes),
                    params.space,
                    "config",
                    joints,
                    params.max_keyframes,
                )
        except ValueError as err:
            problems.append((("keyframes",), str(err)))
        if params.file is not None:
            try:
                _file_set(
                    read_keyframe_file(Path(params.file)),
                    params.space,
                    "file",
                    joints,
                    params.max_keyframes,
                )
            except ValueError as err:
                problems.append((("file",), str(err)))
        if params.library is not None and not Path(params.library).parent.is_dir():
            problems.append(
                (("library",), f"the folder {Path(params.library).parent} does not exist")
            )
        if params.preview_required and not any(
            o.source == "keyframe-path" for i in config.interfaces for o in i.outputs
        ):
            problems.append(
                (
                    ("preview_required",),
                    "no interface sends the preview: add an output with source keyframe-path "
                    "(POLYDATA) for 3D Slicer (and keyframe-points, POINT), or set "
                    "preview_required: false",
                )
            )
        return problems

    def configure(self, data: RobotData, ctx: ControllerContext) -> None:
        super().configure(data, ctx)
        self._frame_planner = ctx.frame.copy()  # the planner thread's own (pinocchio data)
        # started now, not by a command: starting a thread from the loop cost the tick ~1 ms;
        # it ends when this controller is collected (controllers have no shutdown hook)
        self._planner = _PlannerThread()
        weakref.finalize(self, self._planner.stop)
        self.limits = ctx.joint_limits or tuple(
            JointLimits(lo, hi) for lo, hi in zip(ctx.frame.lower, ctx.frame.upper, strict=True)
        )
        p = self.p
        n = len(data.joint_names)
        self.robot_name = data.name
        self.config_hash = config_hash(ctx.frame, data.joint_names)
        if p.library is not None:
            try:
                self.library = Library(p.library)
            except LibraryError as err:
                raise ConfigError(f"controller keyframe: library: {err}") from err
        try:
            if p.keyframes:
                kf = KeyframeFile(keyframes=p.keyframes)
                self._install(_file_set(kf, p.space, "config", n, p.max_keyframes))
            elif p.file is not None:
                path = Path(p.file)
                kf = read_keyframe_file(path)
                self._install(_file_set(kf, p.space, f"file {path.name}", n, p.max_keyframes))
        except ValueError as err:  # occd --check reports these with their line already
            raise ConfigError(f"controller keyframe: {err}") from err
        if p.forbidden:
            try:
                regions = [
                    ForbiddenSphere(f.centre_mm, f.radius_mm, name=f.name)
                    if isinstance(f, ForbiddenSphereItem)
                    else ForbiddenPlane(f.point_mm, f.normal, name=f.name)
                    for f in p.forbidden
                ]
            except ValueError as err:
                raise ConfigError(f"controller keyframe: forbidden: {err}") from err

            def configured_regions(point: tuple[float, float, float]) -> str | None:
                return forbidden_hit(regions, (point[0] * 1e3, point[1] * 1e3, point[2] * 1e3))

            self.add_forbidden_check(configured_regions)
        if ctx.collision is not None:  # safety.collision: the whole arm along the path
            self.add_forbidden_check(ctx.collision.path_check())

    def outputs(self) -> dict[str, SourceFn]:
        return {"keyframe-path": self._source_path, "keyframe-points": self._source_points}

    def commands(self) -> tuple[str, ...]:
        return self.COMMANDS

    def add_forbidden_check(self, check: ForbiddenCheck | PathCheck) -> None:
        """Add a collision check every new plan must pass: a :class:`ForbiddenCheck` of the
        tip, or a :class:`PathCheck` of the whole arm (it has ``check_path``)."""
        if hasattr(check, "check_path"):
            self.path_checks.append(check)  # type: ignore[arg-type]
        else:
            self.forbidden_checks.append(check)  # type: ignore[arg-type]

    def invalidate_plan(self, reason: str) -> None:
        """The world changed (e.g. the forbidden regions): a checked plan not yet acknowledged
        must be planned again. Thread-safe; a running plan is not affected."""
        with self._lock:
            self._generation += 1
            if self.plan is not None:
                self.status = f"plan {self.plan.id} invalidated: {reason}; plan again"
                self._set_plan(None)

    # ------------------------------------------------------------------ inputs
    def on_input(self, event: InputEvent, now: float) -> None:
        """Keyframes from 3D Slicer: a Markups POINT list or a TRAJ (a discrete input)."""
        if event.kind not in ("POINT", "TRAJ"):
            return
        if self.p.input_interface is not None and event.interface != self.p.input_interface:
            return
        assert self.data is not None
        source = f"{event.describe()} from {event.interface}"
        try:
            items = items_from_event(event, self.p.point_interval_s)
            kset = make_set(
                "cartesian",
                items,
                source,
                joints=len(self.data.joint_names),
                max_keyframes=self.p.max_keyframes,
            )
        except ValueError as err:
            self.counters["inputs_refused"] += 1
            self.last_error = f"{source} refused: {err}"
            if self._log_limit.allow():
                log.warning("keyframes: %s", self.last_error)
            return
        self._install(kset)
        log.info("keyframes: %d from %s", len(kset.keyframes), source)

    def _install(self, kset: KeyframeSet | None) -> None:
        """A new keyframe set (or none): any checked plan is dropped (a running one runs on)."""
        with self._lock:
            self._generation += 1
            self.kset = kset
            if kset is not None:
                self.counters["sets"] += 1
            self._set_plan(None)
            self.status = (
                f"{len(kset.keyframes)} keyframes from {kset.source}; send KeyframePlan"
                if kset is not None
                else "no keyframes"
            )

    def _set_plan(self, plan_: CheckedPlan | None) -> None:
        """The previewed plan (caller holds the lock)."""
        if plan_ is self.plan and plan_ is not None:
            return
        self.plan = plan_
        pv = self._preview
        if plan_ is not None or pv.plan is not None:
            # a new preview, or an empty one to clear the viewer's
            self._preview = _PreviewState(pv.version + 1, plan_ if plan_ is not None else None, {})

    # ------------------------------------------------------------------ commands
    def on_command(self, request: Request, now: float) -> str | Deferred | None:
        key = request.name.strip().lower()
        args = {k.lower(): v for k, v in request.args.items()}
        if key == "keyframelist":
            return self.describe()
        if key == "keyframeclear":
            if self.active is not None:
                raise CommandError(f"plan {self.active.id} is running; Stop first")
            self._install(None)
            return "keyframes and plan cleared"
        if key == "keyframeadd":
            return self._cmd_add(args)
        if key == "keyframeload":
            return self._cmd_load(args)
        if key == "keyframeplan":
            return self._cmd_plan(args)
        if key == "keyframeack":
            return self._cmd_ack(args, now)
        if key == "keyframesave":
            return self._cmd_save(args)
        if key == "keyframelibrary":
            return self._cmd_library()
        if key == "keyframedelete":
            return self._cmd_delete(args)
        raise CommandError(f"unknown command {request.name!r}")

    def _cmd_add(self, args: dict[str, str]) -> str:
        assert self.data is not None
        try:
            t = float(args["t"])
            pose = [float(v) for v in args["pose"].replace(",", " ").split()]
        except KeyError as err:
            raise CommandError(f"KeyframeAdd needs T and Pose (missing {err})") from None
        except ValueError as err:
            raise CommandError(f"KeyframeAdd: {err}") from None
        current = self.kset
        space = args.get("space", current.space if current else self.p.space).strip().lower()
        if space not in ("joint", "cartesian"):
            raise CommandError(f"KeyframeAdd: Space must be joint or cartesian, got {space!r}")
        if current is not None and current.space != space:
            raise CommandError(
                f"KeyframeAdd: the stored keyframes are {current.space}; KeyframeClear first"
            )
        rotation: list[float] | None = None
        if "rotation" in args:
            try:
                rotation = [float(v) for v in args["rotation"].replace(",", " ").split()]
            except ValueError as err:
                raise CommandError(f"KeyframeAdd: Rotation: {err}") from None
        items: list[tuple[float, Sequence[float], str, Any]] = (
            [
                (k.t, k.pose, n, k.rotation)
                for k, n in zip(current.keyframes, current.names, strict=True)
            ]
            if current is not None
            else []
        )
        if any(abs(t - it[0]) < 1e-12 for it in items):
            raise CommandError(f"KeyframeAdd: there is a keyframe at t={t:g} s already")
        items.append((t, pose, args.get("label", ""), rotation))
        items.sort(key=lambda it: it[0])
        try:
            kset = make_set(
                space,  # type: ignore[arg-type]
                items,
                "operator commands",
                joints=len(self.data.joint_names),
                max_keyframes=self.p.max_keyframes,
            )
        except ValueError as err:
            raise CommandError(f"KeyframeAdd: {err}") from None
        self._install(kset)
        return f"{len(kset.keyframes)} keyframes ({space}); send KeyframePlan"

    def _cmd_load(self, args: dict[str, str]) -> Deferred:
        if "set" in args:
            if "file" in args:
                raise CommandError(
                    "KeyframeLoad takes File (a file) or Set (the library), not both"
                )
            return self._cmd_load_saved(args)
        folder = self.p.keyframe_dir
        if folder is None:
            raise CommandError("KeyframeLoad is off: no keyframe_dir in the configuration")
        name = args.get("file", "").strip()
        if not name:
            raise CommandError(
                "KeyframeLoad needs File (a name in the keyframe folder) or Set (a set in the "
                "library)"
            )
        root = Path(folder).resolve()
        path = (root / name).resolve()
        if root not in path.parents or Path(name).is_absolute():
            raise CommandError(f"KeyframeLoad: {name!r} is not inside the keyframe folder")
        assert self.data is not None
        joints, p = len(self.data.joint_names), self.p
        generation = self._generation

        def job(answer: Deferred) -> None:
            try:
                kset = _file_set(
                    read_keyframe_file(path), p.space, f"file {name}", joints, p.max_keyframes
                )
            except ValueError as err:
                answer.fail(f"KeyframeLoad refused: {err}")
                return
            with self._lock:
                superseded = self._generation != generation
            if superseded:
                answer.fail("KeyframeLoad: the keyframes changed meanwhile; load again")
                return
            self._install(kset)
            answer.resolve(f"{len(kset.keyframes)} keyframes ({kset.space}) from {name}")

        return self._start(job)

    # ------------------------------------------------------------------ the library
    def _need_library(self, command: str) -> Library:
        if self.library is None:
            raise CommandError(
                f"{command}: there is no trajectory library in the configuration (the keyframe "
                "controller's `library` parameter)"
            )
        return self.library

    @staticmethod
    def _name_arg(command: str, args: dict[str, str]) -> str:
        if not args.get("set", "").strip():
            raise CommandError(f"{command} needs Set (the set's name in the library)")
        try:
            return check_name(args["set"])
        except LibraryError as err:
            raise CommandError(f"{command}: {err}") from None

    def _library_refused(self, answer: Deferred, text: str) -> None:
        with self._lock:
            self.counters["library_refused"] += 1
            self.last_error = text
        answer.fail(text)

    def _cmd_save(self, args: dict[str, str]) -> Deferred:
        library = self._need_library("KeyframeSave")
        name = self._name_arg("KeyframeSave", args)
        flag = args.get("replace", "0").strip().lower()
        if flag not in _FLAGS:
            raise CommandError(f"KeyframeSave: Replace must be 1 or 0, got {flag!r}")
        replace = _FLAGS[flag]
        acked, kset = self._acked, self.kset
        if acked is None or acked.kset is None or acked.settings is None:
            raise CommandError(
                "KeyframeSave: only a planned and acknowledged set is saved: KeyframePlan, "
                "KeyframeAck, then KeyframeSave"
            )
        if acked.kset is not kset:
            raise CommandError(
                f"KeyframeSave: the keyframes changed since plan {acked.id} was acknowledged; "
                "plan and acknowledge them before saving"
            )
        assert self.data is not None
        st = acked.settings
        saved = SavedSet(
            name=name,
            robot=self.robot_name,
            config_hash=self.config_hash,
            space=kset.space,
            interpolation=st.interpolation,
            mode=st.mode,
            steepness=st.steepness,
            ramp=st.ramp,
            duration_s=acked.traj.duration,
            keyframes=tuple(
                (k.t, k.pose, label, k.rotation)
                for k, label in zip(kset.keyframes, kset.names, strict=True)
            ),
            joint_names=self.data.joint_names,
            source=kset.source,
        )

        def job(answer: Deferred) -> None:
            try:
                stored, replaced = library.save(saved, replace=replace)
            except LibraryError as err:
                self._library_refused(answer, f"KeyframeSave refused: {err}")
                return
            with self._lock:
                self.counters["library_saved"] += 1
            answer.resolve(
                f"{'replaced' if replaced else 'saved'} {name!r}: {len(saved.keyframes)} "
                f"keyframes ({saved.space}, {st.interpolation}, {st.mode}), "
                f"{saved.duration_s:.3f} s, plan {acked.id}, robot {saved.robot!r} (config "
                f"{saved.config_hash[:12]}), at {stored.saved_at}"
            )

        return self._start(job)

    def _cmd_load_saved(self, args: dict[str, str]) -> Deferred:
        library = self._need_library("KeyframeLoad Set=...")
        name = self._name_arg("KeyframeLoad", args)
        assert self.data is not None
        joints, cap = len(self.data.joint_names), self.p.max_keyframes
        robot, digest = self.robot_name, self.config_hash
        generation = self._generation

        def job(answer: Deferred) -> None:
            try:
                saved = library.load(robot, name, digest)
                kset = make_set(
                    saved.space,  # type: ignore[arg-type]
                    list(saved.keyframes),
                    f"library {name}",
                    joints=joints,
                    max_keyframes=cap,
                )
                if saved.interpolation not in ("linear", "spline") or saved.mode not in (
                    "stop",
                    "continuous",
                ):
                    raise ValueError(f"unknown plan settings {saved.interpolation}/{saved.mode}")
            except (LibraryError, ValueError) as err:
                self._library_refused(answer, f"KeyframeLoad refused: {err}")
                return
            settings = PlanSettings(
                saved.interpolation,  # type: ignore[arg-type]
                saved.mode,  # type: ignore[arg-type]
                saved.steepness,
                saved.ramp,
            )
            with self._lock:
                superseded = self._generation != generation
            if superseded:
                answer.fail("KeyframeLoad: the keyframes changed meanwhile; load again")
                return
            self._install(dataclasses.replace(kset, settings=settings))
            with self._lock:
                self.counters["library_loaded"] += 1
            answer.resolve(
                f"{len(kset.keyframes)} keyframes ({kset.space}) from the library: {name!r}, "
                f"saved {saved.saved_at} ({saved.interpolation}, {saved.mode}, "
                f"{saved.duration_s:.3f} s); it does not run by itself: send KeyframePlan, "
                "look at the preview, then KeyframeAck"
            )

        return self._start(job)

    def _cmd_delete(self, args: dict[str, str]) -> Deferred:
        library = self._need_library("KeyframeDelete")
        name = self._name_arg("KeyframeDelete", args)
        robot = self.robot_name

        def job(answer: Deferred) -> None:
            try:
                library.delete(robot, name)
            except LibraryError as err:
                self._library_refused(answer, f"KeyframeDelete refused: {err}")
                return
            with self._lock:
                self.counters["library_deleted"] += 1
            answer.resolve(f"deleted {name!r} (robot {robot!r}) from the library")

        return self._start(job)

    def _cmd_library(self) -> Deferred:
        library = self._need_library("KeyframeLibrary")
        robot, digest = self.robot_name, self.config_hash

        def job(answer: Deferred) -> None:
            try:
                entries, total = library.entries(MAX_LIBRARY_LINES)
            except LibraryError as err:
                self._library_refused(answer, f"KeyframeLibrary: {err}")
                return
            sets = "1 saved set" if total == 1 else f"{total} saved sets"
            lines = [f"{sets} in {library.path.name}; this robot: {robot!r}"]
            for e in entries:
                if e.robot != robot:
                    mark = " [another robot: not loadable here]"
                elif e.config_hash != digest:
                    mark = " [another kinematic configuration: refused]"
                else:
                    mark = ""
                lines.append(
                    f"  {e.name}: robot {e.robot!r}, {e.keyframe_count} keyframes ({e.space}, "
                    f"{e.interpolation}, {e.mode}), {e.duration_s:.3f} s, saved {e.saved_at}"
                    f"{mark}"
                )
            if total > len(entries):
                lines.append(f"  ... and {total - len(entries)} more")
            answer.resolve("\n".join(lines))

        return self._start(job)

    def _cmd_plan(self, args: dict[str, str]) -> Deferred:
        data, ctx, p = self.data, self.ctx, self.p
        assert data is not None and ctx is not None
        kset = self.kset
        if kset is None:
            raise CommandError("no keyframes to plan: load or send some first")
        if self.active is not None:
            raise CommandError(f"plan {self.active.id} is running; wait or Stop")
        # a set from the library is planned as it was saved, unless told otherwise
        given = kset.settings or PlanSettings(p.interpolation, p.mode, p.steepness, p.ramp)
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
        box = p.workspace_mm
        with self._lock:
            generation = self._generation
            plan_id = self._next_id
            self._next_id += 1
        req = PlanRequest(
            id=plan_id,
            kset=kset,
            q_start=tuple(data.commanded()),
            base=np.array(data.base, dtype=float),
            interpolation=interpolation,  # type: ignore[arg-type]
            mode=mode,  # type: ignore[arg-type]
            steepness=steepness,
            ramp=ramp,
            period=ctx.period_s,
            joint_names=data.joint_names,
            limits=tuple(self.limits),
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
            forbidden=tuple(self.forbidden_checks),
            path_checks=tuple(self.path_checks),
            max_duration_s=p.max_duration_s,
            preview_points=p.preview_points,
            pace=Pacer(time.perf_counter, ctx.loop_t0, ctx.period_s),
        )
        frame = self._frame_planner
        assert frame is not None

        def job(answer: Deferred) -> None:
            try:
                checked = build_plan(req, frame)
            except PlanRefused as err:
                text = f"plan {plan_id} refused: {err}"
                with self._lock:
                    self._count_waits(req)
                    self.counters["plans_refused"] += 1
                    self.last_error = text
                    if self._generation == generation:
                        self.status = text
                answer.fail(text)
                return
            with self._lock:
                self._count_waits(req)
                self.counters["plans_checked"] += 1
                if self._generation != generation:
                    stale = True
                else:
                    stale = False
                    self._set_plan(checked)
                    self.status = f"plan {plan_id} previewed; KeyframeAck Plan={plan_id} runs it"
            if stale:
                answer.fail(f"plan {plan_id} dropped: the keyframes changed meanwhile; plan again")
            else:
                answer.resolve(checked.summary)

        return self._start(job)

    def _count_waits(self, req: PlanRequest) -> None:
        if req.pace is not None:
            self.counters["planner_waits"] += req.pace.sleeps

    def _cmd_ack(self, args: dict[str, str], now: float) -> str:
        data = self.data
        assert data is not None
        text = args.get("plan", "").strip()
        if not text:
            raise CommandError("KeyframeAck needs Plan (the number of the previewed plan)")
        try:
            plan_id = int(text)
        except ValueError:
            raise CommandError(f"KeyframeAck: Plan must be a number, got {text!r}") from None
        if self.active is not None:
            raise CommandError(f"plan {self.active.id} is running already")
        pending = self.plan
        if pending is None or pending.id != plan_id:
            have = f"plan {pending.id} is previewed" if pending else "no plan is previewed"
            raise CommandError(f"KeyframeAck: plan {plan_id} is not the previewed plan ({have})")
        if self.p.preview_required and not self._preview.sent:
            raise CommandError(
                f"KeyframeAck: plan {plan_id} has not been previewed yet (its preview goes out "
                "with the next keyframe-path output); look at it, then acknowledge"
            )
        if data.state is not RobotState.RUNNING:
            raise CommandError(
                f"KeyframeAck: the robot is {data.state.value}; send Run first (it holds "
                "until a plan is acknowledged)"
            )
        away = max(abs(a - b) for a, b in zip(data.setpoint, pending.q_start, strict=True))
        if away > 1e-9:
            raise CommandError(
                f"KeyframeAck: the robot moved since plan {plan_id} was checked "
                f"({away:.3g} rad/m); plan again"
            )
        self.active = pending
        self._acked = pending
        self._t0 = now
        self._q_last = list(pending.q_start)
        self.counters["runs"] += 1
        with self._lock:
            self.status = f"plan {plan_id} running ({pending.traj.duration:.3f} s)"
        self._announce(STATUS_RUNNING, self.status, _CODE_OK)
        log.info("keyframes: plan %d acknowledged, running %.3f s", plan_id, pending.traj.duration)
        return f"plan {plan_id} running: {pending.traj.duration:.3f} s"

    def _start(self, job: Callable[[Deferred], None]) -> Deferred:
        """Hand ``job`` to the planner thread (one at a time; a second is refused)."""
        planner = self._planner
        if planner is None:
            planner = self._planner = _PlannerThread()
        answer = Deferred()
        if not planner.submit(lambda: job(answer), answer, _loop_priority()):
            raise CommandError("busy: the planner is still working on the last request; retry")
        return answer

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Wait for the planner thread (tests, tools); True when it is idle."""
        return self._planner is None or self._planner.idle.wait(timeout)

    # ------------------------------------------------------------------ the loop
    def on_state(self, old: RobotState, new: RobotState, now: float) -> None:
        run = self.active
        if run is not None and old is RobotState.RUNNING and new is not RobotState.RUNNING:
            t = now - self._t0
            self.active = None
            self.counters["runs_stopped"] += 1
            with self._lock:
                self._generation += 1
                self._set_plan(None)
                self.status = (
                    f"plan {run.id} stopped at t={t:.3f} s of {run.traj.duration:.3f} s "
                    f"({old.value} -> {new.value}); the robot holds there; plan again to run "
                    "the keyframes"
                )
            self._announce(STATUS_ENDED, self.status, _CODE_DROPPED)
            log.warning("keyframes: %s", self.status)

    def update(self, now: float) -> Sequence[float] | None:
        run = self.active
        if run is None:
            return None
        t = now - self._t0
        pos = run.traj.position(t)
        if run.space == "joint":
            q: list[float] = pos.tolist()
        else:
            ctx = self.ctx
            assert ctx is not None
            try:
                if run.traj.has_rotation:
                    q, clamped = pose_ik(ctx.frame, run.traj, t, self._q_last)
                else:
                    q, clamped = ctx.frame.ik_clamped(
                        (float(pos[0]), float(pos[1]), float(pos[2])), self._q_last
                    )
            except (KinematicsError, ValueError) as err:
                clamped, q = True, self._q_last
                self.last_error = f"plan {run.id}: IK failed at t={t:.3f} s: {err}"
            if clamped:
                # checked offline, so only a different sampling time can get here: hold
                self.counters["ik_failures"] += 1
                self.active = None
                with self._lock:
                    self._generation += 1
                    self._set_plan(None)
                    self.status = f"plan {run.id} stopped at t={t:.3f} s: tip unreachable"
                self._announce(STATUS_ENDED, self.status, _CODE_DROPPED)
                log.warning("keyframes: %s", self.status)
                return None
        self._q_last = q
        if t >= run.traj.end:
            self.active = None
            self.counters["runs_completed"] += 1
            with self._lock:
                self._generation += 1
                self._set_plan(None)
                self.status = f"plan {run.id} completed ({run.traj.duration:.3f} s)"
            self._announce(STATUS_ENDED, self.status, _CODE_OK)
            log.info("keyframes: %s", self.status)
        return q

    def _announce(self, name: str, text: str, code: int) -> None:
        """A run's start or end as a STATUS to every viewer and operator (module docstring);
        on the loop thread, once per run and end."""
        ctx = self.ctx
        if ctx is not None and ctx.alert is not None:
            ctx.alert(name, text, code)

    # ------------------------------------------------------------------ preview
    def _due(self, out: Output, now: float) -> _PreviewState | None:
        pv = self._preview
        key = id(out)
        last = pv.sent.get(key)
        repeat = self.p.preview_repeat_s
        if last is not None and (pv.plan is None or repeat is None or now - last[1] < repeat):
            return None
        if last is None and pv.version == 0:
            return None  # nothing was ever previewed
        pv.sent[key] = (pv.version, now)
        return pv

    def _meta(self, out: Output) -> dict[str, str]:
        return {"MRMLNodeName": out.device} if out.header_version == 2 else {}

    def _source_path(self, out: Output, now: float) -> PolylineOut | None:
        pv = self._due(out, now)
        if pv is None:
            return None
        pts = pv.plan.path_mm if pv.plan is not None else np.zeros((0, 3))
        assert self.ctx is not None
        return PolylineOut(pts, self.ctx.clock.wall_time(), self._meta(out))

    def _source_points(self, out: Output, now: float) -> PointsOut | None:
        pv = self._due(out, now)
        if pv is None:
            return None
        plan_ = pv.plan
        names: list[str] = []
        keys: list[list[float]] = []
        if plan_ is not None:
            names = list(plan_.point_names)
            keys = plan_.keys_mm.tolist()
        assert self.ctx is not None
        return PointsOut(names, keys, self.ctx.clock.wall_time(), "Keyframe", meta=self._meta(out))

    # ------------------------------------------------------------------ reporting
    def describe(self) -> str:
        kset = self.kset
        lines = [f"status: {self.status}"]
        if kset is None:
            lines.append("keyframes: none")
        else:
            lines.append(f"keyframes: {len(kset.keyframes)} {kset.space} from {kset.source}")
            unit = "mm" if kset.space == "cartesian" else "rad/m"
            for i, k in enumerate(kset.keyframes):
                pose = " ".join(f"{v:.6g}" for v in k.pose)
                name = f" {kset.names[i]!r}" if kset.names[i] else ""
                lines.append(f"  #{i}{name} t={k.t:g} s pose=[{pose}] {unit}")
        acked = self._acked
        if acked is not None and kset is not None and acked.kset is kset:
            lines.append(f"acknowledged: plan {acked.id} (KeyframeSave Set=... keeps the set)")
        pending = self.plan
        if pending is not None:
            lines.append(f"previewed: {pending.summary}")
        if self.active is not None:
            lines.append(f"running: plan {self.active.id}")
        if self.library is not None:
            lines.append(f"library: {self.library.path} (KeyframeLibrary lists it)")
        return "\n".join(lines)

    def shutdown(self) -> None:
        """The planner thread ends once a job it is running (if any) is done; a plan being
        checked then is dropped (the robot is shutting down)."""
        if self._planner is not None:
            self._planner.stop()
            self._planner = None

    def stats(self) -> dict[str, Any]:
        kset = self.kset
        return {
            **self.counters,
            "keyframes": len(kset.keyframes) if kset else 0,
            "space": kset.space if kset else None,
            "source": kset.source if kset else None,
            "plan": self.plan.id if self.plan else None,
            "running": self.active.id if self.active else None,
            "status": self.status,
            "last_error": self.last_error,
            "forbidden_checks": len(self.forbidden_checks),
            "planner_fifo": self._planner.fifo if self._planner else None,
        }
