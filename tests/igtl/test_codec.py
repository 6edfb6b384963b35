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
    with pytest.raises(DecoderFailedError) as failed:
        list(dec)
    assert str(failed.value).startswith("decoder failed earlier: unknown header version 7")
    with pytest.raises(DecoderFailedError) as failed:
        dec.feed(TRANSFORM)
    assert str(failed.value).startswith("decoder failed earlier: unknown header version 7")


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


# ------------------------------------------------------- what the decoders report and keep
# (each of these was written to catch a fault that the tests above let through: mutation
# testing, docs/VERIFICATION.md)
def with_crc(data: bytes, crc: int) -> bytes:
    return data[:50] + struct.pack(">Q", crc) + data[58:]


def bad_crc_of(data: bytes) -> bytes:
    return with_crc(data, struct.unpack_from(">Q", data, 50)[0] ^ 0x8000_0000_0000_0001)


def decode_stream(data: bytes, **kw) -> list[igtl.Message]:
    dec = igtl.StreamDecoder(**kw)
    dec.feed(data)
    out = list(dec)
    dec.close()
    return out


NON_CANONICAL = {
    # messages that decode but are not what this library would encode: they re-pack to their
    # own bytes, through every decoder path (fast v1, fast v2, generic, unknown type)
    "fast v1": TRANSFORM,
    "fast v2": TRANSFORM2,
    "generic v1": raw_message("STATUS", igtl.StatusMessage(status_message="x").pack()[58:]),
    "generic v2": igtl.StatusMessage(status_message="x", header_version=2,
                                     metadata={"k": "v"}).pack(),
    "unknown v1": raw_message("FOOBAR", b"\x01\x02\x03"),
    "unknown v2": raw_message("FOOBAR", b"\x01\x02\x03", version=2),
}


@pytest.mark.req("SR-CRC-1")
@pytest.mark.parametrize("path", sorted(NON_CANONICAL))
def test_a_wrong_crc_accepted_unchecked_repacks_as_received(path):
    bad = bad_crc_of(NON_CANONICAL[path])
    with pytest.raises(CRCError):
        igtl.unpack(bad)
    with pytest.raises(CRCError):
        igtl.unpack(bytearray(bad))  # the copy made of mutable input is checked too
    with pytest.raises(CRCError):
        decode_stream(bad)
    for msg in (igtl.unpack(bad, crc_check=False), igtl.unpack(bytearray(bad), crc_check=False),
                *decode_stream(bad, crc_check=False)):
        assert msg.pack() == bad
        assert msg.pack(header_version=msg.header_version) == bad


def test_mutable_input_is_decoded_field_for_field_and_not_kept():
    for data in (TRANSFORM, TRANSFORM2, NON_CANONICAL["unknown v2"]):
        expected = igtl.unpack(data)
        for buf in (bytearray(data), memoryview(bytearray(data))):
            msg = igtl.unpack(buf)
            assert (msg.message_type, msg.device_name, msg.header_version) == (
                expected.message_type, expected.device_name, expected.header_version)
            assert msg == expected
            buf[:] = bytes(len(data))  # the caller reuses its buffer
            assert msg.pack() == data and msg == expected


def test_header_timestamps_decode_to_seconds_on_every_path():
    for t in (1_700_000_000.0, 1_700_000_000.25, 3.5, 0.0):
        raw = wire.seconds_to_raw(t)
        for msg in (
            igtl.TransformMessage.from_matrix(np.eye(4), timestamp=t),  # fast v1
            igtl.PositionMessage((1.0, 2.0, 3.0), timestamp=t, header_version=2),  # fast v2
            igtl.StatusMessage(status_message="s", timestamp=t),  # generic
        ):
            data = msg.pack()
            assert struct.unpack_from(">Q", data, 34)[0] == raw
            for got in (igtl.unpack(data), *decode_stream(data)):
                assert got.timestamp == pytest.approx(t, abs=1e-9) and got.raw_timestamp == raw
                assert got.timestamp == wire.raw_to_seconds(raw)


def test_a_fast_path_type_of_the_wrong_size_is_a_content_error():
    for version in (1, 2):
        data = raw_message("TRANSFORM", bytes(47), version=version)
        with pytest.raises(ContentError) as e:
            igtl.unpack(data)
        assert e.value.message_type == "TRANSFORM" and e.value.recoverable


