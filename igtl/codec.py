"""Decoding: one message from bytes (:func:`unpack`) and the sans-IO :class:`StreamDecoder`.

The stream decoder never touches a socket (see h11 in shared/STYLE.md): transports, file readers,
replay tools and fuzzers all feed it bytes and iterate over complete, validated messages. A
header split across two reads is its normal case. Limits (body size) and the CRC check live
here, once, for every transport.

What happens after a bad message (``DecodeError.recoverable``):

- the header was sound (known version, body size within the limit) but the body is bad (CRC
  mismatch, inconsistent extended header or metadata, content that does not fit its type): the
  whole message is consumed, the error is raised once, and decoding continues with the next
  message. The stream is still in sync.
- the header itself is unusable (unknown version, oversized body): the stream cannot be
  re-framed. The decoder raises the error, enters the failed state and raises
  :class:`DecoderFailedError` on every later call. Transports close such a connection.

No other exception leaves :func:`unpack` or :class:`StreamDecoder` for any input bytes: a
content codec that trips over values its type cannot hold is reported as ContentError.

Re-packing: every decodable message re-packs byte for byte (``msg.pack() == data``), or is
refused:

- A decoded message remembers the bytes it was decoded from (``Message._wire``, set here and
  nowhere else) and ``pack()`` without a version change or a ``metadata`` override returns
  them, whether they are what this library would encode or not: names that are not UTF-8
  (decoded as latin-1 so operator tools get an answer), v2 metadata not sorted by key or with a
  key twice, EXT_HEADER_SIZE > 12, reserved, version or padding bytes that are not the
  canonical value, float32 signalling NaNs (a Python float makes them quiet), a wrong CRC
  accepted with ``crc_check=False``. A message built or changed (``dataclasses.replace``,
  ``stamped``) has none and is encoded from its fields.
- Remembering copies nothing on the common path: :func:`unpack` keeps a reference to the
  ``bytes`` it was given (a bytearray or memoryview: the 58 header bytes and the body copy the
  content needs anyway); the :class:`StreamDecoder` keeps the body it copied out of its buffer
  and the parsed header fields, re-encoded when packing (the header bytes themselves are
  copied only when a name is not ASCII); a big body collected apart is kept as the collected
  buffer (which an IMAGE's or NDARRAY's arrays view anyway) plus the extended header and
  metadata bytes cut off around it. The pieces are joined only when the message is packed.
- NUL-padded text fields (the header's TYPE and DEVICE_NAME, names in contents) must hold
  nothing but NULs after their first NUL, else the bytes behind the terminator would be lost
  to every reader of the decoded fields: refused with InvalidTextError, for the header
  HeaderTextError, which is recoverable (the sizes are sound, so the message is skipped and the
  stream goes on). The reference and every peer we know zero-fill these fields (strncpy).
- :func:`decode_body` is given the header parsed: it re-encodes the names as UTF-8 (a name that
  arrived as latin-1 cannot be told apart once decoded) and keeps every other header value.

Big bodies: see :class:`StreamDecoder` (checksummed piece by piece, decoded without a copy).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from . import wire
from .errors import (
    ContentError,
    CRCError,
    DecodeError,
    DecoderFailedError,
    HeaderTextError,
    TruncatedMessageError,
)
from .messages.base import (
    FAST_V1,
    FAST_V2,
    REGISTRY,
    Message,
    RawMessage,
    WirePieces,
    set_wire,
)

_HEADER_SIZE = wire.HEADER_SIZE
_header_fields = wire.header_fields
_crc64 = wire.crc64
_crcmod_c, _crcmod_table, _crc_big = wire._crcmod_c, wire._crcmod_table, wire._crc_big
_CRC_SMALL = wire.CRC_SMALL
_T0, _T1, _T2, _T3 = wire._T0, wire._T1, wire._T2, wire._T3  # frac -> ns tables
_registry_get = REGISTRY.get
_fast_v1_get = FAST_V1.get
_fast_v2_get = FAST_V2.get
_set_wire = set_wire
# Classes that want the wire type name in ``common`` (query families, COLORT/COLORTABLE...).
_needs_type_name: dict[type, bool] = {}


def _decode(
    version: int,
    message_type: str,
    device_name: str,
    ts: int,
    crc: int,
    body: bytes | bytearray,
    crc_check: bool,
    wire_bytes: bytes | WirePieces,
) -> Message:
    """Decode a complete body whose header fields are already validated.

    A bytearray body is a big body the StreamDecoder collected apart: it is handed to the
    content codec as it is (a header-version-2 body is first trimmed in place to its content),
    so the message's arrays view it without a copy. Content codecs take bytes or bytearray.

    ``wire_bytes`` is what the message re-packs to: the whole encoded message, or pieces of it
    the caller already holds (``(header, body)``, see ``base.WirePieces``), so that
    remembering them copies nothing. A bytearray body that is trimmed here gets its pieces
    rebuilt around the trimmed content.
    """
    if crc_check and body:
        # wire.crc64, inlined: this runs for every message decoded
        actual = _crcmod_c(body, 0, _crcmod_table) if len(body) < _CRC_SMALL else _crc_big(body, 0)
        if actual != crc:
            raise _crc_error(crc, actual, message_type, device_name)
    # wire.raw_to_seconds, inlined: this runs for every message decoded
    frac = ts & 0xFFFFFFFF
    t = (
        (ts >> 32)
        + (_T0[frac >> 24] + _T1[(frac >> 16) & 0xFF] + _T2[(frac >> 8) & 0xFF] + _T3[frac & 0xFF])
        * 1e-9
        if frac
        else float(ts >> 32)
    )
    if version == 1:
        fast = _fast_v1_get(message_type)
        if fast is not None:
            # a length check first
            msg = fast(body, device_name, t, ts, wire_bytes)  # type: ignore[arg-type]
            if msg is not None:
                return msg
    elif type(body) is bytes:  # not a big body being trimmed in place
        fast = _fast_v2_get(message_type)
        if fast is not None:
            msg = fast(body, device_name, t, ts, wire_bytes)
            if msg is not None:
                return msg
    return _decode_slow(version, message_type, device_name, t, ts, body, wire_bytes)


def _decode_slow(
    version: int,
    message_type: str,
    device_name: str,
    t: float,
    ts: int,
    body: bytes | bytearray,
    wire_bytes: bytes | WirePieces,
) -> Message:
    """:func:`_decode` past the fast paths: a header-version-2 body's metadata, then the
    registered class's content codec (a :class:`RawMessage` for a type nobody registered)."""
    common: dict[str, Any] = {
        "device_name": device_name,
        "timestamp": t,
        "raw_timestamp": ts,
        "header_version": version,
    }
    try:
        if version == 2:
            content, content_offset, wire_bytes = _v2_content(body, wire_bytes, common)
        else:
            content = body
            content_offset = _HEADER_SIZE
        cls = _registry_get(message_type)
        if cls is None:
            common["message_type"] = message_type
            raw_msg = RawMessage.unpack_content(content, common)  # type: ignore[arg-type]
            if type(content) is bytearray and type(wire_bytes) is tuple:
                # RawMessage copies its content: keep that copy, not the collected body too
                raw = raw_msg.content
                wire_bytes = tuple(raw if p is content else p for p in wire_bytes)
            _set_wire(raw_msg, wire_bytes)
            return raw_msg
        needs = _needs_type_name.get(cls)
        if needs is None:
            needs = _needs_type_name[cls] = bool(getattr(cls, "NEEDS_TYPE_NAME", False))
        if needs:
            common["message_type"] = message_type
        try:
            msg = cls.unpack_content(content, common)  # type: ignore[arg-type]
        except DecodeError as err:
            if err.offset is not None:
                err.offset += content_offset
            raise
        except Exception as err:  # noqa: BLE001 - any failure on peer bytes is the peer's error
            raise ContentError(
                f"invalid {message_type} content: {type(err).__name__}: {err}",
                offset=content_offset,
            ) from err
        _set_wire(msg, wire_bytes)
        return msg
    except DecodeError as err:
        if err.message_type is None:
            err.message_type = message_type
            err.device_name = device_name
        raise


