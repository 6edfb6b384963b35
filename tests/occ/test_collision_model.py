"""Whole-arm collision checking (occ/kinematics/collision.py) piece by piece, without a loop: the
`collision` selection of scripts/mutate (test_collision.py has the same through the robot).

- Regions: spheres, planes and meshes placed in metres with their broad-phase bounds; every
  definition that cannot be used refused with its reason; from the config and from 3D Slicer
  (visible points only, each point's radius or the metadata's; a plane's z axis; polygons and
  strips triangulated with one winding).
- The model: the UR5's links, self pairs (adjacent and SRDF-disabled pairs left out), margins,
  the tool capsule from the tip along its z, the capsules of a URDF without geometry joining
  the joint origins, the configured base link, the reach covering every geometry point.
- The checks: every pair's distance is a lower bound of the exact one (coal, computed here
  without the broad phase), exact near the margin, a mesh's the largest level it exceeds;
  ``check`` and ``clearance`` are the pairs' verdict; excluded links are not checked.
- The plan check finds the first sample inside a margin and skips only what the motion bound
  clears; the run-time guard admits within half the last clearance, stops once per verdict
  inside the margin, lets a run that started inside move away, paces its verdicts, and says
  why its worker failed.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import coal
import numpy as np
import pinocchio as pin
import pytest

import igtl
from occ.clock import SimClock
from occ.config import CollisionConfig, RegionConfig
from occ.core.assembly import build_hardware
from occ.core.data import RobotData
from occ.core.loader import load_config
from occ.core.safety import RobotState
from occ.core.supervision import Worker
from occ.errors import ConfigError
from occ.kinematics.armgeom import rotation_to as _rotation_to
from occ.kinematics.armgeom import srdf_disabled as _srdf_disabled
from occ.kinematics.collision import (
    BROAD_PAD_M,
    ESCAPE_TOLERANCE_M,
    MAX_TRIANGLES,
    MESH_LEVELS,
    CollisionGuard,
    CollisionModel,
    Contact,
    Region,
    RegionError,
    Verdict,
    mesh_region,
    plane_region,
    region_from_config,
    regions_from_event,
    sphere_region,
)
from occ.kinematics.frame import Frame
from occ.net.decoders import event_of
from occ_testkit.testing import CONFIGS, SimRobot

HOME = [0.0, -1.2, 1.5, -1.9, -1.57, 0.0]
RAISED = [0.0, -1.5, 2.0, -2.0, -1.57, 0.0]  # the forearm through z = 560 mm
FOLDED = [2.33, -0.32, 2.97, -1.03, -0.2, 3.06]  # the wrist on the upper arm
CEILING = {"name": "ceiling", "kind": "plane", "point_mm": [0, 0, 560], "normal": [0, 0, -1]}
UR5 = load_config(CONFIGS / "ur5.yaml").robot
UR5_FRAME = build_hardware(UR5)[1]
UR5_LINKS = [
    "base_link", "shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link",
    "wrist_2_link", "wrist_3_link", "ee_link",
]  # fmt: skip


def ur5(frame: Frame = UR5_FRAME, **cfg: Any) -> CollisionModel:
    return CollisionModel.build(CollisionConfig(**cfg), UR5.frame, frame)


def turned_base() -> np.ndarray:
    b = np.eye(4)
    c, s = math.cos(0.5), math.sin(0.5)
    b[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    b[:3, 3] = [0.05, -0.03, -0.02]
    return b


def world_placements(cm: CollisionModel, q: Any, base: Any) -> list[pin.SE3]:
    """Each geometry object's pose in the world (patient frame), from pinocchio directly."""
    data, gdata = cm.model.createData(), pin.GeometryData(cm.geom)
    pin.updateGeometryPlacements(cm.model, data, cm.geom, gdata, np.asarray(q, dtype=float))
    world = pin.SE3(np.asarray(base, dtype=float)) if base is not None else pin.SE3.Identity()
    if cm.base_inv is not None:
        world = world * cm.base_inv
    return [world * m for m in gdata.oMg]


def exact_pairs(cm: CollisionModel, q: Any, base: Any) -> dict[tuple[str, str], float]:
    """Every (link, region or self:link) distance, by coal without any broad phase."""
    tf = [coal.Transform3s(m) for m in world_placements(cm, q, base)]
    objs = cm.geom.geometryObjects
    out = {}
    for lk in cm.links:
        for r in cm.regions:
            if lk.name not in r.exclude:
                res = coal.DistanceResult()
                out[(lk.name, r.name)] = coal.distance(
                    objs[lk.index].geometry, tf[lk.index], r.geometry, r.placement,
                    coal.DistanceRequest(), res,
                )  # fmt: skip
    for a, b in cm.self_pairs:
        res = coal.DistanceResult()
        d = coal.distance(
            objs[a].geometry, tf[a], objs[b].geometry, tf[b], coal.DistanceRequest(), res
        )
        out[(cm.links[a].name, f"self:{cm.links[b].name}")] = d
    return out


def box(lo: Any, hi: Any) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """A closed box (mm): its 8 corners and 12 triangles."""
    c = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    quads = ((0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3))
    return c, [t for a, b, cc, d in quads for t in ((a, b, cc), (a, cc, d))]


def triangles(region: Region) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    g = region.geometry
    tris = []
    for i in range(g.num_tris):
        t = g.tri_indices(i)
        tris.append((int(t[0]), int(t[1]), int(t[2])))
    return np.asarray(g.vertices()), tris


def normals(v: np.ndarray, tris: list[tuple[int, int, int]]) -> np.ndarray:
    """Each triangle's area vector (half the cross product: its normal times its area)."""
    return np.array([0.5 * np.cross(v[b] - v[a], v[c] - v[a]) for a, b, c in tris])


# ------------------------------------------------------------------------------ regions
@pytest.mark.req("SR-COLL-1")
def test_a_sphere_region_is_placed_in_metres_and_bounded_by_its_ball() -> None:
    r = sphere_region("s", [10.0, -20.0, 30.0], 5.0, exclude=["base_link"], source="Markups")
    assert (r.name, r.kind, r.source, r.exclude) == ("s", "sphere", "Markups", {"base_link"})
    assert r.geometry.radius == pytest.approx(0.005)
    assert np.asarray(r.placement.getTranslation()) == pytest.approx([0.01, -0.02, 0.03])
    assert np.asarray(r.placement.getRotation()) == pytest.approx(np.eye(3))
    assert r.bound == pytest.approx((0.01, -0.02, 0.03, 0.0, 0.005))
    assert sphere_region("t", (0, 0, 0), 1.0).source == "config"
    assert sphere_region("t", (0, 0, 0), 1.0).exclude == frozenset()


@pytest.mark.req("SR-COLL-1")
def test_a_plane_region_forbids_the_side_behind_its_unit_normal() -> None:
    r = plane_region("p", [0.0, 0.0, 560.0], [0.0, 0.0, -2.0], source="Ceiling")
    assert (r.kind, r.source) == ("plane", "Ceiling")
    assert np.asarray(r.geometry.n) == pytest.approx([0.0, 0.0, -1.0])
    # the half-space {x: n.x <= d}: everything above 560 mm
    assert r.geometry.d == pytest.approx(-0.56)
    assert r.bound[:4] == pytest.approx((0.0, 0.0, -1.0, -0.56)) and math.isnan(r.bound[4])
    ball = coal.Sphere(0.01)

    def gap(z_mm: float) -> float:
        res = coal.DistanceResult()
        tf = coal.Transform3s(np.eye(3), np.array([0.0, 0.0, z_mm * 1e-3]))
        return coal.distance(ball, tf, r.geometry, r.placement, coal.DistanceRequest(), res)

    assert gap(500.0) == pytest.approx(0.05) and gap(600.0) < 0.0
    tilted = plane_region("q", [100.0, 0.0, 0.0], [3.0, 0.0, 4.0])
    assert np.asarray(tilted.geometry.n) == pytest.approx([0.6, 0.0, 0.8])
    assert tilted.geometry.d == pytest.approx(0.06)
    assert plane_region("q", [0, 0, 0], [0, 0, 1]).source == "config"


