"""Property tests (hypothesis): round trips for every registered type in both header versions,
stream splitting, and corruption that must only ever raise DecodeError, and be refused.

Seed messages include the OpenIGTLink project's reference vectors (github.com/openigtlink/
OpenIGTLink test data; BSD-style licence, Copyright Insight Software Consortium).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import igtl
from igtl import codec, wire
from igtl.messages import base

from .conftest import VECTORS_DIR

SETTINGS = settings(max_examples=10, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

# ---------------------------------------------------------------------------- strategies
def name(max_size: int, min_size: int = 0) -> st.SearchStrategy[str]:
    return st.text(st.characters(min_codepoint=1, max_codepoint=255), min_size=min_size,
                   max_size=max_size).filter(lambda s: len(s.encode("utf-8")) <= max_size)


text = st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\0"),
               max_size=30)
f32 = st.floats(width=32, allow_nan=False)
f64 = st.floats(allow_nan=False)
u8, u16, u32 = st.integers(0, 255), st.integers(0, 0xFFFF), st.integers(0, 0xFFFFFFFF)


def J(c: dict) -> dict:
    """Common field values as strategies for st.builds."""
    return {k: st.just(v) for k, v in c.items()}


def floats(n: int, s=f32):
    return st.tuples(*[s] * n)


rgba = st.tuples(u8, u8, u8, u8)
small3 = st.tuples(st.integers(0, 40), st.integers(0, 40), st.integers(0, 40))
meta_key = st.text(st.characters(blacklist_categories=("Cs",)), max_size=12)
meta_val = st.text(st.characters(blacklist_categories=("Cs",)), max_size=12)


@st.composite
def common(draw, version: int) -> dict:
    raw = draw(st.sampled_from([0, 1234567892, 0xFFFFFFFF]) | st.integers(0, 2**64 - 1))
    out = {"device_name": draw(name(20)), "timestamp": wire.raw_to_seconds(raw),
           "raw_timestamp": raw, "header_version": version}
    if version == 2:
        out["metadata"] = draw(st.dictionaries(meta_key, meta_val, max_size=4))
        out["message_id"] = draw(u32)
    return out


def arrays(dtypes, max_dims=3):
    return st.sampled_from(dtypes).flatmap(
        lambda dt: hnp.arrays(dt, hnp.array_shapes(min_dims=0, max_dims=max_dims, max_side=4),
                              elements=hnp.from_dtype(np.dtype(dt), allow_nan=False)))


def cells():
    return st.lists(st.tuples(*[]) | st.lists(u32, max_size=4).map(tuple), max_size=4).map(tuple)


@st.composite
def image(draw, c):
    dt = draw(st.sampled_from(["i1", "u1", "<i2", ">u2", "i4", "u4", "f4", ">f8"]))
    shape = draw(st.tuples(st.integers(1, 3), st.integers(1, 3), st.integers(1, 3),
                           st.integers(1, 3)))
    px = draw(hnp.arrays(dt, shape, elements=hnp.from_dtype(np.dtype(dt), allow_nan=False)))
    off = draw(small3)
    extra = draw(small3)
    size = tuple(o + s + e for o, s, e in zip(off, (shape[2], shape[1], shape[0]), extra,
                                              strict=True))
    return igtl.ImageMessage(pixels=px, elements=draw(floats(12)), size=size, offset=off,
                             coordinate=draw(st.sampled_from([1, 2])),
                             endian=draw(st.sampled_from([1, 2])), **c)


def encoded_text():
    return (st.tuples(st.text(st.characters(max_codepoint=127, blacklist_characters="\0"),
                              max_size=30), st.just(3))
            | st.tuples(text, st.just(106)))


def bind_child():
    return st.builds(igtl.BindChild, name(12, 1), name(20).filter(lambda s: "\0" not in s),
                     st.binary(max_size=9))


def request():
    return st.lists(st.tuples(name(12, 1), name(20)), max_size=3).map(tuple)


CONTENT = {
    igtl.TransformMessage: lambda c: st.builds(igtl.TransformMessage, floats(12), **J(c)),
    igtl.PositionMessage: lambda c: st.builds(igtl.PositionMessage, floats(3), floats(4),
                                              st.just(28), **J(c))
    | st.builds(igtl.PositionMessage, floats(3), st.just((0.0, 0.0, 0.0, 1.0)), st.just(12),
                **J(c)),
    igtl.StatusMessage: lambda c: st.builds(igtl.StatusMessage, u16,
                                            st.integers(-(2**63), 2**63 - 1), name(20), text,
                                            **J(c)),
    igtl.StringMessage: lambda c: encoded_text().map(
        lambda t: igtl.StringMessage(t[0], t[1], **c)),
    igtl.CapabilityMessage: lambda c: st.builds(igtl.CapabilityMessage,
                                                st.lists(name(12, 1), max_size=4).map(tuple), **J(c)),
    igtl.PointMessage: lambda c: st.builds(igtl.PointMessage, st.lists(st.builds(
        igtl.PointElement, name(64), name(32), rgba, floats(3), f32, name(20)), max_size=3), **J(c)),
    igtl.TrajectoryMessage: lambda c: st.builds(igtl.TrajectoryMessage, st.lists(st.builds(
        igtl.TrajectoryElement, name(64), name(32), st.integers(-128, 127), rgba, floats(3),
        floats(3), f32, name(20)), max_size=3), **J(c)),
    igtl.TrackingDataMessage: lambda c: st.builds(igtl.TrackingDataMessage, st.lists(st.builds(
        igtl.TrackingElement, name(20), u8, floats(12)), max_size=3), **J(c)),
    igtl.QuaternionTrackingDataMessage: lambda c: st.builds(
        igtl.QuaternionTrackingDataMessage, st.lists(st.builds(
            igtl.QuaternionTrackingElement, name(20), u8, floats(3), floats(4)), max_size=3), **J(c)),
    igtl.SensorMessage: lambda c: st.builds(igtl.SensorMessage, st.lists(f64, max_size=8),
                                            st.integers(0, 2**64 - 1).map(igtl.Unit.unpack), u8,
                                            **J(c)),
    igtl.NDArrayMessage: lambda c: st.builds(igtl.NDArrayMessage, arrays(
        ["i1", "u1", ">i2", "<u2", "i4", "u4", "f4", "f8", "c16"]), **J(c)),
    igtl.ImageMessage: lambda c: image(c),
    igtl.ImageMetaMessage: lambda c: st.builds(igtl.ImageMetaMessage, st.lists(st.builds(
        igtl.ImageMetaElement, name(64), name(20), name(32), name(64), name(64),
        st.integers(0, 2**64 - 1), st.tuples(u16, u16, u16), u8), max_size=2), **J(c)),
    igtl.LabelMetaMessage: lambda c: st.builds(igtl.LabelMetaMessage, st.lists(st.builds(
        igtl.LabelMetaElement, name(64), name(20), u8, rgba, st.tuples(u16, u16, u16), name(20)),
        max_size=2), **J(c)),
    igtl.ColorTableMessage: lambda c: st.builds(
        igtl.ColorTableMessage,
        st.sampled_from([(256,), (256, 3)]).flatmap(lambda s: hnp.arrays(np.uint8, s))
        | hnp.arrays(np.uint16, (256,)),
        st.sampled_from(["COLORT", "COLORTABLE"]), **J(c)),
    igtl.PolyDataMessage: lambda c: st.builds(
        igtl.PolyDataMessage, hnp.arrays(np.float32, st.tuples(st.integers(0, 4), st.just(3)),
                                         elements=f32),
        cells(), cells(), cells(), cells(),
        st.lists(st.builds(igtl.PolyDataAttribute, u8,
                           name(20).filter(lambda s: "\0" not in s),
                           hnp.arrays(np.float32, st.tuples(st.integers(0, 3),
                                                            st.integers(1, 4)), elements=f32)),
                 max_size=3).map(tuple), **J(c)),
    igtl.BindMessage: lambda c: st.builds(igtl.BindMessage, st.lists(bind_child(), max_size=3)
                                          .map(tuple), **J(c)),
    igtl.GetBindMessage: lambda c: st.builds(igtl.GetBindMessage, request(), **J(c)),
    igtl.StartBindMessage: lambda c: st.builds(igtl.StartBindMessage,
                                               st.integers(0, 2**64 - 1), request(), **J(c)),
    igtl.CommandMessage: lambda c: st.tuples(u32, name(128), encoded_text()).map(
        lambda t: igtl.CommandMessage(t[0], t[1], t[2][0], t[2][1], **c)),
    igtl.RTSCommandMessage: lambda c: st.tuples(u32, name(128), encoded_text()).map(
        lambda t: igtl.RTSCommandMessage(t[0], t[1], t[2][0], t[2][1], **c)),
    igtl.QueryMessage: lambda c: st.builds(igtl.QueryMessage,
                                           st.sampled_from(igtl.QueryMessage.TYPES), **J(c)),
    igtl.RTSMessage: lambda c: st.builds(igtl.RTSMessage, st.sampled_from(igtl.RTSMessage.TYPES),
                                         st.none() | u8, **J(c)),
    igtl.StartTrackingMessage: lambda c: st.builds(
        igtl.StartTrackingMessage, st.sampled_from(["STT_TDATA", "STT_QTDATA"]),
        st.integers(-(2**31), 2**31 - 1), name(32), **J(c)),
    igtl.StartPolyDataMessage: lambda c: st.builds(igtl.StartPolyDataMessage,
                                                   st.none() | st.integers(0, 2**64 - 1), **J(c)),
    igtl.StartVideoMessage: lambda c: st.builds(igtl.StartVideoMessage, name(4), u32, u8, **J(c)),
    igtl.VideoMetaMessage: lambda c: st.builds(igtl.VideoMetaMessage, st.lists(st.builds(
        igtl.VideoMetaElement, name(64), name(64), name(64), name(64),
        st.integers(-32768, 32767), f64, st.tuples(u16, u16, u16), floats(12), u8),
        max_size=2), **J(c)),
    igtl.VideoMessage: lambda c: st.builds(
        igtl.VideoMessage, st.binary(max_size=20), name(4), u16, u8, u8,
        st.tuples(u16, u16, u16), floats(12), st.tuples(u16, u16, u16), st.tuples(u16, u16, u16),
        **J(c)),
    igtl.VirtualFixtureMessage: lambda c: st.builds(
        igtl.VirtualFixtureMessage, f32, st.lists(floats(4), max_size=4), u8, **J(c)),
}


def test_every_registered_class_has_a_strategy():
    assert set(base.REGISTRY.values()) <= set(CONTENT)


def messages(version: int | None = None):
    versions = st.sampled_from([1, 2]) if version is None else st.just(version)
    return versions.flatmap(common).flatmap(
        lambda c: st.sampled_from(sorted(CONTENT, key=lambda k: k.__name__)).flatmap(
            lambda cls: CONTENT[cls](c)))


@pytest.mark.parametrize("cls", sorted(CONTENT, key=lambda k: k.__name__), ids=lambda c: c.__name__)
@pytest.mark.parametrize("version", [1, 2])
@SETTINGS
@given(data=st.data())
def test_round_trip_every_type(cls, version, data):
    msg = data.draw(common(version).flatmap(CONTENT[cls]))
    packed = msg.pack()
    again = igtl.unpack(packed)
    assert type(again) is cls
    assert again == msg
    assert again.pack() == packed


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(
    st.text("ABCDEFGHIJKLMNOPQRSTUVWXYZ_0123456789", min_size=1, max_size=12).filter(
        lambda s: s not in base.REGISTRY),
    st.binary(max_size=30), st.sampled_from([1, 2])), max_size=3))
def test_unknown_types_round_trip(items):
    for t, content, v in items:
        m = igtl.RawMessage(type_name=t, content=content, header_version=v)
        assert igtl.unpack(m.pack()) == m


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(messages(), min_size=1, max_size=5), st.data())
def test_stream_splits(msgs, data):
    stream = b"".join(m.pack() for m in msgs)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=8)))
    dec = igtl.StreamDecoder()
    out = []
    prev = 0
    for cut in [*cuts, len(stream)]:
        dec.feed(stream[prev:cut])
        out.extend(dec)
        prev = cut
    assert out == msgs
    dec = igtl.StreamDecoder()
    out = []
    for i in range(len(stream)):
        dec.feed(stream[i : i + 1])
        out.extend(dec)
    assert out == msgs
    dec.close()


# ---------------------------------------------------------------------------- corruption
SEEDS = [p.read_bytes() for p in sorted(VECTORS_DIR.glob("*.bin")) if p.name != "rtpwrapper.bin"
         and p.stat().st_size < 1500]


def decode_all(data: bytes, *, crc_check: bool) -> list[bytes]:
    """Decode ``data`` both ways; only DecodeError may escape (anything else fails the test).
    Returns the wire bytes of every message the stream decoder accepted."""
    try:
        igtl.unpack(data, crc_check=crc_check)
    except igtl.DecodeError:
        pass
    dec = igtl.StreamDecoder(crc_check=crc_check, max_body_size=1 << 20)
    dec.feed(data)
    accepted = []
    while True:
        try:
            msg = dec.next_message()
        except igtl.DecodeError as err:
            if not err.recoverable:
                break
            continue
        if msg is None:
            break
        accepted.append(msg.pack())
    try:
        dec.close()
    except igtl.DecodeError:
        pass
    return accepted


def _body_and_crc(data: bytes) -> tuple[bytes, bytes]:
    return data[50:58], data[58:]


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(SEEDS), st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 7)),
                                        min_size=1, max_size=4), st.booleans())
@pytest.mark.req("SR-CRC-1")
def test_bit_flips(seed, flips, crc_check):
    data = bytearray(seed)
    for pos, bit in flips:
        data[pos % len(data)] ^= 1 << bit
    data = bytes(data)
    accepted = decode_all(data, crc_check=crc_check)
    if not crc_check:
        return
    if _body_and_crc(data) != _body_and_crc(seed):
        # a changed body or CRC field (the flips did not cancel) is refused, never decoded
        with pytest.raises(igtl.DecodeError):
            igtl.unpack(data)
        assert all(_body_and_crc(m) == _body_and_crc(seed) for m in accepted)


@settings(max_examples=150, deadline=None)
@given(st.sampled_from(SEEDS), st.integers(0, 10**6), st.binary(max_size=80))
@pytest.mark.req("SR-SIZE-1")
def test_truncation_and_garbage(seed, cut, garbage):
    short = seed[: cut % len(seed)]  # always shorter than the message
    with pytest.raises(igtl.errors.TruncatedMessageError):
        igtl.unpack(short)
    assert decode_all(short, crc_check=True) == []
    decode_all(garbage, crc_check=False)
    if garbage:  # bytes after a complete message are refused by unpack ...
        with pytest.raises(igtl.DecodeError):
            igtl.unpack(seed + garbage)
    # ... and the stream decoder gives the message first, whatever follows
    assert decode_all(seed + garbage, crc_check=True)[:1] == [seed]
    decode_all(garbage + seed, crc_check=True)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 3), st.sampled_from(sorted(base.REGISTRY)) | name(12), name(20),
       st.integers(0, 2**64 - 1), st.integers(0, 2**64 - 1) | st.integers(0, 200),
       st.binary(max_size=200))
def test_random_headers_with_any_body(version, mtype, device, ts, size, body):
    """Random headers (incl. huge sizes) followed by random bodies, CRC right or wrong."""
    for crc in (wire.crc64(body[:size]), 0):
        header = wire.HEADER.pack(version, mtype.encode("latin-1"), device.encode("latin-1"), ts,
                                  size, crc)
        decode_all(header + body, crc_check=crc == 0)


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(sorted(base.REGISTRY)), st.binary(max_size=300), st.sampled_from([1, 2]))
def test_random_content_for_every_type(mtype, content, version):
    """Any content bytes under any registered type: decoded or a DecodeError, nothing else."""
    data = igtl.RawMessage(type_name=mtype, content=content, header_version=version).pack()
    try:
        m = igtl.unpack(data)
    except igtl.DecodeError:
        return
    assert m.message_type == mtype


# ---------------------------------------------------------------------------- big bodies
def _same_fields(a: base.Message, b: base.Message) -> None:
    """Equal, and equal down to field types and array writability (bytes stay bytes)."""
    assert a == b
    assert a.pack() == b.pack()
    for f in dataclasses.fields(a):
        if f.name == "_wire":  # bytes or pieces of them, depending on the decode path
            continue
        x, y = getattr(a, f.name), getattr(b, f.name)
        assert type(x) is type(y), f.name
        if isinstance(x, np.ndarray):
            assert x.flags.writeable == y.flags.writeable, f.name
        if isinstance(x, (tuple, list)):
            for xi, yi in zip(x, y, strict=True):
                assert type(xi) is type(yi), f.name
                if dataclasses.is_dataclass(xi):
                    for g in dataclasses.fields(xi):
                        assert type(getattr(xi, g.name)) is type(getattr(yi, g.name)), g.name


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(messages(), min_size=1, max_size=4), st.data())
def test_big_body_path_decodes_like_unpack(msgs, data):
    """With big_body=1 every body that arrives in pieces is collected apart, checksummed piece
    by piece and decoded from its own bytearray: the messages must be those unpack gives."""
    stream = b"".join(m.pack() for m in msgs)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=12)))
    dec = igtl.StreamDecoder(big_body=1)
    out = []
    prev = 0
    for cut in [*cuts, len(stream)]:
        dec.feed(stream[prev:cut])
        out.extend(dec)
        prev = cut
    dec.close()
    assert len(out) == len(msgs)
    for got, m in zip(out, msgs, strict=True):
        _same_fields(got, igtl.unpack(m.pack()))


# ---------------------------------------------------------------------------- exact re-pack
ALL_SEEDS = [p.read_bytes() for p in sorted(VECTORS_DIR.glob("*.bin")) if p.name != "rtpwrapper.bin"]


def _with_crc(data: bytes | bytearray) -> bytes:
    data = bytearray(data)
    data[50:58] = wire.HEADER.pack(0, b"", b"", 0, 0, wire.crc64(bytes(data[58:])))[50:58]
    return bytes(data)


def _repacks_exactly(data: bytes, *, crc_check: bool = True, cuts: list[int] = ()) -> bool:
    """Whatever ``unpack`` accepts re-packs to the same bytes, and so does what the stream
    decoder gives for the same bytes (byte at a time, at ``cuts``, big-body path or not).
    False when the input is refused."""
    try:
        msg = igtl.unpack(data, crc_check=crc_check)
    except igtl.DecodeError:
        return False  # refused: fine, as long as it is an IGTLError
    assert msg.pack() == data
    assert msg.pack(header_version=msg.header_version) == data  # no change asked for
    assert igtl.unpack(bytearray(data), crc_check=crc_check).pack() == data
    assert igtl.unpack(memoryview(data), crc_check=crc_check).pack() == data
    for big_body in (codec.BIG_BODY, 1):
        for pieces in (
            [data[i : i + 1] for i in range(len(data))],
            [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)], strict=True)],
        ):
            dec = igtl.StreamDecoder(crc_check=crc_check, big_body=big_body)
            out = []
            for piece in pieces:
                dec.feed(piece)
                out.extend(dec)
            dec.close()
            assert [m.pack() for m in out] == [data]
    return True


def _cuts(n: int) -> st.SearchStrategy[list[int]]:
    return st.lists(st.integers(0, n), max_size=6).map(sorted)


@settings(max_examples=400, deadline=None)
@given(st.sampled_from(ALL_SEEDS), st.integers(2, 33), st.binary(min_size=1, max_size=4))
def test_header_names_repack_exactly_or_are_refused(seed, pos, raw):
    """TYPE and DEVICE_NAME: any bytes there either decode and re-pack to the same bytes (names
    that are not UTF-8 too), or (bytes after a NUL) are refused with HeaderTextError,
    recoverably."""
    data = bytearray(seed)
    data[pos : pos + len(raw)] = raw
    data = _with_crc(data[: len(seed)])
    try:
        igtl.unpack(data)
    except igtl.errors.HeaderTextError as err:
        assert err.recoverable
        dec = igtl.StreamDecoder()
        dec.feed(data + seed)
        with pytest.raises(igtl.errors.HeaderTextError):
            list(dec)
        assert list(dec) == [igtl.unpack(seed)]  # skipped, and the stream goes on
        return
    except igtl.DecodeError:
        return
    assert _repacks_exactly(data)


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(ALL_SEEDS), st.lists(st.tuples(st.integers(0, 10**6),
                                                      st.binary(min_size=1, max_size=4)),
                                            min_size=1, max_size=3),
       st.booleans(), st.data())
def test_every_accepted_mutation_repacks_exactly(seed, changes, fix_crc, data):
    """Any bytes of a reference vector overwritten (header, extended header, metadata,
    reserved and padding bytes, floats): accepted means re-packed byte for byte. With the CRC
    left wrong, only an unchecked decode accepts them, and re-packs the wrong CRC too."""
    mutated = bytearray(seed)
    for pos, raw in changes:
        pos %= len(seed)
        mutated[pos : pos + len(raw)] = raw
    mutated = bytes(mutated[: len(seed)])
    if fix_crc:
        mutated = _with_crc(mutated)
    _repacks_exactly(mutated, crc_check=fix_crc, cuts=data.draw(_cuts(len(mutated))))


@settings(max_examples=200, deadline=None)
@given(messages(), st.data())
def test_every_random_message_repacks_exactly(msg, data):
    packed = msg.pack()
    assert _repacks_exactly(packed, cuts=data.draw(_cuts(len(packed))))


@settings(max_examples=200, deadline=None)
@given(messages(), st.sampled_from(ALL_SEEDS), name(20), st.integers(0, 0xFFFFFFFF))
def test_a_replaced_message_packs_canonically(msg, seed, device, message_id):
    """dataclasses.replace (and any constructor) gives a message without the remembered
    bytes: it is encoded from its fields, and decodes to the changed values."""
    for decoded in (igtl.unpack(msg.pack()), igtl.unpack(seed)):
        changes = {"device_name": device}
        if decoded.header_version == 2:
            changes["message_id"] = message_id
        changed = dataclasses.replace(decoded, **changes)
        fresh = changed.pack()
        assert fresh == dataclasses.replace(changed).pack()  # canonical: from the fields
        again = igtl.unpack(fresh)
        assert again.device_name == device
        assert again.message_id == changed.message_id
        assert again.pack() == fresh
    changed = dataclasses.replace(igtl.unpack(msg.pack()), device_name=device)
    assert changed.pack() == dataclasses.replace(msg, device_name=device).pack()


# ---------------------------------------------------------------------------- damage is refused
@settings(max_examples=300, deadline=None)
@given(st.sampled_from(ALL_SEEDS) | messages().map(lambda m: m.pack()), st.integers(0, 10**9),
       st.integers(0, 7))
@pytest.mark.req("SR-CRC-1")
def test_a_flipped_body_bit_is_a_crc_error(data, pos, bit):
    if len(data) == 58:
        return
    bad = bytearray(data)
    bad[58 + pos % (len(data) - 58)] ^= 1 << bit
    with pytest.raises(igtl.errors.CRCError) as e:
        igtl.unpack(bytes(bad))
    assert e.value.recoverable and e.value.offset == 58
    dec = igtl.StreamDecoder()
    dec.feed(bytes(bad) + data)
    with pytest.raises(igtl.errors.CRCError):
        dec.next_message()
    assert [m.pack() for m in dec] == [data]  # the next message is intact


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(ALL_SEEDS) | messages().map(lambda m: m.pack()), st.integers(0, 10**9))
@pytest.mark.req("SR-SIZE-1")
def test_a_truncated_message_is_a_truncation_error(data, cut):
    short = data[: cut % len(data)]
    with pytest.raises(igtl.errors.TruncatedMessageError):
        igtl.unpack(short)
    dec = igtl.StreamDecoder()
    dec.feed(short)
    assert list(dec) == []
    if short:
        with pytest.raises(igtl.errors.TruncatedMessageError):
            dec.close()


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(ALL_SEEDS) | messages().map(lambda m: m.pack()), st.integers(1, 10**6))
@pytest.mark.req("SR-SIZE-1")
def test_a_wrong_body_size_is_refused(data, size):
    n = len(data) - 58
    if size == n:
        return
    bad = bytearray(data)
    bad[42:50] = size.to_bytes(8, "big")
    bad = bytes(bad)
    if size > n:
        with pytest.raises(igtl.errors.TruncatedMessageError):
            igtl.unpack(bad)
    else:
        with pytest.raises(igtl.DecodeError, match="follow"):
            igtl.unpack(bad)
        dec = igtl.StreamDecoder()
        dec.feed(bad)
        # the body it frames is not the one summed, unless the CRC cannot tell (init 0: a
        # body of zero bytes sums to 0 whatever its length)
        if wire.crc64(bad[58 : 58 + size]) != wire.unpack_header(data).crc:
            with pytest.raises(igtl.errors.CRCError):
                dec.next_message()


def _known_gaps() -> list[bytes]:
    v = {p.name: p.read_bytes() for p in VECTORS_DIR.glob("*.bin")}
    unsorted = bytearray(v["transformFormat2.bin"])  # swap the two metadata entries
    meta = bytes(unsorted[-57:])
    unsorted[-57:] = meta[:2] + meta[10:18] + meta[2:10] + meta[-20:] + meta[-39:-20]
    image_version = bytearray(v["image.bin"])
    image_version[59] = 4  # IMAGE header version 4 instead of 1
    latin1 = bytearray(v["transform.bin"])
    latin1[14:16] = b"\xe9\xe9"  # a latin-1 device name
    snan = bytearray(v["transform.bin"])
    snan[58:62] = b"\x7f\xa0\x00\x00"  # a float32 signalling NaN
    two = igtl.TransformMessage(device_name="T", header_version=2, metadata={"a": "1", "b": "2"})
    duplicate = bytearray(two.pack())
    assert duplicate[-4:] == b"a1b2"
    duplicate[-4:] = b"a1a2"  # the key "a" twice
    longer = bytearray(two.pack())
    longer[58:60] = (16).to_bytes(2, "big")  # EXT_HEADER_SIZE 16: four bytes nobody defines
    longer[70:70] = b"\x01\x02\x03\x04"
    longer[42:50] = (len(longer) - 58).to_bytes(8, "big")
    return [_with_crc(b) for b in (unsorted, image_version, snan, latin1, duplicate, longer)]


# Accepted input that is not what this library would encode comes back unchanged too (issue
# 8; each was re-packed canonically before): names that are not UTF-8 (decoded as latin-1 so
# that operator tools get an answer, tests/occ), v2 metadata not sorted by key or with a key
# twice, EXT_HEADER_SIZE > 12, reserved/version bytes that are not the canonical value, float32
# signalling NaNs (a Python float makes them quiet). A decoded message remembers its bytes.
@pytest.mark.parametrize("data", _known_gaps(), ids=["metadata-order", "image-version", "snan",
                                                     "latin1-name", "duplicate-key", "ext-header"])
def test_non_canonical_inputs_repack_exactly(data):
    assert _repacks_exactly(data, cuts=[len(data) // 3])
    msg = igtl.unpack(data)
    # changed, it is encoded from its fields: canonical, and not the input any more
    changed = dataclasses.replace(msg, message_id=msg.message_id)
    assert changed == msg
    assert changed.pack() != data
    again = igtl.unpack(changed.pack())
    # the same values: the same canonical bytes (compared as bytes, a NaN is not equal to itself)
    assert dataclasses.replace(again).pack() == changed.pack()


def test_the_remembered_bytes_are_no_part_of_the_value():
    data = _known_gaps()[0]  # metadata not sorted: packs differently from its fields
    msg = igtl.unpack(data)
    built = dataclasses.replace(msg)
    assert msg == built and built == msg
    assert repr(msg) == repr(built)
    assert msg.pack() == data and built.pack() != data
    assert "_wire" not in {f.name for f in dataclasses.fields(msg) if f.init}
    with pytest.raises(ValueError):  # not an init field: only the codec sets it
        dataclasses.replace(msg, _wire=data)
    # the generated fast constructors leave it unset like __init__ does
    content = data[58 + 12 : 58 + 12 + 48]
    common = {"device_name": "d", "timestamp": 0.0, "header_version": 1}
    assert igtl.TransformMessage.unpack_content(content, common).pack() == (
        igtl.TransformMessage(igtl.unpack(data).elements, device_name="d").pack()
    )


@pytest.mark.parametrize("data", [d for d in _known_gaps() if d[1] == 2], ids=str)
def test_rtp_reassembled_messages_repack_exactly(data):
    from igtl import rtp

    data = bytearray(data)
    data[66:70] = b"\0\0\0\x07"  # a message ID the 16-bit RTP field carries
    data = _with_crc(data)
    reasm = rtp.Reassembler()
    out = [reasm.feed(d, "peer") for d in rtp.fragment(data, payload_length=80)]
    assert out[-1] == data and igtl.unpack(out[-1]).pack() == data


@settings(max_examples=100, deadline=None)
@given(st.sampled_from(ALL_SEEDS + _known_gaps()[:3]) | messages().map(lambda m: m.pack()))
def test_decode_body_repacks_exactly_with_ascii_names(data):
    """decode_body is given the header parsed: exact but for names (re-encoded as UTF-8)."""
    header = wire.unpack_header(data)
    utf8 = (header.message_type.encode("utf-8").ljust(12, b"\0")
            + header.device_name.encode("utf-8").ljust(20, b"\0"))
    assert (igtl.decode_body(header, data[58:]).pack() == data) == (utf8 == data[2:34])