def _v2_content(
    body: bytes | bytearray, wire_bytes: bytes | WirePieces, common: dict[str, Any]
) -> tuple[bytes | bytearray, int, bytes | WirePieces]:
    """A header-version-2 body split: its metadata and message ID into ``common``; returns
    (the content, its offset in the message, what the message re-packs to)."""
    layout = wire.split_v2_body(body)
    meta_start = layout.content_end
    content: bytes | bytearray
    meta_raw: bytes | bytearray
    if type(body) is bytearray:
        # Cut the metadata off the end and the extended header off the front: no copy
        # of the content (CPython deletes a bytearray's head by moving its start).
        meta_raw = bytes(memoryview(body)[meta_start:])
        front = bytes(memoryview(body)[: layout.content_start])
        del body[meta_start:]
        del body[: layout.content_start]
        content = body
        # The content is the message's (its arrays view it): re-packing joins the
        # small pieces cut off around it instead of keeping a copy of the whole body.
        wire_bytes = (wire_bytes[0], front, body, meta_raw)
    else:
        meta_raw = body[meta_start:]
        content = body[layout.content_start : meta_start]
    meta, encodings = wire.unpack_metadata(
        meta_raw[: layout.meta_header_size],
        meta_raw[layout.meta_header_size :],
        base_offset=_HEADER_SIZE + meta_start,
    )
    common["metadata"] = meta
    if encodings:
        common["metadata_encoding"] = encodings
    common["message_id"] = layout.message_id
    return content, _HEADER_SIZE + layout.content_start, wire_bytes


