"""Codec errors, recovery and framing (unpack and StreamDecoder).

Vectors: OpenIGTLink project test data (github.com/openigtlink/OpenIGTLink, BSD-style licence,
Copyright Insight Software Consortium).
"""

from __future__ import annotations

import struct
import tracemalloc

import numpy as np
import pytest

import igtl
from igtl import wire
from igtl.errors import (
    BodyTooLargeError,
    ContentError,
    CRCError,
    DecodeError,
    DecoderFailedError,
    ExtendedHeaderError,
    InvalidTextError,
    MetadataError,
    TruncatedMessageError,
    UnknownHeaderVersionError,
)

from .conftest import vector

TRANSFORM = vector("transform.bin")
TRANSFORM2 = vector("transformFormat2.bin")


def raw_message(mtype: str, content: bytes, version: int = 1, device: str = "Dev") -> bytes:
    return igtl.RawMessage(type_name=mtype, content=content, device_name=device,
                           header_version=version).pack()


def with_body_size(data: bytes, size: int) -> bytes:
    return data[:42] + struct.pack(">Q", size) + data[50:]


@pytest.mark.req("SR-CRC-1")
@pytest.mark.parametrize("bit", range(64))
def test_every_bit_of_the_crc_is_compared(bit):
    # a CRC field wrong in any one of its 64 bits is refused (a check on the low 32 bits only
    # passed every other test); the stream decoder refuses it too and stays framed
    crc = struct.unpack_from(">Q", TRANSFORM, 50)[0] ^ (1 << bit)
    bad = TRANSFORM[:50] + struct.pack(">Q", crc) + TRANSFORM[58:]
    with pytest.raises(CRCError):
        igtl.unpack(bad)
    dec = igtl.StreamDecoder()
    dec.feed(bad + TRANSFORM)
    with pytest.raises(CRCError):
        dec.next_message()
    assert [m.pack() for m in dec] == [TRANSFORM]


@pytest.mark.req("SR-CRC-1")
def test_crc_error():
    bad = TRANSFORM[:-1] + bytes((TRANSFORM[-1] ^ 1,))
    with pytest.raises(CRCError) as e:
        igtl.unpack(bad)
    assert e.value.offset == 58 and e.value.recoverable
    assert e.value.message_type == "TRANSFORM" and e.value.device_name == "DeviceName"
    assert igtl.unpack(bad, crc_check=False).message_type == "TRANSFORM"


@pytest.mark.req("SR-SIZE-1")
def test_truncated_and_trailing():
    with pytest.raises(TruncatedMessageError) as e:
        igtl.unpack(TRANSFORM[:-3])
    assert e.value.offset == len(TRANSFORM) - 3
    with pytest.raises(TruncatedMessageError):
        igtl.unpack(TRANSFORM[:30])
    with pytest.raises(DecodeError, match="follow"):
        igtl.unpack(TRANSFORM + b"\0")


def test_unknown_header_version():
    with pytest.raises(UnknownHeaderVersionError) as e:
        igtl.unpack(b"\x00\x03" + TRANSFORM[2:])
    assert not e.value.recoverable and e.value.offset == 0


@pytest.mark.req("SR-SIZE-1")
def test_body_size_2_63_costs_nothing():
    huge = with_body_size(TRANSFORM[:58], 2**63)
    tracemalloc.start()
    try:
        with pytest.raises(BodyTooLargeError) as e:
            igtl.unpack(huge)
        dec = igtl.StreamDecoder()
        dec.feed(huge)
        with pytest.raises(BodyTooLargeError):
            list(dec)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1_000_000
    assert e.value.offset == 42 and not e.value.recoverable
    assert dec.failed
    with pytest.raises(DecoderFailedError):
        dec.feed(TRANSFORM)
    with pytest.raises(DecoderFailedError):
        dec.next_message()


@pytest.mark.req("SR-SIZE-1")
def test_configurable_limit():
    with pytest.raises(BodyTooLargeError):
        igtl.unpack(TRANSFORM, max_body_size=47)
    assert igtl.unpack(TRANSFORM, max_body_size=48).message_type == "TRANSFORM"


