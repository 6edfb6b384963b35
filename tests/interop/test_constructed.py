"""Messages built with our public constructors (not via igtl.unpack), sent to the peers; and
the typed fields our decoder exposes for what the peers send. Edge cases that matter for
interop: full-length fixed fields (no NUL terminator), image geometry (centre vs corner, rotated
axes), large images split over many TCP segments."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

import igtl

from . import helpers as h

pytestmark = pytest.mark.interop

NAME20 = "ABCDEFGHIJKLMNOPQRST"  # exactly 20 bytes: the DEVICE_NAME field has no NUL left


def _rot_z(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0],
                     [0.0, 0.0, 1.0]])


@pytest.fixture
def receive_server(ref_server, igtl_client):
    peer, port = ref_server("ReceiveServer", "{port}")
    return peer, igtl_client(port)


# ------------------------------------------------------------------------------ reference
def test_long_point_fields_to_receive_server(receive_server):
    """POINT with NAME 63, GROUP 31, OWNER 19 characters (the longest the 1.11 reference keeps)
    and a 20-character device name; plus a full 64/32/20 element, whose bytes must equal the
    protocol layout exactly (fields filled, no terminator).

    Note: the reference 1.11 receiver prints *empty* strings for completely filled name/group/
    owner fields (it rejects names that are not NUL-terminated inside the field), so the full
    element is checked on the bytes and the reference only on the 63/31/19 element."""
    peer, cli = receive_server
    name, group, owner = "N" * 62 + "n", "G" * 30 + "g", "O" * 18 + "o"
    full = dict(name="F" * 64, group="G" * 32, rgba=(5, 6, 7, 8), xyz=(0.5, 0.25, 0.125),
                diameter=1.0, owner="W" * 20)
    msg = igtl.PointMessage(
        points=(igtl.PointElement(name=name, group=group, rgba=(1, 2, 3, 4),
                                  position=(1.0, -2.0, 3.5), radius=4.25, owner=owner),
                igtl.PointElement(name="short", group="g", owner=""),
                igtl.PointElement(name=full["name"], group=full["group"], rgba=full["rgba"],
                                  position=full["xyz"], radius=full["diameter"],
                                  owner=full["owner"])),
        device_name=NAME20,
    )
    assert h.decode_point(h.split_wire(msg.pack()).content)[2] == full
    assert h.split_wire(msg.pack()).device == NAME20
    assert cli.send(msg)
    assert peer.wait_count(r"^ Owner", 3) == 3, peer.describe()
    b0, b1, _b2 = h.element_blocks(peer.lines)
    assert h.value_of(b0, "Name") == name
    assert h.value_of(b0, "GroupName") == group
    assert h.value_of(b0, "Owner") == owner
    assert tuple(int(x) for x in h.floats(h.value_of(b0, "RGBA"))) == (1, 2, 3, 4)
    assert h.close(h.floats(h.value_of(b0, "Position")), (1.0, -2.0, 3.5))
    assert h.close(h.floats(h.value_of(b0, "Radius")), [4.25])
    assert (h.value_of(b1, "Name"), h.value_of(b1, "Owner")) == ("short", "")


def test_large_image_with_full_device_name_to_receive_server(receive_server):
    """A 2 MiB int16 volume (many TCP segments, reference CRC over all of it) with a 20-byte
    device name and rotated axes: ReceiveServer prints size, spacing, name."""
    peer, cli = receive_server
    vol = (np.arange(16 * 256 * 256, dtype=np.int32) % 65521 - 30000).astype(np.int16)
    vol = vol.reshape(16, 256, 256)
    msg = igtl.ImageMessage.from_array(vol, spacing=(0.3, 0.4, 1.5), origin=(-40.0, 10.0, 0.0),
                                       direction=_rot_z(30), device_name=NAME20)
    assert cli.send(msg)
    block = peer.wait_output(
        lambda ls: next((b for b in h.blocks_after(ls, "Time stamp:")
                         if any("Sub-Volume offset" in x for x in b)), None), timeout=20)
    assert block, peer.describe()
    assert h.value_of(block, "Device Name") == NAME20
    assert h.value_of(block, "Scalar Type") == "4"
    assert h.floats(h.value_of(block, "Dimensions")) == [256, 256, 16]
    assert h.close(h.floats(h.value_of(block, "Spacing")), [0.3, 0.4, 1.5])


def test_constructed_types_to_receive_client(ref, igtl_server):
    """Our server sends constructor-built TDATA, QTDATA, TRAJ and CAPABILITY to ReceiveClient."""
    srv = igtl_server()
    peer = ref("ReceiveClient", "127.0.0.1", srv.address[1])
    assert srv.wait_for_peers(1, h.WAIT), peer.describe()
    m = np.eye(4)
    m[:3, :3] = _rot_z(-60)
    m[:3, 3] = (3.0, 2.0, 1.0)
    td = igtl.TrackingDataMessage(
        trackers=(igtl.TrackingElement(name="Probe", tool_type=2,
                                       elements=h.matrix_to_elements(m)),),
        device_name="T")
    qd = igtl.QuaternionTrackingDataMessage(
        trackers=(igtl.QuaternionTrackingElement(name="Probe", tool_type=3,
                                                 position=(7.0, 8.0, 9.0),
                                                 quaternion=(0.0, 0.0, 0.5, math.sqrt(0.75))),),
        device_name="Q")
    tj = igtl.TrajectoryMessage(
        trajectories=(igtl.TrajectoryElement(name="Path", group="Plan", type=3,
                                             rgba=(9, 8, 7, 6), entry=(1.0, 2.0, 3.0),
                                             target=(4.0, 5.0, 6.0), radius=1.25, owner="CT"),),
        device_name="J")
    cap = igtl.CapabilityMessage(types=("TRANSFORM", "GET_CAPABIL", "QTDATA"), device_name="C")
    for msg in (td, qd, tj, cap):
        assert srv.send(msg) == 1
    assert peer.wait_count(r"^Typename #2", 1), peer.describe()
    lines = peer.lines
    assert [x for x in lines if x.startswith("Receiving ")] == [
        "Receiving TDATA data type.", "Receiving QTDATA data type.",
        "Receiving TRAJECTORY data type.", "Receiving CAPABILITY data type."]
    assert h.close(h.parse_matrices(lines)[0], m)
    blocks = h.element_blocks(lines)
    assert h.value_of(blocks[0], "Type") == "2"
    assert h.value_of(blocks[1], "Type") == "3"
    assert h.close(h.floats(h.value_of(blocks[1], "Position")), (7, 8, 9))
    assert h.close(h.floats(h.value_of(blocks[1], "Quaternion")), (0, 0, 0.5, math.sqrt(0.75)))
    assert h.close(h.floats(h.value_of(blocks[2], "Target Pt")), (4, 5, 6))
    assert h.value_of(blocks[2], "Owner") == "CT"
    assert [x.split(": ", 1)[1] for x in lines if x.startswith("Typename #")] == [
        "TRANSFORM", "GET_CAPABIL", "QTDATA"]


# ------------------------------------------------------------------------------ typed fields
def test_typed_fields_of_reference_point_and_capability(ref, igtl_server):
    srv = igtl_server()
    ref("PointClient", "127.0.0.1", srv.address[1])
    ref("CapabilityClient", "127.0.0.1", srv.address[1])
    got = {m.message_type: m for m in h.collect(srv, 2)}
    pts = got["POINT"].points
    assert [(p.name, p.group, p.rgba, p.position, p.radius, p.owner) for p in pts] == [
        ("POINT_0", "GROUP_0", (255, 0, 0, 255), (10.0, 20.0, 30.0), 15.0, "IMAGE_0"),
        ("POINT_1", "GROUP_0", (0, 255, 0, 255), (40.0, 50.0, 60.0), 45.0, "IMAGE_0"),
        ("POINT_2", "GROUP_0", (0, 0, 255, 255), (70.0, 80.0, 90.0), 75.0, "IMAGE_0"),
    ]
    assert tuple(got["CAPABILITY"].types) == ("TRANSFORM", "GET_IMAGE", "GET_LBMETA")


def test_typed_fields_of_reference_stt_tdata(ref, igtl_server):
    srv = igtl_server()
    ref("TrackingDataClient", "127.0.0.1", srv.address[1], 25)  # resolution 1000/25 = 40 ms
    (stt,) = h.collect(srv, 1, where=h.of_type("STT_TDATA"))
    assert (stt.resolution, stt.coordinate_name) == (40, "Patient")


def test_typed_fields_of_reference_image_metadata(ref_server, igtl_client):
    peer, port = ref_server("ImageMetaServer", "{port}")
    cli = igtl_client(port)
    assert cli.send(igtl.QueryMessage(type_name="GET_IMGMETA"))
    (msg,) = h.collect(cli, 1, where=h.of_type("IMGMETA"))
    imgs = msg.images
    assert [(e.name, e.image_id, e.modality, e.size, e.scalar_type) for e in imgs] == [
        ("IMAGE_DESCRIPTION_0", "IMAGE_0", "CT", (512, 512, 64), 5),
        ("IMAGE_DESCRIPTION_1", "IMAGE_1", "MRI", (256, 128, 32), 5),
        ("IMAGE_DESCRIPTION_2", "IMAGE_2", "PET", (256, 256, 32), 5),
    ]
    assert [e.patient_id for e in imgs] == ["PATIENT_ID_0", "PATIENT_ID_1", "PATIENT_ID_2"]
    for e, t in zip(imgs, (1.2345, 2.3456, 3.4567), strict=True):
        assert abs(e.timestamp - t) < 1e-6


def test_typed_fields_of_reference_image(ref, igtl_server, tmp_path):
    """ImagerClient's image as our ImageMessage: pixels (k, j, i, c), spacing, centre, corner."""
    px = (np.arange(256 * 256) % 251).astype(np.uint8)
    for n in range(1, 6):
        (tmp_path / f"igtlTestImage{n}.raw").write_bytes(px.tobytes())
    srv = igtl_server()
    ref("ImagerClient", "127.0.0.1", srv.address[1], 50, tmp_path)
    (img,) = h.collect(srv, 1, where=h.of_type("IMAGE"))
    assert img.pixels.shape == (1, 256, 256, 1)
    assert np.array_equal(np.asarray(img.pixels).ravel(), px)
    assert img.size == (256, 256, 1) and img.offset == (0, 0, 0)
    assert h.close(img.spacing, (1.0, 1.0, 5.0))
    assert h.close(img.center, (0.0, 0.0, 0.0))
    # centre (0,0,0), axes i=(1,0,0) j=(0,-1,0) k=(0,0,5): corner = -(255/2, -255/2, 0)
    assert h.close(img.origin, (-127.5, 127.5, 0.0))


