"""pyigtl <-> our transports, both roles, TRANSFORM / STRING / IMAGE / POINT, header v1 and v2.

pyigtl keeps only the latest message per device name and never checks CRCs, so every check
here is on content: pyigtl's decoded fields, and for our side the typed message re-encoded and
read by the independent decoder in helpers.py. POSITION is not tested: pyigtl's POSITION layout
is non-standard (protocol doc 6.3).

Facts about pyigtl 0.3.x that shape these tests:
- a pyigtl server serves exactly one connection in its lifetime (a fresh one per test);
- ``send_message(wait=True)`` blocks forever without a connected peer, so we queue with
  ``wait=False`` and poll the queue with a timeout;
- it writes non-ASCII metadata values badly (``UnicodeEncodeError`` not caught), so metadata
  sent *by* pyigtl is ASCII; metadata we send may be UTF-8.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

import igtl

from . import helpers as h

pytestmark = pytest.mark.interop

KINDS = ["TRANSFORM", "STRING", "IMAGE", "POINT"]
VERSIONS = [1, 2]
META_ASCII = {"Patient": "Doe^Jane", "Status": "OK", "Empty": ""}
META_UTF8 = {"Surgeon": "Dr. Müller", "Status": "OK", "Empty": ""}
MSG_ID = 4242

MATRIX = np.array([[0.0, -1.0, 0.0, 10.5], [1.0, 0.0, 0.0, -20.25], [0.0, 0.0, 1.0, 300.0],
                   [0.0, 0.0, 0.0, 1.0]])
TEXT_ASCII = "Needle inserted: depth 42 mm"
TEXT_UTF8 = "Nadel eingeführt: Tiefe 42 mm ✓"
VOLUME = ((np.mgrid[0:3, 0:5, 0:7][2] * 1000 + np.mgrid[0:3, 0:5, 0:7][1] * 10
           + np.mgrid[0:3, 0:5, 0:7][0]).astype(np.int16) - 3000)  # [k, j, i]
SPACING = (0.5, 0.75, 2.5)
ORIGIN = (-10.0, 20.0, 5.0)  # corner (voxel 0,0,0) in world coordinates
POINTS = [
    dict(name="Entry", group="Landmark", rgba=(255, 0, 0, 255), xyz=(1.5, -2.0, 30.25),
         diameter=2.5, owner="CT_1"),
    dict(name="Target", group="Fiducial", rgba=(0, 255, 0, 128), xyz=(-100.125, 0.0, 1000.0),
         diameter=5.0, owner="CT_1"),
]


def _ijk_to_world() -> np.ndarray:
    m = np.diag([*SPACING, 1.0])
    m[:3, 3] = ORIGIN
    return m


def _center() -> np.ndarray:
    nk, nj, ni = VOLUME.shape
    return _ijk_to_world()[:3, :3] @ np.array([(ni - 1) / 2, (nj - 1) / 2, (nk - 1) / 2]) + ORIGIN


# ------------------------------------------------------------------------------ builders
def _pyigtl_message(pyigtl, kind: str, version: int):
    dev = f"Py{kind.title()}"
    if kind == "TRANSFORM":
        msg = pyigtl.TransformMessage(MATRIX, device_name=dev)
    elif kind == "STRING":
        msg = pyigtl.StringMessage(TEXT_ASCII, device_name=dev)
    elif kind == "IMAGE":
        msg = pyigtl.ImageMessage(VOLUME, ijk_to_world_matrix=_ijk_to_world(),
                                  world_coordinate_system="ras", device_name=dev)
    else:
        msg = pyigtl.PointMessage(
            positions=[list(p["xyz"]) for p in POINTS], names=[p["name"] for p in POINTS],
            rgba_colors=[list(p["rgba"]) for p in POINTS],
            diameters=[p["diameter"] for p in POINTS], groups=[p["group"] for p in POINTS],
            owners=[p["owner"] for p in POINTS], device_name=dev)
    if version == 2:
        msg.header_version = 2
        msg.metadata = dict(META_ASCII)
        msg.message_id = MSG_ID
    return msg


def _our_message(kind: str, version: int, stamp: float):
    dev = f"Occ{kind.title()}"
    common = dict(device_name=dev, timestamp=stamp)
    if version == 2:
        common.update(header_version=2, metadata=dict(META_UTF8), message_id=MSG_ID)
    if kind == "TRANSFORM":
        return igtl.TransformMessage.from_matrix(MATRIX, **common)
    if kind == "STRING":
        return igtl.StringMessage(string=TEXT_UTF8, **common)
    if kind == "IMAGE":
        content = h.encode_image(VOLUME.astype("<i2"), spacing=SPACING, center=tuple(_center()))
    else:
        content = h.encode_point(POINTS)
    raw = h.pack_wire(kind, dev, content, version=version, timestamp_raw=0,
                      metadata=META_UTF8 if version == 2 else None,
                      message_id=MSG_ID if version == 2 else 0)
    return h.ours(raw).replace(timestamp=stamp)


# ------------------------------------------------------------------------------ checks
def _check_ours_received(msg, kind: str, version: int, sent_stamp: float):
    """Our decoded copy of what pyigtl sent."""
    assert msg.message_type == kind
    assert msg.device_name == f"Py{kind.title()}"
    assert msg.header_version == version
    assert abs(msg.timestamp - sent_stamp) < 1e-6
    if version == 2:
        assert dict(msg.metadata) == META_ASCII
        assert msg.message_id == MSG_ID
    else:
        assert not msg.metadata and msg.message_id == 0
    w = h.typed(msg)
    if kind == "TRANSFORM":
        assert np.array_equal(msg.matrix, MATRIX)
        assert np.array_equal(h.decode_transform(w.content), MATRIX)
    elif kind == "STRING":
        assert (msg.string, msg.encoding) == (TEXT_ASCII, 3)
        assert h.decode_string(w.content) == (3, TEXT_ASCII)
    elif kind == "IMAGE":
        img = h.decode_image(w.content)
        assert img["size"] == (7, 5, 3) and img["scalar_type"] == 4 and img["components"] == 1
        assert img["coord"] == 1  # RAS, as pyigtl was told
        assert h.close(img["t"], (SPACING[0], 0, 0)) and h.close(img["s"], (0, SPACING[1], 0))
        assert h.close(img["n"], (0, 0, SPACING[2]))
        assert h.close(img["p"], _center())  # PX..PZ is the centre, pyigtl and reference agree
        dt = np.dtype(">i2" if img["endian"] == 1 else "<i2")
        assert np.array_equal(np.frombuffer(img["pixels"], dt).reshape(3, 5, 7), VOLUME)
    else:
        assert h.decode_point(w.content) == POINTS


def _check_pyigtl_received(msg, kind: str, version: int, sent, metadata_expected: bool):
    """pyigtl's decoded copy of what we sent."""
    assert msg.device_name == f"Occ{kind.title()}"
    assert msg.header_version == (2 if metadata_expected else 1)
    assert abs(msg.timestamp - sent.timestamp) < 1e-6
    if metadata_expected:
        assert msg.metadata == META_UTF8
        assert msg.message_id == MSG_ID
    else:
        assert not msg.metadata
    if kind == "TRANSFORM":
        assert np.array_equal(np.asarray(msg.matrix), MATRIX)
    elif kind == "STRING":
        assert msg.string == TEXT_UTF8
    elif kind == "IMAGE":
        assert msg.world_coordinate_system == "ras"
        assert msg.image.shape == VOLUME.shape
        assert np.array_equal(msg.image.astype(np.int16), VOLUME)
        assert h.close(msg.ijk_to_world_matrix, _ijk_to_world())  # corner origin rebuilt
    else:
        assert msg.names == [p["name"] for p in POINTS]
        assert msg.groups == [p["group"] for p in POINTS]
        assert msg.owners == [p["owner"] for p in POINTS]
        assert [tuple(c) for c in msg.rgba_colors] == [p["rgba"] for p in POINTS]
        assert h.close(msg.positions, [p["xyz"] for p in POINTS])
        assert h.close(msg.diameters, [p["diameter"] for p in POINTS])