@pytest.mark.req("SR-COLL-1")
def test_a_mesh_region_keeps_its_triangles_in_metres() -> None:
    corners, tris = box([0.0, 0.0, 0.0], [100.0, 200.0, 300.0])
    r = mesh_region("m", corners.ravel().tolist(), np.array(tris).ravel(), exclude=["tool"])
    assert (r.kind, r.source, r.exclude) == ("mesh", "config", {"tool"})
    v, got = triangles(r)
    assert v == pytest.approx(corners * 1e-3) and got == tris
    # the bound: a ball around the box (its centre, half its diagonal)
    assert r.bound == pytest.approx((0.05, 0.1, 0.15, 0.0, 0.5 * math.sqrt(0.01 + 0.04 + 0.09)))
    # integer vertices are taken as numbers of mm
    v2, _ = triangles(mesh_region("n", [[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]))
    assert v2 == pytest.approx(np.array([[0, 0, 0], [1e-3, 0, 0], [0, 1e-3, 0]]))


@pytest.mark.req("SR-COLL-1")
@pytest.mark.parametrize(
    ("make", "error"),
    [
        (lambda: sphere_region("s", [0, 0, 0], 0.0), "region 's': radius 0.0 must be > 0"),
        (lambda: sphere_region("s", [0, 0, 0], -1.0), "radius -1.0 must be > 0"),
        (lambda: sphere_region("s", [0, 0, 0], math.inf), "radius inf must be > 0"),
        (lambda: sphere_region("s", [0, 0, 0], math.nan), "radius nan must be > 0"),
        (lambda: sphere_region("s", [0, 0], 1.0), "region 's': the centre needs three numbers"),
        (lambda: sphere_region("s", [0, 0, "x"], 1.0), "the centre needs three numbers"),
        (lambda: sphere_region("s", [0, math.nan, 0], 1.0), "region 's': the centre is not finite"),
        (lambda: plane_region("p", [0, 0, 0], [0, 0, 0]), "region 'p': the normal is zero"),
        (lambda: plane_region("p", [0, 0, 0], [1e-13, 0, 0]), "the normal is zero"),
        (lambda: plane_region("p", [0, 0], [0, 0, 1]), "region 'p': the point needs three"),
        (
            lambda: plane_region("p", [0, 0, 0], [0, math.inf, 1]),
            "region 'p': the normal is not finite",
        ),
        (lambda: mesh_region("m", [[0, 0, 0]] * 3, []), "region 'm': the mesh has no triangles"),
        (
            lambda: mesh_region("m", [[0, 0, 0]] * 3, [[0, 1, 2]] * (MAX_TRIANGLES + 1)),
            f"region 'm': {MAX_TRIANGLES + 1} triangles (at most {MAX_TRIANGLES})",
        ),
        (
            lambda: mesh_region("m", [[0, 0, 0], [1, 0, 0], [0, math.nan, 0]], [[0, 1, 2]]),
            "region 'm': a vertex is not a finite number",
        ),
        (
            lambda: mesh_region("m", [[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 3]]),
            "region 'm': a triangle refers to a missing point",
        ),
        (
            lambda: mesh_region("m", [[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, -1, 2]]),
            "a triangle refers to a missing point",
        ),
    ],
)
def test_a_region_that_cannot_be_used_is_refused_with_the_reason(make: Any, error: str) -> None:
    with pytest.raises(RegionError) as err:
        make()
    assert error in str(err.value)


@pytest.mark.req("SR-COLL-1")
def test_the_largest_mesh_is_taken() -> None:
    r = mesh_region("m", [[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]] * MAX_TRIANGLES)
    assert r.triangles == MAX_TRIANGLES and len(r.parts) > 1  # built in parts


@pytest.mark.req("SR-COLL-1")
def test_regions_from_the_config_of_each_kind(tmp_path: Path) -> None:
    s = region_from_config(
        RegionConfig(name="s", kind="sphere", point_mm=(1, 2, 3), radius_mm=4, exclude_links=("a",))
    )
    assert (s.kind, s.bound, s.exclude) == (
        "sphere",
        pytest.approx((1e-3, 2e-3, 3e-3, 0, 4e-3)),
        {"a"},
    )
    p = region_from_config(
        RegionConfig(
            name="p", kind="plane", point_mm=(0, 0, 100), normal=(0, 0, 2), exclude_links=("b",)
        )
    )
    assert p.kind == "plane" and p.exclude == {"b"}
    assert p.bound[:4] == pytest.approx((0.0, 0.0, 1.0, 0.1))
    stl = tmp_path / "tri.stl"
    stl.write_text(
        "solid t\nfacet normal 0 0 1\n outer loop\n  vertex 0 0 0\n  vertex 10 0 0\n"
        "  vertex 0 10 0\n endloop\nendfacet\nendsolid t\n"
    )
    m = region_from_config(
        RegionConfig(name="m", kind="mesh", file=stl, point_mm=(100, 0, 5), exclude_links=("c",))
    )
    v, tris = triangles(m)
    assert m.kind == "mesh" and m.exclude == {"c"} and len(tris) == 1
    # the file's origin at point_mm: the triangle moved by it
    assert sorted(map(tuple, (v * 1e3).round(6).tolist())) == [
        (100.0, 0.0, 5.0), (100.0, 10.0, 5.0), (110.0, 0.0, 5.0)
    ]  # fmt: skip
    bad = tmp_path / "bad.stl"
    bad.write_text("not a mesh")
    with pytest.raises(RegionError, match=f"region 'x': cannot read {bad}"):
        region_from_config(RegionConfig(name="x", kind="mesh", file=bad))
    # building the model: a config error naming the key
    with pytest.raises(ConfigError) as err:
        ur5(regions=[CEILING, {"name": "x", "kind": "mesh", "file": str(bad)}])
    assert str(err.value).startswith(f"safety.collision.regions: region 'x': cannot read {bad}")
    with pytest.raises(ConfigError) as err:
        ur5(regions=[CEILING, {**CEILING, "name": "c2", "exclude_links": ["base_link", "arm"]}])
    assert str(err.value) == (
        "safety.collision.regions[1].exclude_links: no link 'arm' with collision geometry "
        f"(links: {', '.join(sorted(UR5_LINKS))})"
    )


def forbidden(**meta: str) -> dict[str, str]:
    return {"kind": "forbidden-region", **meta}


@pytest.mark.req("SR-COLL-3")
def test_slicer_points_are_spheres_of_their_radius_and_only_the_visible_ones() -> None:
    pts = (
        igtl.PointElement(position=(1.0, 2.0, 3.0), radius=4.0),
        igtl.PointElement(position=(5.0, 6.0, 7.0), rgba=(255, 0, 0, 0)),  # hidden
        igtl.PointElement(position=(8.0, 9.0, 10.0), rgba=(255, 0, 0, 1)),  # no radius
    )
    msg = igtl.PointMessage(pts, device_name="Marks", header_version=2, metadata=forbidden())
    name, regions = regions_from_event(event_of(msg))  # type: ignore[misc]
    assert name == "Marks"
    assert [(r.name, r.kind, r.source) for r in regions] == [
        ("Marks:0", "sphere", "Marks"), ("Marks:1", "sphere", "Marks")
    ]  # fmt: skip
    assert regions[0].bound == pytest.approx((1e-3, 2e-3, 3e-3, 0.0, 4e-3))
    assert regions[1].bound == pytest.approx((8e-3, 9e-3, 10e-3, 0.0, 10e-3))  # 10 mm default
    msg = igtl.PointMessage(
        pts, device_name="M", header_version=2, metadata=forbidden(radius="2.5")
    )
    _, regions = regions_from_event(event_of(msg))  # type: ignore[misc]
    assert [r.bound[4] for r in regions] == pytest.approx([4e-3, 2.5e-3])
    # a point radius under 1 mm is still the point's
    small = (igtl.PointElement(radius=0.5),)
    msg = igtl.PointMessage(small, device_name="P", header_version=2, metadata=forbidden())
    assert regions_from_event(event_of(msg))[1][0].bound[4] == pytest.approx(0.5e-3)  # type: ignore[index]
    # a point with a zero radius and one negative: the metadata's
    zero = (igtl.PointElement(radius=0.0), igtl.PointElement(radius=-1.0))
    msg = igtl.PointMessage(zero, device_name="Z", header_version=2, metadata=forbidden(radius="3"))
    _, regions = regions_from_event(event_of(msg))  # type: ignore[misc]
    assert [r.bound[4] for r in regions] == pytest.approx([3e-3, 3e-3])
    bad = igtl.PointMessage(
        pts, device_name="B", header_version=2, metadata=forbidden(radius="big")
    )
    with pytest.raises(RegionError) as err:
        regions_from_event(event_of(bad))
    assert str(err.value) == "region 'B': radius 'big' is no number"
    # a point list with no visible point: the definition removes its regions
    hidden = igtl.PointMessage(pts[1:2], device_name="H", header_version=2, metadata=forbidden())
    assert regions_from_event(event_of(hidden)) == ("H", [])


@pytest.mark.req("SR-COLL-3")
def test_a_slicer_plane_is_the_half_space_behind_its_z_axis() -> None:
    m = np.eye(4)
    m[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]  # z axis: -y
    m[:3, 3] = [10.0, 20.0, 30.0]
    msg = igtl.TransformMessage.from_matrix(
        m, device_name="Wall", header_version=2, metadata={"kind": " Forbidden-Region "}
    )
    name, (r,) = regions_from_event(event_of(msg))  # type: ignore[misc]
    assert (name, r.name, r.kind, r.source) == ("Wall", "Wall", "plane", "Wall")
    assert r.bound[:4] == pytest.approx((0.0, -1.0, 0.0, -0.02))
    bad = np.eye(4)
    bad[0, 3] = math.inf
    msg = igtl.TransformMessage.from_matrix(
        bad, device_name="W", header_version=2, metadata=forbidden()
    )
    with pytest.raises(RegionError) as err:
        regions_from_event(event_of(msg))
    assert str(err.value) == "region 'W': not a transform"
    # no device name: the definition is called "region"
    anon = igtl.TransformMessage.from_matrix(np.eye(4), header_version=2, metadata=forbidden())
    assert regions_from_event(event_of(anon))[0] == "region"  # type: ignore[index]


@pytest.mark.req("SR-COLL-3")
def test_slicer_polygons_and_strips_are_triangulated_with_one_winding() -> None:
    # a pentagon (a fan of 3 triangles) and a strip of 5 points (3 triangles) in z = 0
    pts = np.array(
        [[0, 0, 0], [20, 0, 0], [30, 15, 0], [10, 30, 0], [-10, 15, 0],
         [100, 0, 0], [100, 10, 0], [110, 0, 0], [110, 10, 0], [120, 0, 0]],
        dtype=np.float32,
    )  # fmt: skip
    msg = igtl.PolyDataMessage(
        points=pts, polygons=((0, 1, 2, 3, 4),), strips=((5, 6, 7, 8, 9),),
        device_name="Organ", header_version=2, metadata=forbidden(),
    )  # fmt: skip
    name, (r,) = regions_from_event(event_of(msg))  # type: ignore[misc]
    assert (name, r.name, r.kind, r.source) == ("Organ", "Organ", "mesh", "Organ")
    v, tris = triangles(r)
    assert v == pytest.approx(pts * 1e-3)
    assert tris[:3] == [(0, 1, 2), (0, 2, 3), (0, 3, 4)]
    assert sorted(map(sorted, tris[3:])) == [[5, 6, 7], [6, 7, 8], [7, 8, 9]]
    n = normals(v * 1e3, tris)
    # the fan covers the pentagon (shoelace area 750 mm^2), the strip its 3 triangles of 50
    assert n[:3, 2].sum() == pytest.approx(750.0) and (n[:3, 2] > 0).all()
    assert (np.abs(n[3:, 2]) == pytest.approx(50.0)) and len(set(np.sign(n[3:, 2]))) == 1
    tiny = igtl.PolyDataMessage(
        points=pts, polygons=((0, 1),), device_name="T", header_version=2, metadata=forbidden()
    )
    with pytest.raises(RegionError) as err:
        regions_from_event(event_of(tiny))
    assert str(err.value) == "region 'T': polygon 0 has fewer than 3 points"
    only_strip = igtl.PolyDataMessage(
        points=pts, strips=((5, 6, 7),), device_name="S", header_version=2, metadata=forbidden()
    )
    _, (s,) = regions_from_event(event_of(only_strip))  # type: ignore[misc]
    assert triangles(s)[1] == [(5, 6, 7)]


@pytest.mark.req("SR-COLL-3")
def test_messages_that_define_no_region() -> None:
    plain = igtl.TransformMessage.from_matrix(np.eye(4), device_name="Base")
    assert regions_from_event(event_of(plain)) is None  # no metadata
    other = igtl.TransformMessage.from_matrix(np.eye(4), header_version=2, metadata={"x": "1"})
    assert regions_from_event(event_of(other)) is None
    text = igtl.StringMessage("x", device_name="S", header_version=2, metadata=forbidden())
    with pytest.raises(RegionError) as err:
        regions_from_event(event_of(text))
    assert str(err.value) == ("region 'S': a STRING defines no region (POINT, TRANSFORM, POLYDATA)")


# ------------------------------------------------------------------------------ the model
@pytest.mark.req("SR-COLL-1")
def test_the_ur5_model_has_its_links_self_pairs_and_margins() -> None:
    cm = ur5(margin_mm=12.5, self_margin_mm=3.0, tool={"length_mm": 100.0})
    assert [lk.name for lk in cm.links] == [*UR5_LINKS, "tool"]
    assert [lk.index for lk in cm.links] == list(range(9))
    assert [lk.joint for lk in cm.links] == [0, 1, 2, 3, 4, 5, 6, 6, 6]
    assert cm.margin == pytest.approx(0.0125) and cm.self_margin == pytest.approx(0.003)
    assert all(type(g.geometry).__name__ == "Convex" for g in cm.geom.geometryObjects[:7])
    names = {(cm.links[a].name, cm.links[b].name) for a, b in cm.self_pairs}
    parents = cm.model.parents
    for a, b in cm.self_pairs:
        ja, jb = cm.links[a].joint, cm.links[b].joint
        assert a < b and ja != jb and parents[ja] != jb and parents[jb] != ja
    disabled = _srdf_disabled(
        Path(UR5.frame.urdf_path()).parent.parent / "srdf" / "ur5.srdf"  # type: ignore[union-attr]
    )
    assert not any(frozenset(p) in disabled for p in names)
    assert ("upper_arm_link", "wrist_3_link") in names and ("base_link", "tool") in names
    assert len(cm.self_pairs) == 20
    assert cm.base_inv is not None and cm.base_inv.isIdentity()
    # without the SRDF's exclusions there are more pairs; self_collision off, none
    empty = Path(__file__).with_name("_empty.srdf")
    try:
        empty.write_text("<robot name='ur5'/>")
        assert len(ur5(srdf=empty, tool={"length_mm": 100.0}).self_pairs) > 20
    finally:
        empty.unlink()
    assert ur5(self_collision=False).self_pairs == ()
    # meshes kept as meshes (convex off)
    assert type(ur5(convex=False).geom.geometryObjects[1].geometry).__name__.startswith("BVH")


@pytest.mark.req("SR-COLL-1")
def test_the_srdf_is_read_and_a_bad_one_is_a_config_error(tmp_path: Path) -> None:
    srdf = tmp_path / "arm.srdf"
    srdf.write_text(
        "<robot name='arm'><disable_collisions link1='a' link2='b' reason='x'/>"
        "<disable_collisions link1='c' link2='d'/><group name='g'/></robot>"
    )
    assert _srdf_disabled(srdf) == {frozenset(("a", "b")), frozenset(("c", "d"))}
    ET.parse(srdf)  # well formed
    srdf.write_text("<robot>")
    with pytest.raises(ConfigError, match=f"safety.collision.srdf: cannot read {srdf}"):
        _srdf_disabled(srdf)
    with pytest.raises(ConfigError, match="safety.collision.srdf: cannot read"):
        _srdf_disabled(tmp_path / "none.srdf")
    # a configured SRDF disabling one more pair
    srdf.write_text("<robot><disable_collisions link1='base_link' link2='wrist_3_link'/></robot>")
    names = {(cm_a.name, cm_b.name) for cm_a, cm_b in _pair_links(ur5(srdf=srdf))}
    assert ("base_link", "wrist_3_link") not in names and ("wrist_1_link", "wrist_3_link") in names


def _pair_links(cm: CollisionModel) -> list[Any]:
    return [(cm.links[a], cm.links[b]) for a, b in cm.self_pairs]


@pytest.mark.req("SR-COLL-1")
def test_the_tool_is_a_capsule_from_the_tip_along_its_z() -> None:
    cm = ur5(tool={"length_mm": 120.0, "radius_mm": 7.0})
    tool = cm.geom.geometryObjects[cm.links[-1].index]
    assert (tool.name, type(tool.geometry).__name__) == ("tool", "Capsule")
    assert tool.geometry.radius == pytest.approx(0.007)
    assert tool.geometry.halfLength == pytest.approx(0.06)
    for q in (HOME, RAISED, FOLDED):
        tip = UR5_FRAME.fk(q)
        m = world_placements(cm, q, None)[cm.links[-1].index]
        start, end = m.act(np.array([0, 0, -0.06])), m.act(np.array([0, 0, 0.06]))
        assert start == pytest.approx(tip[:3, 3], abs=1e-12)
        assert end == pytest.approx(tip[:3, 3] + 0.12 * tip[:3, 2], abs=1e-12)


MOUNTED = """<robot name="mounted">
  <link name="world"/>
  <joint name="mount" type="fixed"><parent link="world"/><child link="plate"/>
    <origin xyz="0.1 -0.2 0.3" rpy="0 0 0.5"/></joint>
  <link name="plate"/>
  <joint name="j1" type="revolute"><parent link="plate"/><child link="l1"/>
    <origin xyz="0 0 0.1"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <link name="l1"/>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0 0 0.2"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <link name="l2"/>
  <joint name="tip_joint" type="fixed"><parent link="l2"/><child link="tip"/>
    <origin xyz="0.3 0 0"/></joint>
  <link name="tip"/>
</robot>
"""


@pytest.mark.req("SR-COLL-1")
def test_the_arm_stands_on_its_configured_base_link(tmp_path: Path) -> None:
    """A base link away from the URDF's root (a plate 0.3 m up, turned): every link is placed
    relative to it, the tool starting at the frame's tip as the robot's tip is shown; capsules
    (no collision geometry in this URDF) join the joint origins."""
    from occ.config import FrameConfig

    urdf = tmp_path / "mounted.urdf"
    urdf.write_text(MOUNTED)
    frame = Frame.from_urdf(urdf, "tip", "plate")
    fc = FrameConfig(urdf=urdf, tip_link="tip", base_link="plate")
    cm = CollisionModel.build(
        CollisionConfig(link_radius_mm=10.0, tool={"length_mm": 50.0}), fc, frame
    )
    assert [type(g.geometry).__name__ for g in cm.geom.geometryObjects] == ["Capsule"] * 4
    # each capsule hangs on its joint's first body: the root's is the URDF's world link
    assert [lk.name for lk in cm.links] == ["world", "l1", "l2", "tool"]
    assert np.asarray(cm.base_inv.homogeneous) == pytest.approx(
        np.linalg.inv(cm.model.frames[cm.model.getFrameId("plate")].placement.homogeneous)
    )
    base = turned_base()
    checker = cm.checker()
    for q in ([0.0, 0.0], [0.7, -0.4]):
        tip = base @ frame.fk(q)
        m = world_placements(cm, q, base)[-1]
        assert m.act(np.array([0, 0, -0.025])) == pytest.approx(tip[:3, 3], abs=1e-12)
        checker._place(q, base)
        assert checker._world[-1].getTranslation() == pytest.approx(tip[:3, 3] + 0.025 * tip[:3, 2])
        # the first capsule from the URDF's root (below the plate, where the base puts it)
        half = cm.geom.geometryObjects[0].geometry.halfLength
        root = (base @ cm.base_inv.homogeneous)[:3, 3]
        assert checker._world[0].transform(np.array([0.0, 0.0, -half])) == pytest.approx(root)
    # no base pose given: the base link at the origin
    checker._place([0.0, 0.0], None)
    root = cm.base_inv.translation
    assert checker._world[0].transform(np.array([0.0, 0.0, -half])) == pytest.approx(root)
    tip = frame.fk([0.0, 0.0])
    assert checker._world[-1].getTranslation() == pytest.approx(tip[:3, 3] + 0.025 * tip[:3, 2])


MESHED = """<robot name="meshed">
  <link name="world"/>
  <joint name="mount" type="fixed"><parent link="world"/><child link="plate"/>
    <origin xyz="0.1 -0.2 0.3" rpy="0 0 0.5"/></joint>
  <link name="plate"><collision><geometry><mesh filename="package://meshes/MESH"/></geometry>
    </collision></link>
  <joint name="j1" type="revolute"><parent link="plate"/><child link="l1"/>
    <origin xyz="0 0 0.1"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <link name="l1"/>
  <joint name="j2" type="prismatic"><parent link="l1"/><child link="l2"/>
    <origin xyz="0 0 0.2"/><axis xyz="0 0 1"/>
    <limit lower="0" upper="0.2" effort="1" velocity="1"/></joint>
  <link name="l2"/>
  <joint name="j3" type="revolute"><parent link="l2"/><child link="l3"/>
    <origin xyz="0 0 0.05"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <link name="l3"><collision><origin xyz="0.15 0 0"/>
    <geometry><mesh filename="package://meshes/box.stl"/></geometry></collision></link>
  <joint name="tip_joint" type="fixed"><parent link="l3"/><child link="tip"/>
    <origin xyz="0.3 0 0"/></joint>
  <link name="tip"/>
</robot>
"""


def ascii_stl(lo: Any, hi: Any) -> str:
    c, tris = box(lo, hi)
    facets = "".join(
        " facet normal 0 0 0\n  outer loop\n"
        + "".join(f"   vertex {v[0]} {v[1]} {v[2]}\n" for v in (c[a], c[b], c[d]))
        + "  endloop\n endfacet\n"
        for a, b, d in tris
    )
    return f"solid box\n{facets}endsolid box\n"


def meshed(tmp_path: Path, mesh: str = "box.stl", **cfg: Any) -> tuple[Frame, CollisionModel]:
    """An arm of its own: meshes beside its URDF (``package://meshes/``, found through the
    URDF's directory), a base link away from the root, a prismatic joint along z between two
    revolute ones, no SRDF."""
    from occ.config import FrameConfig

    (tmp_path / "meshes").mkdir(exist_ok=True)
    (tmp_path / "meshes" / "box.stl").write_text(ascii_stl([-0.01] * 3, [0.01] * 3))
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(MESHED.replace("MESH", mesh))
    frame = Frame.from_urdf(urdf, "tip", "plate")
    fc = FrameConfig(urdf=urdf, tip_link="tip", base_link="plate")
    return frame, CollisionModel.build(CollisionConfig(**cfg), fc, frame)


@pytest.mark.req("SR-COLL-1")
def test_an_arm_with_meshes_beside_its_urdf(tmp_path: Path) -> None:
    frame, cm = meshed(tmp_path, tool={"length_mm": 50.0})
    assert [(lk.name, lk.joint) for lk in cm.links] == [("plate", 0), ("l3", 3), ("tool", 3)]
    assert [type(g.geometry).__name__ for g in cm.geom.geometryObjects] == [
        "Convex", "Convex", "Capsule"
    ]  # fmt: skip
    # no SRDF here: every pair of links not on one joint nor parent and child
    assert [(cm.links[a].name, cm.links[b].name) for a, b in cm.self_pairs] == [
        ("plate", "l3"), ("plate", "tool")
    ]  # fmt: skip
    # the prismatic joint (pinocchio's JointModelPZ) moves a point by its travel
    assert cm.reach[1] == 1.0 and len(cm.reach) == 3
    assert 0.3 < cm.reach[2] < cm.reach[0] < 1.0
    assert type(meshed(tmp_path, convex=False)[1].geom.geometryObjects[0].geometry).__name__ == (
        "BVHModelOBBRSS"
    )
    # the plate's box sits on the base: a check with the base pose puts it there
    checker = cm.checker()
    base = turned_base()
    checker._place([0.0, 0.0, 0.0], base)
    assert checker._world[0].getTranslation() == pytest.approx(base[:3, 3], abs=1e-12)
    with pytest.raises(
        ConfigError, match="safety.collision: the URDF's collision geometry does not"
    ):
        meshed(tmp_path, mesh="none.stl")


@pytest.mark.req("SR-COLL-1")
def test_a_urdf_without_collision_geometry_gets_capsules_joining_the_joint_origins() -> None:
    daemon = load_config(CONFIGS / "slave.yaml")
    frame = build_hardware(daemon.robot)[1]
    cfg = CollisionConfig(link_radius_mm=4.0, tool={"length_mm": 30.0, "radius_mm": 2.0})
    cm = CollisionModel.build(cfg, daemon.robot.frame, frame)
    objs = cm.geom.geometryObjects
    caps = [g for g in objs if g.name != "tool"]
    assert all(type(g.geometry).__name__ == "Capsule" for g in objs)
    assert [g.geometry.radius for g in caps] == pytest.approx([0.004] * len(caps))
    assert cm.self_pairs == ()  # capsules meet at every joint: no self pairs
    model = cm.model
    tip = model.frames[model.getFrameId(frame.tip_link)]
    segments = [
        (int(model.parents[j]), model.jointPlacements[j].translation)
        for j in range(1, model.njoints)
    ]
    segments.append((int(tip.parentJoint), tip.placement.translation))
    segments = [(p, np.asarray(t)) for p, t in segments if np.linalg.norm(t) >= 1e-6]
    assert len(caps) == len(segments) >= 2
    for q in ([0.0, 0.35, 0.05], [0.4, -0.3, 0.12]):
        data = model.createData()
        pin.forwardKinematics(model, data, np.asarray(q))
        world = world_placements(cm, q, None)
        for g, (parent, t) in zip(caps, segments, strict=True):
            i = [o.name for o in objs].index(g.name)
            half = g.geometry.halfLength
            assert 2 * half == pytest.approx(np.linalg.norm(t))
            ends = world[i].act(np.array([0, 0, -half])), world[i].act(np.array([0, 0, half]))
            expect = data.oMi[parent].act(np.zeros(3)), data.oMi[parent].act(t)
            assert ends[0] == pytest.approx(expect[0], abs=1e-12)
            assert ends[1] == pytest.approx(expect[1], abs=1e-12)
            assert g.parentJoint == parent
            assert model.frames[g.parentFrame].type == pin.FrameType.BODY
            assert int(model.frames[g.parentFrame].parentJoint) == parent
    # the link names: the body each capsule hangs on
    assert [lk.name for lk in cm.links] == [model.frames[g.parentFrame].name for g in caps] + [
        "tool"
    ]
    # the prismatic insertion moves every point after it by at most its travel
    assert cm.reach[2] == 1.0


@pytest.mark.req("SR-COLL-1")
@pytest.mark.parametrize(
    "z",
    [(0, 0, 1), (1, 0, 0), (0, 1, 0), (-1, 0, 0), (0.95, 0.1, 0.0), (0.9, 0.3, 0.3166),
     (1, 1, 0), (1, 0, 1), (0, 1, 1), (0.3, -0.5, 0.8)],
)  # fmt: skip
def test_a_rotation_to_any_axis(z: Any) -> None:
    zu = np.asarray(z, dtype=float) / np.linalg.norm(z)
    r = _rotation_to(zu)
    assert r @ r.T == pytest.approx(np.eye(3), abs=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    assert r[:, 2] == pytest.approx(zu)


@pytest.mark.req("SR-COLL-1")
def test_the_reach_covers_every_geometry_point_and_the_bounds_add_it_up() -> None:
    cm = ur5(tool={"length_mm": 100.0})
    assert len(cm.reach) == 6
    checker = cm.checker()
    data = cm.model.createData()
    rng = np.random.default_rng(3)
    farthest = [0.0] * 6
    # each joint's origin to each point of each geometry after it, over random poses
    for _ in range(30):
        q = rng.uniform(-3.0, 3.0, 6)
        pin.forwardKinematics(cm.model, data, q)
        pin.updateGeometryPlacements(cm.model, data, cm.geom, checker.gdata, q)
        for j in range(1, 7):
            origin = data.oMi[j].translation
            for i, g in enumerate(cm.geom.geometryObjects):
                k = int(g.parentJoint)
                while k > j:
                    k = int(cm.model.parents[k])
                if k != j:
                    continue
                geo, m = g.geometry, checker.gdata.oMg[i]
                pts = np.asarray(geo.points()) if hasattr(geo, "points") else np.zeros((1, 3))
                far = np.max(np.linalg.norm(pts @ m.rotation.T + m.translation - origin, axis=1))
                assert far <= cm.reach[j - 1] + 1e-9
                farthest[j - 1] = max(farthest[j - 1], float(far))
    # and not much more than the farthest point seen (chain lengths and bounding radii add up)
    # (measured 2026-11-27: 0.06-0.37 m over; the tool counted at its centre only)
    assert all(r - f < 0.4 for r, f in zip(cm.reach, farthest, strict=True))
    assert list(cm.reach) == sorted(cm.reach, reverse=True)
    qa, qb = np.array(HOME), np.array(HOME) + [0.1, -0.2, 0.0, 0.05, 0.0, -0.3]
    assert cm.bound(qa, qb) == pytest.approx(float(np.abs(qb - qa) @ np.array(cm.reach)))
    assert cm.bound(qb, qa) == cm.bound(qa, qb) and cm.bound(qa, qa) == 0.0
    with pytest.raises(ValueError):
        cm.bound(qa[:5], qb)
    v = [1.0, 2.0, 0.5, 0.0, 1.0, 3.0]
    assert cm.step_bound(v, 0.002) == pytest.approx(0.002 * float(np.dot(v, cm.reach)))
    with pytest.raises(ValueError):
        cm.step_bound(v[:5], 0.002)


@pytest.mark.req("SR-COLL-3")
def test_define_replaces_a_sources_regions_and_bumps_the_version() -> None:
    cm = ur5(regions=[CEILING], margin_mm=12.3456, self_margin_mm=2.3456)
    assert cm.version == 0 and [r.name for r in cm.regions] == ["ceiling"]
    a = sphere_region("A:0", (0, 0, 0), 1.0, source="A")
    b = sphere_region("B:0", (0, 0, 0), 1.0, source="B")
    assert cm.define("A", [a]) == 1 and cm.define("B", [b]) == 2
    assert [r.name for r in cm.regions] == ["ceiling", "A:0", "B:0"]
    a2 = sphere_region("A:1", (0, 0, 0), 1.0, source="A")
    assert cm.define("A", [a2]) == 3 and [r.name for r in cm.regions] == ["ceiling", "B:0", "A:1"]
    assert cm.define("B", []) == 4 and [r.name for r in cm.regions] == ["ceiling", "A:1"]
    assert cm.version == 4
    assert cm.describe() == {
        "links": [*UR5_LINKS],
        "self_pairs": 15,
        "regions": ["ceiling", "A:1"],
        "margin_mm": 12.346,
        "self_margin_mm": 2.346,
        "reach_m": [round(r, 4) for r in cm.reach],
    }
    assert all(len(str(r).split(".")[1]) <= 4 for r in cm.describe()["reach_m"])
    assert cm.describe()["reach_m"] != list(cm.reach)
    assert cm.path_check().cm is cm and cm.checker().cm is cm


# ------------------------------------------------------------------------------ the checks
def scene(**cfg: Any) -> CollisionModel:
    """The UR5 with a tool, a ceiling, a slanted wall, a sphere and a box around where the
    wrist passes."""
    wall = {"name": "wall", "kind": "plane", "point_mm": [600, 300, 0], "normal": [-1, -0.8, 0.3]}
    cm = ur5(
        tool={"length_mm": 100.0},
        regions=[
            CEILING,
            wall,
            {"name": "ball", "kind": "sphere", "point_mm": [300, 250, 300], "radius_mm": 60},
        ],
        **cfg,
    )
    corners, tris = box([560.0, 40.0, 300.0], [700.0, 200.0, 450.0])
    cm.define("Tumour", [mesh_region("Tumour", corners, tris, source="Tumour")])
    return cm


def sample_poses(n: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = [np.array(HOME), np.array(RAISED), np.array(FOLDED)]
    out += [np.array(HOME) + rng.normal(0.0, 0.6, 6) for _ in range(n)]
    return out


@pytest.mark.req("SR-COLL-1")
@pytest.mark.parametrize("base", [None, "turned"])
def test_every_pair_is_a_lower_bound_of_its_exact_distance_and_exact_near_the_margin(
    base: str | None,
) -> None:
    cm = scene()
    b = turned_base() if base else None
    checker = cm.checker()
    levels = {cm.margin + lv * BROAD_PAD_M for lv in MESH_LEVELS}
    seen = {"bounded": 0, "exact": 0, "level": 0}
    radius = {lk.name: cm.geom.geometryObjects[lk.index].geometry.aabb_radius for lk in cm.links}

    def far(lk: str, rg: str, e: float) -> bool:
        """Settled by the balls: a link lies within its ball, so the ball's distance to a
        sphere or a plane (or to another link's ball) is at most twice the radii short."""
        if rg == "Tumour":
            return False
        if rg.startswith("self:"):
            return e - 2.0 * (radius[lk] + radius[rg[5:]]) > cm.self_margin + BROAD_PAD_M
        return e - 2.0 * radius[lk] > cm.margin + BROAD_PAD_M

    for q in sample_poses(40, 11):
        truth = exact_pairs(cm, q, b)
        pairs = checker.pairs(q, b) if b is not None else checker.pairs(q)
        assert checker.exact + checker.bounded == len(pairs) == len(truth)
        assert checker.exact >= sum(d <= cm.margin + BROAD_PAD_M for d in truth.values())
        # the cost: what the balls settle is never computed (its distance is the balls', short
        # of the exact one)
        assert checker.bounded >= sum(far(lk, rg, e) for (lk, rg), e in truth.items())
        for _, d, lk, rg in pairs:
            if far(lk, rg, truth[(lk, rg)]):
                assert d < truth[(lk, rg)] - 1e-9, (lk, rg)
        assert [(lk, rg) for _, _, lk, rg in pairs] == list(truth)
        for slack, d, lk, rg in pairs:
            margin = cm.self_margin if rg.startswith("self:") else cm.margin
            assert slack == pytest.approx(d - margin, abs=1e-15)
            e = truth[(lk, rg)]
            assert d <= e + 1e-9, (lk, rg)
            near = e <= margin + BROAD_PAD_M
            if rg == "Tumour" and near and e >= cm.margin + 1e-6:
                assert any(d == pytest.approx(x) for x in levels) and d <= e + 1e-9
                seen["level"] += 1
            elif near:
                assert d == pytest.approx(e, abs=1e-9), (lk, rg)
                seen["exact"] += 1
            else:
                seen["bounded"] += d != pytest.approx(e, abs=1e-6)
    assert min(seen.values()) > 0, seen


@pytest.mark.req("SR-COLL-1")
def test_a_mesh_pair_is_the_largest_level_its_distance_exceeds() -> None:
    cm = ur5()
    checker = cm.checker()
    # a triangle below the arm at home, moved up to each distance from the lowest link point
    lowest = min(
        float(np.min((np.asarray(g.geometry.points()) @ m.rotation.T + m.translation)[:, 2]))
        for g, m in zip(cm.geom.geometryObjects, world_placements(cm, HOME, None), strict=True)
        if hasattr(g.geometry, "points")
    )
    # 100 mm: the triangle's ball reaches the arm, the first level (margin + 50 mm) is known
    for gap_mm, expect in ((100.0, 0.06), (45.0, 0.035), (20.0, 0.01625), (5.0, 0.005)):
        z = (lowest * 1e3) - gap_mm
        tri = [[-2000, -2000, z], [2000, -2000, z], [0, 2000, z]]
        cm.define("floor", [mesh_region("floor", tri, [[0, 1, 2]], source="floor")])
        (_, d, _, _), *_ = sorted(
            (p for p in checker.pairs(HOME) if p[3] == "floor"), key=lambda p: p[1]
        )
        assert d == pytest.approx(expect, abs=1e-5), gap_mm


@pytest.mark.req("SR-COLL-1")
def test_check_and_clearance_are_the_pairs_verdict() -> None:
    cm = scene()
    checker = cm.checker()
    b = turned_base()
    for q in sample_poses(10, 5):
        pairs = checker.pairs(q, b)
        hits = checker.check(q, b)
        inside = sorted((d, lk, rg) for s, d, lk, rg in pairs if s < 0.0)
        assert [(h.distance, h.link, h.region) for h in hits] == inside
        slack, gap, worst = checker.clearance(q, b)
        s0, d0, lk0, rg0 = next(p for p in pairs if p[0] == min(pp[0] for pp in pairs))
        assert slack == s0 and gap == min(p[1] for p in pairs)
        assert worst == Contact(lk0, rg0, d0)
    # the base pose is used: the raised arm clears the ceiling 300 mm lower
    lowered = np.eye(4)
    lowered[2, 3] = -0.3
    assert any(h.region == "ceiling" for h in checker.check(RAISED))
    assert not any(h.region == "ceiling" for h in checker.check(RAISED, lowered))
    assert checker.clearance(RAISED, lowered)[0] > checker.clearance(RAISED)[0]
    # two pairs equally close: the first is named (the ceiling, then its copy)
    twice = ur5(regions=[CEILING, {**CEILING, "name": "copy"}], self_collision=False)
    slack, gap, worst = twice.checker().clearance(RAISED)
    assert worst is not None and (worst.link, worst.region) == ("forearm_link", "ceiling")
    # one check a call, whichever asks
    fresh = cm.checker()
    assert (fresh.checks, fresh.exact, fresh.bounded) == (0, 0, 0)
    fresh.pairs(HOME)
    fresh.check(HOME)
    fresh.clearance(HOME)
    assert fresh.checks == 3


@pytest.mark.req("SR-COLL-1")
def test_nothing_to_check_is_infinitely_clear() -> None:
    cm = ur5(self_collision=False)
    checker = cm.checker()
    assert checker.pairs(HOME) == [] and checker.check(HOME) == []
    assert checker.clearance(HOME) == (math.inf, math.inf, None)


@pytest.mark.req("SR-COLL-1")
def test_an_excluded_link_is_not_checked_against_its_region() -> None:
    floor = {"name": "table", "kind": "plane", "point_mm": [0, 0, 10], "normal": [0, 0, 1]}
    cm = ur5(self_collision=False, regions=[{**floor, "exclude_links": ["base_link"]}, CEILING])
    checker = cm.checker()
    assert [(lk, rg) for _, _, lk, rg in checker.pairs(HOME)] == [
        (lk, rg)
        for lk in UR5_LINKS
        for rg in ("table", "ceiling")
        if (lk, rg) != ("base_link", "table")
    ]
    assert checker.check(HOME) == []
    cm2 = ur5(self_collision=False, regions=[floor])
    assert [h.link for h in cm2.checker().check(HOME)] == ["base_link"]


@pytest.mark.req("SR-COLL-1")
def test_a_contact_describes_link_region_and_distance() -> None:
    assert Contact("forearm_link", "ceiling", -0.00123).describe() == (
        "link 'forearm_link' penetrates forbidden region 'ceiling' by 1.23 mm"
    )
    assert Contact("tool", "ball", 0.0045).describe() == (
        "link 'tool' is 4.50 mm from forbidden region 'ball'"
    )
    assert (
        Contact("tool", "ball", 0.0).describe()
        == "link 'tool' is 0.00 mm from forbidden region 'ball'"
    )
    assert Contact("upper_arm_link", "self:wrist_3_link", 0.5).describe() == (
        "link 'upper_arm_link' is 500.00 mm from link 'wrist_3_link'"
    )


# ------------------------------------------------------------------------------ the plan check
def raise_path(n: int = 400) -> list[list[float]]:
    return [list(np.array(HOME) + (np.array(RAISED) - HOME) * k / (n - 1)) for k in range(n)]


@pytest.mark.req("SR-COLL-1")
def test_the_plan_check_finds_the_first_sample_inside_a_margin() -> None:
    cm = ur5(regions=[CEILING])
    pc = cm.path_check()
    checker = cm.checker()
    qs = raise_path()
    first = next(i for i, q in enumerate(qs) if checker.clearance(q)[0] < 0.0)
    paced: list[int] = []
    hit = pc.check_path(qs, np.eye(4), pace=lambda: paced.append(1))
    assert hit is not None and hit[0] == first
    slack, _gap, worst = checker.clearance(qs[first])
    assert hit[1] == f"{worst.describe()} (margin 10 mm)"  # type: ignore[union-attr]
    # conservative advancement: far fewer checks than samples, one pacing per check
    assert 2 < pc.checked == len(paced) < first
    # the same path without pacing, and the last check's count starts again from zero
    assert pc.check_path(qs, np.eye(4)) == hit and pc.checked == len(paced)
    # clear of everything: None; a start inside: sample 0
    lowered = np.eye(4)
    lowered[2, 3] = -0.3
    assert pc.check_path(qs, lowered) is None
    assert pc.check_path(qs[::-1], np.eye(4))[0] == 0  # type: ignore[index]
    assert pc.checked == 1


@pytest.mark.req("SR-COLL-1")
def test_the_plan_check_skips_only_what_the_bound_clears() -> None:
    cm = ur5(regions=[CEILING])
    pc = cm.path_check()
    # a sample inside right after a clear one, far from it: checked, not skipped
    assert pc.check_path([HOME, RAISED, HOME, HOME], np.eye(4))[0] == 1  # type: ignore[index]
    assert pc.checked == 2
    # two samples at the start, then the one inside
    assert pc.check_path([HOME, HOME, RAISED], np.eye(4))[0] == 2  # type: ignore[index]
    assert pc.checked == 2
    # a self contact is told with the self margin
    assert "(margin 2 mm)" in pc.check_path([HOME, FOLDED], np.eye(4))[1]  # type: ignore[index]
    # nothing to check: no contact, one look
    none = ur5(self_collision=False).path_check()
    assert none.checked == 0
    assert none.check_path([HOME, RAISED, FOLDED], np.eye(4)) is None and none.checked == 1


# ------------------------------------------------------------------------------ the guard
@pytest.mark.req("SR-COLL-2")
def test_the_guard_admits_within_half_the_last_clearance_for_its_regions_and_base() -> None:
    cm = ur5(regions=[CEILING])
    guard = CollisionGuard(cm, inline=True)
    base = np.eye(4)
    assert not guard.admit(HOME, base) and guard.holds == 1  # no verdict
    guard.publish(HOME, base)
    v = guard.verdict
    assert v is not None and v.q == tuple(HOME) and v.base is base and v.version == 0
    assert (v.slack, v.gap, v.worst) == cm.checker().clearance(HOME, base)
    assert guard.admit(HOME, base) and guard.admit(HOME, base.copy())  # the same pose
    step = 0.45 * v.gap / cm.reach[1]
    near, far = list(HOME), list(HOME)
    near[1] -= step
    far[1] -= 2.0 * step
    assert guard.admit(near, base) and guard.holds == 1
    assert not guard.admit(far, base) and guard.holds == 2
    assert guard.held_for == "the setpoint left half the last verdict's clearance"
    moved = base.copy()
    moved[0, 3] = 0.001
    assert not guard.admit(HOME, moved) and guard.holds == 3  # another base pose: hold
    assert guard.held_for == "no verdict for this base pose yet"
    # exactly half the clearance away: held (the bound must stay under it)
    r5 = cm.reach[5]
    guard.verdict = Verdict(tuple(HOME), base, 0.0, r5, None, cm.version)
    assert guard.admit([*HOME[:5], 0.4999], base) and guard.holds == 3
    assert not guard.admit([*HOME[:5], 0.5], base) and guard.holds == 4
    guard.verdict = v
    cm.define("x", [])
    assert not guard.admit(HOME, base) and guard.holds == 5  # other regions: hold
    guard.publish(HOME, base)
    assert guard.verdict.version == 1 and guard.admit(HOME, base)  # type: ignore[union-attr]
    assert guard.holds == 5 and guard.verdicts == 2


@pytest.mark.req("SR-COLL-2")
def test_the_guard_checks_with_the_base_pose_it_is_given() -> None:
    cm = ur5(regions=[CEILING])
    guard = CollisionGuard(cm, inline=True)
    lowered = np.eye(4)
    lowered[2, 3] = -0.3
    guard.publish(RAISED, lowered)
    assert guard.verdict.slack == cm.checker().clearance(RAISED, lowered)[0] > 0.0  # type: ignore[union-attr]
    assert guard.min_slack == guard.verdict.slack  # type: ignore[union-attr]
    guard.publish(RAISED, np.eye(4))
    assert guard.verdict.slack < 0.0 and guard.min_slack == guard.verdict.slack  # type: ignore[union-attr]
    guard.publish(HOME, np.eye(4))
    assert guard.min_slack < guard.verdict.slack  # type: ignore[union-attr]  # the least seen


@pytest.mark.req("SR-COLL-2")
def test_the_guard_stops_once_per_verdict_inside_the_margin_while_running() -> None:
    cm = ur5(regions=[CEILING])
    guard = CollisionGuard(cm, inline=True)
    assert guard.poll() is None  # no verdict
    guard.publish(RAISED, np.eye(4))
    assert guard.poll() is None  # not running
    guard.publish(HOME, np.eye(4))
    guard.on_running(True)  # started clear: the margin is the threshold
    guard.publish(RAISED, np.eye(4))
    why = guard.poll()
    worst = cm.checker().clearance(RAISED)[2]
    assert why == f"collision: {worst.describe()} (margin 10 mm)"  # type: ignore[union-attr]
    assert guard.last_contact == why[len("collision: ") :] and guard.stops == 1  # type: ignore[index]
    assert guard.poll() is None and guard.stops == 1  # once per verdict
    guard.publish(RAISED, np.eye(4))
    assert guard.poll() is not None and guard.stops == 2  # a new verdict inside: again
    # a self contact is told with the self margin
    guard.publish(FOLDED, np.eye(4))
    assert "link 'upper_arm_link'" in guard.poll() and "(margin 2 mm)" in guard.last_contact  # type: ignore[operator]


def verdict(guard: CollisionGuard, slack: float, worst: Contact | None = None) -> None:
    w = worst if worst is not None else Contact("forearm_link", "ceiling", slack + 0.01)
    guard.verdict = Verdict(tuple(HOME), None, slack, slack + 0.01, w, guard.cm.version)


@pytest.mark.req("SR-COLL-2")
def test_a_run_started_inside_the_margin_may_move_away_but_not_closer() -> None:
    guard = CollisionGuard(ur5(regions=[CEILING]), inline=True)
    on = ESCAPE_TOLERANCE_M
    verdict(guard, -0.004)
    guard.on_running(True)  # its best: -4 mm
    verdict(guard, -0.004 - 0.9 * on)  # closer, within the tolerance: on
    assert guard.poll() is None
    verdict(guard, -0.003)  # away: the new best
    assert guard.poll() is None
    verdict(guard, -0.003 - 0.9 * on)
    assert guard.poll() is None
    verdict(guard, -0.003 - 1.1 * on)  # closer than the best by more than the tolerance
    assert guard.poll() is not None and guard.stops == 1
    # out of the margin: the threshold is the margin again (no tolerance past zero)
    guard.on_running(False)
    verdict(guard, 0.002)
    guard.on_running(True)
    verdict(guard, -0.1 * on)
    assert guard.poll() is not None
    # exactly at the threshold: on (a link exactly at its margin is no contact)
    guard.on_running(False)
    verdict(guard, 0.001)
    guard.on_running(True)
    verdict(guard, 0.0)
    assert guard.poll() is None
    verdict(guard, -1e-12)
    assert guard.poll() is not None
    # a verdict with nothing checked never stops
    guard.on_running(False)
    guard.on_running(True)
    guard.verdict = Verdict(tuple(HOME), None, -1.0, -1.0, None, 0)
    assert guard.poll() is None
    # a run started with no verdict yet: the margin itself
    g2 = CollisionGuard(ur5(regions=[CEILING]), inline=True)
    g2.on_running(True)
    verdict(g2, -0.1 * on)
    assert g2.poll() is not None


@pytest.mark.req("SR-COLL-2")
def test_verdicts_are_paced_by_runtime_hz() -> None:
    cm = ur5(regions=[CEILING])
    guard = CollisionGuard(cm, inline=True, runtime_hz=100.0)
    guard.publish(HOME, np.eye(4), 1.0)
    assert guard.verdicts == 1
    guard.publish(RAISED, np.eye(4), 1.005)
    assert guard.verdicts == 1 and guard.verdict.q == tuple(HOME)  # type: ignore[union-attr]
    guard.publish(RAISED, np.eye(4), 1.01)  # due
    assert guard.verdicts == 2
    guard.publish(HOME, np.eye(4), 1.015)
    guard.publish(HOME, np.eye(4), 1.0199)
    assert guard.verdicts == 2
    guard.publish(HOME, np.eye(4))  # no time given: checked
    assert guard.verdicts == 3
    every = CollisionGuard(cm, inline=True)  # no rate: every one due
    for t, q in ((1.0, HOME), (1.0, RAISED), (1.001, HOME)):
        every.publish(q, np.eye(4), t)
    assert every.verdicts == 3


@pytest.mark.req("SR-COLL-2")
def test_the_worker_gets_one_job_at_a_time_and_a_failed_one_is_told() -> None:
    cm = ur5(regions=[CEILING])
    guard = CollisionGuard(cm, name="test-collision")
    worker = guard._worker
    assert worker is not None and not worker._started
    guard.publish(HOME, np.eye(4))  # the worker not started: refused, not busy
    assert worker.refused == 1 and guard.verdict is None
    silent = Worker("silent", depth=4)
    silent._started = True  # takes jobs, never runs them
    guard._worker = silent
    guard.publish(HOME, np.eye(4))
    guard.publish(HOME, np.eye(4))  # busy: not queued
    assert silent._jobs.qsize() == 1 and silent.refused == 0
    job = silent._jobs.get_nowait()
    job()  # the worker runs it
    assert guard.verdict is None and guard.fresh is not None and guard.verdicts == 1
    guard.take()  # the loop takes it (the start of after_control)
    assert guard.verdict is not None and guard.fresh is None
    guard.publish(HOME, np.eye(4))  # the verdict covers it: not due
    assert silent._jobs.qsize() == 0 and guard.skipped == 1
    guard.publish(RAISED, np.eye(4))
    assert silent._jobs.qsize() == 1
    # a failing check: no verdict, the reason kept, the next one taken
    guard._checker = None  # type: ignore[assignment]
    with pytest.raises(AttributeError):
        silent._jobs.get_nowait()()
    assert guard.worker_failed == "AttributeError: 'NoneType' object has no attribute 'clearance'"
    assert guard.verdicts == 1
    guard.publish(RAISED, np.eye(4))
    assert silent._jobs.qsize() == 1
    # a real worker thread
    real = CollisionGuard(cm, name="test-collision-2")
    real.start()
    try:
        real.publish(RAISED, np.eye(4))
        for _ in range(2000):
            if real.fresh is not None:
                break
            threading_sleep()
        real.take()
        assert real.verdict is not None and real.verdict.slack < 0.0
    finally:
        real.stop()
    # the worker thread: its name, its priority, one job and the stop's mark in its queue
    named = CollisionGuard(cm, name="occ-arm-collision", fifo_priority=41)._worker
    assert named is not None and named._thread.name == "occ-arm-collision"
    assert named.fifo_priority == 41 and named._jobs.maxsize == 2
    default = CollisionGuard(cm)._worker
    assert default is not None and default._thread.name == "occ-collision"
    assert default.fifo_priority is None
    assert default is not None and CollisionGuard(cm).policy == "hold"
    no_thread = CollisionGuard(cm, inline=True)
    assert no_thread._worker is None
    no_thread.start()
    no_thread.stop()
    assert CollisionGuard(cm, runtime=False)._worker is None


def threading_sleep() -> None:
    import time

    time.sleep(0.005)


def robot_data() -> RobotData:
    return RobotData("ur5", [f"j{i}" for i in range(6)], HOME, UR5_FRAME, SimClock())


@pytest.mark.req("SR-COLL-2")
def test_after_control_tells_running_stops_and_checks_the_powered_setpoint() -> None:
    cm = ur5(regions=[CEILING])
    guard = CollisionGuard(cm, inline=True, runtime_hz=100.0)
    data = robot_data()
    for state in (RobotState.READY, RobotState.FAULT, RobotState.ESTOP):
        data.state = state
        assert guard.after_control(state, data, 0.0) is None
    assert guard.verdicts == 0  # drives off: nothing checked
    data.state = RobotState.ENABLED
    data.hold_setpoint = list(RAISED)
    assert guard.after_control(RobotState.ENABLED, data, 0.0) is None  # not running: no stop
    assert guard.verdict.q == tuple(RAISED) and not guard.running  # type: ignore[union-attr]
    data.state = RobotState.RUNNING
    data.setpoint = list(HOME)
    assert guard.after_control(RobotState.RUNNING, data, 0.005) is None  # best: RAISED's
    assert guard.running and guard.verdicts == 1  # paced: the time is passed on
    assert guard.after_control(RobotState.RUNNING, data, 0.01) is None
    assert guard.verdict.q == tuple(HOME) and guard.verdict.base is data.base  # type: ignore[union-attr]
    data.setpoint = list(RAISED)
    guard.after_control(RobotState.RUNNING, data, 0.02)
    why = guard.after_control(RobotState.RUNNING, data, 0.025)
    assert why is not None and "forearm_link" in why
    data.state = RobotState.STOPPED
    data.hold_setpoint = list(HOME)
    assert guard.after_control(RobotState.STOPPED, data, 0.03) is None
    assert not guard.running and guard.verdict.q == tuple(HOME)  # type: ignore[union-attr]
    off = CollisionGuard(cm, inline=True, runtime=False)
    assert off.admitter(data) is None
    assert off.after_control(RobotState.RUNNING, data, 0.0) is None and off.verdicts == 0
    assert off.running


@pytest.mark.req("SR-COLL-2")
def test_the_admitter_asks_with_the_robots_base_pose_now() -> None:
    cm = ur5(regions=[CEILING])
    guard = CollisionGuard(cm, inline=True)
    data = robot_data()
    admit = guard.admitter(data)
    assert admit is not None
    guard.publish(HOME, data.base)
    assert admit(HOME, 0.0)
    data.base = turned_base()  # a tracker moved it: no verdict for it yet
    assert not admit(HOME, 0.0)
    guard.publish(HOME, data.base)
    assert admit(HOME, 0.0)


def ur5_collision(**collision: Any) -> dict[str, Any]:
    import yaml

    cfg: dict[str, Any] = yaml.safe_load((CONFIGS / "ur5.yaml").read_text())
    cfg["safety"]["collision"] = collision
    return cfg


@pytest.mark.req("SR-COLL-2")
def test_the_robots_guard_from_its_config() -> None:
    sim = SimRobot(ur5_collision(margin_mm=4.0, policy="fault", runtime_hz=50.0, regions=[CEILING]))
    try:
        guard = sim.robot.collision
        assert guard is not None and guard.inline and guard.runtime and guard._every == 0.02
        assert guard.policy == "fault" and guard.cm.margin == pytest.approx(0.004)
        assert [r.name for r in guard.cm.regions] == ["ceiling"]
        assert guard._worker is None
    finally:
        sim.close()
    sim = SimRobot(ur5_collision(runtime=False))
    try:
        guard = sim.robot.collision
        assert guard is not None and not guard.runtime and guard.policy == "hold"
    finally:
        sim.close()
    raw = ur5_collision()
    del raw["safety"]["collision"]
    sim = SimRobot(raw)
    try:
        assert sim.robot.collision is None
    finally:
        sim.close()


@pytest.mark.req("SR-COLL-2")
def test_a_robot_on_the_real_clock_checks_on_a_worker_thread_of_its_own() -> None:
    import yaml

    from occ.clock import RealClock
    from occ.core.loader import parse_config
    from occ.core.robot import build_robot
    from occ.recording.record import writer_priority
    from occ_testkit.testing import inproc_config

    cfg = parse_config(yaml.safe_dump(ur5_collision(margin_mm=5.0)), base_dir=CONFIGS)
    robot = build_robot(inproc_config(cfg), clock=RealClock())
    try:
        guard = robot.collision
        assert guard is not None and not guard.inline and guard._worker is not None
        assert guard._worker._thread.name == "occ-ur5-collision"
        assert guard._worker.fifo_priority == writer_priority(cfg)
    finally:
        robot.shutdown()


@pytest.mark.req("SR-COLL-2")
def test_a_margin_a_link_can_cross_in_one_tick_is_a_config_error() -> None:
    # the UR5's joints at their velocity limits for one tick: a link point moves up to the
    # period times the velocities weighted by the reaches
    sim = SimRobot(ur5_collision(margin_mm=5.0))
    try:
        robot = sim.robot
        cm = robot.collision.cm  # type: ignore[union-attr]
        velocities = [j.limits.velocity for j in robot.joints]
        step = cm.step_bound(velocities, robot.period)
        assert step == pytest.approx(robot.period * float(np.dot(velocities, cm.reach)))
    finally:
        sim.close()
    with pytest.raises(ConfigError) as err:
        SimRobot(ur5_collision(margin_mm=round(step * 500 * 0.99, 3)))
    assert (
        "safety.collision.margin_mm: must exceed half of what a link can move in one tick"
        in str(err.value)
    )
    assert str(err.value).endswith(f"({step * 500:.3g} mm), got {round(step * 500 * 0.99, 3):g}")
    sim = SimRobot(ur5_collision(margin_mm=round(step * 500 * 1.01, 3)))
    sim.close()


@pytest.mark.req("SR-COLL-2")
def test_a_margin_of_exactly_half_a_ticks_motion_is_refused() -> None:
    """The margin must exceed half of what a link can move in one tick: equal is refused,
    a hair more is taken (one joint moving, its velocity set to the float that makes the step
    exactly twice the margin, then to the next float down that makes it less)."""
    period = 1e-3
    cc = CollisionConfig(margin_mm=10.0)
    cm = ur5(margin_mm=10.0)
    vel = [0.0] * 5 + [2.0 * cm.margin / (period * cm.reach[5])]
    for _ in range(8):
        step = cm.step_bound(vel, period)
        if step == 2.0 * cm.margin:
            break
        vel[5] = math.nextafter(vel[5], 0.0 if step > 2.0 * cm.margin else math.inf)
    assert step == 2.0 * cm.margin

    def build() -> CollisionGuard | None:
        return CollisionGuard.build(
            cc, UR5.frame, UR5_FRAME, vel, period, real=False, fifo_priority=None, name="t"
        )

    with pytest.raises(ConfigError, match="must exceed half of what a link can move"):
        build()
    while cm.step_bound(vel, period) == step:
        vel[5] = math.nextafter(vel[5], 0.0)
    guard = build()
    assert guard is not None and guard.cm.margin == cm.margin


def test_the_statistics() -> None:
    cm = ur5(regions=[CEILING])
    guard = CollisionGuard(cm, inline=True)
    assert guard.stats() == {
        **cm.describe(),
        "verdicts": 0, "skipped": 0, "holds": 0, "held_for": "", "stops": 0,
        "last_contact": "", "clearance_mm": None, "min_slack_mm": None, "worker_failed": "",
    }  # fmt: skip
    guard.admit(HOME, np.eye(4))
    guard.on_running(True)
    guard.publish(RAISED, np.eye(4))
    guard.poll()
    guard.publish(HOME, np.eye(4))
    v = guard.verdict
    st = guard.stats()
    assert st["verdicts"] == 2 and st["holds"] == 1 and st["stops"] == 1
    assert st["last_contact"] == guard.last_contact != ""
    assert st["clearance_mm"] == round(v.gap * 1e3, 3)  # type: ignore[union-attr]
    assert st["min_slack_mm"] == round(guard.min_slack * 1e3, 3) < 0.0
    empty = CollisionGuard(ur5(self_collision=False), inline=True)
    empty.publish(HOME, None)
    assert empty.stats()["clearance_mm"] is None and empty.stats()["min_slack_mm"] is None