def test_metadata_encodings_other_than_the_default_are_decoded():
    msg = igtl.StatusMessage(status_message="s", header_version=2,
                             metadata={"a": "x", "b": "é"}, metadata_encoding={"a": 4, "b": 4})
    got = igtl.unpack(msg.pack())
    assert got.metadata == {"a": "x", "b": "é"}
    assert got.metadata_encoding == {"a": 4, "b": 4}
    assert decode_stream(msg.pack())[0].metadata_encoding == {"a": 4, "b": 4}


def test_errors_inside_the_body_name_the_message():
    bad = bytearray(TRANSFORM2)
    bad[58 + 12 + 48 + 18] = 0xFF  # a metadata key that is not UTF-8
    bad[50:58] = struct.pack(">Q", wire.crc64(bytes(bad[58:])))
    for decode in (igtl.unpack, decode_stream):
        with pytest.raises(MetadataError) as e:
            decode(bytes(bad))
        assert e.value.message_type == "TRANSFORM" and e.value.device_name == "DeviceName"


def _registered(monkeypatch, name: str, *, needs_type_name: bool, fail: bool = False):
    """A message type registered for this test only (a fresh class each time)."""
    import dataclasses
    from typing import ClassVar

    from igtl.messages.base import REGISTRY, Message

    @dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
    class Custom(Message):
        TYPE: ClassVar[str] = name
        payload: bytes = b""

        def pack_content(self) -> bytes:
            return self.payload

        @classmethod
        def unpack_content(cls, content, common):
            if fail:
                raise ValueError("payload refused by the custom codec")
            seen = common.pop("message_type", None)
            if needs_type_name and seen != name:
                raise AssertionError(f"type name not given: {seen!r}")
            if not needs_type_name and seen is not None:
                raise AssertionError("type name given to a class that did not ask")
            return cls(payload=bytes(content), **common)

    if needs_type_name:
        Custom.NEEDS_TYPE_NAME = True  # type: ignore[attr-defined]
    monkeypatch.setitem(REGISTRY, name, Custom)
    return Custom


@pytest.mark.parametrize("needs_type_name", [True, False])
def test_a_registered_type_gets_its_type_name_only_if_it_asks(monkeypatch, needs_type_name):
    cls = _registered(monkeypatch, "TSTNAME", needs_type_name=needs_type_name)
    data = cls(payload=b"abc", device_name="D").pack()
    for _ in range(2):  # the first decode and the remembered answer
        msg = igtl.unpack(data)
        assert type(msg) is cls and msg.payload == b"abc" and msg.pack() == data


@pytest.mark.parametrize("version", [1, 2])
def test_a_content_codec_that_raises_is_a_content_error_with_offset(monkeypatch, version):
    cls = _registered(monkeypatch, "TSTFAIL", needs_type_name=False, fail=True)
    data = cls(payload=b"abc", device_name="D", header_version=version).pack()
    with pytest.raises(ContentError) as e:
        igtl.unpack(data)
    assert e.value.offset == 58 + (12 if version == 2 else 0) and e.value.recoverable
    text = str(e.value)
    assert "invalid TSTFAIL content" in text and "ValueError" in text
    assert "payload refused by the custom codec" in text
    assert e.value.message_type == "TSTFAIL" and e.value.device_name == "D"


@pytest.mark.req("SR-SIZE-1")
def test_truncated_and_trailing_errors_say_what_and_where():
    with pytest.raises(TruncatedMessageError) as e:
        igtl.unpack(TRANSFORM[:-3])
    assert "announces 48 body bytes, only 45 present" in str(e.value)
    assert (e.value.message_type, e.value.device_name) == ("TRANSFORM", "DeviceName")
    with pytest.raises(DecodeError) as e:
        igtl.unpack(TRANSFORM + b"\0\0")
    assert "2 bytes follow the message" in str(e.value)
    assert e.value.offset == len(TRANSFORM)
    assert (e.value.message_type, e.value.device_name) == ("TRANSFORM", "DeviceName")
    # exactly complete decodes; one byte short or over does not
    assert igtl.unpack(TRANSFORM).message_type == "TRANSFORM"
    with pytest.raises(TruncatedMessageError):
        igtl.unpack(TRANSFORM[:-1])
    with pytest.raises(DecodeError, match="1 bytes follow"):
        igtl.unpack(TRANSFORM + b"\0")


def test_crc_error_text_gives_both_values():
    bad = with_crc(TRANSFORM, 0x0123456789ABCDEF)
    with pytest.raises(CRCError) as e:
        igtl.unpack(bad)
    actual = wire.crc64(TRANSFORM[58:])
    assert f"header says {0x0123456789ABCDEF:#018x}" in str(e.value)
    assert f"body gives {actual:#018x}" in str(e.value)


