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
    TruncatedMessageError,
)
from .messages.base import REGISTRY, Message, RawMessage


def decode_body(header: wire.Header, body: bytes | memoryview, *, crc_check: bool = True) -> Message:
    """Decode a message from its parsed header and its complete body."""
    if crc_check and header.body_size:
        crc = wire.crc64(body)
        if crc != header.crc:
            raise CRCError(
                f"CRC mismatch: header says {header.crc:#018x}, body gives {crc:#018x}",
                offset=wire.HEADER_SIZE,
                message_type=header.message_type,
                device_name=header.device_name,
            )
    common: dict[str, Any] = {
        "device_name": header.device_name,
        "timestamp": wire.raw_to_seconds(header.timestamp_raw),
        "raw_timestamp": header.timestamp_raw,
        "header_version": header.version,
    }
    try:
        if header.version == 2:
            layout = wire.split_v2_body(body)
            content = body[layout.content_start : layout.content_end]
            meta_start = layout.content_end
            meta, encodings = wire.unpack_metadata(
                body[meta_start : meta_start + layout.meta_header_size],
                body[meta_start + layout.meta_header_size :],
                base_offset=wire.HEADER_SIZE + meta_start,
            )
            common["metadata"] = meta
            if encodings:
                common["metadata_encoding"] = encodings
            common["message_id"] = layout.message_id
            content_offset = wire.HEADER_SIZE + layout.content_start
        else:
            content = body
            content_offset = wire.HEADER_SIZE
        cls = REGISTRY.get(header.message_type)
        if cls is None:
            common["message_type"] = header.message_type
            return RawMessage.unpack_content(bytes(content), common)
        if getattr(cls, "NEEDS_TYPE_NAME", False):
            common["message_type"] = header.message_type
        try:
            return cls.unpack_content(bytes(content), common)
        except DecodeError as err:
            if err.offset is not None:
                err.offset += content_offset
            raise
        except (ValueError, TypeError, IndexError, OverflowError) as err:
            # A content codec tripped over values its type cannot hold: still the peer's error.
            raise ContentError(
                f"invalid {header.message_type} content: {err}", offset=content_offset
            ) from err
    except DecodeError as err:
        if err.message_type is None:
            err.message_type = header.message_type
            err.device_name = header.device_name
        raise


def unpack(
    data: bytes | bytearray | memoryview,
    *,
    crc_check: bool = True,
    max_body_size: int = wire.DEFAULT_MAX_BODY_SIZE,
) -> Message:
    """Decode exactly one complete encoded message (header + body), CRC verified."""
    header = wire.unpack_header(data, 0, max_body_size=max_body_size)
    end = wire.HEADER_SIZE + header.body_size
    if len(data) < end:
        raise TruncatedMessageError(
            f"message announces {header.body_size} body bytes, only {len(data) - 58} present",
            offset=len(data),
            message_type=header.message_type,
            device_name=header.device_name,
        )
    if len(data) > end:
        raise DecodeError(
            f"{len(data) - end} bytes follow the message; use StreamDecoder for a stream",
            offset=end,
            message_type=header.message_type,
            device_name=header.device_name,
        )
    return decode_body(header, memoryview(data)[wire.HEADER_SIZE : end], crc_check=crc_check)


class StreamDecoder:
    """Incremental decoder for a byte stream of concatenated messages.

    ``feed(data)`` appends bytes; iterating yields every complete message fed so far and stops
    when more data is needed. Bad messages raise :class:`DecodeError` subclasses (see the module
    docstring for what happens next). ``buffered`` tells how many bytes wait for completion.
    """

    __slots__ = ("_buf", "_pos", "_crc_check", "_max_body", "_failed", "_pending", "offset",
                 "messages", "errors")

    def __init__(
        self, *, crc_check: bool = True, max_body_size: int = wire.DEFAULT_MAX_BODY_SIZE
    ) -> None:
        self._buf = bytearray()
        self._pos = 0
        self._crc_check = crc_check
        self._max_body = max_body_size
        self._failed: DecodeError | None = None
        self._pending: wire.Header | None = None
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
        return len(self._buf) - self._pos

    def feed(self, data: bytes | bytearray | memoryview) -> None:
        if self._failed is not None:
            raise DecoderFailedError(f"decoder failed earlier: {self._failed}")
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
            if len(buf) - pos < wire.HEADER_SIZE:
                return None
            try:
                header = wire.unpack_header(buf, pos, max_body_size=self._max_body)
            except DecodeError as err:
                err.offset = self.offset + (err.offset or pos) - pos
                self._failed = err
                self.errors += 1
                raise
            self._pending = header
        end = pos + wire.HEADER_SIZE + header.body_size
        if len(buf) < end:
            return None
        self._pending = None
        self._pos = end
        start_offset = self.offset
        self.offset += end - pos
        try:
            msg = decode_body(
                header, memoryview(buf)[pos + wire.HEADER_SIZE : end], crc_check=self._crc_check
            )
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
                message_type=self._pending.message_type if self._pending else None,
            )