def _pyigtl_send(endpoint, msg) -> None:
    """Queue on a pyigtl endpoint and wait (bounded) until its I/O thread has sent it."""
    assert endpoint.send_message(msg, wait=False)

    def drained():
        with endpoint.lock_outgoing_messages:
            return not endpoint.outgoing_messages

    assert h.poll(drained), "pyigtl did not send the message"


# ------------------------------------------------------------------------------ pyigtl sends
@pytest.mark.parametrize("version", VERSIONS, ids=["v1", "v2"])
@pytest.mark.parametrize("kind", KINDS)
def test_pyigtl_server_to_our_client(pyigtl, pyigtl_server, igtl_client, kind, version):
    srv, port = pyigtl_server()
    cli = igtl_client(port)
    assert h.poll(srv.is_connected)
    sent = _pyigtl_message(pyigtl, kind, version)
    _pyigtl_send(srv, sent)
    got = h.collect(cli, 1, where=h.of_type(kind))
    assert got, f"{kind} from the pyigtl server did not arrive"
    _check_ours_received(got[0], kind, version, sent.timestamp)


@pytest.mark.parametrize("version", VERSIONS, ids=["v1", "v2"])
@pytest.mark.parametrize("kind", KINDS)
def test_pyigtl_client_to_our_server(pyigtl, pyigtl_client, igtl_server, kind, version):
    srv = igtl_server()
    cli = pyigtl_client(srv.address[1])
    assert srv.wait_for_peers(1, h.WAIT)
    sent = _pyigtl_message(pyigtl, kind, version)
    _pyigtl_send(cli, sent)
    got = h.collect(srv, 1, where=h.of_type(kind))
    assert got, f"{kind} from the pyigtl client did not arrive"
    _check_ours_received(got[0], kind, version, sent.timestamp)
    (peer,) = srv.peers
    assert peer.header_version == version  # negotiation saw what the client speaks


