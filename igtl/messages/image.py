"""IMAGE, IMGMETA and LBMETA (protocol doc 3.11-3.13).

IMAGE geometry: the 12 floats are the i, j and k axis directions each scaled by its spacing,
then PX..PZ, which by every implementation's convention is the **centre** of the image, not
the corner voxel (OpenIGTLinkIO, pyigtl: ``centre = corner + sum(axis * (size - 1) / 2)``).
:meth:`ImageMessage.from_array` takes either and :attr:`ImageMessage.origin` gives the corner
back. Pixel bytes are in the order the E field declares (1 big, 2 little); every other number
is big-endian.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal, cast

import numpy as np

from ..errors import ContentError
from .base import Message, check_uint, common_equal, fixed, need_multiple, register, unfixed

_IMAGE_HEAD = struct.Struct(">HBBBB3H12f3H3H")  # 72 bytes

#: IMAGE scalar types -> numpy dtype (byte order applied separately).
IMAGE_DTYPES: dict[int, np.dtype] = {
    2: np.dtype("i1"),
    3: np.dtype("u1"),
    4: np.dtype("i2"),
    5: np.dtype("u2"),
    6: np.dtype("i4"),
    7: np.dtype("u4"),
    10: np.dtype("f4"),
    11: np.dtype("f8"),
}
_IMAGE_CODES = {(dt.kind, dt.itemsize): code for code, dt in IMAGE_DTYPES.items()}

ENDIAN_BIG = 1
ENDIAN_LITTLE = 2
COORDINATE_RAS = 1
COORDINATE_LPS = 2
_ENDIANS = {"big": ENDIAN_BIG, "little": ENDIAN_LITTLE, ENDIAN_BIG: 1, ENDIAN_LITTLE: 2}
_COORDS = {"RAS": COORDINATE_RAS, "LPS": COORDINATE_LPS, 1: 1, 2: 2}
_BYTE_ORDER: dict[int, Literal[">", "<"]] = {ENDIAN_BIG: ">", ENDIAN_LITTLE: "<"}

#: Identity geometry in wire order (i, j, k axes with spacing 1, centre at 0).
IMAGE_IDENTITY: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


def image_scalar_type(dtype: np.dtype) -> int:
    try:
        return _IMAGE_CODES[(dtype.kind, dtype.itemsize)]
    except KeyError:
        raise ValueError(
            f"IMAGE dtype {dtype} not supported (int8/16/32, uint8/16/32, float32/64)"
        ) from None


def _triple(v: Sequence[int], what: str) -> tuple[int, int, int]:
    t = tuple(int(x) for x in v)
    if len(t) != 3:
        raise ValueError(f"{what} needs 3 values, got {v!r}")
    for x in t:
        check_uint(x, 16, what)
    return t  # type: ignore[return-value]


@register("IMAGE")
@dataclass(frozen=True, slots=True, eq=False)
class ImageMessage(Message):
    """A 2-D/3-D image or a sub-volume of one.

    - ``pixels``: numpy array of shape (k, j, i, components) holding the sub-volume (i
      fastest). 2-D (j, i) and 3-D (k, j, i) arrays are accepted and stored as 4-D.
    - ``elements``: 12 float32 in wire order (TX TY TZ, SX SY SZ, NX NY NZ, PX PY PZ).
    - ``size``: full image size (i, j, k); None = the sub-volume's extent plus ``offset``.
    - ``offset``: sub-volume start index (i, j, k).
    - ``coordinate``: 1 RAS (default), 2 LPS. ``endian``: pixel byte order on the wire, 1 big
      or 2 little (default, no byte swap on x86). Decoded pixels keep the wire order in their
      dtype (a read-only view of the received bytes, no copy).
    """

    TYPE: ClassVar[str] = "IMAGE"

    pixels: np.ndarray = field(default_factory=lambda: np.zeros((1, 1, 1, 1), np.uint8))
    elements: tuple[float, ...] = IMAGE_IDENTITY
    size: tuple[int, int, int] | None = None
    offset: tuple[int, int, int] = (0, 0, 0)
    coordinate: int = COORDINATE_RAS
    endian: int = ENDIAN_LITTLE

    def __post_init__(self) -> None:
        p = np.asarray(self.pixels)
        if p.ndim == 2:
            p = p[np.newaxis, :, :, np.newaxis]
        elif p.ndim == 3:
            p = p[:, :, :, np.newaxis]
        elif p.ndim != 4:
            raise ValueError(f"pixels must be 2-D, 3-D or 4-D (k, j, i, c), got shape {p.shape}")
        image_scalar_type(p.dtype)
        if not 1 <= p.shape[3] <= 255:
            raise ValueError(f"components must be 1..255, got {p.shape[3]}")
        object.__setattr__(self, "pixels", p)
        els = tuple(float(v) for v in self.elements)
        if len(els) != 12:
            raise ValueError(f"IMAGE geometry needs 12 numbers, got {len(els)}")
        object.__setattr__(self, "elements", els)
        offset = _triple(self.offset, "sub-volume offset")
        object.__setattr__(self, "offset", offset)
        sub = self.subvolume_size
        _triple(sub, "sub-volume size")
        size = (
            tuple(o + s for o, s in zip(offset, sub, strict=True))
            if self.size is None
            else self.size
        )
        size = _triple(size, "image size")
        if any(o + s > n for o, s, n in zip(offset, sub, size, strict=True)):
            raise ValueError(f"sub-volume {offset}+{sub} exceeds image size {size}")
        object.__setattr__(self, "size", size)
        try:
            object.__setattr__(self, "endian", _ENDIANS[self.endian])
            object.__setattr__(self, "coordinate", _COORDS[self.coordinate])
        except KeyError as err:
            raise ValueError(f"bad endian/coordinate value {err}") from None

    # ---------------------------------------------------------------- construction helper
    @classmethod
    def from_array(
        cls,
        array: Any,
        spacing: Sequence[float] = (1.0, 1.0, 1.0),
        origin: Sequence[float] | None = None,
        *,
        center: Sequence[float] | None = None,
        direction: Any = None,
        coordinate: str | int = "RAS",
        endian: str | int = "little",
        offset: Sequence[int] = (0, 0, 0),
        size: Sequence[int] | None = None,
        **common: Any,
    ) -> ImageMessage:
        """Build from an array (k, j, i[, c]), spacing (i, j, k), and either the corner
        ``origin`` (position of voxel 0,0,0) or the ``center``; ``direction`` is a 3x3 whose
        columns are the i, j, k axis unit vectors (default identity)."""
        if origin is not None and center is not None:
            raise ValueError("give origin (corner) or center, not both")
        # __post_init__ checks the triples and maps the names ("RAS", "little") to wire codes.
        msg = cls(
            pixels=array,
            offset=cast("tuple[int, int, int]", tuple(offset)),
            size=None if size is None else cast("tuple[int, int, int]", tuple(size)),
            coordinate=cast(int, coordinate),
            endian=cast(int, endian),
            **common,
        )
        d = np.eye(3) if direction is None else np.asarray(direction, dtype=float)
        if d.shape != (3, 3):
            raise ValueError(f"direction must be 3x3, got shape {d.shape}")
        sp = np.asarray(spacing, dtype=float)
        if sp.shape != (3,):
            raise ValueError(f"spacing needs 3 values, got {spacing!r}")
        axes = d * sp  # column c = axis c scaled by spacing c
        if center is None:
            corner = np.zeros(3) if origin is None else np.asarray(origin, dtype=float)
            assert msg.size is not None
            c = corner + axes @ ((np.asarray(msg.size, dtype=float) - 1.0) / 2.0)
        else:
            c = np.asarray(center, dtype=float)
        els = (*axes.T.ravel().tolist(), *c.tolist())
        return msg.replace(elements=els)

    # ---------------------------------------------------------------- geometry
    @property
    def scalar_type(self) -> int:
        return image_scalar_type(self.pixels.dtype)

    @property
    def components(self) -> int:
        return int(self.pixels.shape[3])

    @property
    def subvolume_size(self) -> tuple[int, int, int]:
        k, j, i, _ = self.pixels.shape
        return (int(i), int(j), int(k))

    @property
    def axes(self) -> np.ndarray:
        """3x3: columns are the i, j, k axes scaled by spacing."""
        return np.asarray(self.elements[:9], dtype=float).reshape(3, 3).T

    @property
    def spacing(self) -> tuple[float, float, float]:
        n = np.linalg.norm(self.axes, axis=0)
        return (float(n[0]), float(n[1]), float(n[2]))

    @property
    def direction(self) -> np.ndarray:
        """3x3 with unit columns (a zero axis stays zero)."""
        a = self.axes
        n = np.linalg.norm(a, axis=0)
        return a / np.where(n == 0.0, 1.0, n)

    @property
    def center(self) -> tuple[float, float, float]:
        e = self.elements
        return (e[9], e[10], e[11])

    @property
    def origin(self) -> tuple[float, float, float]:
        """The corner origin: position of voxel (0, 0, 0) of the full image."""
        assert self.size is not None
        c = np.asarray(self.center) - self.axes @ ((np.asarray(self.size, float) - 1.0) / 2.0)
        return (float(c[0]), float(c[1]), float(c[2]))

    @property
    def ijk_to_xyz(self) -> np.ndarray:
        """4x4 from voxel index (i, j, k, 1) of the full image to position (mm)."""
        m = np.eye(4)
        m[:3, :3] = self.axes
        m[:3, 3] = self.origin
        return m

    # ---------------------------------------------------------------- codec
    def pack_content(self) -> bytes:
        p = self.pixels
        code = image_scalar_type(p.dtype)
        assert self.size is not None
        head = _IMAGE_HEAD.pack(
            1,
            p.shape[3],
            code,
            self.endian,
            self.coordinate,
            *self.size,
            *self.elements,
            *self.offset,
            *self.subvolume_size,
        )
        dt = IMAGE_DTYPES[code].newbyteorder(_BYTE_ORDER[self.endian])
        return head + np.ascontiguousarray(p, dtype=dt).tobytes()

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> ImageMessage:
        if len(content) < 72:
            raise ContentError(f"IMAGE content must be >= 72 bytes, got {len(content)}", offset=0)
        v = _IMAGE_HEAD.unpack_from(content, 0)
        ncomp, stype, endian, coord = v[1], v[2], v[3], v[4]
        size, els, offset, sub = v[5:8], v[8:20], v[20:23], v[23:26]
        dtype = IMAGE_DTYPES.get(stype)
        if dtype is None:
            raise ContentError(f"IMAGE scalar type {stype} is not defined", offset=3)
        if endian not in _BYTE_ORDER:
            raise ContentError(f"IMAGE endian {endian} is neither 1 (big) nor 2 (little)", offset=4)
        if coord not in (1, 2):
            raise ContentError(f"IMAGE coordinate {coord} is neither 1 (RAS) nor 2 (LPS)", offset=5)
        if ncomp == 0:
            raise ContentError("IMAGE with 0 components", offset=2)
        if any(o + s > n for o, s, n in zip(offset, sub, size, strict=True)):
            raise ContentError(f"IMAGE sub-volume {offset}+{sub} exceeds size {size}", offset=60)
        count = sub[0] * sub[1] * sub[2] * ncomp
        if len(content) - 72 != count * dtype.itemsize:
            raise ContentError(
                f"IMAGE sub-volume {sub} x {ncomp} x {dtype.itemsize} B needs "
                f"{count * dtype.itemsize} data bytes, got {len(content) - 72}",
                offset=72,
            )
        pixels = np.frombuffer(
            content, dtype=dtype.newbyteorder(_BYTE_ORDER[endian]), count=count, offset=72
        ).reshape(sub[2], sub[1], sub[0], ncomp)
        # read-only whatever the content is: a big body arrives as a bytearray (codec.py)
        pixels.flags.writeable = False
        return cls(pixels, els, size, offset, coord, endian, **common)

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        assert isinstance(other, ImageMessage)
        return (
            common_equal(self, other)
            and self.elements == other.elements
            and self.size == other.size
            and self.offset == other.offset
            and self.coordinate == other.coordinate
            and self.endian == other.endian
            and self.pixels.shape == other.pixels.shape
            and self.scalar_type == other.scalar_type
            and np.array_equal(self.pixels, other.pixels, equal_nan=self.pixels.dtype.kind == "f")
        )

    __hash__ = None  # type: ignore[assignment]


# ------------------------------------------------------------------------------------------
_IMGMETA = struct.Struct(">64s20s32s64s64sQ3HBB")  # 260 bytes


@dataclass(frozen=True, slots=True)
class ImageMetaElement:
    """One image in IMGMETA: description, ``image_id`` (device name to GET_IMAGE it), modality,
    patient name and ID, ``timestamp_raw`` (64-bit header format), size (i, j, k), scalar type."""

    name: str = ""
    image_id: str = ""
    modality: str = ""
    patient_name: str = ""
    patient_id: str = ""
    timestamp_raw: int = 0
    size: tuple[int, int, int] = (0, 0, 0)
    scalar_type: int = 3

    def __post_init__(self) -> None:
        for text, n, what in (
            (self.name, 64, "name"),
            (self.image_id, 20, "image id"),
            (self.modality, 32, "modality"),
            (self.patient_name, 64, "patient name"),
            (self.patient_id, 64, "patient id"),
        ):
            fixed(text, n, what)
        check_uint(self.timestamp_raw, 64, "timestamp_raw")
        object.__setattr__(self, "size", _triple(self.size, "size"))
        check_uint(self.scalar_type, 8, "scalar type")

    @property
    def timestamp(self) -> float:
        from .. import wire

        return wire.raw_to_seconds(self.timestamp_raw)


@register("IMGMETA")
@dataclass(frozen=True, slots=True)
class ImageMetaMessage(Message):
    """A list of :class:`ImageMetaElement` (260 bytes each)."""

    TYPE: ClassVar[str] = "IMGMETA"

    images: tuple[ImageMetaElement, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "images", tuple(self.images))

    def pack_content(self) -> bytes:
        return b"".join(
            _IMGMETA.pack(
                fixed(e.name, 64, "name"),
                fixed(e.image_id, 20, "id"),
                fixed(e.modality, 32, "modality"),
                fixed(e.patient_name, 64, "patient name"),
                fixed(e.patient_id, 64, "patient id"),
                e.timestamp_raw,
                *e.size,
                e.scalar_type,
                0,
            )
            for e in self.images
        )

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> ImageMetaMessage:
        n = need_multiple(content, 260, "IMGMETA")
        out = []
        for i in range(n):
            v = _IMGMETA.unpack_from(content, 260 * i)
            out.append(
                ImageMetaElement(
                    unfixed(v[0]),
                    unfixed(v[1]),
                    unfixed(v[2]),
                    unfixed(v[3]),
                    unfixed(v[4]),
                    v[5],
                    v[6:9],
                    v[9],
                )
            )
        return cls(tuple(out), **common)


_LBMETA = struct.Struct(">64s20sBB4B3H20s")  # 116 bytes


@dataclass(frozen=True, slots=True)
class LabelMetaElement:
    """One label map in LBMETA: description, ``image_id``, label value, RGBA, size (i, j, k),
    owner image."""

    name: str = ""
    image_id: str = ""
    label: int = 0
    rgba: tuple[int, int, int, int] = (255, 255, 255, 255)
    size: tuple[int, int, int] = (0, 0, 0)
    owner: str = ""

    def __post_init__(self) -> None:
        fixed(self.name, 64, "name")
        fixed(self.image_id, 20, "image id")
        fixed(self.owner, 20, "owner")
        check_uint(self.label, 8, "label")
        rgba = tuple(self.rgba)
        if len(rgba) != 4:
            raise ValueError(f"rgba needs 4 values, got {rgba!r}")
        for c in rgba:
            check_uint(c, 8, "rgba component")
        object.__setattr__(self, "rgba", rgba)
        object.__setattr__(self, "size", _triple(self.size, "size"))


@register("LBMETA")
@dataclass(frozen=True, slots=True)
class LabelMetaMessage(Message):
    """A list of :class:`LabelMetaElement` (116 bytes each)."""

    TYPE: ClassVar[str] = "LBMETA"

    labels: tuple[LabelMetaElement, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "labels", tuple(self.labels))

    def pack_content(self) -> bytes:
        return b"".join(
            _LBMETA.pack(
                fixed(e.name, 64, "name"),
                fixed(e.image_id, 20, "id"),
                e.label,
                0,
                *e.rgba,
                *e.size,
                fixed(e.owner, 20, "owner"),
            )
            for e in self.labels
        )

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> LabelMetaMessage:
        n = need_multiple(content, 116, "LBMETA")
        out = []
        for i in range(n):
            v = _LBMETA.unpack_from(content, 116 * i)
            out.append(
                LabelMetaElement(
                    unfixed(v[0]), unfixed(v[1]), v[2], v[4:8], v[8:11], unfixed(v[11])
                )
            )
        return cls(tuple(out), **common)
