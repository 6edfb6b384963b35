"""Reference C++ programs send, our TCPServer / TCPClient receive.

Each test checks content, not just arrival: against what the program prints, against its known
constants, or against its motion formula. Our decoded message must be a typed message (not
RawMessage), and re-encoding it must give bytes that the independent decoder in helpers.py
(written from the protocol document) reads back as the reference content.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

import igtl

from . import helpers as h

pytestmark = pytest.mark.interop


def _printed_matrices(peer, n):
    """The first matrices the program printed. It prints each before sending it, but its output
    pipe and its socket are separate channels, so wait for the print (bounded)."""
    got = peer.wait_output(lambda ls: len(m := h.parse_matrices(ls)) >= n and m)
    assert got and len(got) >= n, peer.describe()
    return got


# ------------------------------------------------------------------------------ TRANSFORM
def test_tracker_client_transforms_reach_our_server(ref, igtl_server):
    """TrackerClient -> TCPServer: 20 TRANSFORMs equal to what it printed and to its formula,
    device "Tracker", header v1, wall-clock timestamps."""
    srv = igtl_server()
    t0 = time.time()
    peer = ref("TrackerClient", "127.0.0.1", srv.address[1], 200)
    msgs = h.collect(srv, 20, where=h.of_type("TRANSFORM"))
    assert len(msgs) == 20, peer.describe()
    printed = _printed_matrices(peer, 20)
    formula = h.tracker_matrices(20)
    for i, m in enumerate(msgs):
        assert isinstance(m, igtl.TransformMessage)
        assert m.device_name == "Tracker"
        assert m.header_version == 1
        assert h.close(m.matrix, printed[i]), (i, m.matrix, printed[i])
        assert h.close(m.matrix, formula[i], atol=1e-4), (i, m.matrix, formula[i])
        assert t0 - 1.0 <= m.timestamp <= time.time() + 1.0, m.timestamp
        assert h.close(h.decode_transform(h.typed(m).content), printed[i])
    stamps = [m.timestamp for m in msgs]
    assert stamps == sorted(stamps)


def test_tracker_server_transforms_reach_our_client(ref_server, igtl_client):
    """TrackerServer -> TCPClient: TRANSFORMs equal to the printed matrices; timestamp 0 (the
    server never sets one) decodes as 0."""
    peer, port = ref_server("TrackerServer", "{port}", 200)
    cli = igtl_client(port)
    msgs = h.collect(cli, 15, where=h.of_type("TRANSFORM"))
    assert len(msgs) == 15, peer.describe()
    printed = _printed_matrices(peer, 15)
    formula = h.tracker_matrices(15)
    for i, m in enumerate(msgs):
        assert m.device_name == "Tracker"
        assert m.timestamp == 0
        assert h.close(m.matrix, printed[i]), (i, m.matrix, printed[i])
        assert h.close(m.matrix, formula[i], atol=1e-4)


# ------------------------------------------------------------------------------ STATUS
STATUS_TEXT = "This is a test to send status message."


def _check_example_status(m):
    assert isinstance(m, igtl.StatusMessage)
    assert m.device_name == "Device"
    assert (m.code, m.subcode, m.error_name, m.status_message) == (1, 128, "OK!", STATUS_TEXT)
    st = h.decode_status(h.typed(m).content)
    assert st == dict(code=1, subcode=128, error_name="OK!", message=STATUS_TEXT)


def test_status_client_reaches_our_server(ref, igtl_server):
    srv = igtl_server()
    peer = ref("StatusClient", "127.0.0.1", srv.address[1])
    msgs = h.collect(srv, 1, where=h.of_type("STATUS"))
    assert msgs, peer.describe()
    _check_example_status(msgs[0])


def test_status_server_reaches_our_client(ref_server, igtl_client):
    peer, port = ref_server("StatusServer", "{port}")
    msgs = h.collect(igtl_client(port), 1, where=h.of_type("STATUS"))
    assert msgs, peer.describe()
    _check_example_status(msgs[0])


# ------------------------------------------------------------------------------ STRING
EXAMPLE_STRINGS = ["OpenIGTLink", "Network", "Communication", "Protocol", "Image Guided Therapy"]


def _check_strings(msgs, peer):
    assert len(msgs) == 7, peer.describe()
    for i, m in enumerate(msgs):
        assert isinstance(m, igtl.StringMessage)
        assert m.device_name == "StringMessage"
        assert m.string == EXAMPLE_STRINGS[i % 5]
        assert m.encoding == 3
        assert h.decode_string(h.typed(m).content) == (3, EXAMPLE_STRINGS[i % 5])
    # the program prints before it sends, but its output pipe and the socket are separate
    # channels: wait for the print rather than assume it was read first
    assert peer.wait_count("^Sending string: ", 7) >= 7, peer.describe()
    sent = [line.split("Sending string: ", 1)[1] for line in peer.lines if "Sending string" in line]
    assert sent[:7] == [m.string for m in msgs]


def test_string_client_reaches_our_server(ref, igtl_server):
    srv = igtl_server()
    peer = ref("StringClient", "127.0.0.1", srv.address[1], 200)
    _check_strings(h.collect(srv, 7, where=h.of_type("STRING")), peer)


def test_string_server_reaches_our_client(ref_server, igtl_client):
    peer, port = ref_server("StringServer", "{port}", 200)
    _check_strings(h.collect(igtl_client(port), 7, where=h.of_type("STRING")), peer)


# ------------------------------------------------------------------------------ POINT
EXAMPLE_POINTS = [
    dict(name="POINT_0", group="GROUP_0", rgba=(255, 0, 0, 255), xyz=(10.0, 20.0, 30.0),
         diameter=15.0, owner="IMAGE_0"),
    dict(name="POINT_1", group="GROUP_0", rgba=(0, 255, 0, 255), xyz=(40.0, 50.0, 60.0),
         diameter=45.0, owner="IMAGE_0"),
    dict(name="POINT_2", group="GROUP_0", rgba=(0, 0, 255, 255), xyz=(70.0, 80.0, 90.0),
         diameter=75.0, owner="IMAGE_0"),
]


def test_point_client_reaches_our_server(ref, igtl_server):
    """PointClient sends one POINT (3 elements) and closes at once: the message must still be
    delivered, with every field."""
    srv = igtl_server()
    peer = ref("PointClient", "127.0.0.1", srv.address[1])
    msgs = h.collect(srv, 1, where=h.of_type("POINT"))
    assert msgs, peer.describe()
    assert msgs[0].device_name == "PointSender"
    assert h.decode_point(h.typed(msgs[0]).content) == EXAMPLE_POINTS


def test_point_server_reaches_our_client(ref_server, igtl_client):
    peer, port = ref_server("PointServer", "{port}")
    msgs = h.collect(igtl_client(port), 1, where=h.of_type("POINT"))
    assert msgs, peer.describe()
    assert msgs[0].device_name == "PointSender"
    assert h.decode_point(h.typed(msgs[0]).content) == EXAMPLE_POINTS


# ------------------------------------------------------------------------------ CAPABILITY
def test_capability_client_reaches_our_server(ref, igtl_server):
    srv = igtl_server()
    peer = ref("CapabilityClient", "127.0.0.1", srv.address[1])
    msgs = h.collect(srv, 1, where=h.of_type("CAPABILITY"))
    assert msgs, peer.describe()
    assert msgs[0].device_name == "Device"
    types = h.decode_capability(h.typed(msgs[0]).content)
    assert types == ["TRANSFORM", "GET_IMAGE", "GET_LBMETA"]


def test_capability_server_reaches_our_client(ref_server, igtl_client):
    peer, port = ref_server("CapabilityServer", "{port}")
    msgs = h.collect(igtl_client(port), 1, where=h.of_type("CAPABILITY"))
    assert msgs, peer.describe()
    assert h.decode_capability(h.typed(msgs[0]).content) == ["TRANSFORM", "GET_IMAGE", "GET_LBMETA"]


# ------------------------------------------------------------------------------ TRAJ
def test_trajectory_client_reaches_our_server(ref, igtl_server):
    """TrajectoryClient's TRAJ (3 elements). The example sets trajectory 1's target twice and
    never sets trajectory 2's, which therefore stays at the default (0, 0, 0)."""
    srv = igtl_server()
    peer = ref("TrajectoryClient", "127.0.0.1", srv.address[1])
    msgs = h.collect(srv, 1, where=h.of_type("TRAJ"))
    assert msgs, peer.describe()
    assert msgs[0].device_name == "TrajectorySender"
    els = h.decode_traj(h.typed(msgs[0]).content)
    expect = [
        ("TRAJECTORY_0", (255, 0, 0, 255), (10.0, 20.0, 30.0), (20.0, 20.0, 40.0), 15.0),
        ("TRAJECTORY_1", (0, 255, 0, 255), (40.0, 50.0, 60.0), (10.0, 40.0, 20.0), 45.0),
        ("TRAJECTORY_2", (0, 0, 255, 255), (70.0, 80.0, 90.0), (0.0, 0.0, 0.0), 75.0),
    ]
    assert [(e["name"], e["rgba"], e["entry"], e["target"], e["diameter"]) for e in els] == expect
    assert {(e["group"], e["owner"]) for e in els} == {("GROUP_0", "IMAGE_0")}


