"""VIDEO and VIDEOMETA (protocol 3.1; doc 3.20, reference igtl_video.h / igtl_videometa.h)."""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any, ClassVar

from ..errors import ContentError
from .base import Message, check_uint, fixed, need_multiple, register, unfixed
from .image import IMAGE_IDENTITY

_VIDEOMETA = struct.Struct(">64s64s64s64shd3H12fBB")  # 322 bytes


@dataclass(frozen=True, slots=True)
class VideoMetaElement:
    """One video source: description, ``video_id`` (device name to request it, <= 64 bytes),
    patient name and ID, camera ``zoom_level`` (int16) and ``focal_length`` (float64), size
    (i, j, k), the 12-float geometry in IMAGE wire order, and the scalar type."""

    name: str = ""
    video_id: str = ""
    patient_name: str = ""
    patient_id: str = ""
    zoom_level: int = 0
    focal_length: float = 0.0
    size: tuple[int, int, int] = (0, 0, 0)
    elements: tuple[float, ...] = IMAGE_IDENTITY
    scalar_type: int = 3

    def __post_init__(self) -> None:
        for text, what in (
            (self.name, "name"),
            (self.video_id, "video id"),
            (self.patient_name, "patient name"),
            (self.patient_id, "patient id"),
        ):
            fixed(text, 64, what)
        if not isinstance(self.zoom_level, int) or not -32768 <= self.zoom_level <= 32767:
            raise ValueError(f"zoom_level must fit int16, got {self.zoom_level!r}")
        size = tuple(self.size)
        if len(size) != 3:
            raise ValueError(f"size needs 3 values, got {size!r}")
        for v in size:
            check_uint(v, 16, "size")
        object.__setattr__(self, "size", size)
        els = tuple(float(v) for v in self.elements)
        if len(els) != 12:
            raise ValueError(f"geometry needs 12 numbers, got {len(els)}")
        object.__setattr__(self, "elements", els)
        check_uint(self.scalar_type, 8, "scalar type")

    def pack(self) -> bytes:
        return _VIDEOMETA.pack(
            fixed(self.name, 64, "name"),
            fixed(self.video_id, 64, "video id"),
            fixed(self.patient_name, 64, "patient name"),
            fixed(self.patient_id, 64, "pid"),
            self.zoom_level,
            self.focal_length,
            *self.size,
            *self.elements,
            self.scalar_type,
            0,
        )


@register("VIDEOMETA")
@dataclass(frozen=True, slots=True)
class VideoMetaMessage(Message):
    """A list of :class:`VideoMetaElement` (322 bytes each)."""

    TYPE: ClassVar[str] = "VIDEOMETA"

    videos: tuple[VideoMetaElement, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "videos", tuple(self.videos))

    def pack_content(self) -> bytes:
        return b"".join(v.pack() for v in self.videos)

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> VideoMetaMessage:
        n = need_multiple(content, 322, "VIDEOMETA")
        out = []
        for i in range(n):
            v = _VIDEOMETA.unpack_from(content, 322 * i)
            out.append(
                VideoMetaElement(
                    unfixed(v[0]),
                    unfixed(v[1]),
                    unfixed(v[2]),
                    unfixed(v[3]),
                    v[4],
                    v[5],
                    v[6:9],
                    v[9:21],
                    v[21],
                )
            )
        return cls(tuple(out), **common)


_VIDEO_HEAD = struct.Struct(">HB4sHB3H12f3H3H")  # 76 bytes


@register("VIDEO")
@dataclass(frozen=True, slots=True)
class VideoMessage(Message):
    """One encoded video frame: header (76 bytes) + ``bitstream``.

    ``codec`` is the FourCC (I420, H264, VP90, X265, O265, AV10), ``frame_type`` the encoder's
    frame type, ``endian`` the bitstream byte order (1 big, 2 little), ``coordinate`` 1 RAS /
    2 LPS, then size, IMAGE-style geometry and sub-volume offset/size.
    """

    TYPE: ClassVar[str] = "VIDEO"

    bitstream: bytes = b""
    codec: str = "H264"
    frame_type: int = 0
    endian: int = 2
    coordinate: int = 1
    size: tuple[int, int, int] = (0, 0, 1)
    elements: tuple[float, ...] = IMAGE_IDENTITY
    offset: tuple[int, int, int] = (0, 0, 0)
    subvolume_size: tuple[int, int, int] = (0, 0, 1)

    def __post_init__(self) -> None:
        object.__setattr__(self, "bitstream", bytes(self.bitstream))
        fixed(self.codec, 4, "codec FourCC")
        check_uint(self.frame_type, 16, "frame_type")
        check_uint(self.endian, 8, "endian")
        check_uint(self.coordinate, 8, "coordinate")
        for name in ("size", "offset", "subvolume_size"):
            t = tuple(getattr(self, name))
            if len(t) != 3:
                raise ValueError(f"{name} needs 3 values, got {t!r}")
            for v in t:
                check_uint(v, 16, name)
            object.__setattr__(self, name, t)
        els = tuple(float(v) for v in self.elements)
        if len(els) != 12:
            raise ValueError(f"geometry needs 12 numbers, got {len(els)}")
        object.__setattr__(self, "elements", els)

    def pack_content(self) -> bytes:
        return (
            _VIDEO_HEAD.pack(
                1,
                self.endian,
                fixed(self.codec, 4, "codec"),
                self.frame_type,
                self.coordinate,
                *self.size,
                *self.elements,
                *self.offset,
                *self.subvolume_size,
            )
            + self.bitstream
        )

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> VideoMessage:
        if len(content) < 76:
            raise ContentError(f"VIDEO content must be >= 76 bytes, got {len(content)}", offset=0)
        v = _VIDEO_HEAD.unpack_from(content, 0)
        return cls(
            bytes(memoryview(content)[76:]),  # one copy, also from a bytearray (codec.py)
            unfixed(v[2]),
            v[3],
            v[1],
            v[4],
            v[5:8],
            v[8:20],
            v[20:23],
            v[23:26],
            **common,
        )
