"""igtl.rtp: the reference library's RTP fragmentation, sans-IO.

The reference datagrams come from the OpenIGTLink project's own test data
(Testing/igtlutil/igtl_test_data_rtpwrapper.h, github.com/openigtlink/OpenIGTLink, BSD-style
licence, Copyright Insight Software Consortium), shipped as tests/data/igtl-vectors/rtpwrapper.bin.
"""

from __future__ import annotations

import itertools
import struct
from pathlib import Path

import pytest

import igtl
from igtl import rtp, wire
from igtl.errors import DecodeError

VECTORS = Path(__file__).resolve().parents[1] / "data" / "igtl-vectors"
RTP_VECTOR = VECTORS / "rtpwrapper.bin"


@pytest.fixture(scope="module")
def reference_datagrams() -> list[bytes]:
    data = RTP_VECTOR.read_bytes()
    assert len(data) == 1312 + 1312 + 251
    return [data[:1312], data[1312:2624], data[2624:]]


def _message(size: int, message_id: int = 7, device: str = "Frag") -> bytes:
    content = bytes((i * 7) & 0xFF for i in range(size))
    return igtl.RawMessage(
        type_name="BLOB",
        content=content,
        device_name=device,
        header_version=2,
        message_id=message_id,
        metadata={"k": "v"},
    ).pack()


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


# ------------------------------------------------------------------------- reference vector
def test_reference_vector_reassembles_to_crc_valid_image(reference_datagrams):
    reasm = rtp.Reassembler()
    assert reasm.feed(reference_datagrams[0], "x") is None
    assert reasm.feed(reference_datagrams[1], "x") is None
    whole = reasm.feed(reference_datagrams[2], "x")
    assert whole is not None and len(whole) == 2699
    header = wire.unpack_header(whole)
    assert (header.version, header.message_type, header.body_size) == (2, "IMAGE", 2641)
    assert wire.crc64(whole[58:]) == header.crc == 0xC2E2D852FC02054B
    assert whole[66:70] == b"\x00\x00\x00\x01"  # MSG_ID restored
    msg = igtl.unpack(whole)  # IMAGE may still be a RawMessage: compare bytes, not the class
    assert msg.message_id == 1
    assert dict(msg.metadata) == {"First patient age": "22", "Second patient age": "25"}
    assert msg.pack() == whole
    assert reasm.stats["completed"] == 1 and reasm.pending == 0 and reasm.buffered == 0


def test_fragmenting_reproduces_reference_datagrams(reference_datagrams):
    reasm = rtp.Reassembler()
    whole = [reasm.feed(d) for d in reference_datagrams][-1]
    assert whole is not None
    out = rtp.fragment(whole, payload_length=1300, payload_type=0, ssrc=0, seq_start=0)
    assert [len(d) for d in out] == [1312, 1312, 251]
    for ours, ref in zip(out, reference_datagrams, strict=True):
        assert ours[:4] == ref[:4]
        assert ours[8:] == ref[8:]  # bytes 4..7: wall-clock RTP timestamp, not compared
    assert [d[78:82].hex() for d in out] == ["00018000", "00018001", "0001e002"]


