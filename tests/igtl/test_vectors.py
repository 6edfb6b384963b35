"""Every reference vector decodes to its MANIFEST.json values and re-encodes byte for byte;
each message is also built from its values (not by decoding) and compared with the bytes.

The vectors are the OpenIGTLink project's own test data (github.com/openigtlink/OpenIGTLink,
``Testing/igtlutil/igtl_test_data_*.h``; BSD-style licence, Copyright Insight Software
Consortium), carried in tests/data/igtl-vectors/ with their licence. rtpwrapper.bin belongs to the transport tests.
"""

from __future__ import annotations

import ast
import math

import numpy as np
import pytest

import igtl
from igtl import wire

from .conftest import VECTORS_DIR, vector

FILES = sorted(p.name for p in VECTORS_DIR.glob("*.bin") if p.name != "rtpwrapper.bin")
META = {"First patient age": "22", "Second patient age": "25"}
TS = 1234567892  # raw header timestamp of the vectors (seconds 0, fraction 0x499602D4)
F32 = 1e-6


def parse_header(text: str) -> dict:
    call = ast.parse(f"f({text})", mode="eval").body
    assert isinstance(call, ast.Call)
    return {kw.arg: ast.literal_eval(kw.value) for kw in call.keywords}


def close(a, b) -> bool:
    return all(math.isclose(x, y, rel_tol=F32, abs_tol=F32) for x, y in zip(a, b, strict=True))


def test_all_vectors_listed(manifest):
    assert set(FILES) | {"rtpwrapper.bin"} == set(manifest)


@pytest.mark.parametrize("name", FILES)
def test_header_and_roundtrip(name, manifest):
    data = vector(name)
    entry = manifest[name]
    assert len(data) == entry["bytes"]
    h = parse_header(entry["header"])
    msg = igtl.unpack(data)
    assert msg.header_version == h["version"]
    assert msg.message_type == h["type"]
    assert msg.device_name == h["device"]
    raw = (h["ts_sec"] << 32) | h["ts_frac"]
    assert msg.header_timestamp() == raw
    assert msg.timestamp == wire.raw_to_seconds(raw)
    header = wire.unpack_header(data)
    assert header.body_size == h["body_size"]
    assert header.crc == int(h["crc"], 16)
    if h["version"] == 2:
        assert msg.message_id == h["msg_id"]
        assert dict(msg.metadata) == {k: v for k, _, v in h["metadata"]}
        assert msg.metadata_encoding == {}  # all encoding 3 = the default for ASCII
    else:
        assert msg.metadata == {}
    assert msg.pack() == data
    # The stream decoder agrees, byte by byte.
    dec = igtl.StreamDecoder()
    out = []
    for b in data:
        dec.feed(bytes((b,)))
        out.extend(dec)
    assert out == [msg]


def content(manifest, name):
    return [ast.literal_eval(c) for c in manifest[name].get("content", [])]


def test_capability_values(manifest):
    (pair,) = content(manifest, "capability.bin")
    assert igtl.unpack(vector("capability.bin")).types == tuple(pair[1])


@pytest.mark.parametrize("name", ["colortable.bin", "colortable2.bin"])
def test_colortable_values(manifest, name):
    c = dict(content(manifest, name))
    m = igtl.unpack(vector(name))
    assert (m.index_type, m.map_type, len(m.table)) == (c["index_type"], c["map_type"],
                                                        c["table_len"])
    assert m.table[:16].tobytes().hex() == c["table_first16"]
    assert m.type_name == ("COLORTABLE" if name == "colortable.bin" else "COLORT")


@pytest.mark.parametrize("name", ["command.bin", "commandFormat2.bin"])
def test_command_values(manifest, name):
    c = dict(content(manifest, name))
    m = igtl.unpack(vector(name))
    assert m.command_id == c["command_id"]
    assert m.command_name == c["command_name"]
    assert m.encoding == c["encoding"]
    assert m.command.encode() == c["command"] and len(c["command"]) == c["length"]


def test_image_values(manifest):
    c = dict(content(manifest, "image.bin"))
    m = igtl.unpack(vector("image.bin"))
    hdr = c["img_hdr"]
    assert (1, m.components, m.scalar_type, m.endian, m.coordinate) == hdr[:5]
    assert m.size == hdr[5:8]
    assert close(m.elements, hdr[8:20])
    assert m.offset == hdr[20:23] and m.subvolume_size == hdr[23:26]
    assert m.pixels.size == c["pixels_len"]
    assert m.pixels.tobytes()[:16].hex() == c["first16"]