def decode_body(
    header: wire.Header, body: bytes | bytearray | memoryview, *, crc_check: bool = True
) -> Message:
    """Decode a message from its parsed header and its complete body."""
    if len(body) != header.body_size:
        raise TruncatedMessageError(
            f"body of {len(body)} bytes, header announces {header.body_size}",
            offset=_HEADER_SIZE + min(len(body), header.body_size),
            message_type=header.message_type,
            device_name=header.device_name,
        )
    body = body if type(body) is bytes else bytes(body)
    # The header is given parsed: its names are re-encoded as UTF-8 (a name that arrived as
    # latin-1 cannot be told apart once decoded); every other header byte is kept.
    head = wire.HEADER.pack(
        header.version,
        header.message_type.encode("utf-8"),
        header.device_name.encode("utf-8"),
        header.timestamp_raw,
        header.body_size,
        header.crc,
    )
    return _decode(
        header.version,
        header.message_type,
        header.device_name,
        header.timestamp_raw,
        header.crc,
        body,
        crc_check,
        (head, body),
    )


def unpack(
    data: bytes | bytearray | memoryview,
    *,
    crc_check: bool = True,
    max_body_size: int = wire.DEFAULT_MAX_BODY_SIZE,
) -> Message:
    """Decode exactly one complete encoded message (header + body), CRC verified."""
    version, mtype, device, ts, body_size, crc = _header_fields(data, 0, max_body_size)
    end = _HEADER_SIZE + body_size
    n = len(data)
    if n != end:
        if n < end:
            raise TruncatedMessageError(
                f"message announces {body_size} body bytes, only {n - _HEADER_SIZE} present",
                offset=n,
                message_type=mtype,
                device_name=device,
            )
        raise DecodeError(
            f"{n - end} bytes follow the message; use StreamDecoder for a stream",
            offset=end,
            message_type=mtype,
            device_name=device,
        )
    # One copy of the body, whatever the input type: bytes slicing copies, and a memoryview or
    # bytearray slice is materialised once here. The message re-packs to ``data`` itself, or
    # for mutable input to the 58 header bytes and that copy.
    if type(data) is bytes:
        return _decode(version, mtype, device, ts, crc, data[_HEADER_SIZE:], crc_check, data)
    with memoryview(data) as view:
        head = bytes(view[:_HEADER_SIZE])
        body = bytes(view[_HEADER_SIZE:])
    return _decode(version, mtype, device, ts, crc, body, crc_check, (head, body))


