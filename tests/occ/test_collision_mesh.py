"""3D Slicer mesh regions off the loop thread (issue 40, item 4; occ/kinematics/regions.py,
occ/net/operators.py; docs/SAFETY.md SR-ARMS-4).

- A mesh of more than ``MESH_PART`` triangles is built in spatially compact parts, the pause
  called between two; checked in parts it is the same region: each link's distance a lower
  bound of coal's distance to the whole mesh, exact inside the margin, negative where the
  link penetrates it (a depth is coal's estimate either way).
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
from occ.kinematics.regions import MESH_PART
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
