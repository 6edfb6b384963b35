"""3D Slicer mesh regions off the loop thread (issue 40, item 4; occ/kinematics/regions.py,
occ/net/operators.py; docs/SAFETY.md SR-ARMS-4).

- A mesh of more than ``MESH_PART`` triangles is built in spatially compact parts, the pause
  called between two; checked in parts it is the same region: each link's distance a lower
  bound of coal's distance to the whole mesh, exact inside the margin, negative where the
  link penetrates it (a depth is coal's estimate either way). The parts are cut across a
  long mesh's length (8 of exactly MESH_PART for a 4096-triangle ribbon), each ball centred
  on its part's box; a Slicer model pauses after each block of cells and each part; exactly
  MAX_TRIANGLES are taken, one more refused.
- A Slicer model sent to the robot is built on the operator desk's worker, not on the loop
  thread, and takes effect when built; the loop ticks meanwhile; a bad one is refused to its
  sender from the worker and changes nothing.
"""

from __future__ import annotations

import threading
from typing import Any

import coal
import numpy as np
import pinocchio as pin
import pytest
import yaml

import igtl
from occ.config import CollisionConfig
from occ.core.assembly import build_hardware
from occ.core.loader import load_config
from occ.kinematics.collision import CollisionModel, mesh_region
from occ.kinematics.regions import MAX_TRIANGLES, MESH_PART, RegionError, regions_from_event
from occ.net.decoders import event_of
from occ_testkit.testing import CONFIGS, SimRobot, wait_until

HOME = [0.0, -1.2, 1.5, -1.9, -1.57, 0.0]
UR5 = load_config(CONFIGS / "ur5.yaml").robot
UR5_FRAME = build_hardware(UR5)[1]


