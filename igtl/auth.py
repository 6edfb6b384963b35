"""Message authentication with a shared key: an HMAC carried in header-version-2 metadata.

OpenIGTLink has no authentication: on a network that is not trusted, anyone who can reach a
port can send a plausible stream. Where both ends share a secret key, the sender adds the
metadata entry ``HMAC`` to every message; the receiver recomputes it and refuses a message
whose tag is missing or wrong. The tag is HMAC-SHA256 (RFC 2104), cut to 128 bits (RFC 2104
§5 allows truncation to at least half the hash) and written as 32 lower-case hex digits, over
the message exactly as packed *without* the ``HMAC`` entry: header (type, device name,
timestamp, CRC), message ID, content and every other metadata entry. Anything a peer changes
is therefore covered; replays of a whole message are left to the receiver's sequence and
timestamp checks (the message ID and timestamp are covered, so they cannot be altered).

Peers that do not know the key see an ordinary v2 message with one more metadata entry
(OpenIGTLinkIO and PLUS ignore entries they do not use).

Only header version 2 carries metadata: a signed message is always version 2, and a
version-1 message is never authentic.
"""

from __future__ import annotations

import dataclasses
import hashlib
import hmac

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