def test_a_new_decoder_holds_nothing():
    dec = igtl.StreamDecoder()
    assert dec.buffered == 0 and dec.offset == 0 and dec.next_message() is None
    dec.close()  # nothing buffered: no error
    dec.feed(TRANSFORM)
    assert [m.pack() for m in dec] == [TRANSFORM]


def test_close_inside_a_header_or_a_body_says_where():
    dec = igtl.StreamDecoder()
    dec.feed(TRANSFORM + TRANSFORM[:10])
    assert len(list(dec)) == 1
    with pytest.raises(TruncatedMessageError) as e:
        dec.close()
    assert "stream ended inside a message (10 bytes buffered)" in str(e.value)
    assert e.value.offset == len(TRANSFORM)
    assert e.value.message_type is None and e.value.device_name is None
    dec = igtl.StreamDecoder()
    dec.feed(TRANSFORM + TRANSFORM[:70])
    assert len(list(dec)) == 1
    with pytest.raises(TruncatedMessageError) as e:
        dec.close()
    assert "(70 bytes buffered)" in str(e.value) and e.value.offset == len(TRANSFORM)
    assert (e.value.message_type, e.value.device_name) == ("TRANSFORM", "DeviceName")


def with_device_field(data: bytes, field: bytes) -> bytes:
    return data[:14] + field.ljust(20, b"\0") + data[34:]


def test_a_bad_name_in_a_stream_is_refused_at_its_offset_and_the_stream_goes_on():
    from igtl.errors import HeaderTextError

    bad = with_device_field(TRANSFORM, b"Dev\0x")  # a byte after the terminator
    for big_body in (igtl.codec.BIG_BODY, 1):  # in the buffer, and collected apart
        dec = igtl.StreamDecoder(big_body=big_body)
        dec.feed(TRANSFORM + bad[:60])
        assert dec.next_message().pack() == TRANSFORM
        assert dec.next_message() is None
        dec.feed(bad[60:] + TRANSFORM)
        with pytest.raises(HeaderTextError) as e:
            dec.next_message()
        assert e.value.recoverable
        assert e.value.offset == len(TRANSFORM) + 14 + 3  # the terminator, as unpack says
        assert "device name: non-NUL bytes after the NUL terminator" in str(e.value)
        assert (e.value.message_type, e.value.device_name) == ("TRANSFORM", "Dev")
        assert dec.next_message().pack() == TRANSFORM
        assert dec.messages == 2 and dec.errors == 1 and dec.offset == 3 * len(TRANSFORM)
        dec.feed(bad)
        with pytest.raises(HeaderTextError):
            dec.next_message()
        assert dec.errors == 2
        dec.close()


def test_a_stream_ending_inside_a_refused_message_names_it():
    bad = with_device_field(TRANSFORM, b"Dev\0x")
    dec = igtl.StreamDecoder()
    dec.feed(bad[:70])
    assert dec.next_message() is None
    with pytest.raises(TruncatedMessageError) as e:
        dec.close()
    assert (e.value.message_type, e.value.device_name) == ("TRANSFORM", "Dev")


@pytest.mark.req("SR-SIZE-1")
def test_a_fatal_header_error_is_counted_at_its_stream_offset():
    too_big = with_body_size(TRANSFORM, 10**9)
    dec = igtl.StreamDecoder(max_body_size=1000)
    dec.feed(TRANSFORM + too_big)
    assert dec.next_message().pack() == TRANSFORM
    with pytest.raises(BodyTooLargeError) as e:
        dec.next_message()
    assert e.value.offset == len(TRANSFORM) + 42  # the BODY_SIZE field
    assert dec.errors == 1 and dec.messages == 1 and dec.failed
    dec = igtl.StreamDecoder(max_body_size=1000)  # after a recoverable error: both counted
    dec.feed(bad_crc_of(TRANSFORM) + too_big)
    with pytest.raises(CRCError):
        dec.next_message()
    with pytest.raises(BodyTooLargeError):
        dec.next_message()
    assert dec.errors == 2


@pytest.mark.parametrize("field", [b"Dev\xe9", b"Ger\xc3\xa4t"])  # latin-1, UTF-8
def test_non_ascii_names_repack_as_received(field):
    data = with_device_field(TRANSFORM, field)
    for got in (igtl.unpack(data), *decode_stream(data)):
        expected = "Gerät" if field.startswith(b"Ger") else "Devé"
        assert got.device_name == expected
        assert got.pack() == data


