"""Message base class, the type registry, and the raw message for unknown types.

Every message is a frozen dataclass. Common header fields are keyword-only and shared by all
types; each type adds its content fields and implements two narrow hooks:

- ``pack_content(self) -> bytes``: the content bytes (the v1 body, or the v2 body between the
  extended header and the metadata);
- ``unpack_content(cls, content, common) -> Message`` (classmethod): the inverse, raising
  :class:`igtl.errors.ContentError` (with ``offset`` relative to the content) on bad content.

Type names map to classes through :data:`REGISTRY`; one class may serve several names (the
query families), in which case it stores the name in a ``message_type`` field.

Re-packing: a message the codec decoded remembers its wire bytes (``_wire``: not an init field,
not compared, not in the repr) and :meth:`Message.pack` returns them unless the version or the
metadata is overridden, so any accepted input re-packs byte for byte, canonical or not
(igtl/codec.py says what is kept). Every constructor, the fast builders below and
``dataclasses.replace`` leave it None: a built or changed message is encoded from its fields.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, ClassVar, TypeVar

from .. import wire
from ..errors import ContentError, InvalidTextError

M = TypeVar("M", bound="Message")

#: A decoded message's wire bytes kept in pieces the decoder already held, joined only when it
#: is packed: the header (58 bytes, or the tuple of its parsed fields as
#: ``wire.header_fields`` returns them), then the body (one piece, or for a big
#: header-version-2 body: extended header, content, metadata).
WirePieces = tuple[Any, ...]

#: The metadata of decoded messages that carry none: shared and read-only (messages are frozen).
EMPTY_MAPPING: Mapping[str, Any] = MappingProxyType({})

#: type name -> message class. Filled by :func:`register`.
REGISTRY: dict[str, type[Message]] = {}


def register(*names: str) -> Callable[[type[M]], type[M]]:
    """Class decorator: decode messages of these type names with this class."""

    def deco(cls: type[M]) -> type[M]:
        for name in names or (cls.TYPE,):
            if not name or len(name) > wire.TYPE_SIZE:
                raise ValueError(f"type name {name!r} must be 1..12 characters")
            REGISTRY[name] = cls
        return cls

    return deco


@dataclass(frozen=True, slots=True, kw_only=True)
class Message:
    """Fields common to every OpenIGTLink message.

    ``timestamp`` is float seconds since the Unix epoch (0 = unused, the reference default).
    ``raw_timestamp`` keeps the exact 64-bit header value of a decoded message so it re-encodes
    bit for bit; it is ignored once ``timestamp`` no longer matches it (e.g. after ``replace``).
    ``metadata_encoding`` lists IANA encodings for values that should not use the default
    (US-ASCII when possible, else UTF-8). Header version 2 is needed for metadata and message_id.
    """

    TYPE: ClassVar[str] = ""

    device_name: str = ""
    timestamp: float = 0.0
    header_version: int = 1
    metadata: Mapping[str, str] = field(default_factory=dict)
    message_id: int = 0
    metadata_encoding: Mapping[str, int] = field(default_factory=dict, repr=False)
    raw_timestamp: int | None = field(default=None, repr=False, compare=False)
    #: The encoded message this one was decoded from (set by the codec only): the bytes, or
    #: pieces whose concatenation they are (see :data:`WirePieces`). Not an init field, so
    #: every constructor and ``dataclasses.replace`` leave it None: a changed message packs
    #: canonically.
    _wire: bytes | WirePieces | None = field(default=None, init=False, repr=False, compare=False)

    # ---------------------------------------------------------------- hooks for subclasses
    def pack_content(self) -> bytes:
        raise NotImplementedError

    @classmethod
    def unpack_content(cls: type[M], content: bytes, common: dict[str, Any]) -> M:
        raise NotImplementedError

    # ---------------------------------------------------------------- public API
    @property
    def message_type(self) -> str:
        """The TYPE field on the wire."""
        return self.TYPE

    def replace(self: M, **changes: Any) -> M:
        """A copy with some fields changed (dataclasses.replace)."""
        return dataclasses.replace(self, **changes)

    def stamped(self: M, t: float | None = None) -> M:
        """A copy stamped with ``t`` (default: now, wall-clock)."""
        return dataclasses.replace(self, timestamp=time.time() if t is None else t)

    def header_timestamp(self) -> int:
        """The 64-bit header timestamp this message encodes to."""
        raw = self.raw_timestamp
        if raw is not None and wire.raw_to_seconds(raw) == self.timestamp:
            return raw
        return wire.seconds_to_raw(self.timestamp)

    def pack(
        self, header_version: int | None = None, *, metadata: Mapping[str, str] | None = None
    ) -> bytes:
        """Encode the whole message (header + body).

        ``header_version`` overrides the message's own version, as a server does when it answers a
        client in the version that client speaks: packing as version 1 then drops metadata and
        message ID on purpose. Without the override, metadata on a version-1 message is an error.
        ``metadata`` replaces the message's own metadata in the encoding (its encodings still
        apply), without building a new message: a recorder adding its own entries.

        Re-packing: a decoded message packs to exactly the bytes it was decoded from when
        neither the version changes nor ``metadata`` is given, canonical or not (latin-1 names,
        unsorted or duplicate metadata keys, a longer extended header, reserved bytes that are
        not zero, signalling NaNs, a CRC left unchecked); otherwise it is encoded from its fields.
        """
        remembered = self._wire
        if remembered is not None and metadata is None:
            if header_version is None or header_version == self.header_version:
                return remembered if isinstance(remembered, bytes) else join_wire(remembered)
        version = self.header_version if header_version is None else header_version
        meta = self.metadata if metadata is None else metadata
        content = self.pack_content()
        if version == 1:
            if header_version is None and (meta or self.message_id):
                raise ValueError(
                    "metadata and message_id need header_version=2 "
                    f"({self.message_type} {self.device_name!r})"
                )
            body = content
        elif version == 2:
            meta_header, meta_data = wire.pack_metadata(meta, self.metadata_encoding)
            if not 0 <= self.message_id <= 0xFFFFFFFF:
                raise ValueError(f"message_id {self.message_id} does not fit uint32")
            body = b"".join(
                (
                    wire.EXT_HEADER.pack(
                        wire.EXT_HEADER_SIZE, len(meta_header), len(meta_data), self.message_id
                    ),
                    content,
                    meta_header,
                    meta_data,
                )
            )
        else:
            raise ValueError(f"header_version must be 1 or 2, got {version}")
        raw = self.raw_timestamp
        ts = self.timestamp
        if raw is None or wire.raw_to_seconds(raw) != ts:
            raw = wire.seconds_to_raw(ts)
        return wire.pack_header(version, self.message_type, self.device_name, raw, body) + body

    def content_summary(self) -> dict[str, Any]:
        """Content fields as JSON-friendly values (used by ``igtl listen --json`` and dumps)."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            if f.name in _COMMON_FIELDS:
                continue
            out[f.name] = _jsonable(getattr(self, f.name))
        return out


