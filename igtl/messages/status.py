"""STATUS and STRING (protocol doc 3.3, 3.4)."""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass
from typing import Any, ClassVar

from .. import wire
from ..errors import ContentError, InvalidTextError
from .base import Message, decode_text, encode_text, fixed, register, unfixed


class StatusCode(enum.IntEnum):
    """STATUS codes (igtl_status.h)."""

    INVALID = 0
    OK = 1
    UNKNOWN_ERROR = 2
    PANICK_MODE = 3
    NOT_FOUND = 4
    ACCESS_DENIED = 5
    BUSY = 6
    TIME_OUT = 7
    OVERFLOW = 8
    CHECKSUM_ERROR = 9
    CONFIG_ERROR = 10
    RESOURCE_ERROR = 11
    ILLEGAL_INSTRUCTION = 12
    NOT_READY = 13
    MANUAL_MODE = 14
    DISABLED = 15
    NOT_PRESENT = 16
    UNKNOWN_VERSION = 17
    HARDWARE_FAILURE = 18
    SHUT_DOWN = 19


_STATUS_HEAD = struct.Struct(">Hq20s")


@register("STATUS")
@dataclass(frozen=True, slots=True)
class StatusMessage(Message):
    """Device status: a code (see :class:`StatusCode`), a sub-code, a short error name (<= 20
    bytes) and a free message. Like the reference we always write a terminating NUL after the
    message and accept messages without one."""

    TYPE: ClassVar[str] = "STATUS"

    code: int = StatusCode.OK
    subcode: int = 0
    error_name: str = ""
    status_message: str = ""

    def pack_content(self) -> bytes:
        return (
            _STATUS_HEAD.pack(self.code, self.subcode, fixed(self.error_name, 20, "error name"))
            + self.status_message.encode("utf-8")
            + b"\x00"
        )

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> StatusMessage:
        if len(content) < 30:
            raise ContentError(f"STATUS content must be >= 30 bytes, got {len(content)}", offset=0)
        code, subcode, name = _STATUS_HEAD.unpack_from(content, 0)
        text = content[30:]
        end = text.find(b"\x00")
        if end >= 0:
            text = text[:end]
        return cls(
            code,
            subcode,
            unfixed(name),
            decode_text(bytes(text), wire.UTF_8, "STATUS message", offset=30),
            **common,
        )


_STRING_HEAD = struct.Struct(">HH")


@register("STRING")
@dataclass(frozen=True, slots=True)
class StringMessage(Message):
    """Text with an IANA encoding (MIBenum). ``encoding=None`` picks US-ASCII (3) when the text
    allows it, else UTF-8 (106). At most 65535 encoded bytes; no terminator on the wire.

    Peers often declare US-ASCII (the reference library's default) whatever their bytes are.
    Such a STRING is decoded leniently, as the reference does, not refused: bytes that do not
    fit the declared charset are kept as lone surrogates (Python's ``surrogateescape``) and
    ``charset_mismatch`` is True; packing it gives the original bytes back."""

    TYPE: ClassVar[str] = "STRING"

    string: str = ""
    encoding: int | None = None
    charset_mismatch: bool = False

    def pack_content(self) -> bytes:
        enc = self.encoding if self.encoding is not None else wire.default_encoding(self.string)
        if self.charset_mismatch:
            raw = self.string.encode(wire.codec_for(enc), "surrogateescape")
        else:
            raw = encode_text(self.string, enc, "STRING")
        if len(raw) > 0xFFFF:
            raise ValueError(f"STRING of {len(raw)} bytes; at most 65535 fit")
        return _STRING_HEAD.pack(enc, len(raw)) + raw

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> StringMessage:
        if len(content) < 4:
            raise ContentError(f"STRING content must be >= 4 bytes, got {len(content)}", offset=0)
        enc, length = _STRING_HEAD.unpack_from(content, 0)
        if 4 + length != len(content):
            raise ContentError(
                f"STRING length field says {length} bytes, content holds {len(content) - 4}",
                offset=2,
            )
        raw = bytes(content[4:])
        try:
            return cls(decode_text(raw, enc, "STRING", offset=4), enc, **common)
        except InvalidTextError:
            codec = wire.IANA_ENCODINGS.get(enc)
            if codec is None:
                raise  # an encoding nobody can name: refused, with the reason
            return cls(raw.decode(codec, "surrogateescape"), enc, True, **common)
