"""POINT and TRAJ: fiducials and trajectories (protocol doc 3.6, 3.16).

The reference documents the float after the coordinates as a *diameter*, while its C structs
call it ``radius``; we keep the C name (and the value as sent; Slicer sends 0).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from .base import Message, check_uint, fixed, need_multiple, register, unfixed

_POINT = struct.Struct(">64s32s4B3ff20s")  # 136 bytes
_TRAJ = struct.Struct(">64s32sbb4B3f3ff20s")  # 150 bytes


def _floats(values: Sequence[float], n: int, what: str) -> tuple[float, ...]:
    out = tuple(float(v) for v in values)
    if len(out) != n:
        raise ValueError(f"{what} needs {n} numbers, got {len(out)}")
    return out


def _rgba(values: Sequence[int]) -> tuple[int, int, int, int]:
    out = tuple(values)
    if len(out) != 4:
        raise ValueError(f"rgba needs 4 values, got {len(out)}")
    for v in out:
        check_uint(v, 8, "rgba component")
    return out  # type: ignore[return-value]


@dataclass(frozen=True, slots=True)
class PointElement:
    """One fiducial: name (<= 64 bytes), group (<= 32; "Labeled Point", "Landmark",
    "Fiducial", ...), RGBA 0..255, position (mm), radius (mm), owner image (<= 20)."""

    name: str = ""
    group: str = ""
    rgba: tuple[int, int, int, int] = (255, 255, 255, 255)
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius: float = 0.0
    owner: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "rgba", _rgba(self.rgba))
        object.__setattr__(self, "position", _floats(self.position, 3, "position"))
        fixed(self.name, 64, "point name")
        fixed(self.group, 32, "point group")
        fixed(self.owner, 20, "point owner")

    def pack(self) -> bytes:
        return _POINT.pack(
            fixed(self.name, 64, "name"),
            fixed(self.group, 32, "group"),
            *self.rgba,
            *self.position,
            self.radius,
            fixed(self.owner, 20, "owner"),
        )


@register("POINT")
@dataclass(frozen=True, slots=True)
class PointMessage(Message):
    """A list of :class:`PointElement` (136 bytes each; count = content size / 136)."""

    TYPE: ClassVar[str] = "POINT"

    points: tuple[PointElement, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "points", tuple(self.points))

    def pack_content(self) -> bytes:
        return b"".join(p.pack() for p in self.points)

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> PointMessage:
        n = need_multiple(content, 136, "POINT")
        points = []
        for i in range(n):
            v = _POINT.unpack_from(content, 136 * i)
            points.append(
                PointElement(unfixed(v[0]), unfixed(v[1]), v[2:6], v[6:9], v[9], unfixed(v[10]))
            )
        return cls(tuple(points), **common)


#: TRAJ element types.
TRAJ_ENTRY_ONLY = 1
TRAJ_TARGET_ONLY = 2
TRAJ_ENTRY_TARGET = 3


@dataclass(frozen=True, slots=True)
class TrajectoryElement:
    """One trajectory: name (<= 64), group (<= 32), type (1 entry only, 2 target only, 3 both),
    RGBA, entry and target points (mm), radius (mm), owner image (<= 20)."""

    name: str = ""
    group: str = ""
    type: int = TRAJ_ENTRY_TARGET
    rgba: tuple[int, int, int, int] = (255, 255, 255, 255)
    entry: tuple[float, float, float] = (0.0, 0.0, 0.0)
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius: float = 0.0
    owner: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.type, int) or not -128 <= self.type <= 127:
            raise ValueError(f"trajectory type must fit int8, got {self.type!r}")
        object.__setattr__(self, "rgba", _rgba(self.rgba))
        object.__setattr__(self, "entry", _floats(self.entry, 3, "entry"))
        object.__setattr__(self, "target", _floats(self.target, 3, "target"))
        fixed(self.name, 64, "trajectory name")
        fixed(self.group, 32, "trajectory group")
        fixed(self.owner, 20, "trajectory owner")

    def pack(self) -> bytes:
        return _TRAJ.pack(
            fixed(self.name, 64, "name"),
            fixed(self.group, 32, "group"),
            self.type,
            0,
            *self.rgba,
            *self.entry,
            *self.target,
            self.radius,
            fixed(self.owner, 20, "owner"),
        )


@register("TRAJ")
@dataclass(frozen=True, slots=True)
class TrajectoryMessage(Message):
    """A list of :class:`TrajectoryElement` (150 bytes each). Type name "TRAJ"."""

    TYPE: ClassVar[str] = "TRAJ"

    trajectories: tuple[TrajectoryElement, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "trajectories", tuple(self.trajectories))

    def pack_content(self) -> bytes:
        return b"".join(t.pack() for t in self.trajectories)

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> TrajectoryMessage:
        n = need_multiple(content, 150, "TRAJ")
        items = []
        for i in range(n):
            v = _TRAJ.unpack_from(content, 150 * i)
            items.append(
                TrajectoryElement(
                    unfixed(v[0]),
                    unfixed(v[1]),
                    v[2],
                    v[4:8],
                    v[8:11],
                    v[11:14],
                    v[14],
                    unfixed(v[15]),
                )
            )
        return cls(tuple(items), **common)
