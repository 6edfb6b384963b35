"""Wire layer: CRC-64, timestamps, header, metadata (protocol doc sections 1 and 2).

The header vector ``barray`` is from the OpenIGTLink project's ``igtl_header_test.c``
(github.com/openigtlink/OpenIGTLink, BSD-style licence, Copyright Insight Software Consortium).
"""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from igtl import wire
from igtl.errors import (
    BodyTooLargeError,
    ExtendedHeaderError,
    MetadataError,
    TruncatedMessageError,
    UnknownHeaderVersionError,
)

from .conftest import VECTORS_DIR

BARRAY = bytes.fromhex(
    "00 01 54 59 50 45 4e 41 4d 45 00 00 00 00 44 65 76 69 63 65 4e 61 6d 65 00 00 00 00 00 00"
    "00 00 00 00 00 00 00 00 49 96 02 d2 00 00 00 07 50 88 ff 06 00 00 00 00 00 14 7e a7"
)


@pytest.mark.req("SR-CRC-1")
def test_crc_check_value():
    assert wire.crc64(b"123456789") == 0x6C40DF5F0B497347
    assert wire.crc64(b"") == 0
    assert wire.crc64_crcmod(b"123456789") == 0x6C40DF5F0B497347


def test_anycrc_is_in_use():
    """The issue picked anycrc for bodies of CRC_SMALL bytes and more (~30x faster than crcmod
    at 256 KiB, docs/BENCHMARKS.md); a missing anycrc only warns at import, so say it here."""
    assert wire.CRC_BACKEND == "anycrc", "anycrc is missing: big bodies are checksummed by crcmod"


def _crc_bitwise(data: bytes, crc: int = 0) -> int:
    """CRC-64/ECMA-182 from its definition (protocol doc 1.3), bit by bit: the third opinion."""
    for byte in data:
        crc ^= byte << 56
        for _ in range(8):
            crc = ((crc << 1) ^ wire.CRC_POLY) if crc >> 63 else crc << 1
            crc &= 0xFFFFFFFFFFFFFFFF
    return crc


