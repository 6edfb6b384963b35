"""Our TCPClient / TCPServer send, reference C++ programs receive and print; we parse what they
print and compare with what we sent.

The reference receivers call ``Unpack(1)`` (CRC check on) and print the content only when the
CRC and the layout are right, so every printed block is also a CRC check of our encoder.

Messages are built with our constructors where the API is settled (TRANSFORM, POSITION,
STATUS, STRING). Other types are built as reference-format bytes by the independent encoder in
helpers.py and turned into our typed message by ``igtl.unpack`` (``h.ours``), so the bytes on the
wire are produced by our encoder either way. The reference library is protocol 2 (header v1
only), so everything sent to it is header v1.
"""

from __future__ import annotations

import math
import struct
import time

import numpy as np
import pytest

import igtl

from . import helpers as h

pytestmark = pytest.mark.interop


def _printed_stamp(block):
    sec, ns = h.value_of(block, "Time stamp").split(".")
    return int(sec), int(ns)


def _expected_stamp(msg):
    raw = h.split_wire(msg.pack()).timestamp_raw
    return raw >> 32, h.frac_to_nanosec(raw & 0xFFFFFFFF)


@pytest.fixture
def receive_server(ref_server, igtl_client):
    """ReceiveServer on a free port and our TCPClient connected to it."""
    peer, port = ref_server("ReceiveServer", "{port}")
    return peer, igtl_client(port)


@pytest.fixture
def receive_client(ref, igtl_server):
    """Our TCPServer and ReceiveClient connected to it."""
    srv = igtl_server()
    peer = ref("ReceiveClient", "127.0.0.1", srv.address[1])
    assert srv.wait_for_peers(1, h.WAIT), peer.describe()
    return peer, srv


def _messages(peer):
    return h.blocks_after(peer.lines, "Time stamp:")


def _wait_blocks(peer, n, marker):
    """Wait for ``n`` message blocks whose output contains ``marker``; return all blocks."""
    ok = peer.wait_output(
        lambda ls: sum(1 for b in h.blocks_after(ls, "Time stamp:") if any(marker in x for x in b))
        >= n
    )
    assert ok, peer.describe()
    return _messages(peer)


# ------------------------------------------------------------------------------ TRANSFORM
def _rot(ax: float, ay: float, az: float, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = (math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay),
                              math.cos(az), math.sin(az))
    m = np.eye(4)
    m[:3, :3] = (np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
                 @ np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
                 @ np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]]))
    m[:3, 3] = t
    return m


def test_receive_server_prints_our_transforms_and_timestamps(receive_server):
    """Three TRANSFORMs (non-symmetric rotations, so a row/column swap shows): ReceiveServer
    prints each matrix and the header timestamp exactly as we encoded it."""
    peer, cli = receive_server
    mats = [_rot(0.1, 0.2, 0.3, (1.5, -2.25, 300.125)), _rot(-1.0, 0.5, 2.0, (0, 0, -7)),
            _rot(0.0, -0.7, 0.01, (123.0, 45.5, 6.75))]
    now = time.time()
    sent = [igtl.TransformMessage.from_matrix(m, device_name=f"Tool{i}",
                                              timestamp=now + i * 0.1234567)
            for i, m in enumerate(mats)]
    for msg in sent:
        assert cli.send(msg)
    assert peer.wait_output(lambda ls: len(h.parse_matrices(ls)) >= 3), peer.describe()
    blocks = _messages(peer)
    printed = h.parse_matrices(peer.lines)
    assert len(printed) == len(blocks) == 3
    for msg, mat, got, block in zip(sent, mats, printed, blocks, strict=True):
        assert "Receiving TRANSFORM data type." in block
        assert h.close(got, mat, rtol=1e-5, atol=2e-6), (got, mat)
        # the 1.11 reference prints the stamp after a round trip through a double (~240 ns
        # resolution at today's epoch), so compare to within 0.5 us, not bit for bit
        (sec, ns), (esec, ens) = _printed_stamp(block), _expected_stamp(msg)
        assert sec == esec and abs(ns - ens) <= 500, ((sec, ns), (esec, ens))
        assert abs(sec + ns * 1e-9 - msg.timestamp) < 1e-6