# ------------------------------------------------------------------------------ pyigtl
def test_image_geometry_our_from_array_to_pyigtl(pyigtl_server, igtl_client):
    """Corner origin + rotated axes + spacing through ImageMessage.from_array: pyigtl rebuilds
    the same ijk->world matrix (so both sides agree PX..PZ is the centre)."""
    srv, port = pyigtl_server()
    cli = igtl_client(port)
    assert h.poll(srv.is_connected)
    vol = np.arange(4 * 6 * 8, dtype=np.float32).reshape(4, 6, 8) / 7.0
    direction, spacing, origin = _rot_z(25), (0.5, 0.8, 2.0), (100.0, -50.0, 12.5)
    msg = igtl.ImageMessage.from_array(vol, spacing=spacing, origin=origin, direction=direction,
                                       device_name="Geometry", timestamp=time.time())
    assert cli.send(msg)
    got = srv.wait_for_message("Geometry", timeout=h.WAIT)
    assert got is not None
    expect = np.eye(4)
    expect[:3, :3] = direction * np.asarray(spacing)
    expect[:3, 3] = origin
    assert h.close(got.ijk_to_world_matrix, expect, atol=1e-4)
    assert h.close(msg.ijk_to_xyz, expect, atol=1e-5)
    assert got.world_coordinate_system == "ras"
    assert np.array_equal(got.image, vol)


