"""Message-level API: helpers, conventions and caller errors of the content types."""

from __future__ import annotations

import struct

import numpy as np
import pytest

import igtl
from igtl.errors import ContentError

from .conftest import vector


def rt(m: igtl.Message) -> igtl.Message:
    return igtl.unpack(m.pack())


def test_unit_pack_unpack():
    u = igtl.Unit(0, ((1, 1), (3, -2)))
    assert u.pack() == 0x00443E0000000000
    assert igtl.Unit.unpack(0x00443E0000000000) == u
    assert igtl.Unit.unpack(2**64 - 1).pack() == 2**64 - 1
    assert str(igtl.Unit(11, ((1, 1),))) == "millim"
    with pytest.raises(ValueError):
        igtl.Unit(0, ((64, 1),))
    with pytest.raises(ValueError):
        igtl.Unit(16)


def test_image_center_and_corner():
    a = np.arange(2 * 3 * 4, dtype=np.int16).reshape(2, 3, 4)  # k, j, i
    m = igtl.ImageMessage.from_array(a, spacing=(0.5, 1.0, 2.0), origin=(10, 20, 30),
                                     coordinate="LPS", endian="big")
    assert m.size == (4, 3, 2) and m.coordinate == 2 and m.endian == 1
    assert m.center == (10 + 0.5 * 1.5, 20 + 1.0 * 1.0, 30 + 2.0 * 0.5)
    assert m.origin == (10.0, 20.0, 30.0)
    assert np.allclose(m.spacing, (0.5, 1.0, 2.0))
    back = rt(m)
    assert back == m
    assert back.pixels.dtype.byteorder == ">"  # E flag honoured: wire order kept
    assert (back.pixels[..., 0] == a).all()
    assert m.pack()[58 + 72 : 58 + 74] == b"\x00\x00" and m.pack()[58 + 74 : 58 + 76] == b"\x00\x01"
    little = m.replace(endian=2).pack()
    assert little[58 + 74 : 58 + 76] == b"\x01\x00"
    with pytest.raises(ValueError):
        igtl.ImageMessage.from_array(a, origin=(0, 0, 0), center=(0, 0, 0))


def test_image_subvolume():
    sub = np.ones((1, 2, 3, 3), np.uint8)
    m = igtl.ImageMessage(pixels=sub, size=(10, 10, 5), offset=(7, 8, 4))
    assert rt(m) == m and m.subvolume_size == (3, 2, 1)
    with pytest.raises(ValueError):
        igtl.ImageMessage(pixels=sub, size=(10, 10, 5), offset=(8, 8, 4))


def test_image_data_length_checked():
    data = bytearray(vector("image.bin")[58:])
    short = igtl.RawMessage(type_name="IMAGE", content=bytes(data[:-1])).pack()
    with pytest.raises(ContentError, match="needs 2500") as e:
        igtl.unpack(short)
    assert e.value.offset == 58 + 72


def test_ndarray_complex_and_equality():
    a = np.array([[1 + 2j, -3.5j]], dtype=np.complex128)
    m = igtl.NDArrayMessage(array=a)
    assert m.pack()[58 + 2 + 4 :][:16] == struct.pack(">dd", 1.0, 2.0)
    assert rt(m) == m and rt(m).array.dtype == np.complex128
    assert m != igtl.NDArrayMessage(array=a.real)


def test_queries():
    for name in ("GET_TRANS", "GET_TRANSFOR", "STP_TDATA", "GET_CAPABIL"):
        m = igtl.QueryMessage(type_name=name, device_name="x")
        assert m.message_type == name and len(m.pack()) == 58 and rt(m) == m
    v2 = igtl.QueryMessage(type_name="GET_STATUS", header_version=2)
    assert len(v2.pack()) == 58 + 14 and rt(v2) == v2
    with pytest.raises(ValueError):
        igtl.QueryMessage(type_name="GET_NOPE")
    assert rt(igtl.RTSMessage(type_name="RTS_BIND", status=None)).status is None
    assert rt(igtl.RTSMessage(type_name="RTS_TDATA", status=1)).status == 1
    stt = igtl.StartTrackingMessage("STT_QTDATA", 50, "RAS")
    assert len(stt.pack_content()) == 36 and rt(stt) == stt
    assert len(igtl.StartVideoMessage("H264", 33).pack_content()) == 9
    assert rt(igtl.StartPolyDataMessage(10**9)).resolution == 10**9