# ------------------------------------------------------------------------------ IMAGE
def _write_test_images(folder: Path) -> list[bytes]:
    """Five 256x256 uint8 images for ImagerClient/ImagerServer (igtlTestImage1..5.raw), each a
    distinct pattern so order and pixel placement are checked."""
    imgs = []
    j, i = np.mgrid[0:256, 0:256]
    for n in range(5):
        px = ((i * (n + 1) + j * 3 + n * 17) % 256).astype(np.uint8).tobytes()
        (folder / f"igtlTestImage{n + 1}.raw").write_bytes(px)
        imgs.append(px)
    return imgs


def _check_example_images(msgs, imgs, peer):
    assert len(msgs) == 6, peer.describe()
    for k, m in enumerate(msgs):
        assert m.device_name == "ImagerClient"
        img = h.decode_image(h.typed(m).content)
        assert img["size"] == (256, 256, 1)
        assert (img["components"], img["scalar_type"]) == (1, 3)
        assert img["sub_offset"] == (0, 0, 0) and img["sub_size"] == (256, 256, 1)
        # matrix diag(1, -1, 1), spacing (1, 1, 5), origin column written verbatim (0, 0, 0)
        assert h.close(img["t"], (1, 0, 0)) and h.close(img["s"], (0, -1, 0))
        assert h.close(img["n"], (0, 0, 5)) and h.close(img["p"], (0, 0, 0))
        assert img["pixels"] == imgs[k % 5], f"image {k}: pixels differ"