def test_image_geometry_pyigtl_to_our_decoder(pyigtl, pyigtl_client, igtl_server):
    """pyigtl's LPS image with rotated axes: our ImageMessage gives back its corner origin,
    spacing, direction, coordinate system and pixels."""
    srv = igtl_server()
    cli = pyigtl_client(srv.address[1])
    assert srv.wait_for_peers(1, h.WAIT)
    vol = (np.arange(3 * 4 * 5, dtype=np.uint16).reshape(3, 4, 5) * 1000)
    m = np.eye(4)
    m[:3, :3] = _rot_z(-40) * np.array([0.25, 0.5, 3.0])
    m[:3, 3] = (-5.0, 6.0, -7.0)
    sent = pyigtl.ImageMessage(vol, ijk_to_world_matrix=m, device_name="PyGeom")
    assert sent.world_coordinate_system == "lps"
    assert cli.send_message(sent, wait=False)
    (img,) = h.collect(srv, 1, where=h.of_type("IMAGE"))
    assert img.coordinate == 2  # LPS
    assert h.close(img.origin, (-5.0, 6.0, -7.0), atol=1e-4)
    assert h.close(img.spacing, (0.25, 0.5, 3.0))
    assert h.close(img.direction, _rot_z(-40), atol=1e-6)
    assert h.close(img.ijk_to_xyz, m, atol=1e-4)
    assert np.array_equal(np.asarray(img.pixels)[..., 0].astype(np.uint16), vol)


