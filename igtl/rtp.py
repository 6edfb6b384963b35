"""The reference library's RTP wrapper for OpenIGTLink over UDP, sans-IO (protocol doc section 4).

Written from the description of ``igtlMessageRTPWrapper`` in ``shared/IGTL-PROTOCOL.md`` and checked
byte for byte against the reference test vector (``igtl_test_data_rtpwrapper.h`` from the
OpenIGTLink project, shipped as ``shared/igtl-vectors/rtpwrapper.bin``).

Every datagram is::

    RTP header (12 bytes): 0x80 | payload type | sequence (uint16) | timestamp (uint32) | SSRC
    IGTL header (58) + extended header (12) of the original header-version-2 message, except that
    MSG_ID (absolute offsets 66..69) holds the low 16 bits of the message ID followed by the
    FRAGMENT field: 0x0000 whole message, 0x8000 first, 0x8000+k middle k, 0xE000+k last (k = index)
    the next slice of the body after the extended header (content + metadata)

BODY_SIZE and CRC describe the whole message and are repeated in every fragment, so the reassembled
message is checked by the ordinary codec (``igtl.unpack``). Nothing here touches a socket:
:func:`fragment` returns datagrams, :class:`Reassembler` is fed datagrams and returns complete
messages. Errors in received datagrams raise :class:`FragmentError` (a recoverable
:class:`~igtl.errors.DecodeError`: one bad datagram spoils nothing else).
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable, Hashable
from typing import Any

from . import wire
from .errors import DecodeError, FragmentError

RTP_HEADER = struct.Struct(">BBHII")
RTP_HEADER_SIZE = 12
#: RTP version 2, no padding, no extension, no CSRC: the only first byte the reference writes.
RTP_FIRST_BYTE = 0x80
DEFAULT_PAYLOAD_TYPE = 96
#: RTP_PAYLOAD_LENGTH of the reference (igtlGeneralSocket.h): IGTL headers + chunk per datagram.
DEFAULT_PAYLOAD_LENGTH = 8900
#: The part of the original message copied into every datagram: header + extended header.
PREFIX_SIZE = wire.HEADER_SIZE + wire.EXT_HEADER_SIZE
_MSG_ID_OFFSET = 66  # absolute offset of MSG_ID in a v2 message
_ID_FRAG = struct.Struct(">HH")
_MSG_ID = struct.Struct(">I")

FRAGMENT_NONE = 0x0000
FRAGMENT_FIRST = 0x8000
FRAGMENT_LAST = 0xE000
#: The last fragment's index lives in 13 bits (0xE000 + k), which caps a message's fragments.
MAX_FRAGMENTS = 0x2000


def rtp_timestamp(t: float | None = None) -> int:
    """The reference's 100 Hz RTP clock: ``100 * seconds + round(100 * usec / 1e6)`` (uint32)."""
    if t is None:
        t = time.time()
    sec = int(t)
    usec = int((t - sec) * 1e6)
    return (100 * sec + round(100 * usec / 1e6)) & 0xFFFFFFFF