def test_extended_header_error():
    # v2 body whose ext header claims more metadata than the body holds
    body = wire.EXT_HEADER.pack(12, 2, 1000, 0) + b"\0\0"
    data = wire.pack_header(2, "STRING", "D", 0, body) + body
    with pytest.raises(ExtendedHeaderError) as e:
        igtl.unpack(data)
    assert e.value.offset == 58 and e.value.recoverable


def test_metadata_error_offset():
    bad = bytearray(TRANSFORM2)
    # First metadata key starts right after content + meta header: 58 + 12 + 48 + 18
    bad[58 + 12 + 48 + 18] = 0xFF
    body = bytes(bad[58:])
    bad[50:58] = struct.pack(">Q", wire.crc64(body))
    with pytest.raises(MetadataError) as e:
        igtl.unpack(bytes(bad))
    assert e.value.offset == 58 + 12 + 48 + 18


def test_content_count_does_not_divide():
    with pytest.raises(ContentError) as e:
        igtl.unpack(raw_message("TDATA", bytes(71)))
    assert e.value.offset == 58 + 70
    assert "multiple of 70" in str(e.value)
    with pytest.raises(ContentError) as e:
        igtl.unpack(raw_message("POINT", bytes(137), version=2))
    assert e.value.offset == 58 + 12 + 136


def test_invalid_text_in_an_unknown_encoding_is_refused():
    content = struct.pack(">HH", 60000, 2) + b"\xff\xfe"  # no IANA MIBenum 60000 here
    with pytest.raises(InvalidTextError) as e:
        igtl.unpack(raw_message("STRING", content))
    assert e.value.offset == 58 + 4
    assert isinstance(e.value, ContentError)


def test_a_string_whose_declared_charset_does_not_fit_is_kept_and_flagged():
    # US-ASCII declared (the reference library's default) with latin-1 / UTF-8 bytes in it
    content = struct.pack(">HH", 3, 5) + "héé".encode()
    data = raw_message("STRING", content)
    msg = igtl.unpack(data)
    assert msg.charset_mismatch and msg.encoding == 3
    assert msg.pack() == data  # byte-exact: nothing was lost
    assert not igtl.unpack(igtl.StringMessage("plain", device_name="x").pack()).charset_mismatch


def test_v2_content_size_excludes_metadata():
    m = igtl.CapabilityMessage(types=("A", "B"), header_version=2, metadata={"k": "v" * 11})
    assert igtl.unpack(m.pack()) == m


def test_unknown_type_is_raw_message():
    data = raw_message("FOOBAR", b"\x01\x02\x03", version=2)
    m = igtl.unpack(data)
    assert isinstance(m, igtl.RawMessage)
    assert (m.message_type, m.content) == ("FOOBAR", b"\x01\x02\x03")
    assert m.pack() == data


def test_decoder_recovers_after_recoverable_error():
    bad_crc = TRANSFORM[:-1] + bytes((TRANSFORM[-1] ^ 1,))
    bad_content = raw_message("TDATA", bytes(71))
    stream = TRANSFORM + bad_crc + TRANSFORM2 + bad_content + TRANSFORM
    dec = igtl.StreamDecoder()
    dec.feed(stream)
    got: list = []
    errors: list = []
    while True:
        try:
            m = dec.next_message()
        except DecodeError as err:
            errors.append(err)
            continue
        if m is None:
            break
        got.append(m)
    assert [m.header_version for m in got] == [1, 2, 1]
    assert [type(e) for e in errors] == [CRCError, ContentError]
    assert errors[0].offset == len(TRANSFORM) + 58  # stream offset of the bad body
    assert errors[1].offset == 2 * len(TRANSFORM) + len(TRANSFORM2) + 58 + 70
    assert not dec.failed and dec.messages == 3 and dec.errors == 2
    dec.close()


def test_decoder_failed_state():
    dec = igtl.StreamDecoder()
    dec.feed(TRANSFORM + b"\x00\x07" + TRANSFORM[2:] + TRANSFORM)
    assert dec.next_message() is not None
    with pytest.raises(UnknownHeaderVersionError) as e:
        dec.next_message()
    assert e.value.offset == len(TRANSFORM)
    assert dec.failed
    with pytest.raises(DecoderFailedError):
        list(dec)


