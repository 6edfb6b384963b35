"""Message authentication with a shared key: an HMAC carried in header-version-2 metadata.

OpenIGTLink has no authentication: on a network that is not trusted, anyone who can reach a
port can send a plausible stream. Where both ends share a secret key, the sender adds the
metadata entry ``HMAC`` to every message; the receiver recomputes it and refuses a message
whose tag is missing or wrong. The tag is HMAC-SHA256 (RFC 2104), cut to 128 bits (RFC 2104
§5 allows truncation to at least half the hash) and written as 32 lower-case hex digits, over
the message exactly as packed *without* the ``HMAC`` entry: header (type, device name,
timestamp, CRC), message ID, content and every other metadata entry. Anything a peer changes
is therefore covered; replays of a whole message are left to the receiver's sequence and
timestamp checks (the message ID and timestamp are covered, so they cannot be altered): a
stream's sequence numbers, and for requests :class:`ReplayGuard` (each tag obeyed once, within
a window of the receiver's clock). :func:`sign` stamps a message that has no timestamp yet.

Peers that do not know the key see an ordinary v2 message with one more metadata entry
(OpenIGTLinkIO and PLUS ignore entries they do not use).

Only header version 2 carries metadata: a signed message is always version 2, and a
version-1 message is never authentic.
"""

from __future__ import annotations

import dataclasses
import hashlib
import hmac
import time
from collections import deque

from .messages.base import Message

#: The metadata key that carries the tag.
HMAC_KEY = "HMAC"
#: Bytes of the SHA-256 tag kept (hex digits: twice that).
TAG_BYTES = 16


def _tag(key: bytes, msg: Message) -> str:
    meta = msg.metadata
    if HMAC_KEY in meta:
        meta = {k: v for k, v in meta.items() if k != HMAC_KEY}
    data = msg.pack(metadata=meta)
    return hmac.new(key, data, hashlib.sha256).digest()[:TAG_BYTES].hex()


def sign(msg: Message, key: bytes) -> Message:
    """A copy of ``msg`` carrying its tag in the ``HMAC`` metadata entry (a version-1 message
    becomes version 2: only version 2 has metadata)."""
    if msg.header_version != 2:
        msg = dataclasses.replace(msg, header_version=2)
    if not msg.timestamp > 0.0:  # when it was sent: the receiver's freshness check reads it
        msg = dataclasses.replace(msg, timestamp=time.time())
    meta = {k: v for k, v in msg.metadata.items() if k != HMAC_KEY}
    meta[HMAC_KEY] = _tag(key, msg)
    return dataclasses.replace(msg, metadata=meta)


def verify(msg: Message, key: bytes) -> str:
    """``''`` when ``msg`` carries a valid tag for ``key``, else why it does not."""
    if msg.header_version != 2:
        return "header version 1 carries no HMAC"
    tag = msg.metadata.get(HMAC_KEY)
    if tag is None:
        return "no HMAC"
    if not hmac.compare_digest(str(tag).encode("ascii", "replace"), _tag(key, msg).encode()):
        return "wrong HMAC"
    return ""


class ReplayGuard:
    """Signed requests obeyed once: a tag seen before is a replay, and so is a timestamp more
    than ``max_age_s`` from the receiver's clock (past or future) or older than the tags it
    had to forget.

    A tag cannot be made without the key, so the memory holds genuine requests only: those
    of the last ``max_age_s`` (older ones are refused by their age anyway), at most
    ``capacity``; past that the oldest is forgotten and nothing signed before it is taken
    again. The clocks of both ends must agree within ``max_age_s`` (NTP on a lab network).
    """

    def __init__(self, max_age_s: float = 30.0, capacity: int = 4096) -> None:
        if not max_age_s > 0.0 or capacity < 1:
            raise ValueError("max_age_s must be > 0 and capacity >= 1")
        self.max_age_s = float(max_age_s)
        self.capacity = int(capacity)
        self._seen: set[str] = set()
        self._order: deque[tuple[float, str]] = deque()
        #: nothing signed at or before this time is taken (tags forgotten for room)
        self._floor = 0.0
        self.refused = 0

    def check(self, msg: Message, now: float) -> str:
        """``''`` for a signed request seen for the first time within the window (then
        remembered), else why it is refused. ``now``: the receiver's wall clock (Unix s);
        ``msg`` has a valid tag already."""
        why = self._why(msg, now)
        if why:
            self.refused += 1
        return why

    def _why(self, msg: Message, now: float) -> str:
        ts = msg.timestamp
        limit = self.max_age_s
        if not ts > 0.0:
            return "a signed request must carry the time it was sent (header timestamp 0)"
        age = now - ts
        if age > limit:
            return f"signed {age:.1f} s ago (at most {limit:g} s): a replay, or the clocks disagree"
        if -age > limit:
            return (
                f"signed {-age:.1f} s ahead of this clock (at most {limit:g} s): "
                "the clocks disagree"
            )
        if ts <= self._floor:
            return "signed before requests already forgotten: a replay"
        tag = str(msg.metadata.get(HMAC_KEY, ""))
        if tag in self._seen:
            return "a replay: this signed request was taken already"
        seen, order = self._seen, self._order
        while order and (order[0][0] < now - limit or len(order) >= self.capacity):
            old_ts, old_tag = order.popleft()
            seen.discard(old_tag)
            if old_ts >= now - limit:  # forgotten for room while still in the window
                self._floor = max(self._floor, old_ts)
        seen.add(tag)
        order.append((ts, tag))
        return ""


def load_key(text: str) -> bytes:
    """A key from the text of a key file: the first line, stripped; ``hex:`` for hex bytes.

    Raises ValueError when it is empty or shorter than 16 bytes (128 bits, the tag's
    strength).
    """
    line = text.strip().splitlines()[0].strip() if text.strip() else ""
    key = bytes.fromhex(line[4:]) if line.startswith("hex:") else line.encode("utf-8")
    if len(key) < 16:
        raise ValueError(f"the key must be at least 16 bytes, got {len(key)}")
    return key
