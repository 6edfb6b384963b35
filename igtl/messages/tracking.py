"""TDATA and QTDATA: tracking data for several tools in one message (protocol doc 3.7, 3.8)."""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from .base import Message, fixed, need_multiple, register, unfixed
from .transform import IDENTITY12

_TDATA = struct.Struct(">20sBB12f")  # 70 bytes
_QTDATA = struct.Struct(">20sBB7f")  # 50 bytes

#: Tool types.
TRACKER = 1
INSTRUMENT_6D = 2
INSTRUMENT_3D = 3
INSTRUMENT_5D = 4


def _check_tool(name: str, tool_type: int) -> None:
    fixed(name, 20, "tracking element name")
    if not isinstance(tool_type, int) or not 0 <= tool_type <= 255:
        raise ValueError(f"tool type must fit uint8, got {tool_type!r}")


@dataclass(frozen=True, slots=True)
class TrackingElement:
    """One tool in TDATA: name (<= 20 bytes), type (1 tracker, 2 6D, 3 3D, 4 5D) and the 12
    float32 of a TRANSFORM in wire order (upper 3x4, column-major, translation in mm)."""

    name: str = ""
    tool_type: int = INSTRUMENT_6D
    elements: tuple[float, ...] = IDENTITY12

    def __post_init__(self) -> None:
        _check_tool(self.name, self.tool_type)
        els = tuple(float(v) for v in self.elements)
        if len(els) != 12:
            raise ValueError(f"tracking element needs 12 numbers, got {len(els)}")
        object.__setattr__(self, "elements", els)

    @classmethod
    def from_matrix(cls, name: str, matrix: Any, tool_type: int = INSTRUMENT_6D) -> TrackingElement:
        m = np.asarray(matrix, dtype=float)
        if m.shape not in ((4, 4), (3, 4)):
            raise ValueError(f"matrix must be 4x4 or 3x4, got shape {m.shape}")
        return cls(name, tool_type, tuple(m[:3, :].T.ravel().tolist()))

    @property
    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :] = np.asarray(self.elements, dtype=float).reshape(4, 3).T
        return m


@register("TDATA")
@dataclass(frozen=True, slots=True)
class TrackingDataMessage(Message):
    """Tracking data: a list of :class:`TrackingElement` (70 bytes each)."""

    TYPE: ClassVar[str] = "TDATA"

    trackers: tuple[TrackingElement, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "trackers", tuple(self.trackers))

    def pack_content(self) -> bytes:
        return b"".join(
            _TDATA.pack(fixed(t.name, 20, "name"), t.tool_type, 0, *t.elements)
            for t in self.trackers
        )

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> TrackingDataMessage:
        n = need_multiple(content, 70, "TDATA")
        out = []
        for i in range(n):
            v = _TDATA.unpack_from(content, 70 * i)
            out.append(TrackingElement(unfixed(v[0]), v[1], v[3:]))
        return cls(tuple(out), **common)


@dataclass(frozen=True, slots=True)
class QuaternionTrackingElement:
    """One tool in QTDATA: name, type, position (mm) and quaternion (qx, qy, qz, w)."""

    name: str = ""
    tool_type: int = INSTRUMENT_6D
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quaternion: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        _check_tool(self.name, self.tool_type)
        object.__setattr__(self, "position", _n(self.position, 3, "position"))
        object.__setattr__(self, "quaternion", _n(self.quaternion, 4, "quaternion"))


def _n(values: Sequence[float], n: int, what: str) -> tuple[float, ...]:
    out = tuple(float(v) for v in values)
    if len(out) != n:
        raise ValueError(f"{what} needs {n} numbers, got {len(out)}")
    return out


@register("QTDATA")
@dataclass(frozen=True, slots=True)
class QuaternionTrackingDataMessage(Message):
    """Quaternion tracking data: a list of :class:`QuaternionTrackingElement` (50 bytes each)."""

    TYPE: ClassVar[str] = "QTDATA"

    trackers: tuple[QuaternionTrackingElement, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "trackers", tuple(self.trackers))

    def pack_content(self) -> bytes:
        return b"".join(
            _QTDATA.pack(fixed(t.name, 20, "name"), t.tool_type, 0, *t.position, *t.quaternion)
            for t in self.trackers
        )

    @classmethod
    def unpack_content(
        cls, content: bytes, common: dict[str, Any]
    ) -> QuaternionTrackingDataMessage:
        n = need_multiple(content, 50, "QTDATA")
        out = []
        for i in range(n):
            v = _QTDATA.unpack_from(content, 50 * i)
            out.append(QuaternionTrackingElement(unfixed(v[0]), v[1], v[3:6], v[6:10]))
        return cls(tuple(out), **common)
