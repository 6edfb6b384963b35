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
    InvalidTextError,
    MetadataError,
    TruncatedMessageError,
    UnknownHeaderVersionError,
)

from .conftest import VECTORS_DIR


@pytest.fixture(autouse=True)
def cold_caches():
    """Each test starts with the name and metadata memos empty, as a new process does: what
    is checked is the decoding, not a memo filled by an earlier test (a memo hit would hide a
    broken decode: mutation testing, docs/VERIFICATION.md). Repeats are checked in-test."""
    for name in ("_decoded_names", "_encoded_types", "_encoded_devices", "_META_CACHE",
                 "_META_DECODED"):
        memo = getattr(wire, name, None)
        if memo is not None:
            memo.clear()

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
        assert len(wire._META_CACHE) <= 256 and len(wire._META_DECODED) <= 256
    # unhashable value: the usual error, not a cache error
    with pytest.raises(TypeError, match="metadata value for 'k' must be str, got list"):
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


# --------------------------------------------- limits and reports (mutation testing kills)
def test_timestamps_whole_seconds_and_the_carry_into_the_next_second():
    assert wire.raw_to_seconds(5 << 32) == 5.0
    assert wire.raw_to_seconds((5 << 32) | 0x80000000) == 5.5
    assert wire.raw_to_seconds((2**32 - 1) << 32) == float(2**32 - 1)
    # a fraction that rounds to a whole 1e9 ns carries into the seconds
    assert wire.seconds_to_raw(5.9999999999) == 6 << 32
    assert wire.seconds_to_raw(5.999999999) == (5 << 32) | wire.nanosec_to_frac(999_999_999)
    assert wire.seconds_to_raw(0.0) == 0 and wire.seconds_to_raw(-1.0) == 0
    assert wire.seconds_to_raw(7.0) == 7 << 32


def test_fixed_text_fields_exactly():
    assert wire.decode_fixed(b"ABCD") == "ABCD"  # full field, no terminator
    assert wire.decode_fixed(b"AB\0\0") == "AB"
    assert wire.decode_fixed(b"\0\0\0") == ""
    assert wire.decode_fixed(b"D\xe9v\0") == "D\xe9v"  # not UTF-8: latin-1
    for raw, at in ((b"AB\0C", 2), (b"\0C", 0), (b"AB\0\0\0x", 2)):
        with pytest.raises(InvalidTextError) as e:
            wire.decode_fixed(raw, "device name", offset=14)
        assert e.value.offset == 14 + at
        assert str(e.value).startswith("device name: non-NUL bytes after the NUL terminator")
    assert wire.encode_fixed("x" * 20, 20, "device name") == b"x" * 20  # exactly the size
    with pytest.raises(ValueError, match=r"^device name 'xxxxxxxxxxxxxxxxxxxxx' is 21 bytes"):
        wire.encode_fixed("x" * 21, 20, "device name")
    with pytest.raises(ValueError, match=r"^device name 5 is not encodable text"):
        wire.encode_fixed(5, 20, "device name")  # type: ignore[arg-type]


def test_names_decode_right_past_the_memo_bound():
    # more distinct names than the memo holds: every one decodes right, the memo stays bounded
    n = wire._NAME_CACHE_MAX + 100
    for i in range(n):
        for mtype in ("TRANSFORM", f"T{i}"):  # a known type with a new device, then both new
            raw = wire.pack_header(1, mtype, f"dev{i}", 0, b"")
            h = wire.unpack_header(raw)
            assert (h.message_type, h.device_name) == (mtype, f"dev{i}"), i
            assert wire.unpack_header(raw) == h
        assert len(wire._decoded_names) <= wire._NAME_CACHE_MAX
        assert len(wire._encoded_devices) <= wire._NAME_CACHE_MAX