def test_bind_children_and_padding():
    t = igtl.TransformMessage(device_name="T")
    s = igtl.StringMessage("odd", device_name="S")  # 7-byte content: padded
    b = igtl.BindMessage(children=(s, t))
    content = b.pack_content()
    assert len(content) == 2 + 40 + 2 + 4 + 7 + 1 + 48  # name table "S\0T\0" is even
    back = rt(b)
    assert back == b
    kids = back.messages()
    assert kids[0].string == "odd" and kids[1].elements == t.elements
    g = igtl.GetBindMessage(children=(("TRANSFORM", "T"), ("IMAGE", "AB")))
    assert len(g.pack_content()) % 2 == 0 and rt(g) == g
    assert igtl.GetBindMessage().pack_content() == b""
    assert rt(igtl.StartBindMessage(100, (("STATUS", "x"),))).resolution == 100


def test_vfixture_both_layouts():
    m = igtl.VirtualFixtureMessage(hardness=2.5, spheres=((1, 2, 3, 4), (5, 6, 7, 8)))
    content = m.pack_content()
    assert len(content) == 7 + 32 and content[:7] == struct.pack(">BHf", 1, 2, 2.5)
    padded = content[:1] + b"\0" + content[1:]
    decoded = igtl.unpack(igtl.RawMessage(type_name="VFIXTURE", content=padded).pack())
    assert decoded == m and decoded.padded
    assert decoded.pack_content() == content
    for bad in (content[:-1], content[:1] + b"\0\x03" + content[3:]):
        with pytest.raises(ContentError):
            igtl.unpack(igtl.RawMessage(type_name="VFIXTURE", content=bad).pack())


def test_command_and_rts_command():
    c = igtl.CommandMessage(7, "Get", "<Command/>", header_version=2, metadata={"k": "v"})
    r = igtl.RTSCommandMessage(7, "", "<CommandReply Status=\"SUCCESS\"/>", header_version=2,
                               metadata={"Status": "SUCCESS"})
    assert rt(c) == c.replace(encoding=3) and rt(r).message_type == "RTS_COMMAND"
    with pytest.raises(ValueError):
        igtl.CommandMessage(2**32)


def test_colortable_names():
    m = igtl.ColorTableMessage(table=np.zeros((256, 3), np.uint8), type_name="COLORTABLE")
    assert m.map_type == 19 and m.message_type == "COLORTABLE" and rt(m) == m
    assert igtl.ColorTableMessage().message_type == "COLORT"


def test_caller_errors_are_value_errors():
    with pytest.raises(ValueError):
        igtl.PointElement(name="x" * 65)
    with pytest.raises(ValueError):
        igtl.TrackingElement(elements=(1.0,))
    with pytest.raises(ValueError):
        igtl.SensorMessage(data=[0.0] * 256)
    with pytest.raises(ValueError):
        igtl.NDArrayMessage(array=np.zeros(3, np.float16))
    with pytest.raises(ValueError):
        igtl.TransformMessage(elements=(1.0,)).pack()


def test_position_v2_builds_the_same_message_as_the_constructor():
    """The stream sender's fast constructor: equal to the dataclass one, same bytes, and the
    bytes decode back to it (both POSITION layouts)."""
    from types import MappingProxyType

    from igtl.codec import unpack
    from igtl.messages.transform import PositionMessage, position_v2

    meta = MappingProxyType({"run": "1", "clutch": "0"})
    for layout, quat in ((24, (0.0, 0.0, 0.0, 1.0)), (28, (0.5, 0.5, 0.5, 0.5))):
        fast = position_v2("Master", 1.7e9 + 0.25, 77, meta, (1.5, -2.0, 3.25), quat, layout)
        slow = PositionMessage(
            (1.5, -2.0, 3.25),
            quat,
            layout,
            device_name="Master",
            timestamp=1.7e9 + 0.25,
            header_version=2,
            message_id=77,
            metadata={"run": "1", "clutch": "0"},
        )
        assert fast == slow
        assert fast.pack() == slow.pack()
        back = unpack(fast.pack())
        assert back == slow and back.message_id == 77 and back.metadata["run"] == "1"