# ------------------------------------------------------------------------- fragment()
def test_fragment_header_fields_and_timestamp():
    data = _message(5000, message_id=0x1234)
    out = rtp.fragment(
        data,
        seq_start=0xFFFE,
        payload_type=96,
        ssrc=0xDEADBEEF,
        payload_length=1000,
        timestamp=0x1_2345_6789,
    )
    assert len(out) == -(-(len(data) - 70) // 930)
    for k, d in enumerate(out):
        first, pt, seq, ts, ssrc = rtp.RTP_HEADER.unpack_from(d)
        assert (first, pt, ssrc, ts) == (0x80, 96, 0xDEADBEEF, 0x2345_6789)
        assert seq == (0xFFFE + k) & 0xFFFF  # wraps
        assert d[12:78] == data[:66]  # header + ext header up to MSG_ID, unchanged
        msg_id, _frag = struct.unpack_from(">HH", d, 78)
        assert msg_id == 0x1234
        assert len(d) <= 12 + 1000
    assert [struct.unpack_from(">H", d, 80)[0] for d in out] == (
        [0x8000] + [0x8000 + k for k in range(1, len(out) - 1)] + [0xE000 + len(out) - 1]
    )


def test_fragment_small_message_is_one_unfragmented_datagram():
    data = _message(10)
    (d,) = rtp.fragment(data)
    assert d[78:82] == b"\x00\x07\x00\x00"  # 16-bit message id 7, FRAGMENT 0x0000
    assert d[12:78] == data[:66] and d[82:] == data[70:]
    assert rtp.Reassembler().feed(d) == data


def test_rtp_timestamp_is_100hz_clock():
    assert rtp.rtp_timestamp(1000.25) == 100025
    assert rtp.rtp_timestamp(2**32) == (100 * 2**32) & 0xFFFFFFFF


@pytest.mark.parametrize(
    "data, kwargs",
    [
        (igtl.StringMessage(string="v1").pack(), {}),  # header version 1
        (_message(10, message_id=0x10000), {}),  # message id does not fit 16 bits
        (_message(10), {"payload_length": 70}),  # no room for body bytes
        (_message(10)[:-1], {}),  # inconsistent BODY_SIZE
        (_message(9000), {"payload_length": 71}),  # 1 byte per fragment: > 8192 fragments
        (b"\x00\x02" + bytes(30), {}),  # too short
    ],
    ids=["v1", "id-too-big", "no-room", "bad-size", "too-many-fragments", "too-short"],
)
def test_fragment_refuses_what_the_scheme_cannot_carry(data, kwargs):
    with pytest.raises(ValueError):
        rtp.fragment(data, **kwargs)


# ------------------------------------------------------------------------- Reassembler
@pytest.mark.parametrize("size", [0, 1, 929, 930, 931, 1860, 5000])
def test_round_trip_sizes(size):
    data = _message(size)
    out = rtp.fragment(data, payload_length=1000)
    reasm = rtp.Reassembler()
    results = [reasm.feed(d, "a") for d in out]
    assert results[:-1] == [None] * (len(out) - 1)
    assert results[-1] == data
    assert igtl.unpack(results[-1]).pack() == data


def test_any_arrival_order_and_duplicates():
    data = _message(3000)
    out = rtp.fragment(data, payload_length=1000)
    assert len(out) == 4
    for order in itertools.permutations(range(4)):
        reasm = rtp.Reassembler()
        results = []
        for i in order:
            results.append(reasm.feed(out[i], "a"))
            if i == order[0]:
                assert reasm.feed(out[i], "a") is None  # duplicate ignored
        assert results[-1] == data and results[:-1] == [None] * 3
        assert reasm.duplicates == 1 and reasm.pending == 0


def test_interleaved_messages_with_same_id_and_senders_do_not_mix():
    a = _message(2500, message_id=0, device="A")
    b = _message(2500, message_id=0, device="B")
    fa = rtp.fragment(a, payload_length=1000, seq_start=10)
    fb = rtp.fragment(b, payload_length=1000, seq_start=10 + len(fa))
    fc = rtp.fragment(b, payload_length=1000, seq_start=10)  # other sender, same seq as fa
    reasm = rtp.Reassembler()
    done = []
    for x, y, z in zip(fa, fb, fc, strict=True):
        for d, sender in ((x, "s1"), (y, "s1"), (z, "s2")):
            r = reasm.feed(d, sender)
            if r is not None:
                done.append(r)
    assert sorted(done) == sorted([a, b, b])


def test_incomplete_messages_expire():
    clock = Clock()
    reasm = rtp.Reassembler(timeout=0.5, clock=clock)
    out = rtp.fragment(_message(3000), payload_length=1000)
    reasm.feed(out[0], "a")
    reasm.feed(out[1], "a")
    assert reasm.pending == 1 and reasm.buffered == 2 * 930
    clock.now += 0.4
    assert reasm.expire() == 0
    clock.now += 0.2
    assert reasm.expire() == 1
    assert reasm.pending == 0 and reasm.buffered == 0 and reasm.expired == 1
    # The rest alone never completes; it expires in turn (checked on the next feed too).
    assert reasm.feed(out[2], "a") is None and reasm.feed(out[3], "a") is None
    clock.now += 1.0
    reasm.feed(rtp.fragment(_message(10))[0], "a")
    assert reasm.pending == 0 and reasm.expired == 2


def test_pending_and_memory_limits_evict_oldest():
    reasm = rtp.Reassembler(max_pending=2, max_buffered=10_000)
    firsts = [
        rtp.fragment(_message(3000, message_id=i), payload_length=1000, seq_start=100 * i)[0]
        for i in range(3)
    ]
    for d in firsts:
        reasm.feed(d, "a")
    assert reasm.pending == 2 and reasm.evicted == 1
    big = rtp.fragment(_message(40_000), payload_length=8000, seq_start=1000)
    reasm.feed(big[0], "a")
    reasm.feed(big[1], "a")
    assert reasm.buffered <= 10_000 and reasm.evicted >= 3


def _corrupt(d: bytes, offset: int, value: bytes) -> bytes:
    return d[:offset] + value + d[offset + len(value) :]


@pytest.mark.parametrize(
    "mutate",
    [
        lambda d: d[:50],  # too short
        lambda d: _corrupt(d, 0, b"\x90"),  # RTP with extension bit
        lambda d: _corrupt(d, 12, b"\x00\x01"),  # header version 1 inside
        lambda d: _corrupt(d, 12, b"\x00\x09"),  # unknown header version
        lambda d: _corrupt(d, 80, b"\x40\x00"),  # FRAGMENT without the top bit
        lambda d: _corrupt(d, 80, b"\xe0\x00"),  # "last" fragment with index 0
        lambda d: _corrupt(d, 80, b"\x00\x00"),  # claims unfragmented, holds a slice
    ],
    ids=[
        "short",
        "rtp-extension",
        "v1-inside",
        "bad-version",
        "bad-fragment",
        "last-0",
        "not-whole",
    ],
)
def test_bad_datagrams_raise_recoverable_fragment_error(mutate):
    out = rtp.fragment(_message(3000), payload_length=1000)
    reasm = rtp.Reassembler()
    with pytest.raises(rtp.FragmentError) as info:
        reasm.feed(mutate(out[0]), "a")
    assert isinstance(info.value, DecodeError) and info.value.recoverable
    assert reasm.errors == 1
    # The reassembler is still usable afterwards.
    results = [reasm.feed(d, "b") for d in out]
    assert results[-1] is not None


def test_fragments_that_do_not_add_up_are_refused():
    out = rtp.fragment(_message(3000), payload_length=1000)
    reasm = rtp.Reassembler()
    for d in out[:-1]:
        reasm.feed(d, "a")
    with pytest.raises(rtp.FragmentError):
        reasm.feed(out[-1][:-5], "a")  # last chunk short
    assert reasm.pending == 0 and reasm.buffered == 0
    reasm.feed(out[0], "b")
    with pytest.raises(rtp.FragmentError):
        reasm.feed(out[1] + bytes(2000), "b")  # more bytes than BODY_SIZE announces
    assert reasm.pending == 0


def test_body_size_limit_applies_before_buffering():
    out = rtp.fragment(_message(3000), payload_length=1000)
    reasm = rtp.Reassembler(max_body_size=1000)
    with pytest.raises(rtp.FragmentError):
        reasm.feed(out[0], "a")
    assert reasm.pending == 0


def test_a_header_version_1_message_in_an_rtp_datagram_is_taken_whole() -> None:
    """What the reference's UDP example sends: a v1 TDATA after a 12-byte RTP header."""
    from igtl.rtp import RTP_HEADER, Reassembler

    v1 = (VECTORS / "tdata.bin").read_bytes()
    datagram = RTP_HEADER.pack(0x80, 96, 7, 123456, 0) + v1
    out = Reassembler().feed(datagram, ("127.0.0.1", 1))
    assert out == v1  # untouched: a v1 message has no fragment field to rewrite
    msg = igtl.unpack(out)
    assert msg.message_type == "TDATA" and msg.header_version == 1
    with pytest.raises(DecodeError):  # a truncated one is refused with the reason
        Reassembler().feed(datagram[:-1], ("127.0.0.1", 1))