def test_receive_server_skips_unknown_type_and_stays_in_sync(receive_server):
    """An unknown type is skipped by BODY_SIZE; the TRANSFORM after it still decodes."""
    peer, cli = receive_server
    assert cli.send(igtl.RawMessage(type_name="OCC_PRIVATE", content=b"\x01\x02\x03odd!",
                                    device_name="x"))
    assert cli.send(igtl.TransformMessage.from_matrix(_rot(0.3, 0.2, 0.1, (1, 2, 3))))
    assert peer.wait_output(lambda ls: len(h.parse_matrices(ls)) >= 1), peer.describe()
    blocks = _messages(peer)
    assert "Receiving : OCC_PRIVATE" in blocks[0] and "Size : 7" in blocks[0]
    assert "Receiving TRANSFORM data type." in blocks[1]
    assert h.close(h.parse_matrices(peer.lines)[0], _rot(0.3, 0.2, 0.1, (1, 2, 3)))


# ------------------------------------------------------------------------------ POSITION
@pytest.mark.parametrize("layout", [28, 24, 12])
def test_receive_server_prints_our_position(receive_server, layout):
    """POSITION in its three content sizes (28: position + quaternion, 24: position + 3-element
    quaternion with w rebuilt by the receiver, 12: position only -> identity quaternion)."""
    peer, cli = receive_server
    q = np.array([0.1, -0.5, 0.3, 0.8])
    q = tuple((q / np.linalg.norm(q)).tolist())
    pos = (12.5, -3.25, 250.0)
    assert cli.send(igtl.PositionMessage(position=pos, quaternion=q, layout=layout,
                                         device_name="Needle"))
    _wait_blocks(peer, 1, "quaternion =")
    text = peer.text
    got_pos = h.floats(text.split("position   = ", 1)[1].split("\n", 1)[0])
    got_q = h.floats(text.split("quaternion = ", 1)[1].split("\n", 1)[0])
    assert h.close(got_pos, pos)
    expect_q = (0.0, 0.0, 0.0, 1.0) if layout == 12 else q
    assert h.close(got_q, expect_q, atol=1e-5), (got_q, expect_q)


# ------------------------------------------------------------------------------ STATUS / STRING
def test_receive_server_prints_our_status(receive_server):
    peer, cli = receive_server
    assert cli.send(igtl.StatusMessage(code=15, subcode=-42, error_name="ACTUATOR_DISABLED",
                                       status_message="Joint 3 brake engaged; homing needed",
                                       device_name="Robot"))
    block = _wait_blocks(peer, 1, " Status    :")[0]
    assert "Receiving STATUS data type." in block
    assert h.value_of(block, "Code") == "15"
    assert h.value_of(block, "SubCode") == "-42"
    assert h.value_of(block, "Error Name") == "ACTUATOR_DISABLED"
    assert h.value_of(block, "Status") == "Joint 3 brake engaged; homing needed"


@pytest.mark.parametrize(
    "text,encoding",
    [("Welcome to OpenIGTLink", 3), ("Grüße aus dem OP: 45° ✓", 106), ("", 3)],
    ids=["ascii", "utf8", "empty"],
)
def test_receive_server_prints_our_string(receive_server, text, encoding):
    peer, cli = receive_server
    assert cli.send(igtl.StringMessage(string=text, encoding=encoding, device_name="Text"))
    block = _wait_blocks(peer, 1, "Encoding:")[0]
    line = next(x for x in block if x.startswith("Encoding:"))
    assert line == f"Encoding: {encoding}; String: {text}"


def test_string_echo_server_echoes_our_strings(ref_server, igtl_client):
    """StringEchoServer sends each STRING back (device renamed "StringEchoServer"): ASCII and
    UTF-8 (MIBenum 106) text survive both directions, in order."""
    peer, port = ref_server("StringEchoServer", "{port}")
    cli = igtl_client(port)
    texts = [("Hello, robot", 3), ("Résection à 5 mm ✓", 106), ("x" * 1000, 3)]
    for text, enc in texts:
        assert cli.send(igtl.StringMessage(string=text, encoding=enc, device_name="Me"))
    echoes = h.collect(cli, 3, where=h.of_type("STRING"))
    assert [(m.string, m.encoding) for m in echoes] == texts, peer.describe()
    assert {m.device_name for m in echoes} == {"StringEchoServer"}
    assert peer.wait_count("^Echoing: ", 3) == 3