def test_the_big_body_threshold_is_inclusive():
    # a body of exactly big_body bytes is collected apart: its CRC is taken piece by piece
    # and the last piece is not copied again (the same as test_big_body_is_not_copied...)
    data = big_image(side=500).pack()
    body = len(data) - 58
    for big_body in (body, body + 1):
        dec = igtl.StreamDecoder(big_body=big_body)
        dec.feed(data[: len(data) // 2])
        assert dec.next_message() is None
        assert dec.buffered == len(data) // 2
        tracemalloc.start()
        try:
            before, _ = tracemalloc.get_traced_memory()
            dec.feed(data[len(data) // 2 :])
            (msg,) = list(dec)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert msg.pack() == data
        # collected apart: the body's buffer grows once (1.5x the body at its peak); in the
        # stream buffer: that growth, then the body copied out of it (2x)
        copied = peak - before > 1.75 * len(data)
        assert copied == (big_body > body), (big_body, peak)


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("mtype", ["IMAGE", "BIGRAW"])
def test_a_big_body_collected_apart_repacks_as_received(version, mtype):
    msg = big_image(side=300, version=version)
    data = msg.pack() if mtype == "IMAGE" else raw_message(
        mtype, bytes(range(256)) * 400, version=version)
    data = bad_crc_of(data)  # a CRC left unchecked: only the remembered bytes give it back
    for step in (1000, 70_000):
        dec = igtl.StreamDecoder(crc_check=False, big_body=1000)
        (got,) = feed_in_pieces(dec, data, step)
        assert got.pack() == data
        if mtype == "BIGRAW":
            assert got.content == (bytes(range(256)) * 400)
    dec = igtl.StreamDecoder(big_body=1000)
    with pytest.raises(CRCError) as e:
        feed_in_pieces(dec, data, 1000)
    assert (e.value.message_type, e.value.device_name) == (mtype, "Big" if mtype == "IMAGE"
                                                            else "Dev")


def test_an_unknown_big_body_is_kept_once():
    # RawMessage copies its content out of the collected buffer: the message must then not
    # keep the buffer too (twice the memory for every big unknown message held)
    import gc

    content = bytes(range(256)) * 8192  # 2 MiB
    data = raw_message("BIGRAW", content)
    dec = igtl.StreamDecoder()
    gc.collect()
    tracemalloc.start()
    try:
        (msg,) = feed_in_pieces(dec, data, 256 * 1024)
        del dec
        gc.collect()
        held, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert msg.content == content and msg.pack() == data
    assert held < 1.5 * len(content), held


def test_big_body_crc_errors_are_each_counted():
    bad = bad_crc_of(big_image(side=300).pack())
    dec = igtl.StreamDecoder(big_body=1000)
    errors = 0
    for _ in range(3):
        try:
            feed_in_pieces(dec, bad, 5000)
        except CRCError as err:
            errors += 1
            assert err.device_name == "Big"
    assert errors == 3 and dec.errors == 3 and dec.messages == 0


@pytest.mark.req("SR-SIZE-1")
def test_decode_body_checks_the_size_and_the_crc():
    header = wire.unpack_header(TRANSFORM)
    body = TRANSFORM[58:]
    for given in (body, bytearray(body), memoryview(body)):
        msg = igtl.decode_body(header, given)
        assert msg == igtl.unpack(TRANSFORM) and msg.pack() == TRANSFORM
        assert (msg.device_name, msg.header_version, msg.raw_timestamp) == (
            "DeviceName", 1, header.timestamp_raw)
    v2 = wire.unpack_header(TRANSFORM2)
    assert igtl.decode_body(v2, TRANSFORM2[58:]).pack() == TRANSFORM2
    caller = bytearray(TRANSFORM2[58:])  # the caller's buffer is neither changed nor kept
    msg = igtl.decode_body(v2, caller)
    assert caller == TRANSFORM2[58:]
    caller[:] = bytes(len(caller))
    assert msg.pack() == TRANSFORM2 and msg == igtl.unpack(TRANSFORM2)
    for wrong in (body[:-1], body + b"\0"):
        with pytest.raises(TruncatedMessageError) as e:
            igtl.decode_body(header, wrong)
        assert f"body of {len(wrong)} bytes, header announces 48" in str(e.value)
        assert e.value.offset == 58 + min(len(wrong), 48)
        assert (e.value.message_type, e.value.device_name) == ("TRANSFORM", "DeviceName")
    bad = bad_crc_of(TRANSFORM)
    bad_header = wire.unpack_header(bad)
    with pytest.raises(CRCError):
        igtl.decode_body(bad_header, body)
    unchecked = igtl.decode_body(bad_header, body, crc_check=False)
    assert unchecked == igtl.unpack(TRANSFORM) and unchecked.pack() == bad
