"""The slave's contact force made visible to 3D Slicer (issue 27, "Visible"; occ/haptics/forceviz.py).

The geometry (the TRANSFORM whose z axis is the force, the arrow mesh) is checked as numbers;
the output source ``force`` on the shipped wall pair (configs/master.yaml + configs/wall.yaml,
:class:`occ_testkit.testing.SimPair`) through the daemons' own code in simulated time: what 3D
Slicer's port receives against what the slave sent its master on the return channel and against the
simulated tissue's force.
"""

from __future__ import annotations

import math
from collections import Counter
from typing import Any

import numpy as np
import pytest
import yaml

from occ.errors import ConfigError
from occ.haptics.forceviz import MIN_LENGTH_MM, arrow_mesh, force_matrix, parse_force
from occ.core.loader import parse_config
from occ_testkit.testing import CONFIGS, SimPair, SimRobot

MM_PER_N = 10.0


def wall() -> dict[str, Any]:
    return dict(yaml.safe_load((CONFIGS / "wall.yaml").read_text()))


# ------------------------------------------------------------------------------ geometry
@pytest.mark.parametrize(
    "force", [(1.0, 0.0, 0.0), (-0.3, 2.0, 0.5), (0.0, 0.0, -4.0), (1e-3, -1e-3, 0.0)]
)
def test_the_transform_puts_the_force_on_z_at_the_tip(force: tuple[float, float, float]) -> None:
    tip = (12.5, -3.0, 40.0)
    m = force_matrix(tip, force, MM_PER_N)
    f = np.array(force)
    assert np.allclose(m[:3, 3], tip) and np.allclose(m[3], (0, 0, 0, 1))
    assert np.allclose(m[:3, 2], f * MM_PER_N)  # z: the force, mm per N
    x, y = m[:3, 0], m[:3, 1]
    assert np.isclose(np.linalg.norm(x), 1.0) and np.isclose(np.linalg.norm(y), 1.0)
    assert abs(x @ y) < 1e-12 and abs(x @ f) < 1e-12 and abs(y @ f) < 1e-12
    # right-handed: a model under it is not mirrored
    assert np.linalg.det(m[:3, :3]) == pytest.approx(np.linalg.norm(f) * MM_PER_N)


def test_no_force_is_a_short_invertible_transform() -> None:
    m = force_matrix((1.0, 2.0, 3.0), (0.0, 0.0, 0.0), MM_PER_N)
    assert np.allclose(m[:3, :3], np.diag([1.0, 1.0, MIN_LENGTH_MM]))
    assert np.isfinite(np.linalg.inv(m)).all()


def _edges(polys: tuple[tuple[int, ...], ...]) -> Counter[tuple[int, int]]:
    return Counter((p[i], p[(i + 1) % len(p)]) for p in polys for i in range(len(p)))


def _signed_volume(points: np.ndarray, polys: tuple[tuple[int, ...], ...]) -> float:
    vol = 0.0
    for p in polys:
        a = points[p[0]]
        for i in range(1, len(p) - 1):
            vol += float(np.dot(a, np.cross(points[p[i]], points[p[i + 1]]))) / 6.0
    return vol


@pytest.mark.parametrize("force", [(2.0, 0.0, 0.0), (0.3, -0.4, 1.2), (0.0, 0.0, -0.05)])
def test_the_arrow_is_a_closed_outward_mesh_from_the_tip(
    force: tuple[float, float, float],
) -> None:
    tip = np.array([5.0, -7.0, 30.0])
    points, polys = arrow_mesh(tuple(tip), force, MM_PER_N)
    f = np.array(force)
    length = float(np.linalg.norm(f)) * MM_PER_N
    d = f / np.linalg.norm(f)
    # closed and consistently oriented: every directed edge once, its reverse once
    edges = _edges(polys)
    assert all(n == 1 for n in edges.values())
    assert all(edges[(b, a)] == 1 for a, b in edges)
    # faces outward: positive volume, about a shaft plus a cone
    along = (points - tip) @ d
    assert along.min() == pytest.approx(0.0, abs=1e-9)
    assert along.max() == pytest.approx(length)
    apex = points[int(np.argmax(along))]
    assert np.allclose(apex, tip + f * MM_PER_N)
    radial = np.linalg.norm((points - tip) - np.outer(along, d), axis=1)
    r_shaft, r_head = sorted(set(np.round(radial[radial > 1e-9], 9)))
    head = length - float(np.round(along[np.isclose(radial, r_head)][0], 9))
    neck = length - head
    sides = 12
    # the prisms and cones inscribed in the circles: n/2 sin(2 pi/n) r^2 is a polygon's area
    area = sides / 2 * math.sin(2 * math.pi / sides)
    expected = area * (r_shaft**2 * neck + r_head**2 * head / 3.0)
    assert _signed_volume(points - tip, polys) == pytest.approx(expected, rel=1e-6)