# ------------------------------------------------------------------------------ POINT / TRAJ
POINTS = [
    dict(name="Entry", group="Landmark", rgba=(255, 0, 0, 255), xyz=(1.5, -2.0, 30.25),
         diameter=2.5, owner="CT_1"),
    dict(name="Target (tumour centre)", group="Fiducial", rgba=(10, 20, 30, 0),
         xyz=(-100.125, 0.0, 1e3), diameter=0.0, owner=""),
]


def _check_point_blocks(blocks, points):
    assert len(blocks) == len(points)
    for b, p in zip(blocks, points, strict=True):
        assert h.value_of(b, "Name") == p["name"]
        assert h.value_of(b, "GroupName") == p["group"]
        assert tuple(int(x) for x in h.floats(h.value_of(b, "RGBA"))) == p["rgba"]
        assert h.close(h.floats(h.value_of(b, "Position")), p["xyz"])
        assert h.close(h.floats(h.value_of(b, "Radius")), [p["diameter"]])
        assert h.value_of(b, "Owner") == p["owner"]


def test_receive_server_prints_our_point(receive_server):
    peer, cli = receive_server
    assert cli.send(h.ours(h.pack_wire("POINT", "Plan", h.encode_point(POINTS))))
    assert peer.wait_count(r"^ Owner", 2) == 2, peer.describe()
    _check_point_blocks(h.element_blocks(peer.lines), POINTS)


def test_receive_client_prints_our_point(receive_client):
    peer, srv = receive_client
    assert srv.send(h.ours(h.pack_wire("POINT", "Plan", h.encode_point(POINTS)))) == 1
    assert peer.wait_count(r"^ Owner", 2) == 2, peer.describe()
    _check_point_blocks(h.element_blocks(peer.lines), POINTS)


TRAJ = [
    dict(name="Path A", group="Plan", type=3, rgba=(0, 128, 255, 255), entry=(10, 20, 30),
         target=(40.5, 50.25, 60.125), diameter=1.8, owner="MR"),
    dict(name="Path B", group="Plan", type=3, rgba=(1, 2, 3, 4), entry=(-1, -2, -3),
         target=(0, 0, 0), diameter=0.5, owner="MR"),
]


def test_receive_server_prints_our_trajectory(receive_server):
    peer, cli = receive_server
    assert cli.send(h.ours(h.pack_wire("TRAJ", "Trajectories", h.encode_traj(TRAJ))))
    assert peer.wait_count(r"^ Owner", 2) == 2, peer.describe()
    for b, t in zip(h.element_blocks(peer.lines), TRAJ, strict=True):
        assert (h.value_of(b, "Name"), h.value_of(b, "GroupName")) == (t["name"], t["group"])
        assert tuple(int(x) for x in h.floats(h.value_of(b, "RGBA"))) == t["rgba"]
        assert h.close(h.floats(h.value_of(b, "Entry Pt")), t["entry"])
        assert h.close(h.floats(h.value_of(b, "Target Pt")), t["target"])
        assert h.close(h.floats(h.value_of(b, "Radius")), [t["diameter"]])


# ------------------------------------------------------------------------------ CAPABILITY
def test_receive_server_prints_our_capability(receive_server):
    peer, cli = receive_server
    types = ["TRANSFORM", "GET_TRANS", "STATUS", "STRING", "CAPABILITY", "STT_TDATA"]
    assert cli.send(h.ours(h.pack_wire("CAPABILITY", "Robot", h.encode_capability(types))))
    assert peer.wait_count(r"^Typename #", len(types)) == len(types), peer.describe()
    got = [x.split(": ", 1)[1] for x in peer.lines if x.startswith("Typename #")]
    assert got == types