def test_imager_client_images_reach_our_server(ref, igtl_server, tmp_path):
    imgs = _write_test_images(tmp_path)
    srv = igtl_server()
    peer = ref("ImagerClient", "127.0.0.1", srv.address[1], 100, tmp_path)
    _check_example_images(h.collect(srv, 6, where=h.of_type("IMAGE")), imgs, peer)


def test_imager_server_images_reach_our_client(ref_server, igtl_client, tmp_path):
    imgs = _write_test_images(tmp_path)
    peer, port = ref_server("ImagerServer", "{port}", 100, tmp_path)
    _check_example_images(h.collect(igtl_client(port), 6, where=h.of_type("IMAGE")), imgs, peer)


# ------------------------------------------------------------------------------ BIND
def test_bind_client_reaches_our_server(ref, igtl_server):
    """BindClient: BIND of STRING "OpenIGTLink" (the example never advances its index) and a
    TRANSFORM equal to the matrix it printed."""
    srv = igtl_server()
    peer = ref("BindClient", "127.0.0.1", srv.address[1], 100)
    msgs = h.collect(srv, 3, where=h.of_type("BIND"))
    assert len(msgs) == 3, peer.describe()
    printed = _printed_matrices(peer, 3)
    for i, m in enumerate(msgs):
        assert m.device_name == "BindMessage"
        children = h.decode_bind(h.typed(m).content)
        assert [(t, n) for t, n, _ in children] == [("STRING", "StringMessage"),
                                                   ("TRANSFORM", "Tracker")]
        assert h.decode_string(children[0][2]) == (3, "OpenIGTLink")
        assert h.close(h.decode_transform(children[1][2]), printed[i])