def test_no_force_is_no_arrow() -> None:
    points, polys = arrow_mesh((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), MM_PER_N)
    assert points.shape == (0, 3) and polys == ()
    points, polys = arrow_mesh((0.0, 0.0, 0.0), (math.nan, 0.0, 0.0), MM_PER_N)
    assert points.shape == (0, 3) and polys == ()


def test_parse_force() -> None:
    assert parse_force("1,-2.5,3e-2") == (1.0, -2.5, 0.03)
    for bad in (None, "", "1,2", "1,2,3,4", "1,x,3", "nan,0,0", "inf,0,0"):
        assert parse_force(bad) is None


# ------------------------------------------------------------------------------ config
def test_a_force_output_needs_a_force_and_a_type_that_carries_it() -> None:
    cfg = wall()
    cfg["interfaces"][0]["outputs"].append(
        {"type": "POINT", "device": "F", "source": "force", "rate_hz": 10}
    )
    with pytest.raises(ConfigError, match="source 'force' goes as TRANSFORM, POLYDATA"):
        parse_config(yaml.safe_dump(cfg))
    cfg = yaml.safe_load((CONFIGS / "slave.yaml").read_text())
    cfg["interfaces"][0]["outputs"].append(
        {"type": "TRANSFORM", "device": "TipForce", "source": "force", "rate_hz": 10}
    )
    with pytest.raises(ConfigError, match="source 'force' needs the controller's force"):
        parse_config(yaml.safe_dump(cfg))


# ------------------------------------------------------------------------------ the pair
@pytest.fixture(scope="module")
def pair_run() -> dict[str, Any]:
    """8 s of the wall pair; per slave tick: the tissue's force, the force sent on the
    return channel; what Slicer's port got."""
    returned: list[Any] = []

    def keep(direction: str, msg: Any, index: int) -> bool:
        if direction == "return":
            returned.append(msg)
        return False  # nothing lost

    with SimPair(CONFIGS / "master.yaml", wall(), drop=keep) as p:
        slicer = p.slave.peer("slicer")
        p.start()
        env = p.slave.robot.hardware.environment
        ctl: Any = p.slave.robot.controller.controllers[0]
        own = ctl.stats()["force"]["display"]["own_estimates"]
        truth = []
        start = len(slicer.received)
        for _ in range(8000):
            p.step(1)
            truth.append(env.force_n)
        got = slicer.received[start:]
        return {
            "own_estimates": ctl.stats()["force"]["display"]["own_estimates"] - own,
            "got": got,
            "returned": [m for m in returned if m.device_name == "SlaveTip"],
            "truth": np.array(truth),
            "stats": ctl.stats()["force"],
            "states": (p.master.robot.state.value, p.slave.robot.state.value),
        }