#: Bodies of at least this many bytes that do not arrive in one piece are collected apart from
#: the stream buffer and checksummed as they arrive (StreamDecoder).
BIG_BODY = 64 * 1024


def _crc_error(crc: int, actual: int, message_type: str, device_name: str) -> CRCError:
    return CRCError(
        f"CRC mismatch: header says {crc:#018x}, body gives {actual:#018x}",
        offset=_HEADER_SIZE,
        message_type=message_type,
        device_name=device_name,
    )


class StreamDecoder:
    """Incremental decoder for a byte stream of concatenated messages.

    ``feed(data)`` appends bytes; iterating yields every complete message fed so far and stops
    when more data is needed. Bad messages raise :class:`DecodeError` subclasses (see the module
    docstring for what happens next). ``buffered`` tells how many bytes wait for completion.
    Offsets in errors are stream offsets (bytes since the decoder was created).

    Big bodies (``big_body`` bytes or more, up to ``max_body_size``) cost no single call more
    than the bytes it was given: once such a header is read and its body is still incomplete,
    the body is collected in a buffer of its own and its CRC is computed piece by piece in
    ``feed`` as the bytes arrive (the CRC backends hold the interpreter lock, ~25 ms per 256 MiB
    with anycrc, ~800 ms with crcmod). When the last piece arrives the CRC is compared and the
    content decoded from that buffer without copying it (an IMAGE's pixels view it). The
    message re-packs from that same buffer (see "Re-packing" in the module docstring): free
    for the types whose fields view it (IMAGE, NDARRAY, POLYDATA points), while types that copy
    their content out of it (VIDEO frames, BIND children, STATUS) keep both for the message's
    lifetime; an unknown type re-packs from its own ``content`` copy instead.
    """

    __slots__ = (
        "_buf",
        "_pos",
        "_crc_check",
        "_max_body",
        "_big_body",
        "_failed",
        "_pending",
        "_body",
        "_body_crc",
        "_head",
        "_refuse",
        "offset",
        "messages",
        "errors",
    )

    def __init__(
        self,
        *,
        crc_check: bool = True,
        max_body_size: int = wire.DEFAULT_MAX_BODY_SIZE,
        big_body: int = BIG_BODY,
    ) -> None:
        self._buf = bytearray()
        self._pos = 0
        self._crc_check = crc_check
        self._max_body = max_body_size
        self._big_body = max(1, big_body)
        self._failed: DecodeError | None = None
        self._pending: tuple[int, str, str, int, int, int] | None = None
        #: The body of the pending message while it is collected apart (big bodies only).
        self._body: bytearray | None = None
        self._body_crc = 0
        #: The header bytes of the message whose body is collected apart.
        self._head = b""
        #: A recoverable header error, raised once the message's body has been skipped.
        self._refuse: HeaderTextError | None = None
        #: Stream offset of the next unread byte (for error reports).
        self.offset = 0
        #: Counters: messages decoded, errors raised.
        self.messages = 0
        self.errors = 0

    @property
    def failed(self) -> bool:
        return self._failed is not None

    @property
    def buffered(self) -> int:
        n = len(self._buf) - self._pos
        if self._body is not None:
            n += _HEADER_SIZE + len(self._body)
        return n

    def feed(self, data: bytes | bytearray | memoryview) -> None:
        if self._failed is not None:
            raise DecoderFailedError(f"decoder failed earlier: {self._failed}")
        body = self._body
        if body is not None and self._pending is not None:
            need = self._pending[4] - len(body)
            if need > 0:
                if len(data) <= need:
                    body += data
                    if self._crc_check:
                        self._body_crc = _crc64(data, self._body_crc)
                    return
                view = memoryview(data)
                part = view[:need]
                body += part
                if self._crc_check:
                    self._body_crc = _crc64(part, self._body_crc)
                data = view[need:]
        if self._pos and self._pos >= len(self._buf) // 2:
            del self._buf[: self._pos]
            self._pos = 0
        self._buf += data

    def __iter__(self) -> Iterator[Message]:
        while True:
            msg = self.next_message()
            if msg is None:
                return
            yield msg

    def next_message(self) -> Message | None:
        """The next complete message, or None when more bytes are needed."""
        if self._failed is not None:
            raise DecoderFailedError(f"decoder failed earlier: {self._failed}")
        buf = self._buf
        pos = self._pos
        header = self._pending
        if header is None:
            if len(buf) - pos < _HEADER_SIZE:
                return None
            try:
                header = _header_fields(buf, pos, self._max_body)
            except HeaderTextError as err:
                # The sizes are sound: frame the message as usual, refuse it once it is read.
                err.offset = (pos if err.offset is None else err.offset) - pos
                self._refuse = err
                header = (1, err.message_type or "", err.device_name or "", 0, err.body_size, 0)
            except DecodeError as err:
                err.offset = self.offset + (pos if err.offset is None else err.offset) - pos
                self._failed = err
                self.errors += 1
                raise
            self._pending = header
        elif self._body is not None:
            return self._big_message(header)
        version, mtype, device, ts, body_size, crc = header
        end = pos + _HEADER_SIZE + body_size
        if len(buf) < end:
            if body_size >= self._big_body:
                self._collect_apart(body_size)
            return None
        self._pending = None
        self._pos = end
        start_offset = self.offset
        self.offset += end - pos
        if self._refuse is not None:
            self._raise_refusal(start_offset)
        with memoryview(buf) as view:
            body = bytes(view[pos + _HEADER_SIZE : end])
            # Remembered for re-packing without a copy: the parsed header re-encodes to the same
            # 58 bytes when the names are ASCII (the other fields are kept as numbers).
            head: bytes | tuple[int, str, str, int, int, int] = (
                header
                if mtype.isascii() and device.isascii()
                else bytes(view[pos : pos + _HEADER_SIZE])
            )
        try:
            msg = _decode(version, mtype, device, ts, crc, body, self._crc_check, (head, body))
        except DecodeError as err:
            self.errors += 1
            if err.offset is not None:
                err.offset += start_offset
            raise
        self.messages += 1
        return msg

    def _raise_refusal(self, start_offset: int) -> None:
        err = self._refuse
        assert err is not None
        self._refuse = None
        self.errors += 1
        if err.offset is not None:
            err.offset += start_offset
        raise err

    def _collect_apart(self, body_size: int) -> None:
        """Move the pending big body's first bytes out of the stream buffer (all buffered bytes
        belong to it: it is incomplete) and start its CRC; ``feed`` does the rest."""
        buf = self._buf
        with memoryview(buf) as view:
            self._head = bytes(view[self._pos : self._pos + _HEADER_SIZE])
            part = view[self._pos + _HEADER_SIZE :]
            self._body = bytearray(part)
            self._body_crc = _crc64(part) if self._crc_check else 0
            part.release()
        buf.clear()
        self._pos = 0

    def _big_message(self, header: tuple[int, str, str, int, int, int]) -> Message | None:
        body = self._body
        version, mtype, device, ts, body_size, crc = header
        if body is None or len(body) < body_size:
            return None
        self._body = None
        self._pending = None
        start_offset = self.offset
        self.offset += _HEADER_SIZE + body_size
        if self._refuse is not None:
            self._raise_refusal(start_offset)
        try:
            if self._crc_check and self._body_crc != crc:
                raise _crc_error(crc, self._body_crc, mtype, device)
            msg = _decode(version, mtype, device, ts, crc, body, False, (self._head, body))
        except DecodeError as err:
            self.errors += 1
            if err.offset is not None:
                err.offset += start_offset
            raise
        self.messages += 1
        return msg

    def close(self) -> None:
        """Declare end of stream; TruncatedMessageError if a partial message is buffered."""
        if self._failed is None and self.buffered:
            raise TruncatedMessageError(
                f"stream ended inside a message ({self.buffered} bytes buffered)",
                offset=self.offset,
                message_type=self._pending[1] if self._pending else None,
                device_name=self._pending[2] if self._pending else None,
            )