# ------------------------------------------------------------------------------ TDATA / QTDATA
def _stt(type_name: str, device: str, resolution_ms: int, coord: str = "Patient"):
    return igtl.StartTrackingMessage(type_name=type_name, resolution=resolution_ms,
                                     coordinate_name=coord, device_name=device)


def _query(type_name: str, device: str = ""):
    return igtl.QueryMessage(type_name=type_name, device_name=device)


# (phi step, theta step) per channel in TrackingDataServer / QuaternionTrackingDataServer
_CHANNEL_STEPS = [(0.1, 0.2), (0.2, 0.1), (0.3, 0.05)]
_CHANNEL_TYPES = [1, 2, 4]  # TYPE_TRACKER, TYPE_6D, TYPE_5D


def test_tracking_data_server_streams_to_our_client(ref_server, igtl_client):
    """STT_TDATA from our client starts TrackingDataServer's stream; 5 TDATA frames of 3
    channels follow its formula; STP_TDATA stops it (the server then closes)."""
    peer, port = ref_server("TrackingDataServer", "{port}")
    cli = igtl_client(port)
    assert cli.send(_stt("STT_TDATA", "TDataClient", 10))
    msgs = h.collect(cli, 5, where=h.of_type("TDATA"))
    assert len(msgs) == 5, peer.describe()
    assert peer.wait_count(r"Interval = 10 \(ms\)", 1)
    for k, m in enumerate(msgs):
        assert m.device_name == "Tracker"
        els = h.decode_tdata(h.typed(m).content)
        assert [e["name"] for e in els] == ["Channel 0", "Channel 1", "Channel 2"]
        assert [e["type"] for e in els] == _CHANNEL_TYPES
        for e, (dphi, dtheta) in zip(els, _CHANNEL_STEPS, strict=True):
            phi, theta = h.float_steps(dphi, k + 1)[k], h.float_steps(dtheta, k + 1)[k]
            assert h.close(e["matrix"], h.example_matrix(phi, theta), atol=1e-4), (k, e)
    assert cli.send(_query("STP_TDATA", "TDataClient"))
    assert peer.wait_count("Received a STP_TDATA message", 1), peer.describe()


def test_qtdata_server_streams_to_our_client(ref_server, igtl_client):
    peer, port = ref_server("QuaternionTrackingDataServer", "{port}")
    cli = igtl_client(port)
    assert cli.send(_stt("STT_QTDATA", "QTDataClient", 10))
    msgs = h.collect(cli, 5, where=h.of_type("QTDATA"))
    assert len(msgs) == 5, peer.describe()
    for k, m in enumerate(msgs):
        assert m.device_name == "Tracker"
        els = h.decode_qtdata(h.typed(m).content)
        assert [e["name"] for e in els] == ["Channel 0", "Channel 1", "Channel 2"]
        assert [e["type"] for e in els] == _CHANNEL_TYPES
        for e, (dphi, dtheta) in zip(els, _CHANNEL_STEPS, strict=True):
            phi, theta = h.float_steps(dphi, k + 1)[k], h.float_steps(dtheta, k + 1)[k]
            pos, quat = h.example_pose(phi, theta)
            assert h.close(e["position"], pos, atol=1e-4) and h.close(e["quaternion"], quat)
    assert cli.send(_query("STP_QTDATA", "QTDataClient"))
    assert peer.wait_count("Received a STP_QTDATA message", 1), peer.describe()