def test_slicer_gets_the_arrow_and_the_transform_at_10_hz(pair_run: dict[str, Any]) -> None:
    assert pair_run["states"] == ("RUNNING", "RUNNING")
    got = pair_run["got"]
    tf = [m for m in got if m.message_type == "TRANSFORM" and m.device_name == "TipForce"]
    arrows = [m for m in got if m.message_type == "POLYDATA" and m.device_name == "ForceArrow"]
    tips = [m for m in got if m.message_type == "TRANSFORM" and m.device_name == "Tip"]
    assert len(tf) == len(arrows) == len(tips) == 80  # 10 Hz for 8 s
    assert pair_run["own_estimates"] == 0  # the return channel's estimates, every time
    forces = np.array([parse_force(m.metadata["force_n"]) for m in tf])
    mags = np.linalg.norm(forces, axis=1)
    assert mags.max() > 1.0  # the paper's motion presses into the wall
    for m, arrow, tip, f in zip(tf, arrows, tips, forces, strict=True):
        assert m.header_version == 2 and m.metadata["frame"] == "patient"
        assert m.metadata["source"] == "tissue" and m.metadata["MRMLNodeName"] == "LinearTransform"
        assert float(m.metadata["force_mag_n"]) == pytest.approx(np.linalg.norm(f), abs=2e-4)
        assert arrow.metadata["force_n"] == m.metadata["force_n"]
        assert arrow.metadata["MRMLNodeName"] == "Model"
        # at the Tip Slicer is sent in the same tick, z the force at 10 mm per N
        assert np.allclose(m.matrix[:3, 3], tip.matrix[:3, 3], atol=1e-4)
        length = np.linalg.norm(f) * MM_PER_N
        if length >= MIN_LENGTH_MM:
            assert np.allclose(m.matrix[:3, 2], f * MM_PER_N, atol=2e-3)
            pts = np.asarray(arrow.points, dtype=float)
            along = (pts - tip.matrix[:3, 3]) @ (f / np.linalg.norm(f))
            assert along.max() == pytest.approx(length, abs=2e-3)
            assert len(arrow.polygons) == 48
        else:
            assert len(arrow.points) == 0


def test_the_force_shown_is_the_force_sent_to_the_master(pair_run: dict[str, Any]) -> None:
    """Each TipForce carries the force of the last SlaveTip sent before it (500 Hz: at most
    2 ms older; in a tick with both, Slicer's interface sends first), and it follows the
    tissue's force (the effort estimate's error aside)."""
    returned = pair_run["returned"]
    stamps = np.array([m.timestamp for m in returned])
    tf = [m for m in pair_run["got"] if m.device_name == "TipForce"]
    for m in tf:
        i = int(np.searchsorted(stamps, m.timestamp, side="left")) - 1
        assert i >= 0 and 0.0 < m.timestamp - stamps[i] <= 0.002 + 1e-6
        assert m.metadata["force_n"] == returned[i].metadata["force_n"]
    shown = np.array([parse_force(m.metadata["force_n"]) for m in tf])
    truth = pair_run["truth"][99::100]  # the tissue at each output's tick
    peak = float(np.linalg.norm(pair_run["truth"], axis=1).max())
    err = np.linalg.norm(shown - truth, axis=1)
    assert float(np.sqrt((err**2).mean())) < 0.1 * peak, (err.max(), peak)


def test_without_a_master_the_source_estimates_itself() -> None:
    """A slave alone (no return channel) pressed into the tissue at rest: Slicer still gets
    the force, estimated by the source itself (``tissue``: the simulated sensor)."""
    cfg = wall()
    cfg["controller"]["params"]["force"] = {"sources": ["tissue"]}
    master = next(i for i in cfg["interfaces"] if i["name"] == "master")
    del master["outputs"]  # no return channel: nobody else estimates the force
    with SimRobot(cfg) as probe:
        tip_x = probe.robot.data.world_tip()[0, 3] * 1e3
    # the wall 1 mm behind the tip at home: 0.5 N/mm pushes the tool back along -x
    cfg["environment"]["contacts"][0]["point_mm"] = [tip_x - 1.0, 0.0, 0.0]
    with SimRobot(cfg) as sim:
        slicer = sim.peer("slicer")
        op = sim.peer("operator")
        op.send_command("Enable")
        sim.run_for(1.0)
        tf = slicer.messages("TRANSFORM", "TipForce")
        assert len(tf) >= 10
        f = parse_force(tf[-1].metadata["force_n"])
        assert f is not None and f[0] < -0.3 and abs(f[1]) < 0.05 and abs(f[2]) < 0.05
        assert tf[-1].metadata["source"] == "tissue"
        ctl: Any = sim.robot.controller.controllers[0]
        display = ctl.stats()["force"]["display"]
        assert display["own_estimates"] == display["sent"] / 2  # once a tick for two outputs
        arrow = slicer.messages("POLYDATA", "ForceArrow")[-1]
        assert len(arrow.points) == 38