_COMMON_FIELDS = frozenset(f.name for f in dataclasses.fields(Message))
_COMMON_ORDER = tuple(f.name for f in dataclasses.fields(Message))


#: Sets a decoded message's remembered wire bytes (for the codec; messages are frozen).
set_wire: Callable[[Message, bytes | WirePieces], None] = vars(Message)["_wire"].__set__


def join_wire(pieces: WirePieces) -> bytes:
    """The encoded message remembered as pieces: the header (its 58 bytes, or its parsed fields
    when they re-encode to the same bytes: names that are ASCII), then the body's pieces."""
    head = pieces[0]
    if type(head) is tuple:
        version, mtype, device, ts, body_size, crc = head
        head = wire.HEADER.pack(
            version, mtype.encode("ascii"), device.encode("ascii"), ts, body_size, crc
        )
    return b"".join((head, *pieces[1:]))  # type: ignore[arg-type]


def common_equal(a: Message, b: Message) -> bool:
    """True when two messages agree on every compared common field (for custom ``__eq__``)."""
    return (
        a.device_name == b.device_name
        and a.timestamp == b.timestamp
        and a.header_version == b.header_version
        and a.metadata == b.metadata
        and a.message_id == b.message_id
        and a.metadata_encoding == b.metadata_encoding
    )


