"""BIND, GET_BIND and STT_BIND: several messages' contents in one (protocol doc 3.17).

BIND layout: uint16 N | N x (char[12] type, uint64 size) | uint16 NTABLE_SIZE | name table
(NUL-terminated device names, padded with one 0 byte to an even length; NTABLE_SIZE includes
the pad) | child contents, each followed by one pad byte when its size is odd (the sizes do not
include the pad). GET_BIND: uint16 N | N x char[12] | uint16 NTABLE_SIZE | name table (padded
to even, as the reference reader requires); an empty body requests everything. STT_BIND:
uint64 resolution (ns) then the GET_BIND layout.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from .. import wire
from ..errors import ContentError, DecodeError
from .base import REGISTRY, Message, RawMessage, fixed, register, unfixed

_U16 = struct.Struct(">H")
_U64 = struct.Struct(">Q")
_CHILD = struct.Struct(">12sQ")


@dataclass(frozen=True, slots=True)
class BindChild:
    """One child: its type name, device name (<= 20 bytes, no NUL) and content bytes."""

    type_name: str
    device_name: str = ""
    content: bytes = b""

    def __post_init__(self) -> None:
        fixed(self.type_name, wire.TYPE_SIZE, "child type")
        _check_name(self.device_name)
        object.__setattr__(self, "content", bytes(self.content))

    @classmethod
    def of(cls, message: Message) -> BindChild:
        """The child for a message (its type, device name and content; header fields drop)."""
        return cls(message.message_type, message.device_name, message.pack_content())

    def decode(self, **common: Any) -> Message:
        """Decode the content with the registered class (RawMessage for unknown types)."""
        base: dict[str, Any] = {
            "device_name": self.device_name,
            "timestamp": 0.0,
            "header_version": 1,
            **common,
        }
        cls = REGISTRY.get(self.type_name)
        if cls is None:
            return RawMessage.unpack_content(self.content, {**base, "message_type": self.type_name})
        if getattr(cls, "NEEDS_TYPE_NAME", False):
            base["message_type"] = self.type_name
        try:
            return cls.unpack_content(self.content, base)
        except DecodeError:
            raise
        except Exception as err:  # noqa: BLE001 - bytes from a peer
            raise ContentError(f"invalid {self.type_name} child content: {err}") from err


def _check_name(name: str) -> bytes:
    raw = fixed(name, wire.DEVICE_NAME_SIZE, "child device name")
    if b"\0" in raw:
        raise ValueError(f"child device name {name!r} contains NUL")
    return raw


def _name_table(names: Sequence[str]) -> bytes:
    table = b"".join(_check_name(n) + b"\0" for n in names)
    if len(table) % 2:
        table += b"\0"
    return _U16.pack(len(table)) + table


def _read_names(content: bytes, pos: int, n: int, what: str) -> tuple[list[str], int]:
    """Parse NTABLE_SIZE + table at ``pos``; return the names and the position after it."""
    if pos + 2 > len(content):
        raise ContentError(f"{what}: name table size missing", offset=pos)
    (tsize,) = _U16.unpack_from(content, pos)
    start = pos + 2
    end = start + tsize
    if end > len(content):
        raise ContentError(f"{what}: name table of {tsize} bytes overruns the content", offset=pos)
    table = content[start:end]
    if tsize == 0:
        return [""] * n, end  # the reference skips an empty table: names stay empty
    names = []
    p = 0
    for _ in range(n):
        e = table.find(b"\0", p)
        if e < 0:
            raise ContentError(f"{what}: name table holds fewer than {n} names", offset=start + p)
        if e - p > wire.DEVICE_NAME_SIZE:
            raise ContentError(f"{what}: child name longer than 20 bytes", offset=start + p)
        names.append(wire.decode_fixed(table[p:e]))
        p = e + 1
    if table[p:] not in (b"", b"\0"):
        raise ContentError(
            f"{what}: {tsize - p} unexpected bytes in the name table", offset=start + p
        )
    return names, end


@register("BIND")
@dataclass(frozen=True, slots=True)
class BindMessage(Message):
    """``children``: :class:`BindChild` items (Message instances are converted with
    :meth:`BindChild.of`). :meth:`messages` decodes them."""

    TYPE: ClassVar[str] = "BIND"

    children: tuple[BindChild, ...] = ()

    def __post_init__(self) -> None:
        kids = tuple(BindChild.of(c) if isinstance(c, Message) else c for c in self.children)
        for c in kids:
            if not isinstance(c, BindChild):
                raise TypeError(f"children must be BindChild or Message, got {type(c).__name__}")
        if len(kids) > 0xFFFF:
            raise ValueError(f"at most 65535 children, got {len(kids)}")
        object.__setattr__(self, "children", kids)

    def messages(self, **common: Any) -> tuple[Message, ...]:
        """Each child decoded as a message (header fields from ``common``)."""
        return tuple(c.decode(**common) for c in self.children)

    def pack_content(self) -> bytes:
        parts = [_U16.pack(len(self.children))]
        parts += [
            _CHILD.pack(fixed(c.type_name, 12, "type"), len(c.content)) for c in self.children
        ]
        parts.append(_name_table([c.device_name for c in self.children]))
        for c in self.children:
            parts.append(c.content)
            if len(c.content) % 2:
                parts.append(b"\0")
        return b"".join(parts)

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> BindMessage:
        size = len(content)
        if size < 2:
            raise ContentError(f"BIND content must be >= 2 bytes, got {size}", offset=0)
        (n,) = _U16.unpack_from(content, 0)
        pos = 2 + 20 * n
        if pos > size:
            raise ContentError(f"BIND of {n} children: child table overruns the content", offset=2)
        heads = [_CHILD.unpack_from(content, 2 + 20 * i) for i in range(n)]
        (tsize,) = _U16.unpack_from(content, pos) if pos + 2 <= size else (0,)
        if tsize % 2:
            raise ContentError(f"BIND name table size {tsize} is odd", offset=pos)
        names, pos = _read_names(content, pos, n, "BIND")
        children = []
        for (ctype, csize), name in zip(heads, names, strict=True):
            end = pos + csize
            if end > size:
                raise ContentError(
                    f"BIND child {name!r} of {csize} bytes overruns the content", offset=pos
                )
            children.append(BindChild(unfixed(ctype), name, bytes(content[pos:end])))
            pos = end + (csize % 2)
        if pos < size or pos > size + 1:  # tolerate a missing pad after an odd last child
            raise ContentError(f"BIND: {size - pos} bytes follow the last child", offset=pos)
        return cls(tuple(children), **common)


def _pack_request(children: Sequence[tuple[str, str]]) -> bytes:
    if not children:
        return b""
    return b"".join(
        (
            _U16.pack(len(children)),
            *(fixed(t, 12, "type").ljust(12, b"\0") for t, _ in children),
            _name_table([name for _, name in children]),
        )
    )


def _unpack_request(content: bytes, base: int, what: str) -> tuple[tuple[str, str], ...]:
    if len(content) == base:
        return ()
    if len(content) < base + 2:
        raise ContentError(f"{what}: child count missing", offset=base)
    (n,) = _U16.unpack_from(content, base)
    pos = base + 2 + 12 * n
    if pos > len(content):
        raise ContentError(f"{what} of {n} children: type table overruns the content", offset=base)
    types = [unfixed(content[base + 2 + 12 * i : base + 14 + 12 * i]) for i in range(n)]
    names, pos = _read_names(content, pos, n, what)
    if pos != len(content):
        raise ContentError(f"{what}: {len(content) - pos} bytes follow the name table", offset=pos)
    if n == 0:
        raise ContentError(
            f"{what} with a zero child count (send an empty body for all)", offset=base
        )
    return tuple(zip(types, names, strict=True))


def _request_children(children: Sequence[Any]) -> tuple[tuple[str, str], ...]:
    out = []
    for c in children:
        t, name = c
        fixed(t, 12, "child type")
        _check_name(name)
        out.append((t, name))
    if len(out) > 0xFFFF:
        raise ValueError("at most 65535 children")
    return tuple(out)


@register("GET_BIND")
@dataclass(frozen=True, slots=True)
class GetBindMessage(Message):
    """Request a BIND of (type, device name) pairs; empty ``children`` = everything."""

    TYPE: ClassVar[str] = "GET_BIND"

    children: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "children", _request_children(self.children))

    def pack_content(self) -> bytes:
        return _pack_request(self.children)

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> GetBindMessage:
        return cls(_unpack_request(content, 0, "GET_BIND"), **common)


@register("STT_BIND")
@dataclass(frozen=True, slots=True)
class StartBindMessage(Message):
    """Start streaming BIND: ``resolution`` (ns, uint64) and the GET_BIND request."""

    TYPE: ClassVar[str] = "STT_BIND"

    resolution: int = 0
    children: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.resolution, int) or not 0 <= self.resolution < 2**64:
            raise ValueError(f"resolution must fit uint64, got {self.resolution!r}")
        object.__setattr__(self, "children", _request_children(self.children))

    def pack_content(self) -> bytes:
        return _U64.pack(self.resolution) + _pack_request(self.children)

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> StartBindMessage:
        if len(content) < 8:
            raise ContentError(f"STT_BIND content must be >= 8 bytes, got {len(content)}", offset=0)
        (resol,) = _U64.unpack_from(content, 0)
        return cls(resol, _unpack_request(content, 8, "STT_BIND"), **common)
