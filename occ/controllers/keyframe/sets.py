"""Keyframe sets: the timelines the keyframe controller plans (:class:`KeyframeSet`), how they
are written in YAML and files, validated (:func:`make_set`) and added to by ``KeyframeAdd``."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from occ.config import Float, NonNegFloat
from occ.errors import CommandError
from occ.kinematics.trajectory import Keyframe

M = TypeVar("M", bound=BaseModel)

Space = Literal["joint", "cartesian"]

#: largest keyframe file read (bytes): a timeline of keyframes is a few kilobytes
MAX_FILE_BYTES = 1 << 20


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

    def describe(self) -> list[str]:
        """KeyframeList's lines for the set: its size and source, then each keyframe."""
        lines = [f"keyframes: {len(self.keyframes)} {self.space} from {self.source}"]
        unit = "mm" if self.space == "cartesian" else "rad/m"
        for i, k in enumerate(self.keyframes):
            pose = " ".join(f"{v:.6g}" for v in k.pose)
            name = f" {self.names[i]!r}" if self.names[i] else ""
            lines.append(f"  #{i}{name} t={k.t:g} s pose=[{pose}] {unit}")
        return lines


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
    return validated_file(KeyframeFile, read_file_data(path), path)


def read_file_data(path: Path) -> Any:
    """A keyframe file's YAML (at most ``MAX_FILE_BYTES``; a bare list is its ``keyframes``);
    ValueError with the reason."""
    try:
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise ValueError(f"{path.name}: {size} bytes, more than {MAX_FILE_BYTES}")
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        raise ValueError(f"{path.name}: cannot read: {err}") from err
    return {"keyframes": data} if isinstance(data, list) else data


def validated_file(model: type[M], data: Any, path: Path) -> M:
    """``data`` as ``model``; ValueError naming the file, the first field wrong and why."""
    try:
        return model.model_validate(data)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise ValueError(f"{path.name}: {where}: {first['msg']}") from err


def file_set(kf: KeyframeFile, default: Space, source: str, joints: int, cap: int) -> KeyframeSet:
    return make_set(
        kf.space or default,
        [(k.t, k.pose, k.name or "", k.rotation) for k in kf.keyframes],
        source,
        joints=joints,
        max_keyframes=cap,
    )


def added_set(
    current: KeyframeSet | None, args: dict[str, str], default: Space, joints: int, cap: int
) -> KeyframeSet:
    """The stored set with the keyframe of ``KeyframeAdd T=.. Pose=".." [Label=..]
    [Space=..] [Rotation=".."]`` (``args``, keys in lower case) inserted at its time; a new set
    when none is stored. CommandError with the reason."""
    try:
        t = float(args["t"])
        pose = [float(v) for v in args["pose"].replace(",", " ").split()]
    except KeyError as err:
        raise CommandError(f"KeyframeAdd needs T and Pose (missing {err})") from None
    except ValueError as err:
        raise CommandError(f"KeyframeAdd: {err}") from None
    space = args.get("space", current.space if current else default).strip().lower()
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
        return make_set(
            space,  # type: ignore[arg-type]
            items,
            "operator commands",
            joints=joints,
            max_keyframes=cap,
        )
    except ValueError as err:
        raise CommandError(f"KeyframeAdd: {err}") from None


def keyframe_path(folder: str | Path | None, args: dict[str, str]) -> tuple[str, Path]:
    """``KeyframeLoad File=NAME``: (the name, the file) in the keyframe folder ``folder``;
    CommandError when the command is off (no folder), the name missing or outside it."""
    if folder is None:
        raise CommandError("KeyframeLoad is off: no keyframe_dir in the configuration")
    name = args.get("file", "").strip()
    if not name:
        raise CommandError(
            "KeyframeLoad needs File (a name in the keyframe folder) or Set (a set in the library)"
        )
    root = Path(folder).resolve()
    path = (root / name).resolve()
    if root not in path.parents or Path(name).is_absolute():
        raise CommandError(f"KeyframeLoad: {name!r} is not inside the keyframe folder")
    return name, path