# ------------------------------------------------------------------------------ IMAGE
def _test_volume() -> np.ndarray:
    k, j, i = np.mgrid[0:3, 0:5, 0:7]
    return (i * 100 + j * 10 + k - 300).astype(">i2")  # int16, big-endian pixels


def test_receive_server_prints_our_image(receive_server):
    """A 7x5x3 int16 volume with spacing (0.5, 0.75, 2.5): ReceiveServer prints the device,
    scalar type, dimensions, spacing and sub-volume we sent."""
    peer, cli = receive_server
    raw = h.encode_image(_test_volume(), spacing=(0.5, 0.75, 2.5), center=(10, 20, 30))
    assert cli.send(h.ours(h.pack_wire("IMAGE", "Ultrasound", raw)))
    block = _wait_blocks(peer, 1, "Sub-Volume offset")[0]
    assert h.value_of(block, "Device Name") == "Ultrasound"
    assert h.value_of(block, "Scalar Type") == "4"
    assert h.floats(h.value_of(block, "Dimensions")) == [7, 5, 3]
    assert h.close(h.floats(h.value_of(block, "Spacing")), [0.5, 0.75, 2.5])
    assert h.floats(h.value_of(block, "Sub-Volume dimensions")) == [7, 5, 3]
    assert h.floats(h.value_of(block, "Sub-Volume offset")) == [0, 0, 0]


# ------------------------------------------------------------------------------ BIND
def test_receive_server_prints_our_bind(receive_server):
    """BIND of a STRING (odd-sized body: exercises the pad byte) and a TRANSFORM."""
    peer, cli = receive_server
    mat = _rot(0.4, -0.2, 1.1, (5, 6, 7))
    children = [
        ("STRING", "Note", struct.pack(">HH", 3, 5) + b"odd!!"),
        ("TRANSFORM", "Probe", struct.pack(">12f", *h.matrix_to_elements(mat))),
    ]
    assert cli.send(h.ours(h.pack_wire("BIND", "Bundle", h.encode_bind(children))))
    assert peer.wait_output(lambda ls: len(h.parse_matrices(ls)) >= 1), peer.describe()
    lines = peer.lines
    names = [x.split(": ", 1)[1] for x in lines if x.startswith("Message name:")]
    assert names == ["Note", "Probe"]
    assert "Encoding: 3; String: odd!!" in lines
    assert h.close(h.parse_matrices(lines)[0], mat)


# ------------------------------------------------------------------------------ TDATA / QTDATA
TDATA = [
    dict(name="Tracker", type=1, matrix=_rot(0, 0, 0, (0, 0, 0))),
    dict(name="Stylus", type=2, matrix=_rot(0.2, 0.4, -0.6, (10.5, -20.25, 30.125))),
    dict(name="Needle tip", type=3, matrix=_rot(1.0, 0.0, 0.5, (1, 2, 3))),
]


def test_receive_client_prints_our_tdata(receive_client):
    peer, srv = receive_client
    assert srv.send(h.ours(h.pack_wire("TDATA", "Tracking", h.encode_tdata(TDATA)))) == 1
    assert peer.wait_output(lambda ls: len(h.parse_matrices(ls)) >= 3), peer.describe()
    blocks = h.element_blocks(peer.lines)
    mats = h.parse_matrices(peer.lines)
    for b, m, e in zip(blocks, mats, TDATA, strict=True):
        assert h.value_of(b, "Name") == e["name"]
        assert h.value_of(b, "Type") == str(e["type"])
        assert h.close(m, e["matrix"])


QTDATA = [
    dict(name="Ref", type=1, position=(0.0, 0.0, 0.0), quaternion=(0.0, 0.0, 0.0, 1.0)),
    dict(name="Tool", type=2, position=(1.25, -2.5, 500.0),
         quaternion=(0.18257419, 0.36514837, 0.54772256, 0.73029674)),
]