@pytest.mark.req("SR-SIZE-1")
def test_header_errors_say_what_and_where():
    with pytest.raises(TruncatedMessageError) as e:
        wire.unpack_header(b"\0" * 10 + BARRAY[:57], 10)  # 57 bytes from offset 10
    assert "header needs 58 bytes, got 57" in str(e.value) and e.value.offset == 10
    assert wire.unpack_header(b"\0" * 10 + BARRAY, 10, max_body_size=2**64).device_name == (
        "DeviceName")
    with pytest.raises(UnknownHeaderVersionError) as e:
        wire.unpack_header(b"\0" * 5 + b"\x00\x03" + BARRAY[2:], 5, max_body_size=2**64)
    assert "unknown header version 3 (supported: 1, 2)" in str(e.value)
    assert (e.value.offset, e.value.message_type, e.value.device_name) == (
        5, "TYPENAME", "DeviceName")
    with pytest.raises(BodyTooLargeError) as e:
        wire.unpack_header(b"\0" * 5 + BARRAY, 5, max_body_size=31415926533)
    assert "body size 31415926534 exceeds the limit of 31415926533 bytes" in str(e.value)
    assert (e.value.offset, e.value.message_type, e.value.device_name) == (
        5 + 42, "TYPENAME", "DeviceName")
    assert wire.unpack_header(BARRAY, max_body_size=31415926534).body_size == 31415926534


@pytest.mark.parametrize(
    ("field", "raw", "at"),
    [("message type", b"TYPE\0X", 2 + 4), ("device name", b"Dev\0\0Y", 14 + 3)],
)
def test_a_name_with_bytes_after_its_terminator_is_refused_with_its_frame(field, raw, at):
    from igtl.errors import HeaderTextError

    data = bytearray(BARRAY)
    start = 2 if field == "message type" else 14
    data[start : start + len(raw)] = raw
    with pytest.raises(HeaderTextError) as e:
        wire.unpack_header(b"\0" * 3 + bytes(data), 3, max_body_size=2**64)
    assert e.value.offset == 3 + at and e.value.recoverable
    assert e.value.body_size == 31415926534  # the message can be skipped
    assert str(e.value).startswith(f"{field}: non-NUL bytes after the NUL terminator")
    names = ("TYPE", "DeviceName") if field == "message type" else ("TYPENAME", "Dev")
    assert (e.value.message_type, e.value.device_name) == names
    # the size limit still comes first: an oversized body cannot be skipped
    with pytest.raises(BodyTooLargeError):
        wire.unpack_header(bytes(data))


def test_pack_header_names_the_field_too_long():
    with pytest.raises(ValueError, match=r"^device name 'DDDDDDDDDDDDDDDDDDDDD' is 21 bytes"):
        wire.pack_header(1, "T", "D" * 21, 0, b"")
    with pytest.raises(ValueError, match=r"^message type 'TTTTTTTTTTTTT' is 13 bytes"):
        wire.pack_header(1, "T" * 13, "D", 0, b"")
    with pytest.raises(ValueError, match="cannot pack header"):
        wire.pack_header(70000, "T", "D", 0, b"")


def test_unknown_text_encoding_is_named():
    assert wire.codec_for(106) == "utf-8"
    with pytest.raises(ValueError, match=r"unsupported text encoding \(IANA MIBenum\) 9999"):
        wire.codec_for(9999)


def test_metadata_encodings_are_not_mixed_up_by_the_memo():
    plain = wire.pack_metadata({"k": "v"}, {})
    assert plain[0] == bytes.fromhex("0001 0001 0003 00000001")
    assert wire.pack_metadata({"k": "v"}, {"k": 4})[0] == bytes.fromhex("0001 0001 0004 00000001")
    assert wire.pack_metadata({"k": "v"}, {"k": 106})[0] == bytes.fromhex(
        "0001 0001 006a 00000001")
    assert wire.pack_metadata({"k": "v"}, {}) == plain


