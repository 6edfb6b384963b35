"""The keyframe controller's parameters (``KeyframeParams``) and their checks against the rest
of the configuration (``occd --check``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import BeforeValidator, DirectoryPath, Field

from occ.config import (
    Bool,
    ExistingFile,
    Float,
    Int,
    Name,
    OutputPath,
    PosFloat,
    Vec3,
)
from occ.config.base import _resolve_path
from occ.controllers.keyframe.sets import (
    KeyframeFile,
    KeyframeItem,
    Space,
    _Model,
    file_set,
    read_keyframe_file,
)
from occ.haptics.fixtures import ForbiddenPlane, ForbiddenSphere, forbidden_hit

if TYPE_CHECKING:
    from occ.config import DaemonConfig
    from occ.controllers import Problem

ExistingDir = Annotated[DirectoryPath, BeforeValidator(_resolve_path)]


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
        "fixtures' forbidden spheres and planes (occ/haptics/fixtures.py; mm, base frame): "
        "`{centre_mm, radius_mm, name}` or `{point_mm, normal, name}`.",
    )
    rcm_mm: Vec3 | None = Field(
        None,
        description="A laparoscopic tool's port, the remote centre of motion its shaft must "
        "keep (patient frame, mm; as teleop-slave's `rcm_mm`); a 6-DOF arm. Every plan then "
        "turns the tool about it: the tip's path as planned, the tool's axis (its z) from the "
        "port through the tip, the roll the keyframes' (interpolated) or, when they give "
        "none, the one it has where the plan starts; joint keyframes are planned through the "
        "port as the tool's poses. A plan is refused unless the shaft passes within 0.05 mm "
        "of the port at every sample, and a run stops (the robot holds) at a tick where it "
        "would not. null = no port.",
    )
    rcm_tolerance_deg: Annotated[Float, Field(gt=0, le=5)] = Field(
        0.5,
        description="With `rcm_mm`: how far a keyframe's own orientation (given, or a joint "
        "keyframe's) may turn the tool's axis from the axis through the port and its tip "
        "(degrees); it is turned onto that axis (the plan's summary says how far), beyond "
        "this the plan is refused naming the keyframe and the angle.",
    )
    rcm_min_depth_mm: PosFloat = Field(
        10.0,
        description="With `rcm_mm`: the tip stays at least this far beyond the port (mm) at "
        "every keyframe and sample: a plan that would draw the tip back to the port is refused.",
    )
    cell_skew_ms: Annotated[Float, Field(ge=0, le=100)] = Field(
        2.0,
        description="A cell keyframe set (one part per arm of the cell): how far apart in time "
        "two members' parts may run (the phase of their loops' ticks, up to one period, plus "
        "the disagreement of their hosts' clocks); the cross-check of the plans counts every "
        "other arm anywhere within this of the aligned time (ms).",
    )
    cell_start_max_s: Annotated[Float, Field(gt=0, le=600)] = Field(
        30.0,
        description="A cell plan's `KeyframeAck StartAt=`: how far ahead (s) a common start "
        "may be; further, or in the past, is refused.",
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


def check_params(params: Any, config: DaemonConfig) -> list[Problem]:
    """What ``KeyframeController.check`` reports: the input interface named, the start-up
    keyframes (YAML or file) valid for this robot, the library's folder, the preview sent."""
    from occ.config.base import _did_you_mean

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
            file_set(
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
            file_set(
                read_keyframe_file(Path(params.file)),
                params.space,
                "file",
                joints,
                params.max_keyframes,
            )
        except ValueError as err:
            problems.append((("file",), str(err)))
    if params.rcm_mm is not None and joints < 6:
        problems.append(
            (("rcm_mm",), f"a port needs a 6-DOF arm to turn the tool about it; {joints} joints")
        )
    if params.library is not None and not Path(params.library).parent.is_dir():
        problems.append((("library",), f"the folder {Path(params.library).parent} does not exist"))
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


def regions_check(
    items: Sequence[ForbiddenSphereItem | ForbiddenPlaneItem],
) -> Callable[[tuple[float, float, float]], str | None]:
    """The ``forbidden`` parameter as one tip check (a ForbiddenCheck: the virtual fixtures'
    regions, mm, base frame; immutable, so the planner thread reads it safely); ValueError for
    a bad region."""
    regions = [
        ForbiddenSphere(f.centre_mm, f.radius_mm, name=f.name)
        if isinstance(f, ForbiddenSphereItem)
        else ForbiddenPlane(f.point_mm, f.normal, name=f.name)
        for f in items
    ]

    def configured_regions(point: tuple[float, float, float]) -> str | None:
        return forbidden_hit(regions, (point[0] * 1e3, point[1] * 1e3, point[2] * 1e3))

    return configured_regions
