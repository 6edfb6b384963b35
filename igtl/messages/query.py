"""Query messages (protocol doc 3.19): GET_/STP_ (and empty STT_) headers, RTS_ status replies,
and the STT_ bodies of TDATA/QTDATA, POLYDATA and VIDEO.

One class serves a whole family of type names; it keeps the wire name in ``type_name`` and asks
the codec for it (``NEEDS_TYPE_NAME``). GET_TRANS (what the reference sends) and GET_TRANSFOR
(what its documentation says) are both accepted, and likewise for the other TRANSFORM queries.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any, ClassVar

from ..errors import ContentError
from .base import Message, check_uint, fixed, need_size, register, unfixed

#: Header-only queries: empty content (GET_ except GET_BIND, STP_, and STT_ for types whose
#: start-streaming request has no parameters).
HEADER_ONLY_TYPES: tuple[str, ...] = (
    "GET_TRANS",
    "GET_TRANSFOR",
    "GET_POSITION",
    "GET_IMAGE",
    "GET_STATUS",
    "GET_CAPABIL",
    "GET_STRING",
    "GET_POINT",
    "GET_TRAJ",
    "GET_TDATA",
    "GET_QTDATA",
    "GET_IMGMETA",
    "GET_LBMETA",
    "GET_COLORT",
    "GET_NDARRAY",
    "GET_SENSOR",
    "GET_POLYDATA",
    "GET_VMETA",
    "GET_VIDEO",
    "STP_TRANS",
    "STP_TRANSFOR",
    "STP_POSITION",
    "STP_IMAGE",
    "STP_TDATA",
    "STP_QTDATA",
    "STP_NDARRAY",
    "STP_SENSOR",
    "STP_POLYDATA",
    "STP_BIND",
    "STP_VIDEO",
    "STT_TRANS",
    "STT_TRANSFOR",
    "STT_POSITION",
    "STT_IMAGE",
    "STT_NDARRAY",
    "STT_SENSOR",
)

#: RTS_ replies whose content is one status byte (0 = success, 1 = error).
RTS_TYPES: tuple[str, ...] = (
    "RTS_TRANS",
    "RTS_TRANSFOR",
    "RTS_POSITION",
    "RTS_IMAGE",
    "RTS_STATUS",
    "RTS_CAPABIL",
    "RTS_STRING",
    "RTS_POINT",
    "RTS_TRAJ",
    "RTS_TDATA",
    "RTS_QTDATA",
    "RTS_IMGMETA",
    "RTS_LBMETA",
    "RTS_COLORT",
    "RTS_NDARRAY",
    "RTS_SENSOR",
    "RTS_POLYDATA",
    "RTS_BIND",
    "RTS_VIDEO",
    "RTS_VMETA",
)


def _check_name(cls: type, name: str, allowed: tuple[str, ...]) -> None:
    if name not in allowed:
        raise ValueError(f"{cls.__name__} does not serve type {name!r} (one of {allowed})")


@register(*HEADER_ONLY_TYPES)
@dataclass(frozen=True, slots=True)
class QueryMessage(Message):
    """A header-only query (GET_*, STP_*, parameterless STT_*): the type name is the request.

    An empty device name means "any/all" for GET_ queries (point.md, imagemeta.md).
    """

    NEEDS_TYPE_NAME: ClassVar[bool] = True
    TYPES: ClassVar[tuple[str, ...]] = HEADER_ONLY_TYPES

    type_name: str = "GET_STATUS"

    def __post_init__(self) -> None:
        _check_name(type(self), self.type_name, self.TYPES)

    @property
    def message_type(self) -> str:
        return self.type_name

    def pack_content(self) -> bytes:
        return b""

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> QueryMessage:
        name = common.pop("message_type")
        need_size(content, 0, name)
        return cls(type_name=name, **common)


@register(*RTS_TYPES)
@dataclass(frozen=True, slots=True)
class RTSMessage(Message):
    """An RTS_ acknowledgement: ``status`` 0 = success, 1 = error (uint8).

    ``status=None`` is an empty body, which bind.md documents for RTS_BIND and some peers send.
    """

    NEEDS_TYPE_NAME: ClassVar[bool] = True
    TYPES: ClassVar[tuple[str, ...]] = RTS_TYPES

    type_name: str = "RTS_TRANS"
    status: int | None = 0

    def __post_init__(self) -> None:
        _check_name(type(self), self.type_name, self.TYPES)
        if self.status is not None:
            check_uint(self.status, 8, "RTS status")

    @property
    def message_type(self) -> str:
        return self.type_name

    def pack_content(self) -> bytes:
        return b"" if self.status is None else bytes((self.status,))

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> RTSMessage:
        name = common.pop("message_type")
        if len(content) > 1:
            raise ContentError(f"{name} content must be 0 or 1 byte, got {len(content)}", offset=1)
        return cls(type_name=name, status=content[0] if content else None, **common)


_STT_TDATA = struct.Struct(">i32s")


@register("STT_TDATA", "STT_QTDATA")
@dataclass(frozen=True, slots=True)
class StartTrackingMessage(Message):
    """STT_TDATA / STT_QTDATA: start streaming tracking data.

    ``resolution`` is the minimum interval between frames in ms (0 = as fast as possible; int32
    as in the reference struct), ``coordinate_name`` names the coordinate system (<= 32 bytes).
    """

    NEEDS_TYPE_NAME: ClassVar[bool] = True
    TYPES: ClassVar[tuple[str, ...]] = ("STT_TDATA", "STT_QTDATA")

    type_name: str = "STT_TDATA"
    resolution: int = 0
    coordinate_name: str = ""

    def __post_init__(self) -> None:
        _check_name(type(self), self.type_name, self.TYPES)
        if not isinstance(self.resolution, int) or not -(2**31) <= self.resolution < 2**31:
            raise ValueError(f"resolution must fit int32, got {self.resolution!r}")
        fixed(self.coordinate_name, 32, "coordinate name")

    @property
    def message_type(self) -> str:
        return self.type_name

    def pack_content(self) -> bytes:
        return _STT_TDATA.pack(self.resolution, fixed(self.coordinate_name, 32, "coordinate name"))

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> StartTrackingMessage:
        name = common.pop("message_type")
        need_size(content, 36, name)
        resolution, coord = _STT_TDATA.unpack(content)
        return cls(name, resolution, unfixed(coord), **common)


_U64 = struct.Struct(">Q")


@register("STT_POLYDATA")
@dataclass(frozen=True, slots=True)
class StartPolyDataMessage(Message):
    """STT_POLYDATA: empty, or a uint64 resolution in ns (``resolution=None`` = empty body)."""

    TYPE: ClassVar[str] = "STT_POLYDATA"

    resolution: int | None = None

    def __post_init__(self) -> None:
        if self.resolution is not None:
            check_uint(self.resolution, 64, "resolution")

    def pack_content(self) -> bytes:
        return b"" if self.resolution is None else _U64.pack(self.resolution)

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> StartPolyDataMessage:
        if len(content) == 0:
            return cls(None, **common)
        need_size(content, 8, "STT_POLYDATA")
        return cls(_U64.unpack(content)[0], **common)


_STT_VIDEO = struct.Struct(">4sI")


@register("STT_VIDEO")
@dataclass(frozen=True, slots=True)
class StartVideoMessage(Message):
    """STT_VIDEO (9 bytes per igtl_video.h IGTL_STT_VIDEO_SIZE): a FourCC ``codec`` (I420,
    H264, VP90, X265, O265, AV10), a uint32 ``time_interval`` in ms, and one trailing byte
    (``reserved``, written as given, 0 by default)."""

    TYPE: ClassVar[str] = "STT_VIDEO"

    codec: str = "H264"
    time_interval: int = 0
    reserved: int = 0

    def __post_init__(self) -> None:
        fixed(self.codec, 4, "codec FourCC")
        check_uint(self.time_interval, 32, "time_interval")
        check_uint(self.reserved, 8, "reserved")

    def pack_content(self) -> bytes:
        return _STT_VIDEO.pack(fixed(self.codec, 4, "codec"), self.time_interval) + bytes(
            (self.reserved,)
        )

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> StartVideoMessage:
        need_size(content, 9, "STT_VIDEO")
        codec, interval = _STT_VIDEO.unpack_from(content, 0)
        return cls(unfixed(codec), interval, content[8], **common)
