"""The ``safety`` section: watchdog, packet-loss monitor, supervisor, collision check."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from occ.config.base import (
    Bool,
    ExistingFile,
    Float,
    Int,
    Loc,
    Name,
    NonNegFloat,
    Policy,
    PosFloat,
    _Model,
    _raise_problems,
)


class WatchdogConfig(_Model):
    """Loop-period watchdog: overruns are alerts; a run of them, or one big gap, is a stop."""

    budget_us: PosFloat = Field(1000.0, description="Cycle budget in µs; over it = an alert.")
    alert_run: Annotated[Int, Field(ge=1)] = Field(
        1, description="Consecutive over-budget cycles that raise an alert."
    )
    stop_run: Annotated[Int, Field(ge=1)] = Field(
        5, description="Consecutive over-budget cycles that stop the robot; >= `alert_run`."
    )
    hard_gap_ms: PosFloat = Field(
        10.0, description="A single gap between cycles longer than this stops the robot."
    )
    policy: Policy = Field(
        "hold", description="On stop: `hold` the last safe position, or latch `fault`."
    )

    @model_validator(mode="after")
    def _runs_ordered(self) -> WatchdogConfig:
        if self.stop_run < self.alert_run:
            _raise_problems(
                [(("stop_run",), f"must be >= alert_run ({self.alert_run}), got {self.stop_run}")]
            )
        return self


class LossConfig(_Model):
    """Packet-loss monitor on one input interface."""

    enabled: Bool = Field(True, description="Run the loss monitor.")
    input: Name | None = Field(
        None, description="Name of the interface whose stream is watched; null = none."
    )
    period_ms: PosFloat = Field(2.0, description="Expected period of the watched stream in ms.")
    max_consecutive: Annotated[Int, Field(ge=0)] = Field(
        2,
        description="Consecutive losses tolerated; `max_consecutive + 1` in a row stop the robot.",
    )
    deadline_ms: PosFloat | None = Field(
        None,
        description="Hold (stop moving, not latched) when no good packet for this long; null "
        "= `period_ms * (max_consecutive + 1) + period_ms / 4` (6.5 ms: the OCC 7 ms rule).",
    )
    grace_ms: PosFloat = Field(
        100.0,
        description="Latched stop with an alert when the stream stays silent this long (a "
        "dead master); a stream back within it, with no gap of `max_consecutive + 1`, "
        "resumes by itself.",
    )
    strict: Bool = Field(
        False,
        description="The paper's rule word for word: the deadline itself latches the stop "
        "(no hold-and-resume).",
    )
    timestamp_tolerance_ms: PosFloat | None = Field(
        50.0,
        description="Refuse samples whose header timestamp is off by more than this from the "
        "peer's learned clock offset (stale or future); a run of refused samples counts like "
        "loss. null = no timestamp check.",
    )
    policy: Policy = Field(
        "hold", description="On a latched loss: `hold` (STOPPED until Run) or latch `fault`."
    )

    @model_validator(mode="after")
    def _grace_after_deadline(self) -> LossConfig:
        deadline = (
            self.deadline_ms
            if self.deadline_ms is not None
            else self.period_ms * (self.max_consecutive + 1.25)
        )
        if self.grace_ms < deadline:
            _raise_problems(
                [
                    (
                        ("grace_ms",),
                        f"must be >= the deadline ({deadline:g} ms), got {self.grace_ms:g}",
                    )
                ]
            )
        return self


class SupervisorConfig(_Model):
    """The supervisor: a thread outside the loop that notices a loop that stopped ticking."""

    enabled: Bool = Field(True, description="Run the supervisor thread.")
    timeout_ms: PosFloat = Field(
        20.0,
        description="A loop that has not ticked for this long is hung: drivers to their safe "
        "state at once, operators alerted, FAULT when the loop comes back.",
    )
    fifo_priority: Annotated[Int, Field(ge=1, le=99)] | None = Field(
        None,
        description="SCHED_FIFO priority of the supervisor thread; null = one above the loop's "
        "`robot.realtime.fifo_priority` (when that is set and permitted).",
    )


_XYZ = tuple[Float, Float, Float]


class RegionConfig(_Model):
    """A forbidden region of the whole-arm collision check (occ/kinematics/collision.py): patient
    frame (3D Slicer's RAS), mm."""

    name: Name = Field(description="Its name (the refusal and the alert name it).")
    kind: Literal["sphere", "plane", "mesh"] = Field(
        description="`sphere`: a ball; `plane`: the half-space behind a plane (opposite its "
        "normal); `mesh`: a triangle mesh from `file` (STL, OBJ, PLY)."
    )
    point_mm: _XYZ = Field(
        (0.0, 0.0, 0.0),
        description="`sphere`: its centre; `plane`: a point of the plane; `mesh`: where the "
        "file's origin goes (patient frame, mm).",
    )
    normal: _XYZ = Field(
        (0.0, 0.0, 1.0),
        description="`plane`: the normal pointing out of the forbidden side, toward the robot "
        "(made unit length).",
    )
    radius_mm: PosFloat = Field(10.0, description="`sphere`: its radius (mm).")
    file: ExistingFile | None = Field(
        None, description="`mesh`: the mesh file (relative to the config file), in mm."
    )
    exclude_links: tuple[Name, ...] = Field(
        (),
        description="Links not checked against this region (the base standing on a table plane).",
    )

    @model_validator(mode="after")
    def _kind_fields(self) -> RegionConfig:
        problems: list[tuple[Loc, str]] = []
        if self.kind == "plane" and not any(abs(c) > 0.0 for c in self.normal):
            problems.append((("normal",), "must not be zero"))
        if self.kind == "mesh" and self.file is None:
            problems.append((("file",), "required for a mesh region"))
        if self.kind != "mesh" and self.file is not None:
            problems.append((("file",), f"only a mesh region has a file (this is a {self.kind})"))
        _raise_problems(problems)
        return self


class ToolConfig(_Model):
    """The tool on the tip link, for the collision check: a capsule along the tip's z axis."""

    length_mm: PosFloat = Field(description="From the tip link's origin along its z axis (mm).")
    radius_mm: PosFloat = Field(5.0, description="Its radius (mm).")


class CollisionConfig(_Model):
    """Whole-arm collision checking (occ/kinematics/collision.py, coal): the arm's links and the
    tool against forbidden regions and each other, in every keyframe plan before it is
    acknowledged, and at run time on a worker thread, which stops the robot when a link comes
    within the margin."""

    margin_mm: PosFloat = Field(
        10.0,
        description="A link or the tool closer than this to a forbidden region is a contact: "
        "a plan is refused, a running robot stops (with an ALERT naming link and region).",
    )
    self_collision: Bool = Field(
        True,
        description="Check the arm against itself too (links not adjacent, minus the "
        "package's SRDF's disabled pairs when it has one).",
    )
    self_margin_mm: NonNegFloat = Field(
        2.0, description="The margin between two links of the arm (mm)."
    )
    link_radius_mm: PosFloat = Field(
        30.0,
        description="Where the URDF has no collision geometry: each link is a capsule of this "
        "radius between its joint's origin and the next one's (and the tip).",
    )
    convex: Bool = Field(
        True,
        description="Check each link mesh as its convex hull (contains the mesh: never misses a "
        "contact; ~2 us a pair instead of ~20-40 us).",
    )
    tool: ToolConfig | None = Field(None, description="The tool on the tip link; null = none.")
    srdf: ExistingFile | None = Field(
        None,
        description="An SRDF whose `disable_collisions` pairs are not self-checked; null = the "
        "package's `srdf/<urdf name>.srdf` when there is one.",
    )
    runtime: Bool = Field(
        True,
        description="Check every new setpoint while the robot runs (a worker thread; the loop "
        "holds a setpoint the last verdict does not cover).",
    )
    runtime_hz: PosFloat | None = Field(
        None,
        description="At most this many run-time verdicts a second (each costs the worker "
        "30-70 us for the UR5; one is computed only when due: the last no longer covers the "
        "setpoint with room); null = a verdict whenever one is due and the worker is idle. "
        "Fewer verdicts mean more holds when moving fast, never less safety.",
    )
    policy: Policy = Field(
        "hold", description="On a contact at run time: `hold` (STOPPED until Run) or `fault`."
    )
    regions: tuple[RegionConfig, ...] = Field(
        (), description="Forbidden regions (3D Slicer adds more at run time: README)."
    )

    @model_validator(mode="after")
    def _unique_names(self) -> CollisionConfig:
        seen: dict[str, int] = {}
        problems: list[tuple[Loc, str]] = []
        for i, r in enumerate(self.regions):
            if r.name in seen:
                first = f"(first at regions[{seen[r.name]}])"
                problems.append((("regions", i, "name"), f"duplicate region '{r.name}' {first}"))
            seen.setdefault(r.name, i)
        _raise_problems(problems)
        return self


class SafetyConfig(_Model):
    """Safety monitors."""

    watchdog: WatchdogConfig = Field(WatchdogConfig(), description="Watchdog.")
    loss: LossConfig = Field(LossConfig(), description="Packet-loss monitor.")
    supervisor: SupervisorConfig = Field(SupervisorConfig(), description="Loop supervisor.")
    collision: CollisionConfig | None = Field(
        None, description="Whole-arm collision checking; null = none."
    )