def sphere_mesh(radius_mm: float, centre_mm: Any, n: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere (mm): 2 n (n - 1) triangles."""
    verts = [(0.0, 0.0, radius_mm), (0.0, 0.0, -radius_mm)]
    for i in range(1, n):
        th = np.pi * i / n
        for j in range(2 * n):
            ph = np.pi * j / n
            verts.append(
                (radius_mm * np.sin(th) * np.cos(ph), radius_mm * np.sin(th) * np.sin(ph),
                 radius_mm * np.cos(th))
            )  # fmt: skip
    ring = lambda i, j: 2 + (i - 1) * 2 * n + (j % (2 * n))  # noqa: E731
    tris = []
    for j in range(2 * n):
        tris.append((0, ring(1, j), ring(1, j + 1)))
        tris.append((1, ring(n - 1, j + 1), ring(n - 1, j)))
    for i in range(1, n - 1):
        for j in range(2 * n):
            a, b, c, d = ring(i, j), ring(i, j + 1), ring(i + 1, j), ring(i + 1, j + 1)
            tris += [(a, c, b), (b, c, d)]
    return np.asarray(verts) + np.asarray(centre_mm, dtype=float), np.asarray(tris)


@pytest.mark.req("SR-ARMS-4")
def test_a_mesh_in_parts_is_checked_as_the_whole_mesh() -> None:
    v, t = sphere_mesh(90.0, [610.0, 110.0, 440.0])  # just above the wrist at home
    assert len(t) > 4 * MESH_PART
    pauses = []
    region = mesh_region("Model", v, t, pause=lambda: pauses.append(1))
    assert region.geometry is None and len(region.parts) == len(pauses) > 4
    assert region.triangles == len(t)
    assert all(int(g.num_tris) <= MESH_PART for g in region.parts)
    whole = coal.BVHModelOBBRSS()
    whole.beginModel(len(t), len(v))
    whole.addVertices(v * 1e-3)
    whole.addTriangles(t)
    whole.endModel()
    cm = CollisionModel.build(CollisionConfig(self_collision=False), UR5.frame, UR5_FRAME)
    cm.define("Model", [region])
    checker = cm.checker()
    data, gdata = cm.model.createData(), pin.GeometryData(cm.geom)
    rng = np.random.default_rng(5)
    inside = 0
    for _ in range(30):
        q = np.array(HOME) + rng.normal(0.0, 0.08, 6)
        got = {lk: d for _s, d, lk, _r in checker.pairs(q, np.eye(4))}
        pin.updateGeometryPlacements(cm.model, data, cm.geom, gdata, q)
        for lk, obj, m in zip(cm.links, cm.geom.geometryObjects, gdata.oMg, strict=True):
            tf = coal.Transform3s(cm.base_inv * m)
            res = coal.DistanceResult()
            exact = coal.distance(
                obj.geometry, tf, whole, coal.Transform3s(), coal.DistanceRequest(), res
            )
            if exact >= 0.0:
                assert got[lk.name] <= exact + 1e-9, lk.name
            if 0.0 <= exact < cm.margin:  # inside the margin: coal's own number
                inside += 1
                assert got[lk.name] == pytest.approx(exact, abs=1e-9)
            elif exact < 0.0:  # penetrating: so it says (depths are coal's estimates)
                assert got[lk.name] < 0.0
    assert inside > 0


def slicer_model(name: str, v: np.ndarray, t: Any) -> igtl.PolyDataMessage:
    return igtl.PolyDataMessage(
        points=v.astype(np.float32),
        polygons=tuple(tuple(int(i) for i in tri) for tri in t),
        device_name=name,
        header_version=2,
        metadata={"kind": "forbidden-region"},
    )


@pytest.mark.req("SR-ARMS-4")
def test_a_slicer_model_is_built_on_the_desks_worker_and_takes_effect_when_built() -> None:
    cfg: dict[str, Any] = yaml.safe_load((CONFIGS / "ur5.yaml").read_text())
    cfg["safety"]["collision"] = {"margin_mm": 10.0}
    cfg["interfaces"][1]["inputs"] = [{"type": "POLYDATA", "queue": "command", "depth": 16}]
    sim = SimRobot(cfg)
    try:
        guard = sim.robot.collision
        assert guard is not None
        where: list[str] = []
        define = guard.cm.define

        def noted(source: str, regions: Any) -> int:
            where.append(threading.current_thread().name)
            return define(source, regions)

        guard.cm.define = noted  # type: ignore[method-assign]
        # the worker busy with something else: the model waits for it, the loop does not
        gate = threading.Event()
        worker = sim.robot.worker
        assert worker.start().submit(lambda: gate.wait(10.0) and None)
        v, t = sphere_mesh(90.0, [610.0, 110.0, 600.0])
        op = sim.peer("operator")
        op.send(slicer_model("Model", v, t))
        before = sim.robot.clock.now()
        sim.step(20)  # the loop ticks on, the message handed over
        assert sim.robot.clock.now() >= before + 0.019
        assert guard.cm.regions == () and where == []  # not built yet: not in effect
        gate.set()
        assert wait_until(lambda: guard.cm.regions)
        (region,) = guard.cm.regions
        assert region.name == "Model" and region.triangles == len(t) and len(region.parts) > 1
        assert where and where[0] != threading.main_thread().name
        # a bad model: refused to its sender from the worker, nothing changes
        op.send(slicer_model("Bad", v, [[0, 1, len(v) + 5]]))
        sim.step(2)

        def refused() -> list[str]:
            return [
                m.status_message
                for m in op.messages("STATUS")
                if "refers to a missing point" in m.status_message
            ]

        assert wait_until(refused) == ["region 'Bad': a triangle refers to a missing point"]
        assert [r.name for r in guard.cm.regions] == ["Model"]
    finally:
        sim.close()


def z_strip(gaps: int, x_mm: float, y_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """A ribbon 1 mm wide along -z from z = 0 (mm): two triangles per 1 mm gap."""
    v = [(x_mm + dx, y_mm, -float(k)) for k in range(gaps + 1) for dx in (0.0, 1.0)]
    t = []
    for k in range(gaps):
        a, b, c, d = 2 * k, 2 * k + 1, 2 * k + 2, 2 * k + 3
        t += [(a, b, c), (b, d, c)]
    return np.asarray(v), np.asarray(t)


@pytest.mark.req("SR-ARMS-4")
def test_a_long_mesh_is_cut_across_its_length_into_parts_with_their_balls() -> None:
    """A ribbon 2048 mm long along z (4096 triangles, far off the origin in x and y) is cut
    across its length, by median splits, into 8 parts of exactly MESH_PART triangles, each 256
    mm of the ribbon; each part's ball is centred on its box and reaches its farthest vertex;
    together they are the whole mesh, with its links excluded and its source; the region's
    ball is centred on the box around the parts' balls and reaches the farthest of them. A mesh
    of exactly MESH_PART triangles is one hierarchy."""
    v, t = z_strip(2048, 5000.0, -5000.0)
    assert len(t) == 8 * MESH_PART
    region = mesh_region("Ribbon", v, t, exclude=["tool"], source="Organs")
    assert region.geometry is None and region.triangles == len(t)
    assert (region.name, region.kind, region.exclude, region.source) == (
        "Ribbon",
        "mesh",
        {"tool"},
        "Organs",
    )
    assert [int(g.num_tris) for g in region.parts] == [MESH_PART] * 8
    balls = np.asarray(region.part_balls)
    spans = []
    for g, ball in zip(region.parts, balls, strict=True):
        pv = np.asarray(g.vertices())
        lo, hi = pv.min(axis=0), pv.max(axis=0)
        centre = (lo + hi) / 2.0
        assert ball[:3] == pytest.approx(centre, abs=1e-12)
        assert ball[3] == pytest.approx(float(np.linalg.norm(pv - centre, axis=1).max()), abs=1e-12)
        spans.append((round(float(lo[2]) * 1e3), round(float(hi[2]) * 1e3)))
    assert sorted(spans) == [(-256 * (i + 1), -256 * i) for i in reversed(range(8))]
    # the region's own ball (the broad phase's bound, which settles a far link without asking
    # a part): centred on the box around the parts' balls, reaching the farthest of them
    lo = (balls[:, :3] - balls[:, 3:]).min(axis=0)
    hi = (balls[:, :3] + balls[:, 3:]).max(axis=0)
    centre = (lo + hi) / 2.0
    reach = float((np.linalg.norm(balls[:, :3] - centre, axis=1) + balls[:, 3]).max())
    assert region.bound == pytest.approx((*centre.tolist(), 0.0, reach), abs=1e-12)
    assert centre * 1e3 == pytest.approx([5000.5, -5000.0, -1024.0], abs=1e-6)
    assert np.linalg.norm(v * 1e-3 - centre, axis=1).max() <= reach
    one = mesh_region("One", *z_strip(MESH_PART // 2, 0.0, 0.0))
    assert one.geometry is not None and one.parts == () and one.triangles == MESH_PART


@pytest.mark.req("SR-ARMS-4")
def test_a_slicer_model_gives_up_the_lock_between_its_blocks_and_parts() -> None:
    """A Slicer model of more than MESH_PART triangles, made into a region with a pause: the
    pause is called after every block of cells converted and after every part built (the
    worker gives up the interpreter lock there, docs/BENCHMARKS.md)."""
    v, t = z_strip(2048, 0.0, 0.0)
    pauses: list[int] = []
    name, (region,) = regions_from_event(  # type: ignore[misc]
        event_of(slicer_model("Ribbon", v, t)), pause=lambda: pauses.append(1)
    )
    assert name == "Ribbon" and region.triangles == len(t) and len(region.parts) == 8
    assert len(pauses) == 1 + 8  # one block of at most 8192 cells, then eight parts


@pytest.mark.req("SR-COLL-3")
def test_a_slicer_model_of_exactly_the_most_triangles_is_taken_one_more_is_refused() -> None:
    """MAX_TRIANGLES polygons (triangles) are taken; one polygon more is refused, as are strips
    that make one triangle more, each saying how many and the bound."""
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    most = slicer_model("Most", pts, [(0, 1, 2)] * MAX_TRIANGLES)
    _, (region,) = regions_from_event(event_of(most))  # type: ignore[misc]
    assert region.triangles == MAX_TRIANGLES
    over = slicer_model("Over", pts, [(0, 1, 2)] * (MAX_TRIANGLES + 1))
    with pytest.raises(RegionError) as err:
        regions_from_event(event_of(over))
    assert str(err.value) == (
        f"region 'Over': {MAX_TRIANGLES + 1} polygons (at most {MAX_TRIANGLES} triangles)"
    )
    strip = igtl.PolyDataMessage(
        points=pts.astype(np.float32),
        strips=(tuple([0, 1, 2] * ((MAX_TRIANGLES + 3) // 3 + 1))[: MAX_TRIANGLES + 3],),
        device_name="Strip",
        header_version=2,
        metadata={"kind": "forbidden-region"},
    )
    with pytest.raises(RegionError) as err:
        regions_from_event(event_of(strip))
    assert (
        str(err.value) == f"region 'Strip': {MAX_TRIANGLES + 1} triangles (at most {MAX_TRIANGLES})"
    )