def test_metadata_limits_exactly():
    # encodings: 0..65535 (unknown codes keep the value as latin-1)
    for enc in (0, 65535):
        head, data = wire.pack_metadata({"k": "v"}, {"k": enc})
        assert head[4:6] == enc.to_bytes(2, "big") and data == b"kv"
    for enc in (-1, 65536):
        with pytest.raises(ValueError, match=f"metadata encoding {enc} for 'k' does not fit"):
            wire.pack_metadata({"k": "v"}, {"k": enc})
    with pytest.raises(ValueError, match="metadata value for 'k' cannot be encoded as 3"):
        wire.pack_metadata({"k": "é"}, {"k": 3})
    with pytest.raises(TypeError, match="metadata key 1 must be str, got int"):
        wire.pack_metadata({1: "v"}, {})  # type: ignore[dict-item]
    with pytest.raises(TypeError, match="metadata value for 'k' must be str, got int"):
        wire.pack_metadata({"k": 1}, {})  # type: ignore[dict-item]
    with pytest.raises(TypeError, match="must be str, got int"):
        wire.pack_metadata({"\ud800": 1}, {})  # type: ignore[dict-item]
    # a key of 65535 bytes fits, one more does not
    assert len(wire.pack_metadata({"k" * 65535: ""}, {})[1]) == 65535
    with pytest.raises(ValueError) as e:
        wire.pack_metadata({"k" * 65536: ""}, {})
    assert str(e.value) == f"metadata key {'k' * 40!r}... is longer than 65535 bytes"


def test_metadata_entry_count_limit_exactly():
    fits = {f"{i:05}": "" for i in range(65535)}
    assert wire.pack_metadata(fits, {})[0][:2] == b"\xff\xff"
    fits["x"] = ""
    with pytest.raises(ValueError, match="65536 metadata entries; at most 65535 fit"):
        wire.pack_metadata(fits, {})


def test_metadata_value_size_limit_exactly():
    # a value's size must fit uint32; a str whose encoding reports that size stands in for
    # the 4 GiB it would take
    class Sized(bytes):
        size = 0

        def __len__(self) -> int:
            return self.size

    class Huge(str):
        def encode(self, *args, **kwargs):  # type: ignore[override]
            out = Sized(b"v")
            out.size = self.size  # type: ignore[attr-defined]
            return out

    at, over = Huge("v"), Huge("v")
    at.size, over.size = 2**32 - 1, 2**32  # type: ignore[attr-defined]
    head, _ = wire.pack_metadata({"k": at}, {"k": 3})
    assert head[6:10] == b"\xff\xff\xff\xff"
    with pytest.raises(ValueError, match="metadata value for 'k' is longer than 2\\*\\*32-1"):
        wire.pack_metadata({"k": over}, {"k": 3})


@pytest.mark.parametrize(
    ("head", "data", "text", "offset"),
    [
        (b"\x00", b"", "metadata header of 1 bytes cannot hold the index count", 100),
        (bytes.fromhex("0002 0001 0003 00000001"), b"ab",
         "metadata index of 2 entries needs 18 bytes, META_HEADER_SIZE is 10", 100),
        (bytes.fromhex("0001 0001 0003 00000005"), b"ab",
         "metadata entry 0 needs bytes up to 6, META_DATA_SIZE is 2", 110),
        (bytes.fromhex("0002 0001 0003 00000001 0001 0003 00000005"), b"abcd",
         "metadata entry 1 needs bytes up to 8", 100 + 18 + 2),
        (bytes.fromhex("0001 0001 0003 00000001"), b"abc",
         "metadata entries hold 2 bytes, META_DATA_SIZE is 3", 112),
        (bytes.fromhex("0002 0001 0003 00000001 0001 0003 00000001"), b"ab\xffa",
         "metadata key 1 is not valid UTF-8", 100 + 18 + 2),
        (bytes.fromhex("0002 0001 0003 00000001 0001 0003 00000001"), b"abc\xff",
         "metadata value of 'c' is not valid in encoding 3 (ascii)", 100 + 18 + 3),
    ],
)
def test_metadata_errors_say_what_and_where(head, data, text, offset):
    with pytest.raises(MetadataError) as e:
        wire.unpack_metadata(head, data, base_offset=100)
    assert text in str(e.value) and e.value.offset == offset


