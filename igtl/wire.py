"""OpenIGTLink wire layer: header, CRC-64, timestamps, v2 extended header and metadata.

Nothing here knows about message types: this is the equivalent of the reference library's
``igtlutil`` layer (packed structs, byte order, CRC), written from the protocol description in
``shared/IGTL-PROTOCOL.md`` (sections 1 and 2).

All multi-byte numbers are big-endian.
"""

from __future__ import annotations

import logging
import struct
import warnings
from bisect import bisect_right as _bisect_right
from collections.abc import Mapping
from typing import NamedTuple

import crcmod

from .errors import (
    BodyTooLargeError,
    ExtendedHeaderError,
    HeaderTextError,
    InvalidTextError,
    MetadataError,
    TruncatedMessageError,
    UnknownHeaderVersionError,
)

log = logging.getLogger(__name__)

HEADER_SIZE = 58
EXT_HEADER_SIZE = 12
TYPE_SIZE = 12
DEVICE_NAME_SIZE = 20
SUPPORTED_HEADER_VERSIONS = (1, 2)
#: Default cap on BODY_SIZE accepted by decoders (a 512x512x256 16-bit volume is 128 MiB).
DEFAULT_MAX_BODY_SIZE = 256 * 1024 * 1024

HEADER = struct.Struct(">H12s20sQQQ")
EXT_HEADER = struct.Struct(">HHII")
META_INDEX_COUNT = struct.Struct(">H")
META_ENTRY = struct.Struct(">HHI")

# --------------------------------------------------------------------------------------------
# CRC-64/ECMA-182: poly 0x42F0E1EBA9EA3693, init 0, no reflection, xorout 0 (protocol doc 1.3).
#
# Two backends, chosen by size (docs/BENCHMARKS.md, "igtl: CRC backends and big bodies"):
# anycrc (carry-less multiply) runs ~10 GB/s but pays ~0.4 us per call whatever the size;
# crcmod's C extension runs ~0.33 GB/s at ~0.15 us per call. They cost the same at ~100 bytes,
# so bodies below CRC_SMALL (TRANSFORM, POSITION, STATUS: the 500 Hz and 100k msg/s streams)
# keep crcmod's table loop, called without its Python wrapper, and everything larger goes to
# anycrc (256 KiB: 32 us instead of 750 us). Neither releases the interpreter lock, which is
# why StreamDecoder checksums a big body piece by piece as it arrives.
# Both chain: crc64(b, crc64(a)) == crc64(a + b) (init 0 and xorout 0 make the register the
# result), which is what the incremental check relies on.
CRC_POLY = 0x42F0E1EBA9EA3693
#: Bodies shorter than this many bytes are checksummed by crcmod, longer ones by anycrc.
CRC_SMALL = 100

_crcmod_fun = crcmod.mkCrcFun(1 << 64 | CRC_POLY, rev=False, initCrc=0, xorOut=0)
# mkCrcFun returns a Python closure around (C function, table); calling the C function directly
# saves a Python frame on every small message. Its defaults are (crc, table, fun).
_crcmod_table: bytes = _crcmod_fun.__defaults__[1]  # type: ignore[index]
_crcmod_c = _crcmod_fun.__defaults__[2]  # type: ignore[index]

try:
    from crcmod import _crcfunext  # noqa: F401  (presence check only)

    CRC_ACCELERATED = True
except ImportError:  # pragma: no cover - depends on the installation
    CRC_ACCELERATED = False

try:
    import anycrc

    _anycrc_calc = anycrc.CRC(
        width=64, poly=CRC_POLY, init=0, refin=False, refout=False, xorout=0
    ).calc
    if _anycrc_calc(b"123456789") != 0x6C40DF5F0B497347:  # pragma: no cover - a broken build
        raise ImportError("anycrc gives the wrong CRC-64/ECMA-182 check value")
    #: Name of the backend that checksums bodies of CRC_SMALL bytes and more.
    CRC_BACKEND = "anycrc"
except ImportError as err:  # pragma: no cover - depends on the installation
    _anycrc_calc = None
    CRC_BACKEND = "crcmod"
    _msg = (
        f"igtl: anycrc is not available ({err}); CRC-64 of large bodies falls back to crcmod "
        "(~30x slower: ~750 us per 256 KiB, holding the interpreter lock). "
        "pip install anycrc"
    )
    warnings.warn(_msg, RuntimeWarning, stacklevel=2)
    log.warning(_msg)

