"""COMMAND and RTS_COMMAND (protocol doc 3.18): same layout, reply echoes COMMAND_ID."""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any, ClassVar

from .. import wire
from ..errors import ContentError
from .base import Message, check_uint, decode_text, encode_text, fixed, register, unfixed

_COMMAND_HEAD = struct.Struct(">I128sHI")  # 138 bytes


@register("COMMAND")
@dataclass(frozen=True, slots=True)
class CommandMessage(Message):
    """A command: ``command_id`` (uint32), ``command_name`` (<= 128 bytes, NUL-padded) and the
    ``command`` text in an IANA ``encoding`` (None: US-ASCII if possible, else UTF-8).

    The reference CommandMessage defaults to header version 2; here the version is the caller's
    choice like every other type (default 1; metadata needs 2).
    """

    TYPE: ClassVar[str] = "COMMAND"

    command_id: int = 0
    command_name: str = ""
    command: str = ""
    encoding: int | None = None

    def __post_init__(self) -> None:
        check_uint(self.command_id, 32, "command_id")
        fixed(self.command_name, 128, "command name")
        if self.encoding is not None:
            check_uint(self.encoding, 16, "encoding")

    def pack_content(self) -> bytes:
        enc = self.encoding if self.encoding is not None else wire.default_encoding(self.command)
        raw = encode_text(self.command, enc, self.TYPE)
        return (
            _COMMAND_HEAD.pack(
                self.command_id, fixed(self.command_name, 128, "command name"), enc, len(raw)
            )
            + raw
        )

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> CommandMessage:
        if len(content) < 138:
            raise ContentError(
                f"{cls.TYPE} content must be >= 138 bytes, got {len(content)}", offset=0
            )
        cid, name, enc, length = _COMMAND_HEAD.unpack_from(content, 0)
        if 138 + length != len(content):
            raise ContentError(
                f"{cls.TYPE} LENGTH says {length} bytes, content holds {len(content) - 138}",
                offset=134,
            )
        text = decode_text(content[138:], enc, cls.TYPE, offset=138)
        return cls(cid, unfixed(name), text, enc, **common)


@register("RTS_COMMAND")
@dataclass(frozen=True, slots=True)
class RTSCommandMessage(CommandMessage):
    """The reply to a COMMAND: same COMMAND_ID; the reference puts an error string in
    ``command_name``; Plus/OpenIGTLinkIO put status in metadata and an XML reply in ``command``."""

    TYPE: ClassVar[str] = "RTS_COMMAND"