def test_v1_v2_interleaved_and_split():
    msgs = [igtl.unpack(TRANSFORM), igtl.unpack(TRANSFORM2),
            igtl.StatusMessage(device_name="", header_version=1),
            igtl.StatusMessage(device_name="", header_version=2, metadata={"dummy": "dummy"})]
    stream = b"".join(m.pack() for m in msgs)
    for step in (1, 3, 57, 58, 59, 1000):
        dec = igtl.StreamDecoder()
        out = []
        for i in range(0, len(stream), step):
            dec.feed(stream[i : i + step])
            out.extend(dec)
        assert out == msgs, step
        dec.close()


def test_close_with_partial_message():
    dec = igtl.StreamDecoder()
    dec.feed(TRANSFORM[:70])
    assert list(dec) == []
    with pytest.raises(TruncatedMessageError) as e:
        dec.close()
    assert e.value.message_type == "TRANSFORM"


def test_memoryview_and_bytearray_input():
    assert igtl.unpack(bytearray(TRANSFORM)) == igtl.unpack(memoryview(TRANSFORM))


# ---------------------------------------------------------------------------- big bodies
def big_image(side: int = 700, version: int = 1, seed: int = 0) -> igtl.ImageMessage:
    import numpy as np

    px = np.random.default_rng(seed).integers(0, 65535, (side, side), dtype=np.uint16)
    msg = igtl.ImageMessage.from_array(px, device_name="Big")
    if version == 2:
        msg = msg.replace(header_version=2, metadata={"b": "2", "a": "1"}, message_id=7)
    return msg


def feed_in_pieces(dec: igtl.StreamDecoder, data: bytes, step: int) -> list[igtl.Message]:
    out: list[igtl.Message] = []
    view = memoryview(data)
    for i in range(0, len(data), step):
        dec.feed(view[i : i + step])
        out.extend(dec)
    return out


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("step", [1000, 65536, 256 * 1024, 10**7])
def test_big_body_in_pieces(version, step):
    msg = big_image(version=version)  # ~1 MiB body, above BIG_BODY
    stream = TRANSFORM + msg.pack() + TRANSFORM2
    dec = igtl.StreamDecoder()
    out = feed_in_pieces(dec, stream, step)
    assert out == [igtl.unpack(TRANSFORM), msg, igtl.unpack(TRANSFORM2)]
    assert not out[1].pixels.flags.writeable
    assert dec.buffered == 0 and dec.offset == len(stream) and dec.messages == 3
    dec.close()


def test_big_body_byte_at_a_time():
    msg = big_image(side=40, version=2)  # 3.2 kB body: the big path with big_body=1000
    stream = msg.pack() + TRANSFORM
    dec = igtl.StreamDecoder(big_body=1000)
    out = feed_in_pieces(dec, stream, 1)
    assert out == [msg, igtl.unpack(TRANSFORM)]
    dec.close()


def test_big_body_crc_is_computed_as_the_bytes_arrive(monkeypatch):
    """No CRC call covers more than the piece just fed: the work per feed is bounded by what
    the transport read, whatever the body size."""
    from igtl import codec

    sizes: list[int] = []
    real = codec._crc64

    def counting(data, crc=0):
        sizes.append(len(data))
        return real(data, crc)

    monkeypatch.setattr(codec, "_crc64", counting)
    data = big_image(side=1000).pack()  # ~2 MB body
    dec = igtl.StreamDecoder()
    step = 64 * 1024
    out = feed_in_pieces(dec, data, step)
    assert len(out) == 1 and out[0] == igtl.unpack(data)
    assert sizes and max(sizes) <= step
    assert sum(sizes) == len(data) - 58


