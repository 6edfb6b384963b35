"""igtl.auth: HMAC tags in v2 metadata; anything changed, added or removed is refused."""

from __future__ import annotations

import dataclasses

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import igtl
from igtl.auth import HMAC_KEY, load_key, sign, verify

KEY = b"0123456789abcdef0123"


def position(seq: int = 7, ts: float = 1_700_000_000.25, run: str = "1") -> igtl.Message:
    return igtl.PositionMessage(
        (1.0, -2.5, 30.0),
        (0.0, 0.0, 0.0, 1.0),
        24,
        device_name="Master",
        header_version=2,
        message_id=seq,
        timestamp=ts,
        metadata={"run": run, "clutch": "0"},
    )


def test_signed_message_verifies_after_the_wire() -> None:
    signed = sign(position(), KEY)
    assert len(signed.metadata[HMAC_KEY]) == 32
    assert verify(igtl.unpack(signed.pack()), KEY) == ""


def test_version_1_message_is_promoted() -> None:
    m = igtl.TransformMessage.from_matrix([[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    assert m.header_version == 1
    signed = sign(m, KEY)
    assert signed.header_version == 2 and verify(igtl.unpack(signed.pack()), KEY) == ""
    assert verify(m, KEY) == "header version 1 carries no HMAC"


def test_refusals_say_why() -> None:
    assert verify(position(), KEY) == "no HMAC"
    assert verify(igtl.unpack(sign(position(), KEY).pack()), b"another key, 16+") == "wrong HMAC"


@settings(max_examples=200, deadline=None)
@given(
    field=st.sampled_from(["message_id", "timestamp", "device_name", "position", "run", "extra"]),
    seq=st.integers(0, 2**32 - 2),
)
def test_any_change_is_refused(field: str, seq: int) -> None:
    signed = igtl.unpack(sign(position(seq=seq), KEY).pack())
    if field == "message_id":
        forged = dataclasses.replace(signed, message_id=seq + 1)
    elif field == "timestamp":
        forged = dataclasses.replace(signed, timestamp=signed.timestamp + 1.0)
    elif field == "device_name":
        forged = dataclasses.replace(signed, device_name="Mastes")
    elif field == "position":
        forged = dataclasses.replace(signed, position=(1.0, -2.5, 31.0))
    else:
        meta = dict(signed.metadata)
        if field == "run":
            meta["run"] = "0"
        else:
            meta["x"] = "1"
        forged = dataclasses.replace(signed, metadata=meta)
    assert verify(igtl.unpack(forged.pack()), KEY) == "wrong HMAC"


def test_load_key() -> None:
    assert load_key("a key of twenty bytes\nignored") == b"a key of twenty bytes"
    assert load_key("hex:" + "ab" * 16) == bytes([0xAB] * 16)
    with pytest.raises(ValueError, match="at least 16 bytes"):
        load_key("short")
    with pytest.raises(ValueError, match="at least 16 bytes"):
        load_key("")