def test_metadata_with_no_entries_and_no_data():
    assert wire.unpack_metadata(b"\x00\x00", b"") == ({}, {})
    assert wire.unpack_metadata(b"\x00\x00", b"") == ({}, {})  # and again, remembered


@pytest.mark.req("SR-SIZE-1")
def test_split_v2_body_limits_exactly():
    bare = wire.EXT_HEADER.pack(12, 0, 0, 5)  # exactly the extended header, nothing else
    assert wire.split_v2_body(bare) == wire.BodyLayout(12, 12, 0, 0, 5)
    fit = wire.EXT_HEADER.pack(12, 2, 0, 0) + b"\0\0"  # metadata header fills the body
    assert wire.split_v2_body(fit) == wire.BodyLayout(12, 12, 2, 0, 0)
    with pytest.raises(ExtendedHeaderError) as e:
        wire.split_v2_body(bare[:11], base_offset=70)
    assert e.value.offset == 70
    assert "header-version-2 body of 11 bytes is shorter than the 12-byte extended header" in (
        str(e.value))
    with pytest.raises(ExtendedHeaderError) as e:
        wire.split_v2_body(wire.EXT_HEADER.pack(11, 0, 0, 0) + b"\0", base_offset=70)
    assert "EXT_HEADER_SIZE 11 is smaller than 12" in str(e.value) and e.value.offset == 70
    over = wire.EXT_HEADER.pack(12, 10, 0, 0) + b"\0" * 3  # 12 + 10 > 15
    with pytest.raises(ExtendedHeaderError) as e:
        wire.split_v2_body(over, base_offset=70)
    assert e.value.offset == 70
    assert "extended header (12) + metadata header (10) + metadata (0) = 22 bytes exceed " \
        "BODY_SIZE 15" in str(e.value)


def test_a_refused_header_names_what_it_can():
    from igtl.errors import HeaderTextError

    # the refused field is read up to its NUL; the other as it is (a full 20-byte name too)
    raw = wire.HEADER.pack(1, b"\0BAD", b"D" * 20, 0, 0, 0)
    with pytest.raises(HeaderTextError) as e:
        wire.unpack_header(raw)
    assert (e.value.message_type, e.value.device_name) == ("", "D" * 20)
    raw = wire.HEADER.pack(1, b"T" * 12, b"Dev\0\xe9", 0, 0, 0)
    with pytest.raises(HeaderTextError) as e:
        wire.unpack_header(raw)
    assert (e.value.message_type, e.value.device_name) == ("T" * 12, "Dev")
    raw = wire.HEADER.pack(1, b"T\xe9\0X", b"D", 0, 0, 0)  # not UTF-8: readable as latin-1
    with pytest.raises(HeaderTextError) as e:
        wire.unpack_header(raw)
    assert e.value.message_type == "T\xe9"


def test_defaults_of_the_checking_helpers():
    with pytest.raises(InvalidTextError) as e:
        wire.decode_fixed(b"a\0b")
    assert str(e.value).startswith("text field: non-NUL bytes") and e.value.offset == 1
    with pytest.raises(MetadataError) as e:
        wire.unpack_metadata(b"\x00", b"")
    assert e.value.offset == 0
    with pytest.raises(ExtendedHeaderError) as e:
        wire.split_v2_body(wire.EXT_HEADER.pack(12, 2, 100, 0) + b"\0\0")
    assert e.value.offset == 58
    assert "(12) + metadata header (2) + metadata (100) = 114 bytes exceed BODY_SIZE 14" in (
        str(e.value))