def test_imgmeta_values(manifest):
    m = igtl.unpack(vector("imgmeta.bin"))
    for e, c in zip(m.images, content(manifest, "imgmeta.bin"), strict=True):
        assert (e.name, e.image_id, e.modality, e.patient_name, e.patient_id) == (
            c["name"], c["id"], c["modality"], c["pname"], c["pid"])
        assert e.timestamp_raw == (c["ts_sec"] << 32) | c["ts_frac"]
        assert (e.size, e.scalar_type) == (c["size"], c["stype"])


def test_lbmeta_values(manifest):
    m = igtl.unpack(vector("lbmeta.bin"))
    for e, c in zip(m.labels, content(manifest, "lbmeta.bin"), strict=True):
        assert (e.name, e.image_id, e.label, e.rgba, e.size, e.owner) == (
            c["name"], c["id"], c["label"], c["rgba"], c["size"], c["owner"])


def test_ndarray_values(manifest):
    c = dict(content(manifest, "ndarray.bin"))
    m = igtl.unpack(vector("ndarray.bin"))
    assert m.scalar_type == c["type"] and m.array.ndim == c["dim"]
    assert m.array.shape == c["size"] and m.array.nbytes == c["data_len"]
    assert m.array.astype(">f8").tobytes()[:32].hex() == c["first32"]
    assert (m.array.ravel() == np.arange(60.0)).all()


def test_point_values(manifest):
    m = igtl.unpack(vector("point.bin"))
    for p, c in zip(m.points, content(manifest, "point.bin"), strict=True):
        assert (p.name, p.group, p.rgba, p.position, p.radius, p.owner) == (
            c["name"], c["group"], c["rgba"], c["xyz"], c["radius"], c["owner"])


def test_polydata_values(manifest):
    (pair,) = content(manifest, "polydata.bin")
    m = igtl.unpack(vector("polydata.bin"))
    flat = lambda cells: 4 * sum(1 + len(c) for c in cells)  # noqa: E731
    assert pair[1] == (
        len(m.points), len(m.vertices), flat(m.vertices), len(m.lines), flat(m.lines),
        len(m.polygons), flat(m.polygons), len(m.strips), flat(m.strips), len(m.attributes))


@pytest.mark.parametrize("name", ["position.bin", "positionFormat2.bin"])
def test_position_values(manifest, name):
    c = dict(content(manifest, name))
    m = igtl.unpack(vector(name))
    assert m.position == c["pos"] and m.quaternion == c["quat(ox,oy,oz,w)"]


def test_sensor_values(manifest):
    c = dict(content(manifest, "sensor.bin"))
    m = igtl.unpack(vector("sensor.bin"))
    assert len(m.data) == c["larray"] and m.status == c["status"]
    assert m.unit.pack() == int(c["unit"], 16)
    assert m.unit == igtl.Unit(0, ((1, 1), (3, -2)))
    assert m.data == c["data"]  # float64: exact


def test_status_values(manifest):
    c = dict(content(manifest, "status.bin"))
    m = igtl.unpack(vector("status.bin"))
    assert (m.code, m.subcode, m.error_name) == (c["code"], c["subcode"], c["error_name"])
    assert m.status_message.encode() + b"\0" == c["message"]


def test_string_values(manifest):
    c = dict(content(manifest, "string.bin"))
    m = igtl.unpack(vector("string.bin"))
    assert m.encoding == c["encoding"] and m.string.encode() == c["string"]


@pytest.mark.parametrize("name", ["tdata.bin", "tdataFormat2.bin"])
def test_tdata_values(manifest, name):
    m = igtl.unpack(vector(name))
    for t, (tname, ttype, _res, els) in zip(m.trackers, content(manifest, name), strict=True):
        assert (t.name, t.tool_type) == (tname, ttype) and t.elements == els


@pytest.mark.parametrize("name", ["trajectory.bin", "trajectoryFormat2.bin"])
def test_trajectory_values(manifest, name):
    m = igtl.unpack(vector(name))
    for t, c in zip(m.trajectories, content(manifest, name), strict=True):
        assert (t.name, t.group, t.type, t.rgba, t.entry, t.target, t.radius, t.owner) == (
            c["name"], c["group"], c["type"], c["rgba"], c["entry"], c["target"], c["radius"],
            c["owner"])