def test_receive_client_prints_our_qtdata(receive_client):
    peer, srv = receive_client
    assert srv.send(h.ours(h.pack_wire("QTDATA", "QTracking", h.encode_qtdata(QTDATA)))) == 1
    assert peer.wait_count(r"^ Quaternion", 2) == 2, peer.describe()
    for b, e in zip(h.element_blocks(peer.lines), QTDATA, strict=True):
        assert h.value_of(b, "Name") == e["name"]
        assert h.value_of(b, "Type") == str(e["type"])
        assert h.close(h.floats(h.value_of(b, "Position")), e["position"])
        assert h.close(h.floats(h.value_of(b, "Quaternion")), e["quaternion"])


def test_receive_client_prints_our_basic_types_in_order(receive_client):
    """Our server's stream of mixed types to one reference client: TRANSFORM, STATUS, STRING,
    POSITION, CAPABILITY, each printed in the order sent."""
    peer, srv = receive_client
    mat = _rot(0.5, 0.25, -0.125, (9, 8, 7))
    for msg in [
        igtl.TransformMessage.from_matrix(mat, device_name="A"),
        igtl.StatusMessage(code=6, subcode=7, error_name="BUSY", status_message="moving",
                           device_name="B"),
        igtl.StringMessage(string="hello from the robot", device_name="C"),
        igtl.PositionMessage(position=(1, 2, 3), quaternion=(0, 0, 0, 1), device_name="D"),
        h.ours(h.pack_wire("CAPABILITY", "E", h.encode_capability(["TRANSFORM", "STATUS"]))),
    ]:
        assert srv.send(msg) == 1
    assert peer.wait_count(r"^Typename #1", 1), peer.describe()
    kinds = [x for x in peer.lines if x.startswith("Receiving ")]
    assert kinds == [f"Receiving {t} data type." for t in
                     ("TRANSFORM", "STATUS", "STRING", "POSITION", "CAPABILITY")]
    assert h.close(h.parse_matrices(peer.lines)[0], mat)
    lines = peer.lines
    assert " Status    : moving" in lines and " Error Name: BUSY" in lines
    assert "Encoding: 3; String: hello from the robot" in lines


# ------------------------------------------------------------------------ query / stream servers
def test_tracking_data_client_stt_stream_stp_with_our_server(ref, igtl_server):
    """TrackingDataClient sends STT_TDATA (resolution 1000/fps ms, coordinate "Patient"); our
    server answers with a TDATA stream, which the client prints; after 10 frames it sends
    STP_TDATA."""
    srv = igtl_server()
    peer = ref("TrackingDataClient", "127.0.0.1", srv.address[1], 50)
    (stt,) = h.collect(srv, 1, where=h.of_type("STT_TDATA"))
    w = h.split_wire(h.ours(stt.pack()).pack())  # typed STT_TDATA, re-encoded intact
    assert stt.device_name == "TDataClient"
    assert h.decode_stt_tdata(w.content) == (20, "Patient")
    frames = []
    for k in range(10):
        els = [dict(name=f"Ch{c}", type=2, matrix=_rot(0.1 * k, 0.05 * c, 0, (k, c, 1.5)))
               for c in range(2)]
        frames.append(els)
        assert srv.send(h.ours(h.pack_wire("TDATA", "Tracker", h.encode_tdata(els)))) == 1
    (stp,) = h.collect(srv, 1, where=h.of_type("STP_TDATA"))
    assert stp.device_name == "TDataClient"
    # STP_TDATA is sent after the 10th frame was printed, but on another channel: wait for it
    assert peer.wait_output(lambda ls: len(h.parse_matrices(ls)) >= 20), peer.describe()
    mats = h.parse_matrices(peer.lines)
    names = [h.value_of(b, "Name") for b in h.element_blocks(peer.lines)]
    assert names == [e["name"] for f in frames for e in f]
    for m, e in zip(mats, [e for f in frames for e in f], strict=True):
        assert h.close(m, e["matrix"])