def fragment(
    message_bytes: bytes | bytearray | memoryview,
    *,
    seq_start: int = 0,
    payload_type: int = DEFAULT_PAYLOAD_TYPE,
    ssrc: int = 0,
    payload_length: int = DEFAULT_PAYLOAD_LENGTH,
    timestamp: int | None = None,
) -> list[bytes]:
    """Split one encoded header-version-2 message into RTP datagrams, as the reference does.

    ``payload_length`` is the RTP payload per datagram (70 header bytes + body chunk), so every
    datagram is at most ``12 + payload_length`` bytes. ``timestamp`` is the raw 32-bit RTP
    timestamp (default: :func:`rtp_timestamp` now), shared by all fragments. Sequence numbers
    run from ``seq_start`` and wrap at 2**16. ValueError for a message the scheme cannot carry
    (header version 1, message ID >= 2**16, inconsistent size, too many fragments).
    """
    data = bytes(message_bytes)
    if len(data) < PREFIX_SIZE:
        raise ValueError(f"{len(data)} bytes cannot be a header-version-2 message (>= 70)")
    version, _t, _d, _ts, body_size, _crc = wire.HEADER.unpack_from(data, 0)
    if version != 2:
        raise ValueError(f"RTP fragmentation needs header version 2, message has {version}")
    if wire.HEADER_SIZE + body_size != len(data):
        raise ValueError(
            f"message of {len(data)} bytes announces BODY_SIZE {body_size} (expected "
            f"{len(data) - wire.HEADER_SIZE})"
        )
    (message_id,) = _MSG_ID.unpack_from(data, _MSG_ID_OFFSET)
    if message_id >= 0x10000:
        raise ValueError(f"RTP fragmentation carries 16-bit message IDs; got {message_id}")
    if not PREFIX_SIZE < payload_length <= 0xFFFF - RTP_HEADER_SIZE:
        raise ValueError(f"payload_length must be in 71..65523, got {payload_length}")
    if not 0 <= payload_type <= 0x7F:
        raise ValueError(f"payload_type must be 0..127, got {payload_type}")
    if not 0 <= ssrc <= 0xFFFFFFFF:
        raise ValueError(f"ssrc must fit 32 bits, got {ssrc}")
    ts = rtp_timestamp() if timestamp is None else timestamp & 0xFFFFFFFF
    head = data[:_MSG_ID_OFFSET]
    rest = memoryview(data)[PREFIX_SIZE:]
    chunk = payload_length - PREFIX_SIZE
    count = max(1, -(-len(rest) // chunk))
    if count > MAX_FRAGMENTS:
        raise ValueError(
            f"message of {len(data)} bytes needs {count} fragments of {chunk} bytes; "
            f"the FRAGMENT field allows {MAX_FRAGMENTS}"
        )
    out = []
    for k in range(count):
        if count == 1:
            frag = FRAGMENT_NONE
        elif k == 0:
            frag = FRAGMENT_FIRST
        elif k == count - 1:
            frag = FRAGMENT_LAST + k
        else:
            frag = FRAGMENT_FIRST + k
        out.append(
            b"".join(
                (
                    RTP_HEADER.pack(
                        RTP_FIRST_BYTE, payload_type, (seq_start + k) & 0xFFFF, ts, ssrc
                    ),
                    head,
                    _ID_FRAG.pack(message_id, frag),
                    rest[k * chunk : (k + 1) * chunk],
                )
            )
        )
    return out


def parse_fragment_field(frag: int) -> tuple[int, bool]:
    """(index k, is_last) of a FRAGMENT value other than 0; FragmentError if malformed."""
    if frag == FRAGMENT_FIRST:
        return 0, False
    if frag & FRAGMENT_LAST == FRAGMENT_LAST:
        k = frag & 0x1FFF
        if k == 0:
            raise FragmentError("last fragment with index 0", offset=_MSG_ID_OFFSET + 2)
        return k, True
    if frag & 0x8000 and frag - FRAGMENT_FIRST < MAX_FRAGMENTS:
        return frag - FRAGMENT_FIRST, False
    raise FragmentError(f"invalid FRAGMENT field {frag:#06x}", offset=_MSG_ID_OFFSET + 2)


class _Partial:
    __slots__ = ("chunks", "last", "prefix", "size", "started", "total")

    def __init__(self, prefix: bytes, total: int, started: float) -> None:
        self.prefix = prefix  # 70 bytes, MSG_ID restored
        self.chunks: dict[int, bytes] = {}
        self.last: int | None = None
        self.size = 0
        self.started = started
        self.total = total  # bytes of body after the extended header


class Reassembler:
    """Rebuilds messages from RTP datagrams, per sender (sans-IO).

    ``feed(datagram, sender)`` returns the complete encoded message (MSG_ID restored to the
    16-bit ID) when the datagram completes one, else None. A message's fragments are grouped by
    (sender, SSRC, first sequence number), which the reference makes consecutive, so messages
    that share a message ID (usually 0) never mix. The result is *not* CRC-checked here: decode
    it with :func:`igtl.unpack`, which is.

    Limits, each counted in :attr:`stats`: incomplete messages older than ``timeout`` seconds
    are dropped (``expired``; checked on every feed and by :meth:`expire`); at most
    ``max_pending`` messages and ``max_buffered`` bytes are held (the oldest is ``evicted``);
    BODY_SIZE over ``max_body_size`` is refused before anything is buffered.
    """

    def __init__(
        self,
        *,
        timeout: float = 1.0,
        max_pending: int = 64,
        max_buffered: int = 64 * 1024 * 1024,
        max_body_size: int = wire.DEFAULT_MAX_BODY_SIZE,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if timeout <= 0 or max_pending < 1 or max_buffered < 1:
            raise ValueError("timeout, max_pending and max_buffered must be positive")
        self.timeout = timeout
        self.max_pending = max_pending
        self.max_buffered = max_buffered
        self.max_body_size = max_body_size
        self._clock = clock
        self._pending: dict[tuple[Any, ...], _Partial] = {}
        self._buffered = 0
        self.datagrams = 0
        self.completed = 0
        self.expired = 0
        self.evicted = 0
        self.duplicates = 0
        self.errors = 0

    @property
    def pending(self) -> int:
        """Incomplete messages currently held."""
        return len(self._pending)

    @property
    def buffered(self) -> int:
        """Bytes of incomplete messages currently held."""
        return self._buffered

    @property
    def stats(self) -> dict[str, int]:
        return {
            "datagrams": self.datagrams,
            "completed": self.completed,
            "expired": self.expired,
            "evicted": self.evicted,
            "duplicates": self.duplicates,
            "errors": self.errors,
            "pending": len(self._pending),
            "buffered": self._buffered,
        }

    def expire(self, now: float | None = None) -> int:
        """Drop incomplete messages older than the timeout; returns how many were dropped."""
        if now is None:
            now = self._clock()
        deadline = now - self.timeout
        dropped = 0
        pending = self._pending
        while pending:
            key = next(iter(pending))
            if pending[key].started > deadline:
                break
            self._discard(key)
            dropped += 1
        self.expired += dropped
        return dropped

    def clear(self) -> None:
        self._pending.clear()
        self._buffered = 0

    def _discard(self, key: tuple[Any, ...]) -> None:
        part = self._pending.pop(key)
        self._buffered -= part.size

    def feed(
        self, datagram: bytes | bytearray | memoryview, sender: Hashable = None
    ) -> bytes | None:
        """Take one datagram; return a complete message when this one completes it."""
        self.datagrams += 1
        try:
            return self._feed(datagram, sender)
        except FragmentError:
            self.errors += 1
            raise

    def _feed(self, datagram: bytes | bytearray | memoryview, sender: Hashable) -> bytes | None:
        # The checks of the headers and the two whole-message cases stay inline (every RTP
        # datagram takes this path); a fragment goes on to _fragment_slot and _add_fragment.
        n = len(datagram)
        if n < RTP_HEADER_SIZE + wire.HEADER_SIZE:
            raise FragmentError(f"RTP datagram of {n} bytes is shorter than 70", offset=n)
        first, _pt, seq, _ts, ssrc = RTP_HEADER.unpack_from(datagram, 0)
        if first != RTP_FIRST_BYTE:
            raise FragmentError(f"RTP first byte {first:#04x}, expected 0x80", offset=0)
        try:
            header = wire.unpack_header(datagram, RTP_HEADER_SIZE, max_body_size=self.max_body_size)
        except DecodeError as err:
            raise FragmentError(f"bad OpenIGTLink header in RTP datagram: {err}") from err
        if header.version == 1:
            # What the reference's UDP example sends (TDATA, header version 1): one whole message
            # per datagram. A v1 message has no extended header, so there is no fragment field:
            # take it as it is. (The reference's unwrapper reads its fragment field and rewrites
            # the message-ID bytes at offsets 66..69 whatever the version, i.e. inside a v1
            # message's content: it works for TDATA, whose content bytes 8..11 are name padding,
            # and misreads a v1 POSITION, whose bytes 8..11 are the z coordinate.)
            if n - RTP_HEADER_SIZE != wire.HEADER_SIZE + header.body_size:
                raise FragmentError(
                    f"header-version-1 RTP datagram holds {n - RTP_HEADER_SIZE - wire.HEADER_SIZE}"
                    f" body bytes, BODY_SIZE says {header.body_size}",
                    offset=n,
                )
            self.completed += 1
            return bytes(memoryview(datagram)[RTP_HEADER_SIZE:])
        if n < RTP_HEADER_SIZE + PREFIX_SIZE:
            raise FragmentError(f"RTP datagram of {n} bytes is shorter than 82", offset=n)
        if header.version != 2:
            raise FragmentError(
                f"RTP fragment with header version {header.version} (the scheme needs 2)",
                offset=RTP_HEADER_SIZE,
                message_type=header.message_type,
                device_name=header.device_name,
            )
        total = header.body_size - wire.EXT_HEADER_SIZE
        if total < 0:
            raise FragmentError(f"BODY_SIZE {header.body_size} < 12", offset=RTP_HEADER_SIZE + 42)
        msg_id, frag = _ID_FRAG.unpack_from(datagram, RTP_HEADER_SIZE + _MSG_ID_OFFSET)
        prefix_end = RTP_HEADER_SIZE + PREFIX_SIZE
        now = self._clock()
        if self._pending:
            self.expire(now)
        if frag == FRAGMENT_NONE:
            if n - prefix_end != total:
                raise FragmentError(
                    f"unfragmented datagram holds {n - prefix_end} body bytes, BODY_SIZE says "
                    f"{total} after the extended header",
                    offset=n,
                )
            out = bytearray(memoryview(datagram)[RTP_HEADER_SIZE:])
            _MSG_ID.pack_into(out, _MSG_ID_OFFSET, msg_id)
            self.completed += 1
            return bytes(out)
        k, is_last = parse_fragment_field(frag)
        key = (sender, ssrc, (seq - k) & 0xFFFF)
        mv = memoryview(datagram)
        head = bytes(mv[RTP_HEADER_SIZE : RTP_HEADER_SIZE + _MSG_ID_OFFSET])
        part = self._fragment_slot(key, head, msg_id, total, now)
        if k in part.chunks:
            self.duplicates += 1
            return None
        return self._add_fragment(key, part, k, is_last, mv[prefix_end:], n)

    def _fragment_slot(
        self, key: tuple[Any, ...], head: bytes, msg_id: int, total: int, now: float
    ) -> _Partial:
        """The incomplete message a fragment belongs to: the one held under ``key`` when its
        header and message ID match the fragment's, else a new one (replacing a stale one, and
        evicting the oldest while ``max_pending`` are held)."""
        part = self._pending.get(key)
        if part is not None and (
            part.prefix[:_MSG_ID_OFFSET] != head
            or _MSG_ID.unpack_from(part.prefix, _MSG_ID_OFFSET)[0] != msg_id
        ):
            # Same slot, different message: the old set is stale (sender restarted its sequence).
            self._discard(key)
            self.evicted += 1
            part = None
        if part is None:
            while len(self._pending) >= self.max_pending:
                self._discard(next(iter(self._pending)))
                self.evicted += 1
            part = _Partial(head + _MSG_ID.pack(msg_id), total, now)
            self._pending[key] = part
        return part

    def _add_fragment(
        self,
        key: tuple[Any, ...],
        part: _Partial,
        k: int,
        is_last: bool,
        body: memoryview,
        n: int,
    ) -> bytes | None:
        """Store fragment ``k`` (not held yet) of ``part``; return the whole message when it
        completes it, else None (evicting the oldest while over ``max_buffered``). ``body`` is
        the datagram after its prefix, ``n`` the datagram's size (the offset in errors)."""
        prefix_end = RTP_HEADER_SIZE + PREFIX_SIZE
        if is_last:
            if part.last is not None or (part.chunks and max(part.chunks) > k):
                self._discard(key)
                raise FragmentError(f"conflicting last fragment index {k}", offset=prefix_end)
            part.last = k
        elif part.last is not None and k > part.last:
            self._discard(key)
            raise FragmentError(f"fragment {k} after last fragment {part.last}", offset=prefix_end)
        chunk = bytes(body)
        part.chunks[k] = chunk
        part.size += len(chunk)
        self._buffered += len(chunk)
        if part.size > part.total:
            self._discard(key)
            raise FragmentError(
                f"fragments hold more than the {part.total} body bytes announced", offset=n
            )
        if part.last is not None and len(part.chunks) == part.last + 1:
            self._discard(key)
            if part.size != part.total:
                raise FragmentError(
                    f"fragments hold {part.size} body bytes, BODY_SIZE announces {part.total}",
                    offset=n,
                )
            self.completed += 1
            chunks = part.chunks
            return part.prefix + b"".join(chunks[i] for i in range(len(chunks)))
        while self._buffered > self.max_buffered and self._pending:
            oldest = next(iter(self._pending))
            self._discard(oldest)
            self.evicted += 1
        return None