@pytest.mark.parametrize("name", ["transform.bin", "transformFormat2.bin"])
def test_transform_values(manifest, name):
    ((_, els),) = content(manifest, name)
    assert igtl.unpack(vector(name)).elements == els


# --------------------------------------------------------------------------------------------
# Built from values (the reference tests' inputs), then compared with the reference bytes.
MATRIX = (-0.954892, 0.196632, -0.222525, -0.196632, 0.142857, 0.970014,
          0.222525, 0.970014, -0.0977491, 46.0531, 19.4709, 46.0531)
COMMON = {"device_name": "DeviceName", "timestamp": wire.raw_to_seconds(TS)}
V2 = {**COMMON, "header_version": 2, "metadata": META, "message_id": 1}


def image_pixels() -> np.ndarray:
    return np.frombuffer(vector("image.bin")[58 + 72:], np.uint8).reshape(1, 50, 50)


def built_image(**common) -> igtl.ImageMessage:
    return igtl.ImageMessage.from_array(
        image_pixels(), spacing=(1, 1, 1), center=MATRIX[9:],
        direction=np.asarray(MATRIX[:9]).reshape(3, 3).T, coordinate="RAS", endian="little",
        **common)


def built_sensor(**common) -> igtl.SensorMessage:
    return igtl.SensorMessage(
        data=(123456.78, 12345.678, 1234.5678, 123.45678, 12.345678, 1.2345678),
        unit=igtl.Unit(0, ((1, 1), (3, -2))), **common)


PT = igtl.PointElement
TR = igtl.TrajectoryElement
IM = igtl.ImageMetaElement
LB = igtl.LabelMetaElement
VM = igtl.VideoMetaElement
TRAJS = (
    TR("TRAJECTORY_DESCRIPTION_0", "TRAJECTORY", 3, (255, 0, 0, 255), (10, 15, 20), (25, 30, 35),
       5.0, "IMAGE_0"),
    TR("TRAJECTORY_DESCRIPTION_1", "TRAJECTORY", 3, (0, 255, 0, 255), (40, 45, 50), (55, 60, 65),
       2.5, "IMAGE_0"),
    TR("TRAJECTORY_DESCRIPTION_2", "TRAJECTORY", 3, (0, 0, 255, 255), (70, 75, 80), (85, 90, 95),
       0.0, "IMAGE_0"),
)
TRACKERS = tuple(igtl.TrackingElement(f"Tracker{i}", 2, MATRIX) for i in range(3))
COMMAND = {"command_id": 5, "command_name": "This is a test command",
           "command": "Start the tracking machine", "encoding": 3}
CUBE = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1),
                 (0, 1, 1)], np.float32)
IDENT_Z = (-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)