# ------------------------------------------------------------------------------ GET_ queries
def test_polydata_server_answers_our_get_polydata(ref_server, igtl_client):
    peer, port = ref_server("PolyDataServer", "{port}")
    cli = igtl_client(port)
    assert cli.send(_query("GET_POLYDATA", "Cube"))
    msgs = h.collect(cli, 1, where=h.of_type("POLYDATA"))
    assert msgs, peer.describe()
    assert msgs[0].device_name == "Cube"  # the server answers with the requested name
    pd = h.decode_polydata(h.typed(msgs[0]).content)
    cube = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]
    assert pd["points"].tolist() == [list(map(float, p)) for p in cube]
    assert pd["polygons"] == [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5],
                              [2, 3, 7, 6], [3, 0, 4, 7]]
    assert pd["vertices"] == pd["lines"] == pd["strips"] == []
    (attr,) = pd["attributes"]
    assert (attr["type"], attr["ncomp"], attr["name"]) == (0, 1, "attr")
    assert attr["data"].ravel().tolist() == [float(x) for x in range(8)]


def test_imagemeta_server_answers_our_get_imgmeta(ref_server, igtl_client):
    peer, port = ref_server("ImageMetaServer", "{port}")
    cli = igtl_client(port)
    assert cli.send(_query("GET_IMGMETA", "Meta"))
    msgs = h.collect(cli, 1, where=h.of_type("IMGMETA"))
    assert msgs, peer.describe()
    els = h.decode_imgmeta(h.typed(msgs[0]).content)
    expect = [
        ("IMAGE_DESCRIPTION_0", "IMAGE_0", "CT", "PATIENT_0", "PATIENT_ID_0", 1.2345,
         (512, 512, 64)),
        ("IMAGE_DESCRIPTION_1", "IMAGE_1", "MRI", "PATIENT_1", "PATIENT_ID_1", 2.3456,
         (256, 128, 32)),
        ("IMAGE_DESCRIPTION_2", "IMAGE_2", "PET", "PATIENT_2", "PATIENT_ID_2", 3.4567,
         (256, 256, 32)),
    ]
    for e, (name, dev, mod, pn, pid, t, size) in zip(els, expect, strict=True):
        assert (e["name"], e["device"], e["modality"], e["patient_name"], e["patient_id"]) == (
            name, dev, mod, pn, pid)
        raw = e["timestamp_raw"]
        secs = (raw >> 32) + h.frac_to_nanosec(raw & 0xFFFFFFFF) * 1e-9
        assert abs(secs - t) < 1e-6
        assert e["size"] == size and e["scalar_type"] == 5


def test_labelmeta_server_answers_our_get_lbmeta(ref_server, igtl_client):
    peer, port = ref_server("LabelMetaServer", "{port}")
    cli = igtl_client(port)
    assert cli.send(_query("GET_LBMETA", "Labels"))
    msgs = h.collect(cli, 1, where=h.of_type("LBMETA"))
    assert msgs, peer.describe()
    assert msgs[0].device_name == "MetaServer"
    els = h.decode_lbmeta(h.typed(msgs[0]).content)
    assert els == [
        dict(name="LABEL_DESCRIPTION_0", device="LABEL_0", label=1, rgba=(255, 0, 0, 255),
             size=(512, 512, 64), owner="IMAGE_0"),
        dict(name="LABEL_DESCRIPTION_1", device="LABEL_1", label=2, rgba=(0, 255, 0, 255),
             size=(256, 128, 32), owner="IMAGE_1"),
        dict(name="LABEL_DESCRIPTION_2", device="LABEL_2", label=3, rgba=(0, 0, 255, 255),
             size=(256, 256, 32), owner="IMAGE_2"),
    ]
