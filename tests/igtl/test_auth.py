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


@pytest.mark.req("SR-SEC-3")
def test_version_1_message_is_promoted() -> None:
    m = igtl.TransformMessage.from_matrix([[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    assert m.header_version == 1
    signed = sign(m, KEY)
    assert signed.header_version == 2 and verify(igtl.unpack(signed.pack()), KEY) == ""
    assert verify(m, KEY) == "header version 1 carries no HMAC"


@pytest.mark.req("SR-SEC-3")
def test_refusals_say_why() -> None:
    assert verify(position(), KEY) == "no HMAC"
    assert verify(igtl.unpack(sign(position(), KEY).pack()), b"another key, 16+") == "wrong HMAC"


@pytest.mark.req("SR-SEC-3")
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


def _with_tag(msg: igtl.Message, tag: str) -> igtl.Message:
    return dataclasses.replace(msg, metadata={**msg.metadata, HMAC_KEY: tag})


@pytest.mark.req("SR-SEC-3")
def test_a_tag_that_is_not_ascii_is_wrong_not_an_error() -> None:
    """Metadata is UTF-8 text from the peer: a tag with characters outside ASCII is a wrong
    tag (refused and counted by the interface), never an exception in its I/O thread."""
    signed = sign(position(), KEY)
    good = signed.metadata[HMAC_KEY]
    for tag in ("é" * 32, good[:-1] + "é", "\udcff" * 32, "ß" + good[1:]):
        forged = _with_tag(signed, tag)
        assert verify(forged, KEY) == "wrong HMAC"
        # and as it arrives: decoded from the wire
        if "\udcff" not in tag:
            assert verify(igtl.unpack(forged.pack()), KEY) == "wrong HMAC"


@pytest.mark.req("SR-SEC-3")
def test_a_truncated_padded_or_recased_tag_is_wrong() -> None:
    signed = sign(position(), KEY)
    good = signed.metadata[HMAC_KEY]
    assert good == good.lower() and len(good) == 32
    for tag in (
        good[:31],
        good[:16],
        good[:1],
        "",
        good + "0",
        good.upper(),
        " " + good,
        good[1:] + good[0],
    ):
        assert verify(igtl.unpack(_with_tag(signed, tag).pack()), KEY) == "wrong HMAC", tag
    assert verify(igtl.unpack(_with_tag(signed, good).pack()), KEY) == ""


@pytest.mark.req("SR-SEC-3")
def test_a_tag_taken_from_another_message_is_wrong() -> None:
    first, second = sign(position(seq=1), KEY), sign(position(seq=2), KEY)
    moved = _with_tag(second, first.metadata[HMAC_KEY])
    assert verify(igtl.unpack(moved.pack()), KEY) == "wrong HMAC"


def test_signing_twice_keeps_one_tag_and_replaces_it() -> None:
    once = sign(position(), KEY)
    twice = sign(once, KEY)
    other = sign(once, b"another key, 16+")
    assert list(twice.metadata).count(HMAC_KEY) == 1 and twice.metadata == once.metadata
    assert verify(other, b"another key, 16+") == "" and verify(other, KEY) == "wrong HMAC"
    assert {k: v for k, v in other.metadata.items() if k != HMAC_KEY} == {"run": "1", "clutch": "0"}


def test_a_replayed_message_verifies_again_the_receiver_judges_replays() -> None:
    """The tag proves who made a message, not when: the same bytes verify every time. A replay
    of a stream sample is the loss monitor's (a duplicate number); see SR-SEC-3."""
    wire_bytes = sign(position(seq=9), KEY).pack()
    assert verify(igtl.unpack(wire_bytes), KEY) == verify(igtl.unpack(wire_bytes), KEY) == ""


def test_load_key_says_how_long_a_refused_key_is() -> None:
    with pytest.raises(ValueError, match=r"^the key must be at least 16 bytes, got 0$"):
        load_key("")
    with pytest.raises(ValueError, match=r"^the key must be at least 16 bytes, got 0$"):
        load_key("  \n\t\n")
    with pytest.raises(ValueError, match=r"^the key must be at least 16 bytes, got 15$"):
        load_key("hex:" + "ab" * 15)
    with pytest.raises(ValueError, match=r"^the key must be at least 16 bytes, got 15$"):
        load_key("fifteen bytes!!")
    # the first line that is not blank, stripped; the rest ignored
    assert load_key("\n\n  a key of 19 bytes \t\nsecond line") == b"a key of 19 bytes"
    assert load_key("sixteen bytes!!!") == b"sixteen bytes!!!"
    # UTF-8: a 16-byte key of 8 characters
    assert load_key("éééééééé") == "éééééééé".encode()


def test_sign_stamps_a_message_without_a_time_and_keeps_one_it_has() -> None:
    import time

    before = time.time()
    stamped = sign(dataclasses.replace(position(), timestamp=0.0), KEY)
    assert before <= stamped.timestamp <= time.time() + 1e-3
    assert verify(stamped, KEY) == ""  # the stamp is under the tag
    assert sign(position(), KEY).timestamp == pytest.approx(1_700_000_000.25, abs=1e-9)
    assert sign(position(ts=0.5), KEY).timestamp == 0.5  # any time given is kept


def _request(mid: int, ts: float) -> igtl.Message:
    msg = igtl.CommandMessage(
        command_id=mid, command_name="Run", command="", header_version=2, message_id=mid,
        timestamp=ts,
    )
    return sign(msg, KEY)


@pytest.mark.req("SR-SEC-7")
def test_the_replay_guard_takes_a_request_once_within_its_window() -> None:
    from igtl.auth import ReplayGuard

    now = 1_800_000_000.0
    g = ReplayGuard(max_age_s=30.0)
    first = _request(1, now - 1.0)
    assert g.check(first, now) == ""
    assert g.check(first, now + 5.0) == "a replay: this signed request was taken already"
    assert g.check(_request(2, now - 1.0), now) == ""  # another request, same second
    assert g.check(_request(3, now - 30.0), now) == ""  # the window's edge is in it
    assert g.check(_request(4, now - 30.5), now) == (
        "signed 30.5 s ago (at most 30 s): a replay, or the clocks disagree"
    )
    assert g.check(_request(5, now + 31.0), now) == (
        "signed 31.0 s ahead of this clock (at most 30 s): the clocks disagree"
    )
    assert g.check(_request(6, now + 30.0), now) == ""
    assert g.check(dataclasses.replace(first, timestamp=0.0), now) == (
        "a signed request must carry the time it was sent (header timestamp 0)"
    )
    assert g.refused == 4
    # past the window its age refuses it; the next request taken forgets what aged out
    assert g.check(first, now + 40.0).startswith("signed 41.0 s ago")
    assert g.check(_request(7, now + 40.0), now + 40.0) == ""
    assert first.metadata[HMAC_KEY] not in g._seen and len(g._seen) == 2  # 6's, 7's
    with pytest.raises(ValueError, match=r"^max_age_s must be > 0 and capacity >= 1$"):
        ReplayGuard(max_age_s=0.0)
    with pytest.raises(ValueError, match=r"^max_age_s must be > 0 and capacity >= 1$"):
        ReplayGuard(capacity=0)
    tiny = ReplayGuard(max_age_s=0.5, capacity=1)  # any window, any room
    assert (tiny.max_age_s, tiny.capacity) == (0.5, 1)
    assert (ReplayGuard().max_age_s, ReplayGuard().capacity) == (30.0, 4096)
    # the guard knows no epoch: a clock that starts at 0 works as well as the Unix one
    early = ReplayGuard(max_age_s=30.0)
    assert early.check(_request(1, 0.5), 10.0) == ""
    assert early.check(_request(2, 0.75), 10.0) == ""


@pytest.mark.req("SR-SEC-7")
def test_the_window_edge_is_in_the_window_for_memory_as_for_age() -> None:
    """A request signed exactly ``max_age_s`` ago is taken (its age is not more than the
    window), so its tag must still be remembered at that instant, after a clean-up too."""
    from igtl.auth import ReplayGuard

    now = 1_800_000_000.0
    g = ReplayGuard(max_age_s=30.0)
    edge = _request(1, now - 30.0)
    assert g.check(edge, now - 1.0) == ""
    assert g.check(_request(2, now - 1.0), now) == ""  # a clean-up at the instant the edge is
    assert g.check(edge, now) == "a replay: this signed request was taken already"
    # forgotten for room at the same instant: nothing signed at or before it is taken either
    small = ReplayGuard(max_age_s=30.0, capacity=1)
    assert small.check(edge, now) == ""
    assert small.check(_request(3, now - 1.0), now) == ""  # edge forgotten for room
    assert small.check(edge, now) == "signed before requests already forgotten: a replay"


@pytest.mark.req("SR-SEC-7")
def test_the_replay_guard_forgets_for_room_but_then_takes_nothing_older() -> None:
    from igtl.auth import ReplayGuard

    now = 1_800_000_000.0
    g = ReplayGuard(max_age_s=30.0, capacity=3)
    reqs = [_request(i, now - 10.0 + i) for i in range(5)]
    for r in reqs[:3]:
        assert g.check(r, now) == ""
    assert g.check(reqs[3], now) == ""  # room made: reqs[0] forgotten
    assert len(g._seen) == 3
    # reqs[0] is still in the window, but anything signed at or before it is refused now
    assert g.check(reqs[0], now) == "signed before requests already forgotten: a replay"
    assert g.check(_request(9, now - 10.0), now) == (
        "signed before requests already forgotten: a replay"
    )
    assert g.check(reqs[4], now) == ""
    assert g.check(reqs[1], now) == "signed before requests already forgotten: a replay"
