"""TRANSFORM and POSITION: poses (protocol doc 3.1, 3.2)."""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from .. import wire
from ..errors import ContentError, DecodeError
from .base import (
    FAST_V1,
    FAST_V2,
    Message,
    fast_builder,
    fast_builder_v1,
    fast_builder_v2,
    need_size,
    register,
)

_F12 = struct.Struct(">12f")
_F7 = struct.Struct(">7f")
_F6 = struct.Struct(">6f")
_F3 = struct.Struct(">3f")

#: Identity in wire order: R11 R21 R31 R12 R22 R32 R13 R23 R33 TX TY TZ (column-major 3x4).
IDENTITY12: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


@register("TRANSFORM")
@dataclass(frozen=True, slots=True)
class TransformMessage(Message):
    """A 4x4 homogeneous transform; translation in mm.

    ``elements`` are the 12 float32 values in wire order (the upper 3x4 of the matrix, column by
    column, then the translation). Use :meth:`from_matrix` and :attr:`matrix` for numpy 4x4.
    """

    TYPE: ClassVar[str] = "TRANSFORM"

    elements: tuple[float, ...] = IDENTITY12

    @classmethod
    def from_matrix(cls, matrix: Any, **common: Any) -> TransformMessage:
        m = np.asarray(matrix, dtype=float)
        if m.shape not in ((4, 4), (3, 4)):
            raise ValueError(f"transform matrix must be 4x4 or 3x4, got shape {m.shape}")
        return cls(elements=tuple(m[:3, :].T.ravel().tolist()), **common)

    @classmethod
    def from_position(cls, xyz: Sequence[float], **common: Any) -> TransformMessage:
        """A pure translation (mm)."""
        x, y, z = xyz
        return cls(elements=(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, x, y, z), **common)

    @property
    def matrix(self) -> np.ndarray:
        """The 4x4 matrix (a new numpy array)."""
        m = np.eye(4)
        m[:3, :] = np.asarray(self.elements, dtype=float).reshape(4, 3).T
        return m

    @property
    def translation(self) -> tuple[float, float, float]:
        e = self.elements
        return (e[9], e[10], e[11])

    def pack_content(self) -> bytes:
        try:
            return _F12.pack(*self.elements)
        except struct.error as err:
            raise ValueError(f"TRANSFORM needs 12 numbers: {err}") from err

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> TransformMessage:
        if len(content) != 48:
            need_size(content, 48, "TRANSFORM")
        return _build_transform(common, _F12_unpack(content))


_F12_unpack = _F12.unpack
_build_transform = fast_builder(TransformMessage)

#: Content sizes of the three POSITION variants.
POSITION_ALL = 28
POSITION_QUATERNION3 = 24
POSITION_ONLY = 12


@register("POSITION")
@dataclass(frozen=True, slots=True)
class PositionMessage(Message):
    """Position (mm) and orientation quaternion (ox, oy, oz, w).

    ``layout`` picks the content variant: 28 bytes (position + 4-element quaternion, the
    default), 24 (position + 3-element quaternion; the receiver rebuilds w >= 0, as sent by the
    OCC master) or 12 (position only).
    """

    TYPE: ClassVar[str] = "POSITION"

    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quaternion: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    layout: int = POSITION_ALL

    def pack_content(self) -> bytes:
        x, y, z = self.position
        if self.layout == POSITION_ALL:
            return _F7.pack(x, y, z, *self.quaternion)
        if self.layout == POSITION_QUATERNION3:
            ox, oy, oz, w = self.quaternion
            if w < 0.0:  # q and -q are the same rotation; the 3-element form implies w >= 0
                ox, oy, oz = -ox, -oy, -oz
            return _F6.pack(x, y, z, ox, oy, oz)
        if self.layout == POSITION_ONLY:
            return _F3.pack(x, y, z)
        raise ValueError(f"POSITION layout must be 28, 24 or 12 bytes, got {self.layout}")

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> PositionMessage:
        n = len(content)
        if n == POSITION_ALL:
            v = _F7.unpack(content)
            return _build_position(common, v[:3], v[3:], POSITION_ALL)
        if n == POSITION_QUATERNION3:
            x, y, z, ox, oy, oz = _F6.unpack(content)
            s = 1.0 - (ox * ox + oy * oy + oz * oz)
            quat = (ox, oy, oz, math.sqrt(s)) if s >= 0.0 else (0.0, 0.0, 0.0, 1.0)
            return cls((x, y, z), quat, POSITION_QUATERNION3, **common)
        if n == POSITION_ONLY:
            return cls(_F3.unpack(content), (0.0, 0.0, 0.0, 1.0), POSITION_ONLY, **common)
        raise ContentError(f"POSITION content must be 28, 24 or 12 bytes, got {n}", offset=0)