BUILT = {
    "bind.bin": lambda: igtl.BindMessage(children=(
        igtl.TransformMessage(elements=MATRIX, device_name="ChildTrans"),
        built_image(device_name="ChildImage"),
        built_sensor(device_name="ChildSensor"),
    ), **COMMON),
    "capability.bin": lambda: igtl.CapabilityMessage(
        types=("IMAGE", "GET_IMAGE", "TRANSFORM", "GET_TRANS"), **COMMON),
    "colortable.bin": lambda: igtl.ColorTableMessage(
        table=np.arange(256, dtype=np.uint8), type_name="COLORTABLE", **COMMON),
    "colortable2.bin": lambda: igtl.ColorTableMessage(table=np.arange(256, dtype=np.uint8),
                                                      **COMMON),
    "command.bin": lambda: igtl.CommandMessage(**COMMAND),
    "commandFormat2.bin": lambda: igtl.CommandMessage(
        **COMMAND, device_name="OpticalTracker", header_version=2, metadata=META, message_id=1),
    "image.bin": lambda: built_image(**COMMON),
    "imgmeta.bin": lambda: igtl.ImageMetaMessage(images=(
        IM("IMAGE_DESCRIPTION_0", "IMAGE_0", "CT", "PATIENT_0", "PATIENT_ID_0", 1234567892,
           (512, 512, 64), 5),
        IM("IMAGE_DESCRIPTION_1", "IMAGE_1", "MRI", "PATIENT_1", "PATIENT_ID_1", 1234567896,
           (256, 128, 32), 5),
        IM("IMAGE_DESCRIPTION_2", "IMAGE_2", "PET", "PATIENT_2", "PATIENT_ID_2", 1234567900,
           (256, 256, 32), 5),
    ), **COMMON),
    "lbmeta.bin": lambda: igtl.LabelMetaMessage(labels=tuple(
        LB(f"LABEL_DESCRIPTION_{i}", f"LABEL_{i}", i + 1, rgba, (256, 128, 32), "IMAGE_0")
        for i, rgba in enumerate([(255, 0, 0, 255), (0, 255, 0, 255), (0, 0, 255, 255)])
    ), **COMMON),
    "ndarray.bin": lambda: igtl.NDArrayMessage(array=np.arange(60.0).reshape(5, 4, 3), **COMMON),
    "point.bin": lambda: igtl.PointMessage(points=(
        PT("POINT_DESCRIPTION_0", "Landmark", (255, 0, 0, 255), (10, 15, 20), 5.0, "IMAGE_0"),
        PT("POINT_DESCRIPTION_1", "Landmark", (0, 255, 0, 255), (25, 30, 35), 3.0, "IMAGE_0"),
        PT("POINT_DESCRIPTION_2", "Landmark", (0, 0, 255, 255), (40, 45, 50), 1.0, "IMAGE_0"),
    ), **COMMON),
    "polydata.bin": lambda: igtl.PolyDataMessage(
        points=CUBE,
        polygons=((0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6),
                  (3, 0, 4, 7)),
        attributes=(igtl.PolyDataAttribute(0, "attr", np.arange(8, dtype=np.float32)),),
        **COMMON),
    "position.bin": lambda: igtl.PositionMessage(
        (46.0531, 19.4709, 46.0531), (0.0, 0.5773502691, 0.5773502692, 0.3333333333), **COMMON),
    "positionFormat2.bin": lambda: igtl.PositionMessage(
        (46.0531, 19.4709, 46.0531), (0.0, 0.5773502691, 0.5773502692, 0.3333333333), **V2),
    "sensor.bin": lambda: built_sensor(**COMMON),
    "status.bin": lambda: igtl.StatusMessage(15, 10, "ACTUATOR_DISABLED",
                                             "Actuator A is disabled.", **COMMON),
    "string.bin": lambda: igtl.StringMessage("Welcome to OpenIGTLink", 3, **COMMON),
    "tdata.bin": lambda: igtl.TrackingDataMessage(trackers=TRACKERS, **COMMON),
    "tdataFormat2.bin": lambda: igtl.TrackingDataMessage(trackers=TRACKERS, **V2),
    "trajectory.bin": lambda: igtl.TrajectoryMessage(trajectories=TRAJS, **COMMON),
    "trajectoryFormat2.bin": lambda: igtl.TrajectoryMessage(trajectories=TRAJS, **V2),
    "transform.bin": lambda: igtl.TransformMessage(elements=MATRIX, **COMMON),
    "transformFormat2.bin": lambda: igtl.TransformMessage(elements=MATRIX, **V2),
    "videometa.bin": lambda: igtl.VideoMetaMessage(videos=(
        VM("VIDEO_DESCRIPTION_0", "VIDEO_0", "PATIENT_0", "PATIENT_ID_0", 4, 50.0,
           (512, 512, 64), MATRIX, 5),
        VM("VIDEO_DESCRIPTION_1", "VIDEO_1", "PATIENT_1", "PATIENT_ID_1", -2, 100.0,
           (256, 128, 32), (*IDENT_Z, 50.0, 100.0, 16.0), 5),
        VM("VIDEO_DESCRIPTION_2", "VIDEO_2", "PATIENT_2", "PATIENT_ID_2", 0, 20.5,
           (256, 256, 32), (*MATRIX[:9], 150.0, 0.0, 200.0), 5),
    ), device_name="DeviceName", timestamp=wire.raw_to_seconds(TS), header_version=2),
}


def test_every_vector_has_a_builder():
    assert set(BUILT) == set(FILES)


@pytest.mark.parametrize("name", FILES)
def test_built_from_values(name):
    built = BUILT[name]()
    assert built.pack() == vector(name)


def test_image_geometry_round_trip():
    m = igtl.unpack(vector("image.bin"))
    again = igtl.ImageMessage.from_array(
        m.pixels, spacing=m.spacing, origin=m.origin, direction=m.direction, **COMMON)
    assert close(again.elements, m.elements)
    assert close(again.origin, m.origin)