@pytest.mark.parametrize("path", sorted(VECTORS_DIR.glob("*.bin")), ids=lambda p: p.name)
@pytest.mark.req("SR-CRC-1")
def test_crc_backends_agree_on_reference_vectors(path):
    data = path.read_bytes()
    assert wire.crc64(data) == wire.crc64_crcmod(data) == _crc_bitwise(data)
    if path.name == "rtpwrapper.bin":  # RTP fragments, not a message (its CRC: test_rtp.py)
        return
    body_size, crc = struct.unpack_from(">QQ", data, 42)
    body = data[58 : 58 + body_size]
    assert len(body) == body_size
    assert wire.crc64(body) == wire.crc64_crcmod(body) == _crc_bitwise(body) == crc
    # the big-body backend directly, whatever the size (crc64 sends small bodies to crcmod)
    assert wire._crc_big(body, 0) == crc
    for cut in (0, 1, len(body) // 2, len(body)):
        assert wire.crc64(body[cut:], wire.crc64(body[:cut])) == crc


@settings(max_examples=400, deadline=None)
@given(
    st.binary(max_size=300) | st.binary(min_size=3000, max_size=70_000),
    st.integers(0, 2**64 - 1),
    st.data(),
)
def test_crc_backends_agree_on_random_bytes(data, start, draw):
    """anycrc (through crc64 and directly) and crcmod agree on any bytes, any chained start
    value, any bytes-like type, and any split (the incremental check in StreamDecoder)."""
    want = wire.crc64_crcmod(data, start)
    assert wire.crc64(data, start) == want
    assert wire._crc_big(data, start) == want
    assert wire.crc64(bytearray(data), start) == want
    assert wire.crc64(memoryview(data)[1:], wire.crc64(data[:1], start)) == want
    cut = draw.draw(st.integers(0, len(data)))
    assert wire.crc64(memoryview(data)[cut:], wire.crc64(data[:cut], start)) == want
    if len(data) < 300:
        assert _crc_bitwise(data, start) == want


@pytest.mark.parametrize(
    ("ns", "frac"),
    [(500_000_000, 0x80000000), (123_456_789, 0x1F9ADD24), (999_999_999, 0xFFFFFFD8), (0, 0)],
)
def test_nanosec_to_frac_examples(ns, frac):
    assert wire.nanosec_to_frac(ns) == frac
    assert wire.nanosec_to_frac_reference(ns) == frac
    assert wire.frac_to_nanosec(frac) == ns  # round trip


@pytest.mark.parametrize(("frac", "ns"), [(0x499602D4, 287_445_240), (0xFFFFFFFF, 1_000_000_010)])
def test_frac_to_nanosec_examples(frac, ns):
    assert wire.frac_to_nanosec(frac) == ns


def _edges() -> list[int]:
    """Every boundary of the byte tables (where the greedy's choices change), +-2."""
    out = set()
    for table in (wire._T0, wire._T1, wire._T2, wire._T3):
        for v in table:
            for d in (-2, -1, 0, 1, 2):
                if 0 <= v + d < 1_000_000_000:
                    out.add(v + d)
    out.update(range(0, 5000))
    out.update(range(999_995_000, 1_000_000_000))
    return sorted(out)


def test_fast_nanosec_to_frac_matches_greedy_on_edges():
    for ns in _edges():
        assert wire.nanosec_to_frac(ns) == wire.nanosec_to_frac_reference(ns), ns


def test_fast_nanosec_to_frac_matches_greedy_strided():
    # A stride coprime with every table period sweeps all byte positions.
    for ns in range(7, 1_000_000_000, 24989):
        assert wire.nanosec_to_frac(ns) == wire.nanosec_to_frac_reference(ns), ns


@settings(max_examples=3000, deadline=None)
@given(st.integers(0, 999_999_999))
def test_fast_nanosec_to_frac_matches_greedy(ns):
    frac = wire.nanosec_to_frac(ns)
    assert frac == wire.nanosec_to_frac_reference(ns)
    assert wire.frac_to_nanosec(frac) == ns


@settings(max_examples=500, deadline=None)
@given(st.floats(0.0, 4e9, allow_nan=False))
def test_seconds_to_raw_matches_reference(t):
    raw = wire.seconds_to_raw(t)
    if t <= 0:
        assert raw == 0
        return
    sec = int(t)
    ns = round((t - sec) * 1e9)
    if ns >= 1_000_000_000:
        sec, ns = sec + 1, ns - 1_000_000_000
    assert raw == ((sec & 0xFFFFFFFF) << 32) | wire.nanosec_to_frac_reference(ns)


def test_barray_header():
    h = wire.unpack_header(BARRAY, max_body_size=2**64)
    assert h == wire.Header(1, "TYPENAME", "DeviceName", 1234567890, 31415926534, 1343143)
    assert wire.HEADER.pack(1, b"TYPENAME", b"DeviceName", 1234567890, 31415926534,
                            1343143) == BARRAY


@pytest.mark.req("SR-SIZE-1")
def test_barray_rejected_by_default_limit():
    with pytest.raises(BodyTooLargeError) as e:
        wire.unpack_header(BARRAY)
    assert e.value.offset == 42 and e.value.message_type == "TYPENAME"


def test_header_errors():
    with pytest.raises(TruncatedMessageError):
        wire.unpack_header(BARRAY[:57])
    with pytest.raises(UnknownHeaderVersionError) as e:
        wire.unpack_header(b"\x00\x03" + BARRAY[2:], max_body_size=2**64)
    assert e.value.offset == 0


def test_full_names_without_terminator():
    raw = wire.HEADER.pack(1, b"ABCDEFGHIJKL", b"D" * 20, 0, 0, 0)
    h = wire.unpack_header(raw)
    assert (h.message_type, h.device_name) == ("ABCDEFGHIJKL", "D" * 20)
    assert wire.pack_header(1, "ABCDEFGHIJKL", "D" * 20, 0, b"") == raw


def test_pack_header_rejects_long_names():
    with pytest.raises(ValueError, match="device name"):
        wire.pack_header(1, "T", "D" * 21, 0, b"")
    with pytest.raises(ValueError, match="message type"):
        wire.pack_header(1, "T" * 13, "D", 0, b"")


# -------------------------------------------------------------------------------- metadata
def test_metadata_sorted_and_counted():
    head, data = wire.pack_metadata({"b": "2", "a": ""}, {})
    assert head == bytes.fromhex("0002" "0001 0003 00000000" "0001 0003 00000001")
    assert data == b"ab2"
    assert wire.unpack_metadata(head, data) == ({"a": "", "b": "2"}, {})


def test_metadata_empty_always_has_count():
    assert wire.pack_metadata({}, {}) == (b"\x00\x00", b"")
    assert wire.unpack_metadata(b"\x00\x00", b"") == ({}, {})
    assert wire.unpack_metadata(b"", b"") == ({}, {})


def test_metadata_non_ascii_and_explicit_encoding():
    head, data = wire.pack_metadata({"Név": "Größe", "k": "v"}, {"k": 106})
    values, enc = wire.unpack_metadata(head, data)
    assert values == {"Név": "Größe", "k": "v"}
    assert enc == {"k": 106}  # UTF-8 on an ASCII value is not the default: kept


def test_metadata_unknown_encoding_round_trips():
    head = bytes.fromhex("0001" "0001 2710 00000002")  # encoding 10000: unknown
    values, enc = wire.unpack_metadata(head, b"k\xff\x01")
    assert values == {"k": "\xff\x01"} and enc == {"k": 10000}
    assert wire.pack_metadata(values, enc) == (head, b"k\xff\x01")


@pytest.mark.parametrize(
    ("head", "data", "match"),
    [
        (b"\x00", b"", "index count"),
        (bytes.fromhex("0002 0001 0003 00000001"), b"ab", "needs 18"),
        (bytes.fromhex("0001 0001 0003 00000005"), b"ab", "entry 0"),
        (bytes.fromhex("0001 0001 0003 00000001"), b"abc", "META_DATA_SIZE"),
        (bytes.fromhex("0001 0001 0003 00000001"), b"\xffa", "UTF-8"),
        (bytes.fromhex("0001 0001 0003 00000001"), b"a\xff", "encoding 3"),
    ],
)
def test_metadata_errors(head, data, match):
    with pytest.raises(MetadataError, match=match) as e:
        wire.unpack_metadata(head, data, base_offset=100)
    assert e.value.offset is not None and e.value.offset >= 100


def test_metadata_caller_errors():
    with pytest.raises(TypeError):
        wire.pack_metadata({"k": 1}, {})  # type: ignore[dict-item]
    with pytest.raises(ValueError):
        wire.pack_metadata({"k": "é"}, {"k": 3})
    with pytest.raises(ValueError):
        wire.pack_metadata({"k": "v"}, {"k": 70000})


def test_metadata_repeat_is_cached_and_bounded():
    """A stream's metadata repeats every message; the cache returns the same bytes, keys in
    either order give the same wire form, and a peer varying its values cannot grow it."""
    first = wire.pack_metadata({"run": "1", "clutch": "0"}, {})
    assert wire.pack_metadata({"run": "1", "clutch": "0"}, {}) == first
    assert wire.pack_metadata({"clutch": "0", "run": "1"}, {}) == first
    assert wire.unpack_metadata(*first) == ({"clutch": "0", "run": "1"}, {})
    for i in range(1000):
        assert wire.unpack_metadata(*wire.pack_metadata({"n": str(i)}, {}))[0] == {"n": str(i)}
    assert len(wire._META_CACHE) <= 256
    with pytest.raises(TypeError):  # unhashable value: the usual error, not a cache error
        wire.pack_metadata({"k": ["v"]}, {})  # type: ignore[dict-item]


def test_split_v2_body():
    body = wire.EXT_HEADER.pack(12, 2, 0, 7) + b"content" + b"\x00\x00"
    assert wire.split_v2_body(body) == wire.BodyLayout(12, 19, 2, 0, 7)
    with pytest.raises(ExtendedHeaderError):
        wire.split_v2_body(body[:11])
    with pytest.raises(ExtendedHeaderError):
        wire.split_v2_body(wire.EXT_HEADER.pack(8, 0, 0, 0))
    with pytest.raises(ExtendedHeaderError):
        wire.split_v2_body(wire.EXT_HEADER.pack(12, 2, 100, 0) + b"\0\0")


def test_crcmod_c_extension_is_in_use() -> None:
    """The issue requires crcmod's C extension (25-40x faster than its Python fallback); the
    test install compiles it from source with gcc where no wheel fits. Fails loudly otherwise."""
    assert wire.CRC_ACCELERATED, "crcmod's C extension is missing: CRC-64 runs in pure Python"