if not CRC_ACCELERATED:  # pragma: no cover - depends on the installation
    _msg = (
        "igtl: crcmod's C extension is not available; CRC-64 of small bodies falls back to "
        "pure Python (25-40x slower). Reinstall crcmod with a C compiler present: "
        "pip install --force-reinstall --no-binary crcmod crcmod"
    )
    if _anycrc_calc is not None:
        CRC_SMALL = 0  # anycrc's fixed cost beats crcmod's pure Python at every size
    warnings.warn(_msg, RuntimeWarning, stacklevel=2)
    log.warning(_msg)


def crc64_crcmod(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    """CRC-64/ECMA-182 by crcmod alone (the cross-check in tests), chained from ``crc``."""
    return _crcmod_c(data, crc, _crcmod_table)  # type: ignore[no-any-return]


if _anycrc_calc is None:  # pragma: no cover - depends on the installation
    _crc_big = crc64_crcmod
else:
    _crc_big = _anycrc_calc


def crc64(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    """CRC-64/ECMA-182 of a bytes-like object (check value for b"123456789":
    0x6C40DF5F0B497347), chained from ``crc``: ``crc64(b, crc64(a)) == crc64(a + b)``."""
    if len(data) < CRC_SMALL:
        return _crcmod_c(data, crc, _crcmod_table)  # type: ignore[no-any-return]
    return _crc_big(data, crc)  # type: ignore[no-any-return]


# --------------------------------------------------------------------------------------------
# Timestamps: uint64 = seconds << 32 | binary fraction (units of 2**-32 s).
# The reference converts nanoseconds <-> fraction with a bitwise successive approximation whose
# 32 "bases" start at 1e9 and are halved rounding up (igtl_util.c). We reproduce it exactly so
# that messages re-encode bit for bit; frac -> ns is linear in the bits, so it is four table
# lookups; ns -> frac is the greedy search itself.
def _bases() -> tuple[int, ...]:
    base = 1_000_000_000
    out = []
    for _ in range(32):
        base = (base + 1) >> 1
        out.append(base)
    return tuple(out)


_FRAC_BASES = _bases()
_FRAC_BITS = tuple(zip(_FRAC_BASES, (1 << (31 - i) for i in range(32)), strict=True))


def _byte_table(byte_index: int) -> tuple[int, ...]:
    # byte_index 0 = most significant byte of the 32-bit fraction.
    table = []
    for value in range(256):
        total = 0
        for bit in range(8):
            if value & (0x80 >> bit):
                total += _FRAC_BASES[byte_index * 8 + bit]
        table.append(total)
    return tuple(table)


_T0, _T1, _T2, _T3 = (_byte_table(i) for i in range(4))


def frac_to_nanosec(frac: int) -> int:
    """Reference conversion of a 32-bit binary fraction to nanoseconds (may exceed 1e9 by 10)."""
    return (
        _T0[(frac >> 24) & 0xFF]
        + _T1[(frac >> 16) & 0xFF]
        + _T2[(frac >> 8) & 0xFF]
        + _T3[frac & 0xFF]
    )


def nanosec_to_frac_reference(ns: int) -> int:
    """The reference greedy conversion, bit by bit (igtl_util.c); kept as the test oracle."""
    result = 0
    for base, mask in _FRAC_BITS:
        if ns >= base:
            result |= mask
            ns -= base
    return result


# The greedy search returns the numerically largest fraction whose reference nanosecond value
# does not exceed ns (setting a bit whenever the rest can stay zero is the lexicographic, hence
# numeric, maximum). Done a byte at a time: the largest byte v with T[v] <= rest is found by
# bisecting the suffix minima of T (non-decreasing), because T itself is not monotone in its
# low bits (the last bases are 8, 4, 2, 1, 1, 1). Proven equal to the greedy in test_wire.py.
def _suffix_min(table: tuple[int, ...]) -> tuple[int, ...]:
    out = list(table)
    for v in range(254, -1, -1):
        out[v] = min(out[v], out[v + 1])
    return tuple(out)


_M0, _M1, _M2, _M3 = (_suffix_min(t) for t in (_T0, _T1, _T2, _T3))


def nanosec_to_frac(ns: int) -> int:
    """Reference conversion of nanoseconds (0 <= ns < 1e9) to a 32-bit binary fraction.

    Bit-exact with the reference's 32-step greedy (:func:`nanosec_to_frac_reference`) in four
    table bisections.
    """
    b0 = _bisect_right(_M0, ns) - 1
    ns -= _T0[b0]
    b1 = _bisect_right(_M1, ns) - 1
    ns -= _T1[b1]
    b2 = _bisect_right(_M2, ns) - 1
    ns -= _T2[b2]
    b3 = _bisect_right(_M3, ns) - 1
    return (b0 << 24) | (b1 << 16) | (b2 << 8) | b3


def raw_to_seconds(raw: int) -> float:
    """Header timestamp (uint64) to float seconds since the Unix epoch."""
    if not raw & 0xFFFFFFFF:
        return float(raw >> 32)
    return (raw >> 32) + (
        _T0[(raw >> 24) & 0xFF] + _T1[(raw >> 16) & 0xFF] + _T2[(raw >> 8) & 0xFF] + _T3[raw & 0xFF]
    ) * 1e-9


def seconds_to_raw(t: float) -> int:
    """Float seconds since the Unix epoch to the header's uint64 (reference fraction algorithm)."""
    if t <= 0.0:
        return 0
    sec = int(t)
    ns = round((t - sec) * 1e9)
    if ns >= 1_000_000_000:
        sec += 1
        ns -= 1_000_000_000
    if not ns:
        return (sec & 0xFFFFFFFF) << 32
    b0 = _bisect_right(_M0, ns) - 1
    ns -= _T0[b0]
    b1 = _bisect_right(_M1, ns) - 1
    ns -= _T1[b1]
    b2 = _bisect_right(_M2, ns) - 1
    ns -= _T2[b2]
    return (
        ((sec & 0xFFFFFFFF) << 32)
        | (b0 << 24)
        | (b1 << 16)
        | (b2 << 8)
        | (_bisect_right(_M3, ns) - 1)
    )


# --------------------------------------------------------------------------------------------
# Fixed-size, NUL-padded text fields (type name, device name, and the content-level names).
def _canonical_text(raw: bytes, what: str, offset: int) -> str:
    """A NUL-padded field's text: up to the first NUL, UTF-8, else latin-1 (never fails on the
    text itself: names from operator tools are answered, tests/occ).

    Bytes other than NUL after the first NUL would be lost on re-packing, so they are refused
    with InvalidTextError. Latin-1 names (invalid UTF-8) are kept readable and re-pack as UTF-8:
    a known gap in byte-exactness (codec.py docstring).
    """
    end = raw.find(b"\x00")
    text_raw = raw if end < 0 else raw[:end]
    if end >= 0 and raw.count(0, end) != len(raw) - end:
        raise InvalidTextError(
            f"{what}: non-NUL bytes after the NUL terminator", offset=offset + end
        )
    try:
        return text_raw.decode("utf-8")
    except UnicodeDecodeError:
        return text_raw.decode("latin-1")


def decode_fixed(
    raw: bytes | bytearray | memoryview, what: str = "text field", offset: int = 0
) -> str:
    """Decode a NUL-padded field: up to the first NUL (UTF-8, else latin-1), all NUL after it
    (else InvalidTextError: those bytes would not survive re-encoding)."""
    return _canonical_text(bytes(raw), what, offset)


def encode_fixed(text: str, size: int, what: str) -> bytes:
    """Encode ``text`` into a NUL-padded field of ``size`` bytes; too long is a caller error.

    The reference truncates silently, which breaks name matching in 3D Slicer; we refuse instead.
    """
    try:
        raw = text.encode("utf-8")
    except (UnicodeEncodeError, AttributeError) as err:
        raise ValueError(f"{what} {text!r} is not encodable text") from err
    if len(raw) > size:
        raise ValueError(f"{what} {text!r} is {len(raw)} bytes; OpenIGTLink allows {size}")
    return raw


# Type and device names repeat on every message of a stream: decoding and encoding them is
# memoised in small dicts (keyed by the raw 12/20 header bytes, or by the str). The dicts are
# cleared when full, so a peer sending ever-new names costs memory bounded by _NAME_CACHE_MAX.
_NAME_CACHE_MAX = 4096
_decoded_names: dict[bytes, str] = {}
_encoded_types: dict[str, bytes] = {}
_encoded_devices: dict[str, bytes] = {}


def _decode_name(raw: bytes, what: str, offset: int) -> str:
    name = _decoded_names.get(raw)
    if name is None:
        name = _canonical_text(raw, what, offset)  # refusals are not cached: they raise
        if len(_decoded_names) >= _NAME_CACHE_MAX:
            _decoded_names.clear()
        _decoded_names[raw] = name
    return name


def _lenient(raw: bytes) -> str:
    """A refused name, readable in the error report: up to the first NUL, latin-1 if need be."""
    end = raw.find(b"\x00")
    raw = raw if end < 0 else raw[:end]
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def _encode_name(text: str, cache: dict[str, bytes], size: int, what: str) -> bytes:
    raw = cache.get(text)
    if raw is None:
        raw = encode_fixed(text, size, what)
        if len(cache) >= _NAME_CACHE_MAX:
            cache.clear()
        cache[text] = raw
    return raw


# --------------------------------------------------------------------------------------------
class Header(NamedTuple):
    """The decoded 58-byte header."""

    version: int
    message_type: str
    device_name: str
    timestamp_raw: int
    body_size: int
    crc: int


_unpack_header_from = HEADER.unpack_from


def header_fields(
    data: bytes | bytearray | memoryview, offset: int, max_body_size: int
) -> tuple[int, str, str, int, int, int]:
    """:func:`unpack_header` as a plain tuple (the decoders' hot path; same checks)."""
    if len(data) - offset < HEADER_SIZE:
        raise TruncatedMessageError(
            f"header needs {HEADER_SIZE} bytes, got {len(data) - offset}", offset=offset
        )
    version, mtype, device, ts, body_size, crc = _unpack_header_from(data, offset)
    message_type = _decoded_names.get(mtype)
    device_name = _decoded_names.get(device)
    bad_name: InvalidTextError | None = None
    if message_type is None or device_name is None:
        try:
            message_type = _decode_name(mtype, "message type", offset + 2)
            device_name = _decode_name(device, "device name", offset + 14)
        except InvalidTextError as err:
            bad_name = err
            message_type = _lenient(mtype)
            device_name = _lenient(device)
    if version != 1 and version != 2:
        raise UnknownHeaderVersionError(
            f"unknown header version {version} (supported: 1, 2)",
            offset=offset,
            message_type=message_type,
            device_name=device_name,
        )
    if body_size > max_body_size:
        raise BodyTooLargeError(
            f"body size {body_size} exceeds the limit of {max_body_size} bytes",
            offset=offset + 42,
            message_type=message_type,
            device_name=device_name,
        )
    if bad_name is not None:
        raise HeaderTextError(
            str(bad_name),
            body_size=body_size,
            offset=bad_name.offset,
            message_type=message_type,
            device_name=device_name,
        ) from bad_name
    return version, message_type, device_name, ts, body_size, crc


def unpack_header(
    data: bytes | bytearray | memoryview,
    offset: int = 0,
    *,
    max_body_size: int = DEFAULT_MAX_BODY_SIZE,
) -> Header:
    """Parse and sanity-check a header at ``data[offset:offset+58]``.

    Raises UnknownHeaderVersionError or BodyTooLargeError (both unrecoverable: the stream cannot
    be re-framed; BODY_SIZE is checked before anything is allocated for the body) and
    TruncatedMessageError when fewer than 58 bytes are given.
    """
    return Header._make(header_fields(data, offset, max_body_size))


_pack_header = HEADER.pack


def pack_header(
    version: int, message_type: str, device_name: str, timestamp_raw: int, body: bytes
) -> bytes:
    """The 58-byte header for ``body`` (CRC computed here)."""
    try:
        return _pack_header(
            version,
            _encode_name(message_type, _encoded_types, TYPE_SIZE, "message type"),
            _encode_name(device_name, _encoded_devices, DEVICE_NAME_SIZE, "device name"),
            timestamp_raw,
            len(body),
            # crc64() inlined: this runs for every message sent
            (_crcmod_c(body, 0, _crcmod_table) if len(body) < CRC_SMALL else _crc_big(body, 0))
            if body
            else 0,
        )
    except struct.error as err:
        raise ValueError(f"cannot pack header: {err}") from err


# --------------------------------------------------------------------------------------------
# Metadata value encodings: IANA MIBenum codes (igtl_types.h IANA_ENCODING_TYPE) -> Python codec.
IANA_ENCODINGS: dict[int, str] = {
    3: "ascii",
    4: "latin-1",
    5: "iso8859-2",
    6: "iso8859-3",
    7: "iso8859-4",
    8: "iso8859-5",
    9: "iso8859-6",
    10: "iso8859-7",
    11: "iso8859-8",
    12: "iso8859-9",
    13: "iso8859-10",
    17: "shift_jis",
    18: "euc_jp",
    36: "euc_kr",
    38: "euc_kr",
    39: "iso2022_jp",
    40: "iso2022_jp_2",
    106: "utf-8",
    109: "iso8859-13",
    110: "iso8859-14",
    111: "iso8859-15",
    112: "iso8859-16",
    113: "gbk",
    114: "gb18030",
    1013: "utf-16-be",
    1014: "utf-16-le",
    1015: "utf-16",
    1017: "utf-32",
    1018: "utf-32-be",
    1019: "utf-32-le",
    2025: "gb2312",
    2026: "big5",
    2084: "koi8-r",
    2250: "cp1250",
    2251: "cp1251",
    2252: "cp1252",
}
US_ASCII = 3
UTF_8 = 106


def codec_for(encoding: int) -> str:
    """Python codec name for an IANA MIBenum; ValueError if we do not know it."""
    try:
        return IANA_ENCODINGS[encoding]
    except KeyError:
        raise ValueError(f"unsupported text encoding (IANA MIBenum) {encoding}") from None


def default_encoding(text: str) -> int:
    """US-ASCII when the text allows it (the reference's recommendation), else UTF-8."""
    return US_ASCII if text.isascii() else UTF_8


_META_CACHE: dict[tuple[tuple[str, str], ...], tuple[bytes, bytes]] = {}


def pack_metadata(metadata: Mapping[str, str], encodings: Mapping[str, int]) -> tuple[bytes, bytes]:
    """Return (metadata header, metadata data). Entries are written sorted by key, like the
    reference's std::map; the 2-byte INDEX_COUNT is always present."""
    if not metadata:
        return b"\x00\x00", b""
    cache_key = None
    if not encodings and len(metadata) <= 8:
        # a stream's few small entries repeat every message (a master's run/clutch at 500 Hz)
        try:
            cache_key = tuple(metadata.items())
            hit = _META_CACHE.get(cache_key)
        except TypeError:  # an unhashable value: the checks below say what is wrong
            cache_key, hit = None, None
        if hit is not None:
            return hit
    for key in metadata:
        if not isinstance(key, str):
            raise TypeError(f"metadata key {key!r} must be str, got {type(key).__name__}")
    keys = sorted(metadata, key=lambda k: k.encode("utf-8", "surrogatepass"))
    if len(keys) > 0xFFFF:
        raise ValueError(f"{len(keys)} metadata entries; at most 65535 fit the index count")
    index = [META_INDEX_COUNT.pack(len(keys))]
    data = []
    for key in keys:
        value = metadata[key]
        if not isinstance(value, str):
            raise TypeError(f"metadata value for {key!r} must be str, got {type(value).__name__}")
        kraw = key.encode("utf-8")
        enc = encodings.get(key)
        if enc is None:
            enc = default_encoding(value)
        if not 0 <= enc <= 0xFFFF:
            raise ValueError(f"metadata encoding {enc} for {key!r} does not fit uint16")
        # Unknown codes: the value was decoded as latin-1 (see unpack_metadata), so it re-encodes.
        try:
            vraw = value.encode(IANA_ENCODINGS.get(enc, "latin-1"))
        except UnicodeEncodeError as err:
            raise ValueError(f"metadata value for {key!r} cannot be encoded as {enc}") from err
        if len(kraw) > 0xFFFF:
            raise ValueError(f"metadata key {key[:40]!r}... is longer than 65535 bytes")
        if len(vraw) > 0xFFFFFFFF:
            raise ValueError(f"metadata value for {key!r} is longer than 2**32-1 bytes")
        index.append(META_ENTRY.pack(len(kraw), enc, len(vraw)))
        data.append(kraw)
        data.append(vraw)
    packed = b"".join(index), b"".join(data)
    if cache_key is not None and len(packed[1]) <= 256:
        if len(_META_CACHE) >= 256:
            _META_CACHE.clear()  # bounded: a peer varying its values cannot grow it
        _META_CACHE[cache_key] = packed
    return packed


def unpack_metadata(
    meta_header: bytes | bytearray | memoryview,
    meta_data: bytes | bytearray | memoryview,
    base_offset: int = 0,
) -> tuple[dict[str, str], dict[str, int]]:
    """Decode metadata; returns (values in wire order, encodings that differ from the default).

    Values in an encoding we do not know are kept as latin-1 text with their code recorded, so
    they re-encode to the same bytes.
    """
    if len(meta_header) == 0:
        return {}, {}
    # A stream repeats the same few metadata blocks (the OCC master: run/clutch on each of 500
    # packets a second): decoded once, then looked up. Bounded: a peer that varies its values
    # only clears the cache.
    cache_key = (bytes(meta_header), bytes(meta_data))
    hit = _META_DECODED.get(cache_key)
    if hit is not None:
        return dict(hit[0]), dict(hit[1])
    values, encodings = _unpack_metadata(meta_header, meta_data, base_offset)
    if len(_META_DECODED) >= 256:
        _META_DECODED.clear()
    _META_DECODED[cache_key] = (dict(values), dict(encodings))
    return values, encodings


_META_DECODED: dict[tuple[bytes, bytes], tuple[dict[str, str], dict[str, int]]] = {}


def _unpack_metadata(
    meta_header: bytes | bytearray | memoryview,
    meta_data: bytes | bytearray | memoryview,
    base_offset: int,
) -> tuple[dict[str, str], dict[str, int]]:
    if len(meta_header) < 2:
        raise MetadataError(
            f"metadata header of {len(meta_header)} bytes cannot hold the index count",
            offset=base_offset,
        )
    (count,) = META_INDEX_COUNT.unpack_from(meta_header, 0)
    if 2 + 8 * count != len(meta_header):
        raise MetadataError(
            f"metadata index of {count} entries needs {2 + 8 * count} bytes, "
            f"META_HEADER_SIZE is {len(meta_header)}",
            offset=base_offset,
        )
    values: dict[str, str] = {}
    encodings: dict[str, int] = {}
    pos = 0
    for i in range(count):
        ksize, enc, vsize = META_ENTRY.unpack_from(meta_header, 2 + 8 * i)
        end = pos + ksize + vsize
        if end > len(meta_data):
            raise MetadataError(
                f"metadata entry {i} needs bytes up to {end}, META_DATA_SIZE is {len(meta_data)}",
                offset=base_offset + len(meta_header) + pos,
            )
        try:
            key = bytes(meta_data[pos : pos + ksize]).decode("utf-8")
        except UnicodeDecodeError as err:
            raise MetadataError(
                f"metadata key {i} is not valid UTF-8", offset=base_offset + len(meta_header) + pos
            ) from err
        vraw = bytes(meta_data[pos + ksize : end])
        codec = IANA_ENCODINGS.get(enc)
        try:
            value = vraw.decode(codec) if codec else vraw.decode("latin-1")
        except UnicodeDecodeError as err:
            raise MetadataError(
                f"metadata value of {key!r} is not valid in encoding {enc} ({codec})",
                offset=base_offset + len(meta_header) + pos + ksize,
            ) from err
        values[key] = value
        if enc != default_encoding(value):
            encodings[key] = enc
        pos = end
    if pos != len(meta_data):
        raise MetadataError(
            f"metadata entries hold {pos} bytes, META_DATA_SIZE is {len(meta_data)}",
            offset=base_offset + len(meta_header) + pos,
        )
    return values, encodings


class BodyLayout(NamedTuple):
    """Where content and metadata sit in a header-version-2 body."""

    content_start: int
    content_end: int
    meta_header_size: int
    meta_data_size: int
    message_id: int


def split_v2_body(body: bytes | bytearray | memoryview, base_offset: int = 58) -> BodyLayout:
    """Validate the extended header of a v2 body and locate content and metadata (doc 2.1)."""
    n = len(body)
    if n < EXT_HEADER_SIZE:
        raise ExtendedHeaderError(
            f"header-version-2 body of {n} bytes is shorter than the 12-byte extended header",
            offset=base_offset,
        )
    ext_size, mh_size, md_size, msg_id = EXT_HEADER.unpack_from(body, 0)
    if ext_size < EXT_HEADER_SIZE:
        raise ExtendedHeaderError(
            f"EXT_HEADER_SIZE {ext_size} is smaller than 12", offset=base_offset
        )
    if ext_size + mh_size + md_size > n:
        raise ExtendedHeaderError(
            f"extended header ({ext_size}) + metadata header ({mh_size}) + metadata "
            f"({md_size}) = {ext_size + mh_size + md_size} bytes exceed BODY_SIZE {n}",
            offset=base_offset,
        )
    return BodyLayout(ext_size, n - mh_size - md_size, mh_size, md_size, msg_id)
