"""Stream behaviour with real peers: bursts (many messages per TCP segment), broadcast to several
reference clients, reconnect after the reference server restarts, large images with pyigtl."""

from __future__ import annotations

import socket
import struct
import time

import numpy as np
import pytest

import igtl

from . import helpers as h

pytestmark = pytest.mark.interop


def test_tracker_client_burst_nothing_lost_in_order(ref, igtl_server):
    """TrackerClient at 1000 fps: 300 TRANSFORMs arrive complete and in order (checked against
    the example's formula, frame by frame)."""
    srv = igtl_server()
    peer = ref("TrackerClient", "127.0.0.1", srv.address[1], 1000)
    msgs = h.collect(srv, 300, where=h.of_type("TRANSFORM"), timeout=20)
    assert len(msgs) == 300, peer.describe()
    for i, (m, f) in enumerate(zip(msgs, h.tracker_matrices(300), strict=True)):
        assert h.close(m.matrix, f, atol=2e-4), f"frame {i}: {m.matrix} != {f}"
    (p,) = srv.peers
    assert p.malformed == 0


def test_our_client_burst_to_receive_server(ref_server, igtl_client):
    """90 TRANSFORMs queued back to back (ReceiveServer reads 100 per connection): all printed,
    in order, with the right content (each one's CRC verified by the reference)."""
    peer, port = ref_server("ReceiveServer", "{port}")
    cli = igtl_client(port)
    for i in range(90):
        assert cli.send(igtl.TransformMessage.from_position((float(i), -float(i), 0.5 * i),
                                                           device_name=f"B{i}"))
    got = peer.wait_output(lambda ls: len(m := h.parse_matrices(ls)) >= 90 and m, timeout=20)
    assert got, peer.describe()
    assert [tuple(m[:3, 3]) for m in got] == [(float(i), -float(i), 0.5 * i) for i in range(90)]


def test_our_server_broadcasts_to_three_reference_clients(ref, igtl_server):
    srv = igtl_server()
    peers = [ref("ReceiveClient", "127.0.0.1", srv.address[1]) for _ in range(3)]
    assert srv.wait_for_peers(3, h.WAIT), [p.describe() for p in peers]
    assert srv.send(igtl.StringMessage(string="to everyone", device_name="All")) == 3
    for p in peers:
        assert p.wait_count(r"^Encoding: 3; String: to everyone$", 1) == 1, p.describe()


def test_our_client_reconnects_to_a_reference_server_on_the_same_port(ref, igtl_client):
    """Our client (reconnect=True) loses its server (connection reset), then a ReceiveServer
    appears on the same port: the client connects again and what it sends is printed.

    The first server is a plain socket closed with RST: the reference binds without
    SO_REUSEADDR, so a killed reference server would leave the port in TIME_WAIT for a minute."""
    lst = socket.create_server(("0.0.0.0", 0))
    port = lst.getsockname()[1]
    cli = igtl_client(port, connect=False)
    lst.settimeout(h.WAIT)
    conn, _ = lst.accept()
    assert cli.wait_connected(h.WAIT)
    conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    conn.close()  # RST: no TIME_WAIT on the server port
    lst.close()
    assert h.poll(lambda: not cli.connected), "client did not notice the reset"
    peer = ref("ReceiveServer", port)
    assert h.poll(lambda: h.is_listening(port) is not False and peer.alive()), peer.describe()
    assert cli.wait_connected(h.WAIT), "client did not reconnect"

    def delivered():  # a send racing the reconnect may be dropped; poll by re-sending
        cli.send(igtl.StringMessage(string="after", device_name="R"))
        return peer.wait_count("String: after", 1, timeout=0.2)

    assert h.poll(delivered, interval=0.0), peer.describe()


# ------------------------------------------------------------------------------ pyigtl, large
BIG = ((np.arange(24 * 256 * 256, dtype=np.int64) % 4093 - 2000)
       .astype(np.int16).reshape(24, 256, 256))


@pytest.mark.parametrize("endian", ["little", "big"])
def test_large_image_our_client_to_pyigtl(pyigtl_server, igtl_client, endian):
    """3 MiB int16 volume, pixels little- or big-endian on the wire (E field): pyigtl returns
    the same values either way."""
    srv, port = pyigtl_server()
    cli = igtl_client(port)
    assert h.poll(srv.is_connected)
    msg = igtl.ImageMessage.from_array(BIG, spacing=(0.2, 0.2, 1.0), endian=endian,
                                       device_name="Big", timestamp=time.time())
    assert h.split_wire(msg.pack()).content[4] == (2 if endian == "little" else 1)
    assert cli.send(msg)
    got = srv.wait_for_message("Big", timeout=20)
    assert got is not None
    assert np.array_equal(got.image.astype(np.int16), BIG)


def test_large_image_pyigtl_to_our_server(pyigtl, pyigtl_client, igtl_server):
    srv = igtl_server()
    cli = pyigtl_client(srv.address[1])
    assert srv.wait_for_peers(1, h.WAIT)
    assert cli.send_message(pyigtl.ImageMessage(BIG, device_name="BigPy"), wait=False)
    (img,) = h.collect(srv, 1, where=h.of_type("IMAGE"), timeout=20)
    assert img.size == (256, 256, 24)
    assert np.array_equal(np.asarray(img.pixels)[..., 0].astype(np.int16), BIG)
