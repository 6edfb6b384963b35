"""CAPABILITY: the list of message types a peer supports (protocol doc 3.5)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from .. import wire
from .base import Message, fixed, need_multiple, register, unfixed


@register("CAPABILITY")
@dataclass(frozen=True, slots=True)
class CapabilityMessage(Message):
    """Supported type names, each a NUL-padded char[12]; no count field (content size / 12)."""

    TYPE: ClassVar[str] = "CAPABILITY"

    types: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "types", tuple(self.types))
        for name in self.types:
            fixed(name, wire.TYPE_SIZE, "capability type name")

    def pack_content(self) -> bytes:
        return b"".join(fixed(t, wire.TYPE_SIZE, "type").ljust(12, b"\0") for t in self.types)

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> CapabilityMessage:
        n = need_multiple(content, 12, "CAPABILITY")
        return cls(tuple(unfixed(content[12 * i : 12 * i + 12]) for i in range(n)), **common)