#: Header-version-1 decoders that skip the generic path, by type name:
#: ``fn(content, device_name, timestamp, raw_timestamp, wire_bytes) -> Message | None``; None
#: means "not the fast case, use unpack_content" (which then reports any error with its offset).
#: ``wire_bytes`` is what the message re-packs to (the codec's, see ``Message._wire``).
FAST_V1: dict[str, Callable[[bytes, str, float, int, Any], Message | None]] = {}
#: The same for header version 2 (``fn(body, ...)``: the whole body, extended header and
#: metadata included): the standard 12-byte extended header only; anything else is None and
#: goes the generic way, which also reports errors with their offsets.
FAST_V2: dict[str, Callable[[bytes, str, float, int, Any], Message | None]] = {}


def _slot_builder(cls: type[M], params: str, common_lines: tuple[str, ...]) -> Callable[..., M]:
    """Generate ``build(<params>, *content_fields)`` filling the slots of a frozen dataclass
    directly through their descriptors; ``common_lines`` set the common fields."""
    content = [f.name for f in dataclasses.fields(cls) if f.name not in _COMMON_FIELDS]
    ns: dict[str, Any] = {"_new": object.__new__, "_cls": cls, "_EMPTY": EMPTY_MAPPING}
    for name in (*_COMMON_ORDER, *content):
        ns[f"_s_{name}"] = getattr(cls, name).__set__
    args = "".join(f", {n}" for n in content)
    src = [
        f"def build({params}{args}):",
        "    self = _new(_cls)",
        *common_lines,
        *(f"    _s_{n}(self, {n})" for n in content),
        "    return self",
    ]
    exec("\n".join(src), ns)  # noqa: S102 - generated from dataclass field names only
    return ns["build"]  # type: ignore[no-any-return]


def fast_builder_v1(cls: type[M]) -> Callable[..., M]:
    """Like :func:`fast_builder` for a header-version-1 message, whose common fields are all
    known: ``build(device_name, timestamp, raw_timestamp, wire_bytes, *content_fields)``. No
    dict, no look-ups: the hot path of a 500 Hz or 100k msg/s stream of TRANSFORM/POSITION."""
    return _slot_builder(
        cls,
        "device_name, timestamp, raw_timestamp, wire_bytes",
        (
            "    _s_device_name(self, device_name)",
            "    _s_timestamp(self, timestamp)",
            "    _s_header_version(self, 1)",
            "    _s_metadata(self, _EMPTY)",
            "    _s_message_id(self, 0)",
            "    _s_metadata_encoding(self, _EMPTY)",
            "    _s_raw_timestamp(self, raw_timestamp)",
            "    _s__wire(self, wire_bytes)",
        ),
    )


def fast_builder_v2(cls: type[M]) -> Callable[..., M]:
    """Like :func:`fast_builder_v1` for header version 2: ``build(device_name, timestamp,
    raw_timestamp, wire_bytes, metadata, metadata_encoding, message_id, *content_fields)``."""
    return _slot_builder(
        cls,
        "device_name, timestamp, raw_timestamp, wire_bytes, metadata, encodings, message_id",
        (
            "    _s_device_name(self, device_name)",
            "    _s_timestamp(self, timestamp)",
            "    _s_header_version(self, 2)",
            "    _s_metadata(self, metadata)",  # a dict, as the generic decoder gives
            "    _s_message_id(self, message_id)",
            "    _s_metadata_encoding(self, encodings if encodings else _EMPTY)",
            "    _s_raw_timestamp(self, raw_timestamp)",
            "    _s__wire(self, wire_bytes)",
        ),
    )


def fast_builder(cls: type[M]) -> Callable[..., M]:
    """A constructor for decoders: ``build(common, *content_fields)`` in field order.

    A frozen dataclass ``__init__`` pays a keyword parse and an ``object.__setattr__`` lookup per
    field (~1.2 us for TRANSFORM). Decoded values are already valid, so this fills the slots
    directly through their descriptors (no ``__post_init__``; use only where none is needed).
    ``common`` is the dict the codec passes to ``unpack_content``.
    """
    return _slot_builder(
        cls,
        "common",
        (
            "    g = common.get",
            "    _s_device_name(self, common['device_name'])",
            "    _s_timestamp(self, common['timestamp'])",
            "    _s_header_version(self, common['header_version'])",
            "    m = g('metadata')",
            "    _s_metadata(self, _EMPTY if m is None else m)",
            "    _s_message_id(self, g('message_id', 0))",
            "    m = g('metadata_encoding')",
            "    _s_metadata_encoding(self, _EMPTY if m is None else m)",
            "    _s_raw_timestamp(self, g('raw_timestamp'))",
            "    _s__wire(self, None)",
        ),
    )


