"""The slave's contact force as 3D Slicer is sent it (occ/haptics/forceviz.py), read by real peers.

The wall pair (configs/master.yaml + configs/wall.yaml, :class:`occ_testkit.testing.SimPair`) runs
the paper's motion into the tissue in simulated time; what the slave's Slicer interface sent at the
peak force (the ``TipForce`` TRANSFORM and the ``ForceArrow`` POLYDATA, the daemon's own bytes)
goes out of our TCP server to:

- pyigtl 0.3.x as a v2 client (as 3D Slicer connects): the TRANSFORM's matrix and metadata as
  pyigtl decodes them (pyigtl cannot decode POLYDATA: its ``_unpack_content`` indexes a
  ``struct.Struct``);
- the reference library's PolyDataClient (header v1, CRC checked): the arrow's points and
  polygons as it prints them.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest
import yaml

from occ.haptics.forceviz import parse_force
from occ_testkit.testing import CONFIGS, SimPair

from . import helpers as h

pytestmark = pytest.mark.interop


@pytest.fixture(scope="module")
def peak() -> dict[str, Any]:
    """The TipForce and ForceArrow sent with the largest force in 10 s of the wall pair."""
    cfg = yaml.safe_load((CONFIGS / "wall.yaml").read_text())
    with SimPair(CONFIGS / "master.yaml", cfg) as p:
        slicer = p.slave.peer("slicer")
        p.start()
        p.run_for(10.0)
        tf = slicer.messages("TRANSFORM", "TipForce")
        arrows = slicer.messages("POLYDATA", "ForceArrow")
    assert len(tf) == len(arrows) >= 100
    mags = [float(m.metadata["force_mag_n"]) for m in tf]
    i = int(np.argmax(mags))
    assert mags[i] > 1.0 and arrows[i].metadata["force_n"] == tf[i].metadata["force_n"]
    return {"transform": tf[i], "arrow": arrows[i]}


def test_pyigtl_reads_the_force_transform(
    pyigtl: Any, pyigtl_client: Any, igtl_server: Any, peak: dict[str, Any]
) -> None:
    srv = igtl_server()
    cli = pyigtl_client(srv.address[1])
    assert srv.wait_for_peers(1, h.WAIT)
    hello = pyigtl.StringMessage("hello", device_name="Hello")  # v2, as Slicer greets
    hello.header_version = 2
    hello.metadata = {"dummy": "dummy"}
    assert cli.send_message(hello, wait=False)
    assert h.collect(srv, 1, where=h.of_type("STRING")), "v2 hello did not arrive"
    sent = peak["transform"]
    assert srv.send(sent) == 1
    got = cli.wait_for_message("TipForce", timeout=h.WAIT)
    assert got is not None, "pyigtl did not get TipForce"
    assert got.header_version == 2
    f = parse_force(got.metadata["force_n"])
    assert f is not None and f == parse_force(sent.metadata["force_n"])
    assert got.metadata["frame"] == "patient" and got.metadata["source"] == "tissue"
    assert got.metadata["MRMLNodeName"] == "LinearTransform"
    m = np.asarray(got.matrix, dtype=float)
    assert np.allclose(m, sent.matrix.astype(np.float32), rtol=0, atol=1e-5)
    # what Slicer would draw: z is the force at mm_per_n, x and y unit and at right angles
    k = float(got.metadata["mm_per_n"])
    assert np.allclose(m[:3, 2], np.array(f) * k, atol=1e-3)
    assert np.allclose(m[:3, :2].T @ m[:3, :2], np.eye(2), atol=1e-5)
    assert got.timestamp == pytest.approx(sent.timestamp, abs=1e-6)


def test_reference_polydata_client_reads_the_arrow(ref: Any, igtl_server: Any,
                                                    peak: dict[str, Any]) -> None:  # fmt: skip
    srv = igtl_server()
    peer = ref("PolyDataClient", "127.0.0.1", srv.address[1])
    (get,) = h.collect(srv, 1, where=h.of_type("GET_POLYDATA"))
    arrow = peak["arrow"]
    # the reference library speaks header v1: the same content without metadata
    v1 = dataclasses.replace(arrow, header_version=1, metadata={})
    assert srv.send(v1) == 1
    assert peer.wait_count(r"^=+$", 1), peer.describe()
    lines = peer.lines
    got_pts = [h.floats(x.split("=", 1)[1]) for x in lines if x.strip().startswith("point[")]
    assert np.allclose(got_pts, np.asarray(arrow.points, dtype=float), atol=1e-4)
    cells = [[int(v) for v in h.floats(x.split("=", 1)[1])] for x in lines if "cell[" in x]
    # the example prints the first index twice: "(a, a, b, c)"
    assert [tuple(c[1:]) for c in cells] == list(arrow.polygons)
    assert len(got_pts) == 38 and len(cells) == 48
