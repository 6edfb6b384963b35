"""POLYDATA: points, cells and attributes of a surface model (protocol doc 3.15).

Layout: 10 x uint32 header (NPOINTS, NVERTICES, SIZE_VERTICES, NLINES, SIZE_LINES, NPOLYGONS,
SIZE_POLYGONS, NTRIANGLE_STRIPS, SIZE_TRIANGLE_STRIPS, NATTRIBUTES); float32 points; four
VTK-style cell arrays (uint32 n, n indices); NATTRIBUTES x (uint8 type, uint8 ncomp, uint32 n);
the NUL-terminated attribute names, padded as a block to an even length; float32 data.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from .. import wire
from ..errors import ContentError, InvalidTextError
from .base import Message, common_equal, register

_HEAD = struct.Struct(">10I")
_ATTR = struct.Struct(">BBI")

#: Attribute types (point data 0x00-0x05, cell data 0x10-0x15).
POINT_SCALAR, POINT_VECTOR, POINT_NORMAL, POINT_TENSOR, POINT_RGBA, POINT_TCOORDS = range(6)
CELL_SCALAR, CELL_VECTOR, CELL_NORMAL, CELL_TENSOR, CELL_RGBA, CELL_TCOORDS = range(0x10, 0x16)

Cells = tuple[tuple[int, ...], ...]


@dataclass(frozen=True, slots=True, eq=False)
class PolyDataAttribute:
    """One attribute: ``type`` (see constants), ``name`` (<= 255 bytes, no NUL) and ``data``
    float32 of shape (n, ncomponents)."""

    type: int = POINT_SCALAR
    name: str = ""
    data: np.ndarray = field(default_factory=lambda: np.zeros((0, 1), np.float32))

    def __post_init__(self) -> None:
        if not isinstance(self.type, int) or not 0 <= self.type <= 255:
            raise ValueError(f"attribute type must fit uint8, got {self.type!r}")
        raw = self.name.encode("utf-8") if isinstance(self.name, str) else b"\0"
        if b"\0" in raw or len(raw) > 255:
            raise ValueError(f"attribute name {self.name!r}: <= 255 UTF-8 bytes, no NUL")
        d = np.asarray(self.data, dtype=np.float32)
        if d.ndim == 1:
            d = d[:, np.newaxis]
        if d.ndim != 2 or not 1 <= d.shape[1] <= 255:
            raise ValueError(f"attribute data must be (n, 1..255), got shape {d.shape}")
        object.__setattr__(self, "data", d)

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        assert isinstance(other, PolyDataAttribute)
        return (
            self.type == other.type
            and self.name == other.name
            and self.data.shape == other.data.shape
            and self.data.astype(">f4").tobytes() == other.data.astype(">f4").tobytes()
        )

    __hash__ = None  # type: ignore[assignment]


def _cells(cells: Sequence[Sequence[int]], what: str) -> Cells:
    out = tuple(tuple(int(i) for i in c) for c in cells)
    for c in out:
        for i in c:
            if not 0 <= i <= 0xFFFFFFFF:
                raise ValueError(f"{what} index {i} does not fit uint32")
    return out


def _pack_cells(cells: Cells) -> bytes:
    flat: list[int] = []
    for c in cells:
        flat.append(len(c))
        flat.extend(c)
    return np.asarray(flat, dtype=">u4").tobytes()


def _unpack_cells(content: bytes, start: int, count: int, size: int, what: str) -> Cells:
    if size % 4:
        raise ContentError(f"POLYDATA {what} size {size} is not a multiple of 4", offset=start)
    flat = np.frombuffer(content, dtype=">u4", count=size // 4, offset=start).tolist()
    cells = []
    pos = 0
    for _ in range(count):
        if pos >= len(flat):
            raise ContentError(
                f"POLYDATA {what}: {count} cells do not fit {size} bytes", offset=start + 4 * pos
            )
        n = flat[pos]
        if pos + 1 + n > len(flat):
            raise ContentError(
                f"POLYDATA {what}: cell of {n} indices overruns its block", offset=start + 4 * pos
            )
        cells.append(tuple(flat[pos + 1 : pos + 1 + n]))
        pos += 1 + n
    if pos != len(flat):
        raise ContentError(
            f"POLYDATA {what}: {count} cells leave {4 * (len(flat) - pos)} bytes",
            offset=start + 4 * pos,
        )
    return tuple(cells)


@register("POLYDATA")
@dataclass(frozen=True, slots=True, eq=False)
class PolyDataMessage(Message):
    """``points`` float32 (n, 3); ``vertices``, ``lines``, ``polygons``, ``strips`` as tuples of
    point-index tuples; ``attributes`` as :class:`PolyDataAttribute`."""

    TYPE: ClassVar[str] = "POLYDATA"

    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    vertices: Cells = ()
    lines: Cells = ()
    polygons: Cells = ()
    strips: Cells = ()
    attributes: tuple[PolyDataAttribute, ...] = ()

    def __post_init__(self) -> None:
        p = np.asarray(self.points, dtype=np.float32)
        if p.size == 0:
            p = p.reshape(0, 3)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points must be (n, 3), got shape {p.shape}")
        object.__setattr__(self, "points", p)
        for name in ("vertices", "lines", "polygons", "strips"):
            object.__setattr__(self, name, _cells(getattr(self, name), name))
        attrs = tuple(self.attributes)
        for a in attrs:
            if not isinstance(a, PolyDataAttribute):
                raise TypeError(f"attributes must be PolyDataAttribute, got {type(a).__name__}")
        object.__setattr__(self, "attributes", attrs)

    def pack_content(self) -> bytes:
        blocks = [_pack_cells(c) for c in (self.vertices, self.lines, self.polygons, self.strips)]
        counts = (len(self.vertices), len(self.lines), len(self.polygons), len(self.strips))
        head = _HEAD.pack(
            len(self.points),
            counts[0],
            len(blocks[0]),
            counts[1],
            len(blocks[1]),
            counts[2],
            len(blocks[2]),
            counts[3],
            len(blocks[3]),
            len(self.attributes),
        )
        names = b"".join(a.name.encode("utf-8") + b"\0" for a in self.attributes)
        if len(names) % 2:
            names += b"\0"
        return b"".join(
            (
                head,
                self.points.astype(">f4").tobytes(),
                *blocks,
                *(_ATTR.pack(a.type, a.data.shape[1], a.data.shape[0]) for a in self.attributes),
                names,
                *(a.data.astype(">f4").tobytes() for a in self.attributes),
            )
        )

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> PolyDataMessage:
        size = len(content)
        if size < 40:
            raise ContentError(f"POLYDATA content must be >= 40 bytes, got {size}", offset=0)
        h = _HEAD.unpack_from(content, 0)
        npoints, nattr = h[0], h[9]
        pos = 40
        need = 40 + 12 * npoints + h[2] + h[4] + h[6] + h[8] + 6 * nattr
        if need > size:
            raise ContentError(
                f"POLYDATA header announces at least {need} bytes, content holds {size}",
                offset=0,
            )
        points = np.frombuffer(content, ">f4", 3 * npoints, pos).reshape(npoints, 3)
        pos += 12 * npoints
        cell_sets: list[Cells] = []
        for what, (n, s) in zip(
            ("vertices", "lines", "polygons", "strips"),
            ((h[1], h[2]), (h[3], h[4]), (h[5], h[6]), (h[7], h[8])),
            strict=True,
        ):
            cell_sets.append(_unpack_cells(content, pos, n, s, what))
            pos += s
        heads = [_ATTR.unpack_from(content, pos + 6 * i) for i in range(nattr)]
        pos += 6 * nattr
        names = []
        for _ in range(nattr):
            end = content.find(b"\0", pos)
            if end < 0:
                raise InvalidTextError("POLYDATA attribute name without NUL terminator", offset=pos)
            if end - pos > 255:
                raise InvalidTextError("POLYDATA attribute name longer than 255 bytes", offset=pos)
            names.append(wire.decode_fixed(content[pos:end]))
            pos = end + 1
        if pos % 2:  # the names block is padded to an even length (content starts even)
            pos += 1
        attrs = []
        for (atype, ncomp, n), name in zip(heads, names, strict=True):
            if ncomp == 0:
                raise ContentError(f"POLYDATA attribute {name!r} has 0 components", offset=pos)
            nbytes = 4 * n * ncomp
            if pos + nbytes > size:
                raise ContentError(
                    f"POLYDATA attribute {name!r} data overruns the content", offset=pos
                )
            data = np.frombuffer(content, ">f4", n * ncomp, pos).reshape(n, ncomp)
            attrs.append(PolyDataAttribute(atype, name, data.astype(np.float32)))
            pos += nbytes
        if pos != size:
            raise ContentError(
                f"POLYDATA: {size - pos} bytes left after the last attribute", offset=pos
            )
        vertices, lines, polygons, strips = cell_sets
        return cls(
            points.astype(np.float32),
            vertices=vertices,
            lines=lines,
            polygons=polygons,
            strips=strips,
            attributes=tuple(attrs),
            **common,
        )

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        assert isinstance(other, PolyDataMessage)
        return (
            common_equal(self, other)
            and self.points.shape == other.points.shape
            and self.points.astype(">f4").tobytes() == other.points.astype(">f4").tobytes()
            and self.vertices == other.vertices
            and self.lines == other.lines
            and self.polygons == other.polygons
            and self.strips == other.strips
            and self.attributes == other.attributes
        )

    __hash__ = None  # type: ignore[assignment]