#: Arrays and byte strings longer than this are summarised in content_summary(), not dumped.
SUMMARY_LIMIT = 64


def _jsonable(value: Any) -> Any:
    if isinstance(value, bytes):
        # always hex, so the reader never has to guess (the form `igtl send --json-body` takes)
        if len(value) > SUMMARY_LIMIT:
            return {"bytes": len(value), "head_hex": value[:SUMMARY_LIMIT].hex()}
        return {"hex": value.hex()}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if hasattr(value, "tolist"):  # numpy arrays and scalars
        size = getattr(value, "size", 1)
        if size > SUMMARY_LIMIT:
            flat = value.reshape(-1)
            return {
                "shape": list(value.shape),
                "dtype": str(value.dtype),
                "min": flat.min().tolist(),
                "max": flat.max().tolist(),
                "head": flat[:8].tolist(),
            }
        return value.tolist()
    if hasattr(value, "value") and hasattr(value, "name"):  # enums
        return value.value
    return value


@dataclass(frozen=True, slots=True)
class RawMessage(Message):
    """A message of a type this library does not decode: kept whole, never dropped.

    ``content`` is the content (for v2: without extended header and metadata, which are decoded
    into the common fields as for any type), so a RawMessage re-encodes to the same bytes.
    """

    type_name: str = ""
    content: bytes = b""

    @property
    def message_type(self) -> str:
        return self.type_name

    def pack_content(self) -> bytes:
        return bytes(self.content)

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> RawMessage:
        return cls(type_name=common.pop("message_type"), content=bytes(content), **common)


# ------------------------------------------------------------------------------------------
# Helpers for content codecs.
def check_uint(value: int, bits: int, what: str) -> int:
    """ValueError unless ``value`` is an int in [0, 2**bits)."""
    if not isinstance(value, int) or not 0 <= value < (1 << bits):
        raise ValueError(f"{what} must be an integer in 0..{(1 << bits) - 1}, got {value!r}")
    return value


def need_size(content: bytes, size: int, what: str) -> None:
    """ContentError unless the content is exactly ``size`` bytes."""
    if len(content) != size:
        raise ContentError(f"{what} content must be {size} bytes, got {len(content)}", offset=0)


def need_multiple(content: bytes, element: int, what: str, header: int = 0) -> int:
    """Number of elements in a count-by-size content; ContentError if it does not divide."""
    rest = len(content) - header
    if rest < 0 or rest % element:
        raise ContentError(
            f"{what} content of {len(content)} bytes is not {header} + a multiple of {element}",
            offset=header + (rest // element) * element if rest > 0 else 0,
        )
    return rest // element


def decode_text(raw: bytes, encoding: int, what: str, offset: int = 0) -> str:
    """Decode text in an IANA encoding; InvalidTextError on bad bytes or unknown encoding."""
    codec = wire.IANA_ENCODINGS.get(encoding)
    if codec is None:
        raise InvalidTextError(f"{what}: unknown text encoding {encoding}", offset=offset)
    try:
        return raw.decode(codec)
    except UnicodeDecodeError as err:
        raise InvalidTextError(
            f"{what}: bytes {err.start}..{err.end} are not valid {codec}", offset=offset + err.start
        ) from err


def encode_text(text: str, encoding: int, what: str) -> bytes:
    try:
        return text.encode(wire.codec_for(encoding))
    except UnicodeEncodeError as err:
        raise ValueError(f"{what} cannot be encoded in encoding {encoding}") from err


def fixed(text: str, size: int, what: str) -> bytes:
    """NUL-padded fixed-size field for struct 's' formats (ValueError when too long)."""
    return wire.encode_fixed(text, size, what)


unfixed = wire.decode_fixed