def test_polydata_client_gets_our_polydata(ref, igtl_server):
    """PolyDataClient sends GET_POLYDATA; our server answers with a POLYDATA (tetrahedron, a
    line, a point scalar) that the client prints."""
    srv = igtl_server()
    peer = ref("PolyDataClient", "127.0.0.1", srv.address[1])
    (get,) = h.collect(srv, 1, where=h.of_type("GET_POLYDATA"))
    assert get.device_name == "Client"
    pts = [(0.0, 0.0, 0.0), (10.0, 0.0, 0.0), (0.0, 10.5, 0.0), (0.0, 0.0, -7.25)]
    polys = [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]
    raw = h.encode_polydata(pts, polys, lines=[[0, 3]], scalars=("temp", [36.5, 37.0, 37.5, 38.0]))
    assert srv.send(h.ours(h.pack_wire("POLYDATA", "Client", raw))) == 1
    assert peer.wait_count(r"^=+$", 1), peer.describe()
    lines = peer.lines
    got_pts = [h.floats(x.split("=", 1)[1]) for x in lines if x.strip().startswith("point[")]
    assert got_pts == [list(p) for p in pts]
    cells = [[int(v) for v in h.floats(x.split("=", 1)[1])] for x in lines if "cell[" in x]
    # the example prints the first index twice: "(a, a, b, c)"
    assert [c[1:] for c in cells] == [[0, 3], *polys]
    assert "  Name = temp" in lines and "  Type = POINT_SCALAR" in lines
    data = [h.floats(x.split("=", 1)[1]) for x in lines if x.strip().startswith("data[")]
    assert data == [[36.5], [37.0], [37.5], [38.0]]


def test_imagemeta_client_gets_our_imgmeta(ref, igtl_server):
    srv = igtl_server()
    peer = ref("ImageMetaClient", "127.0.0.1", srv.address[1])
    (get,) = h.collect(srv, 1, where=h.of_type("GET_IMGMETA"))
    assert get.device_name == "Client"
    items = [dict(name="Pre-op CT", device="CT_1", modality="CT", patient_name="Doe^John",
                  patient_id="P-0001", timestamp_raw=(1_700_000_000 << 32) | 0x80000000,
                  size=(512, 512, 200), scalar_type=4)]
    assert srv.send(h.ours(h.pack_wire("IMGMETA", "Client", h.encode_imgmeta(items)))) == 1
    assert peer.wait_count(r"^ ScalarType", 1), peer.describe()
    (b,) = h.element_blocks(peer.lines)
    assert h.value_of(b, "Name") == "Pre-op CT" and h.value_of(b, "DeviceName") == "CT_1"
    assert h.value_of(b, "Modality") == "CT" and h.value_of(b, "PatientName") == "Doe^John"
    assert h.value_of(b, "PatientID") == "P-0001"
    assert abs(float(h.value_of(b, "TimeStamp")) - 1_700_000_000.5) < 1e-3
    assert h.floats(h.value_of(b, "Size")) == [512, 512, 200]
    assert h.value_of(b, "ScalarType") == "4"


def test_labelmeta_client_gets_our_lbmeta(ref, igtl_server):
    srv = igtl_server()
    peer = ref("LabelMetaClient", "127.0.0.1", srv.address[1])
    (get,) = h.collect(srv, 1, where=h.of_type("GET_LBMETA"))
    items = [dict(name="Liver", device="SEG_1", label=7, rgba=(200, 100, 50, 255),
                  size=(256, 256, 100), owner="CT_1"),
             dict(name="Vessel", device="SEG_1", label=9, rgba=(255, 0, 0, 128),
                  size=(256, 256, 100), owner="CT_1")]
    assert srv.send(h.ours(h.pack_wire("LBMETA", "Labels", h.encode_lbmeta(items)))) == 1
    assert peer.wait_count(r"^ Owner", 2) == 2, peer.describe()
    for b, e in zip(h.element_blocks(peer.lines), items, strict=True):
        assert (h.value_of(b, "Name"), h.value_of(b, "DeviceName")) == (e["name"], e["device"])
        assert h.value_of(b, "Label") == str(e["label"])
        assert tuple(int(x) for x in h.floats(h.value_of(b, "RGBA"))) == e["rgba"]
        assert tuple(int(x) for x in h.floats(h.value_of(b, "Size"))) == e["size"]
        assert h.value_of(b, "Owner") == e["owner"]