def test_subvolume_image_to_receive_server(receive_server):
    """A 4x3x1 sub-volume at offset (2, 5, 0) of a 10x12x1 image: the reference prints the
    full dimensions, the sub-volume size and offset we declared."""
    peer, cli = receive_server
    sub = np.arange(12, dtype=np.uint8).reshape(1, 3, 4)
    msg = igtl.ImageMessage.from_array(sub, spacing=(1.0, 1.0, 1.0), offset=(2, 5, 0),
                                       size=(10, 12, 1), device_name="Sub")
    assert cli.send(msg)
    block = peer.wait_output(
        lambda ls: next((b for b in h.blocks_after(ls, "Time stamp:")
                         if any("Sub-Volume offset" in x for x in b)), None))
    assert block, peer.describe()
    assert h.floats(h.value_of(block, "Dimensions")) == [10, 12, 1]
    assert h.floats(h.value_of(block, "Sub-Volume dimensions")) == [4, 3, 1]
    assert h.floats(h.value_of(block, "Sub-Volume offset")) == [2, 5, 0]
    assert h.value_of(block, "Scalar Type") == "3"


def test_typed_queries_from_reference_clients(ref, igtl_server):
    """GET_POLYDATA / GET_IMGMETA / GET_LBMETA from the reference clients decode as our typed
    query message with the right type name and device."""
    srv = igtl_server()
    for prog in ("PolyDataClient", "ImageMetaClient", "LabelMetaClient"):
        ref(prog, "127.0.0.1", srv.address[1])
    got = h.collect(srv, 3, where=h.of_type("GET_POLYDATA", "GET_IMGMETA", "GET_LBMETA"))
    assert sorted(m.message_type for m in got) == ["GET_IMGMETA", "GET_LBMETA", "GET_POLYDATA"]
    for m in got:
        assert isinstance(m, igtl.QueryMessage), type(m)
        assert m.device_name == "Client" and m.type_name == m.message_type
        assert h.split_wire(m.pack()).content == b""


def test_v2_message_is_downgraded_for_a_v1_reference_client(ref, igtl_server):
    """The 1.11 reference only knows header v1. Our server has never seen v2 from it, so a v2
    message with metadata is sent as v1 (metadata dropped) and the reference decodes it."""
    srv = igtl_server()
    peer = ref("ReceiveClient", "127.0.0.1", srv.address[1])
    assert srv.wait_for_peers(1, h.WAIT)
    msg = igtl.StringMessage(string="negotiated", device_name="V2", header_version=2,
                             metadata={"Status": "OK"}, message_id=9)
    assert srv.send(msg) == 1
    assert peer.wait_count(r"^Encoding: 3; String: negotiated$", 1) == 1, peer.describe()
    (p,) = srv.peers
    assert p.header_version == 1