def test_big_body_is_not_copied_when_complete():
    """The last piece of an 8 MB IMAGE costs no copy of the body: the pixels view
    the buffer the body was collected in."""
    data = big_image(side=2000).pack()
    dec = igtl.StreamDecoder()
    step = 256 * 1024
    last = (len(data) - 1) // step * step
    tracemalloc.start()  # before the body's buffer is made, so that its growth is accounted
    try:
        assert feed_in_pieces(dec, data[:last], step) == []
        before, _ = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        dec.feed(data[last:])
        out = list(dec)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(out) == 1 and out[0] == igtl.unpack(data)
    # the buffer may grow by its over-allocation (1/8); a copy of the body would add 8 MB
    assert peak - before < len(data) // 4, (before, peak)


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.req("SR-CRC-1")
def test_big_body_crc_mismatch_is_recoverable(version):
    good = big_image(version=version).pack()
    bad = bytearray(good)
    bad[len(bad) // 2] ^= 0x10  # a pixel bit; the header's CRC left alone
    stream = TRANSFORM + bytes(bad) + TRANSFORM2
    dec = igtl.StreamDecoder()
    out: list[igtl.Message] = []
    errors: list[DecodeError] = []
    view = memoryview(stream)
    for i in range(0, len(stream), 65536):
        dec.feed(view[i : i + 65536])
        while True:
            try:
                msg = dec.next_message()
            except DecodeError as err:
                errors.append(err)
                continue
            if msg is None:
                break
            out.append(msg)
    assert out == [igtl.unpack(TRANSFORM), igtl.unpack(TRANSFORM2)]
    assert len(errors) == 1 and isinstance(errors[0], CRCError) and errors[0].recoverable
    assert errors[0].offset == len(TRANSFORM) + 58 and errors[0].message_type == "IMAGE"
    assert dec.errors == 1 and not dec.failed
    # without the check the damaged body decodes (and differs from the original)
    dec = igtl.StreamDecoder(crc_check=False)
    got = feed_in_pieces(dec, bytes(bad), 65536)
    assert len(got) == 1 and got[0] != igtl.unpack(good)


def test_big_body_bad_content_is_recoverable():
    msg = big_image()
    data = bytearray(msg.pack())
    data[58 + 3] = 99  # scalar type 99: not defined
    data[50:58] = struct.pack(">Q", wire.crc64(bytes(data[58:])))
    dec = igtl.StreamDecoder()
    dec.feed(bytes(data[:100_000]))
    assert list(dec) == []
    dec.feed(bytes(data[100_000:]) + TRANSFORM)
    with pytest.raises(ContentError) as e:
        list(dec)
    assert e.value.offset == 58 + 3 and e.value.recoverable
    assert list(dec) == [igtl.unpack(TRANSFORM)]


@pytest.mark.req("SR-SIZE-1")
def test_big_body_truncated_at_close():
    data = big_image().pack()
    dec = igtl.StreamDecoder()
    assert feed_in_pieces(dec, data[:-10], 65536) == []
    assert dec.buffered == len(data) - 10
    with pytest.raises(TruncatedMessageError) as e:
        dec.close()
    assert e.value.message_type == "IMAGE"


def _fields(msg: igtl.Message) -> dict[str, object]:
    import dataclasses

    return {
        f.name: getattr(msg, f.name)
        for f in dataclasses.fields(msg)
        if f.name != "_wire" and not isinstance(getattr(msg, f.name), np.ndarray)
    } | {"matrix": msg.matrix.tolist() if hasattr(msg, "matrix") else None}


@pytest.mark.parametrize(
    "msg",
    [
        igtl.PositionMessage((1.5, -2.0, 30.0), (0.1, 0.2, 0.3, 0.9), 24, device_name="Master",
                             header_version=2, message_id=7, timestamp=1_700_000_000.5,
                             metadata={"run": "1", "clutch": "0"}),
        igtl.PositionMessage((1.5, -2.0, 30.0), (0.1, 0.2, 0.3, 0.9), 28, device_name="M",
                             header_version=2, message_id=2**32 - 1),
        igtl.PositionMessage((1.5, -2.0, 30.0), (0.0, 0.0, 0.0, 1.0), 12, device_name="M",
                             header_version=2, metadata={"é": "ü"}),
        igtl.TransformMessage.from_matrix(np.eye(4), device_name="Tip", header_version=2,
                                          message_id=3, metadata={"MRMLNodeName": "Tip"}),
    ],
)
def test_the_v2_fast_path_decodes_like_the_generic_one(
    msg: igtl.Message, monkeypatch: pytest.MonkeyPatch
) -> None:
    """FAST_V2 (the 500 Hz master stream's path) gives field for field what the generic
    decoder gives, and re-packs byte-exact."""
    from igtl.messages import base

    data = msg.pack()
    fast = igtl.unpack(data)
    monkeypatch.setattr(base, "FAST_V2", {})
    import igtl.codec as codec

    monkeypatch.setattr(codec, "_fast_v2_get", {}.get)
    slow = igtl.unpack(data)
    assert type(fast) is type(slow)
    assert _fields(fast) == _fields(slow)
    assert fast.pack() == data == slow.pack()