# ------------------------------------------------------------------------------ we send
@pytest.mark.parametrize("version", VERSIONS, ids=["v1", "v2"])
@pytest.mark.parametrize("kind", KINDS)
def test_our_client_to_pyigtl_server(pyigtl_server, igtl_client, kind, version):
    srv, port = pyigtl_server()
    cli = igtl_client(port)
    assert h.poll(srv.is_connected)
    sent = _our_message(kind, version, time.time())
    assert cli.send(sent)
    got = srv.wait_for_message(sent.device_name, timeout=h.WAIT)
    assert got is not None, f"pyigtl server did not get our {kind}"
    _check_pyigtl_received(got, kind, version, sent, metadata_expected=version == 2)


@pytest.mark.parametrize("version", VERSIONS, ids=["v1", "v2"])
@pytest.mark.parametrize("kind", KINDS)
def test_our_server_to_pyigtl_client(pyigtl, pyigtl_client, igtl_server, kind, version):
    """Our server answers each client in the header version it has seen from it. For v2 the
    pyigtl client first sends a v2 STRING (as Slicer's v2 STATUS handshake does); then our v2
    message arrives with metadata and message id."""
    srv = igtl_server()
    cli = pyigtl_client(srv.address[1])
    assert srv.wait_for_peers(1, h.WAIT)
    if version == 2:
        hello = pyigtl.StringMessage("hello", device_name="Hello")
        hello.header_version = 2
        hello.metadata = {"dummy": "dummy"}
        _pyigtl_send(cli, hello)
        assert h.collect(srv, 1, where=h.of_type("STRING")), "v2 hello did not arrive"
    sent = _our_message(kind, version, time.time())
    assert srv.send(sent) == 1
    got = cli.wait_for_message(sent.device_name, timeout=h.WAIT)
    assert got is not None, f"pyigtl client did not get our {kind}"
    _check_pyigtl_received(got, kind, version, sent, metadata_expected=version == 2)


def test_our_server_downgrades_v2_for_a_v1_pyigtl_client(pyigtl_client, igtl_server):
    """A client that never sent v2 gets our v2 message as v1: same content, no metadata."""
    srv = igtl_server()
    cli = pyigtl_client(srv.address[1])
    assert srv.wait_for_peers(1, h.WAIT)
    sent = _our_message("TRANSFORM", 2, time.time())
    assert srv.send(sent) == 1
    got = cli.wait_for_message(sent.device_name, timeout=h.WAIT)
    assert got is not None
    _check_pyigtl_received(got, "TRANSFORM", 2, sent, metadata_expected=False)


# ------------------------------------------------------------------------------ text edge cases
def test_non_ascii_metadata_keys_both_ways(pyigtl, pyigtl_client, igtl_server):
    """Metadata keys are UTF-8 on both sides (pyigtl writes keys UTF-8 always)."""
    srv = igtl_server()
    cli = pyigtl_client(srv.address[1])
    assert srv.wait_for_peers(1, h.WAIT)
    hello = pyigtl.StringMessage("hi", device_name="Hello")
    hello.header_version = 2
    hello.metadata = {"Größe": "42 mm"}
    _pyigtl_send(cli, hello)
    (got,) = h.collect(srv, 1, where=h.of_type("STRING"))
    assert dict(got.metadata) == {"Größe": "42 mm"}
    ours = igtl.StringMessage(string="ok", device_name="Reply", header_version=2,
                              metadata={"Größe": "43 mm", "Gerät": "Bohrer ✓"})
    assert srv.send(ours) == 1
    back = cli.wait_for_message("Reply", timeout=h.WAIT)
    assert back is not None and back.metadata == {"Größe": "43 mm", "Gerät": "Bohrer ✓"}


def test_non_ascii_device_name_from_pyigtl(pyigtl, pyigtl_client, igtl_server):
    """pyigtl (like 3D Slicer, whose device names are MRML node names) writes DEVICE_NAME as
    UTF-8. Our decoded device_name should be the name that was sent.

    Known failure: igtl.wire decodes names as latin-1, so "Gerät" arrives as "GerÃ¤t" and never
    matches a configured device name."""
    srv = igtl_server()
    cli = pyigtl_client(srv.address[1])
    assert srv.wait_for_peers(1, h.WAIT)
    _pyigtl_send(cli, pyigtl.StringMessage("x", device_name="Gerät"))
    (got,) = h.collect(srv, 1, where=h.of_type("STRING"))
    assert got.device_name == "Gerät"


def test_non_ascii_device_name_to_pyigtl(pyigtl_server, igtl_client):
    """Our message with device name "Gerät" must reach pyigtl under that name.

    Known failure: igtl.wire encodes names as latin-1 (0xE4 for "ä"); pyigtl decodes the header
    as strict UTF-8, raises UnicodeDecodeError in its receive loop and drops the connection, so
    the message (and the connection) is lost."""
    srv, port = pyigtl_server()
    cli = igtl_client(port)
    assert h.poll(srv.is_connected)
    assert cli.send(igtl.TransformMessage.from_matrix(MATRIX, device_name="Gerät"))
    got = srv.wait_for_message("Gerät", timeout=3)
    assert got is not None, "pyigtl could not decode our DEVICE_NAME (latin-1, not UTF-8)"