_build_position = fast_builder(PositionMessage)


_build_transform_v1 = fast_builder_v1(TransformMessage)
_build_position_v1 = fast_builder_v1(PositionMessage)


def _fast_transform(
    content: bytes, device: str, t: float, raw: int, wire_bytes: Any
) -> TransformMessage | None:
    if len(content) != 48:
        return None
    return _build_transform_v1(device, t, raw, wire_bytes, _F12_unpack(content))


def _fast_position(
    content: bytes, device: str, t: float, raw: int, wire_bytes: Any
) -> PositionMessage | None:
    if len(content) != POSITION_ALL:
        return None
    v = _F7.unpack(content)
    return _build_position_v1(device, t, raw, wire_bytes, v[:3], v[3:], POSITION_ALL)


FAST_V1["TRANSFORM"] = _fast_transform
FAST_V1["POSITION"] = _fast_position

_build_transform_v2 = fast_builder_v2(TransformMessage)
_build_position_v2 = fast_builder_v2(PositionMessage)
_EXT = wire.EXT_HEADER
_unpack_metadata = wire.unpack_metadata


def _v2_parts(body: bytes) -> tuple[int, int, dict[str, str], dict[str, int], int] | None:
    """(content start, content end, metadata, encodings, message ID) of a v2 body with the
    standard extended header, or None (the generic path then decides and reports)."""
    n = len(body)
    if n < 12:
        return None
    ext, mh, md, mid = _EXT.unpack_from(body, 0)
    end = n - mh - md
    if ext != 12 or end < 12:
        return None
    if mh:
        try:
            meta, enc = _unpack_metadata(body[end : end + mh], body[end + mh :])
        except DecodeError:
            return None
    else:
        meta, enc = {}, {}
    return 12, end, meta, enc, mid


def _fast_transform_v2(
    body: bytes, device: str, t: float, raw: int, wire_bytes: Any
) -> TransformMessage | None:
    parts = _v2_parts(body)
    if parts is None or parts[1] - parts[0] != 48:
        return None
    start, _, meta, enc, mid = parts
    values = _F12.unpack_from(body, start)
    return _build_transform_v2(device, t, raw, wire_bytes, meta, enc, mid, values)


def _fast_position_v2(
    body: bytes, device: str, t: float, raw: int, wire_bytes: Any
) -> PositionMessage | None:
    """The OCC master's stream: POSITION, 24-byte variant, v2, message ID and run/clutch."""
    parts = _v2_parts(body)
    if parts is None:
        return None
    start, end, meta, enc, mid = parts
    n = end - start
    if n == POSITION_QUATERNION3:
        x, y, z, ox, oy, oz = _F6.unpack_from(body, start)
        s = 1.0 - (ox * ox + oy * oy + oz * oz)
        quat = (ox, oy, oz, math.sqrt(s)) if s >= 0.0 else (0.0, 0.0, 0.0, 1.0)
        return _build_position_v2(
            device, t, raw, wire_bytes, meta, enc, mid, (x, y, z), quat, POSITION_QUATERNION3
        )
    if n == POSITION_ALL:
        v = _F7.unpack_from(body, start)
        return _build_position_v2(
            device, t, raw, wire_bytes, meta, enc, mid, v[:3], v[3:], POSITION_ALL
        )
    return None


FAST_V2["TRANSFORM"] = _fast_transform_v2
FAST_V2["POSITION"] = _fast_position_v2


def position_v2(
    device_name: str,
    timestamp: float,
    message_id: int,
    metadata: Mapping[str, str],
    position: tuple[float, float, float],
    quaternion: tuple[float, float, float, float],
    layout: int = POSITION_ALL,
) -> PositionMessage:
    """A header-version-2 POSITION for a stream's sender (a master's 500 Hz output): the same
    message as ``PositionMessage(position, quaternion, layout, device_name=..., timestamp=...,
    header_version=2, message_id=..., metadata=...)`` without the frozen dataclass ``__init__``
    (a keyword parse and a ``object.__setattr__`` per field: most of the cost of a small
    message). The caller gives plain floats, a ``uint32`` ID and str metadata; the metadata dict
    is kept, not copied (messages are immutable: do not change it afterwards)."""
    return _build_position_v2(
        device_name, timestamp, None, None, metadata, None, message_id, position, quaternion, layout
    )
