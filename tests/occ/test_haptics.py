"""The master's fixtures at run time (occ/haptics/master_fixtures.py, :class:`MasterFixtures`)
driven alone, without a loop: a definition is applied whole or refused whole (counted, the reason
kept and told, the previous set in force), the limits and the per-tick budget at their edges, the
mapping's changes, the force a tick with its time step, and what 3D Slicer is shown (the
fixtures' model and the contact proxy) checked geometrically (issue 29: the mutation run of
occ/haptics/master_fixtures.py; the shipped master in simulated time is
tests/occ/test_haptic_master.py)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import igtl
from igtl.messages.polydata import CELL_SCALAR
from occ.haptics.fixture_defs import Defaults, DefinitionError, PatientMapping
from occ.haptics.fixtures import AccessibleSphere, ForbiddenSphere
from occ.haptics.master_fixtures import KIND_CODE, MasterFixtures, _square
from occ.net.decoders import event_of
from occ.net.packers import mesh_message, transform_message

from .test_fixture_defs import R1, points, pt, vf


def fixtures(scale: float = 0.1, rotation: Any = None, **kw: Any) -> MasterFixtures:
    return MasterFixtures(Defaults(), PatientMapping(scale, rotation), **kw)


def centres(fx: MasterFixtures) -> list[Any]:
    """The active spheres' centres (the master's force frame, mm)."""
    spheres = (AccessibleSphere, ForbiddenSphere)
    return [p.centre for p in fx.active.primitives if isinstance(p, spheres)]


def plane(name: str, point: Any, normal: Any = (0.0, 0.0, 1.0), **meta: str) -> igtl.Message:
    m = np.eye(4)
    n = np.asarray(normal, dtype=float)
    m[:3, 2] = n
    m[:3, 3] = point
    e = tuple(m[:3, :].T.ravel().tolist())
    return igtl.TransformMessage(
        elements=e, device_name=name, header_version=2, metadata={"kind": "plane", **meta}
    )


# ------------------------------------------------------------------ applied or refused, whole
def test_a_new_master_has_nothing_and_shows_nothing() -> None:
    fx = MasterFixtures(Defaults(), PatientMapping(1.0))
    assert (fx.max_force_n, fx.slide_mm, fx.max_primitives, fx.max_planes) == (10.0, 1.0, 64, 8)
    assert (fx.active.max_force_n, fx.active.slide_mm) == (10.0, 1.0)
    assert fx.tool_mm == fx.force_n == fx.raw_force_n == (0.0, 0.0, 0.0)
    assert fx.stats() == {
        "fixtures": 0,
        "fixture_kinds": {"accessible": 0, "forbidden": 0, "plane": 0, "guide": 0},
        "fixture_sources": [],
        "fixtures_applied": 0,
        "fixtures_refused": 0,
        "fixture_last_error": "",
        "fixture_contacts": 0,
        "fixture_clamped": 0,
        "contact": [],
        "peak_force_n": 0.0,
    }
    proxy: Any = transform_message(fx.proxy("P"), "P")
    assert proxy.timestamp == 0.0 and mesh_message(fx.model("M"), "M").timestamp == 0.0
    assert proxy.metadata["tool_mm"] == "0.000,0.000,0.000"
    assert proxy.metadata["force_n"] == "0.0000,0.0000,0.0000"
    # its own limits reach the sets it builds
    small = fixtures(max_force_n=2.5, slide_mm=0.25)
    assert (small.active.max_force_n, small.active.slide_mm) == (2.5, 0.25)
    small.on_event(event_of(vf(((0.0, 0.0, 0.0, 1.0),))), 1.0)
    assert (small.active.max_force_n, small.active.slide_mm) == (2.5, 0.25)


def test_an_empty_definition_from_a_new_source_is_applied() -> None:
    """Slicer sends a Markups node as soon as it is created, before it has points."""
    fx = fixtures()
    assert (
        fx.on_event(event_of(points([], name="New")), 1.0) == "0 fixtures from POINT:New; 0 active"
    )
    assert fx.applied == 1 and fx.groups == {}


def test_a_definition_is_applied_and_described() -> None:
    fx = fixtures()
    assert fx.version == 0 and fx.applied == 0 and len(fx.active) == 0
    said = fx.on_event(event_of(vf(((0.0, 0.0, 0.0, 1.0), (5.0, 0.0, 0.0, 1.0)), name="A")), 1.0)
    assert said == "2 fixtures from VFIXTURE:A; 2 active"
    said = fx.on_event(event_of(points([pt("p", (0.0, 9.0, 0.0), radius=1.0)], name="B")), 1.0)
    assert said == "1 fixtures from POINT:B; 3 active"
    assert fx.applied == 2 and fx.version == 2 and sorted(fx.groups) == ["POINT:B", "VFIXTURE:A"]
    # no fixture message: nothing applied, nothing refused
    assert fx.on_event(event_of(igtl.TransformMessage(device_name="Tracker")), 1.0) is None
    assert (fx.applied, fx.refused, fx.version) == (2, 0, 2)


def test_a_refused_definition_is_counted_told_and_changes_nothing() -> None:
    fx = fixtures()
    fx.on_event(event_of(vf(((0.0, 0.0, 0.0, 1.0),), name="Good")), 1.0)
    active, version = fx.active, fx.version
    for n in (1, 2):
        with pytest.raises(DefinitionError) as err:
            fx.on_event(event_of(vf(((0.0, 0.0, 0.0, -1.0),), name="Bad")), 2.0)
        assert fx.refused == n
    cause = "VFIXTURE sphere 0 (0.0, 0.0, 0.0, -1.0): needs finite numbers and a radius > 0"
    assert fx.last_error == f"VFIXTURE 'Bad': {cause}"
    assert str(err.value) == f"fixture refused (VFIXTURE 'Bad': {cause}); the previous set stays"
    assert str(err.value.__cause__) == cause
    assert fx.active is active and fx.version == version and fx.applied == 1
    assert fx.stats()["fixture_last_error"] == fx.last_error
    assert fx.stats()["fixtures_refused"] == 2


def test_the_limits_count_every_source_but_the_one_replaced() -> None:
    fx = fixtures(max_primitives=4, max_planes=2)
    sphere = (0.0, 0.0, 0.0, 1.0)
    fx.on_event(event_of(vf((sphere, sphere), name="A")), 1.0)
    fx.on_event(event_of(vf((sphere, sphere), name="B")), 2.0)  # 4 in all: the limit itself
    fx.on_event(event_of(vf((sphere, sphere), name="B")), 3.0)  # B replaced: still 4
    with pytest.raises(DefinitionError) as err:
        fx.on_event(event_of(vf((sphere, sphere, sphere), name="B")), 4.0)
    assert fx.last_error == "VFIXTURE 'B': 5 fixtures in all, more than max_primitives 4"
    assert len(fx.active) == 4 and "max_primitives 4" in str(err.value)
    fx.on_event(event_of(vf((), name="B")), 5.0)  # an empty definition removes its source only
    assert sorted(fx.groups) == ["VFIXTURE:A"] and sorted(fx._compiled) == ["VFIXTURE:A"]
    assert len(fx.active) == 2
    # planes: two (the SAW's fixed number here), counted across sources
    fx = fixtures(max_primitives=10, max_planes=2)
    fx.on_event(event_of(vf((sphere, sphere), name="A")), 1.0)
    fx.on_event(event_of(plane("P1", (0.0, 0.0, -5.0))), 6.0)
    fx.on_event(event_of(plane("P2", (0.0, 0.0, -6.0))), 7.0)
    fx.on_event(event_of(plane("P2", (0.0, 0.0, -7.0))), 8.0)  # replaced: still two
    with pytest.raises(DefinitionError):
        fx.on_event(event_of(plane("P3", (0.0, 0.0, -8.0))), 9.0)
    assert fx.last_error == "TRANSFORM 'P3': 3 planes, more than max_planes 2"
    assert fx.stats()["fixture_kinds"] == {"accessible": 2, "forbidden": 0, "plane": 2, "guide": 0}


def test_the_work_of_one_tick_is_bounded_and_the_next_tick_starts_again() -> None:
    fx = fixtures(max_primitives=4)
    sphere = (0.0, 0.0, 0.0, 1.0)
    fx.on_event(event_of(vf((sphere,) * 3, name="A")), 1.0)
    fx.on_event(event_of(vf((sphere,), name="A")), 1.0)  # 4 compiled this tick: the limit itself
    with pytest.raises(DefinitionError):
        fx.on_event(event_of(vf((sphere,), name="A")), 1.0)
    assert fx.last_error == (
        "VFIXTURE 'A': busy: 4 fixtures compiled this tick already; send it again"
    )
    fx.on_event(event_of(vf((sphere,) * 4, name="A")), 1.001)  # the next tick: taken
    assert len(fx.active) == 4 and fx.applied == 3


def test_a_file_loaded_at_start_has_a_budget_of_its_own(tmp_path: Path) -> None:
    fx = fixtures(max_primitives=4)
    fx.on_event(event_of(vf(((0.0, 0.0, 0.0, 1.0),) * 2, name="A")), math.nan)
    path = tmp_path / "plan.mrk.json"
    path.write_text(
        json.dumps(
            {
                "markups": [
                    {
                        "type": "Fiducial",
                        "coordinateSystem": "RAS",
                        "controlPoints": [{"position": [0, 0, float(i)]} for i in range(2)],
                    }
                ]
            }
        )
    )
    assert fx.load_file(path, kind="forbidden", radius_mm=1.0) == 2
    assert sorted(fx.groups) == ["VFIXTURE:A", f"file:{path}"]
    fx.clear()
    assert fx.groups == {} and len(fx.active) == 0
    full = tmp_path / "full.mrk.json"
    full.write_text(
        json.dumps(
            {
                "markups": [
                    {
                        "type": "Fiducial",
                        "coordinateSystem": "RAS",
                        "controlPoints": [{"position": [0, 0, float(i)]} for i in range(4)],
                    }
                ]
            }
        )
    )
    fx.on_event(event_of(vf(((0.0, 0.0, 0.0, 1.0),), name="B")), 1.0)
    fx.clear()
    assert fx.load_file(full) == 4  # max_primitives, whatever the tick compiled before


def test_clear_removes_every_source_and_bumps_the_version() -> None:
    fx = fixtures()
    fx.on_event(event_of(vf(((0.0, 0.0, 0.0, 1.0),), name="A")), 1.0)
    v = fx.version
    fx.clear()
    assert fx.groups == {} and fx._compiled == {} and len(fx.active) == 0
    assert fx.version == v + 1


# ------------------------------------------------------------------ the mapping moves fixtures
def test_a_registration_moves_the_fixtures_at_once() -> None:
    fx = fixtures(scale=0.1)
    fx.on_event(event_of(points([pt("a", (1.0, 0.0, 0.0), radius=1.0)], kind="forbidden")), 1.0)
    assert centres(fx)[0] == pytest.approx((10.0, 0.0, 0.0))
    reg = np.eye(4)
    reg[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    fx.registration(reg.tolist(), 2.0)
    assert centres(fx)[0] == pytest.approx((0.0, -10.0, 0.0))
    assert fx._compiled_version == fx.mapping.version


def test_a_mapping_change_over_the_budget_is_compiled_by_the_next_step() -> None:
    fx = fixtures(scale=0.1, max_primitives=4)
    fx.on_event(event_of(vf(((1.0, 0.0, 0.0, 1.0),) * 2, name="A")), 1.0)
    fx.on_event(event_of(vf(((1.0, 0.0, 0.0, 1.0),) * 2, name="B")), 1.0)  # the tick's budget spent
    before = fx.active
    fx.set_linear([[0.2, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.2]], 1.0)
    assert fx.active is before  # stale until the next step
    assert centres(fx)[0] == pytest.approx((10.0, 0.0, 0.0))
    fx.step((0.0, 0.0, 0.0), 1.001)
    assert centres(fx) == [pytest.approx((5.0, 0.0, 0.0))] * 4
    assert fx._compiled_version == fx.mapping.version
    # that recompilation spent the new tick's budget
    with pytest.raises(DefinitionError, match="busy: 4 fixtures compiled this tick"):
        fx.on_event(event_of(vf(((1.0, 0.0, 0.0, 1.0),), name="A")), 1.001)
    # the same map again changes nothing; a new one within the budget applies at once
    v = fx.version
    fx.set_linear([[0.2, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.2]], 2.0)
    assert fx.version == v
    fx.set_linear([[0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 0.5]], 3.0)
    assert fx.version == v + 1
    assert centres(fx)[0] == pytest.approx((2.0, 0.0, 0.0))


def test_a_registration_over_the_budget_waits_for_the_next_step() -> None:
    fx = fixtures(scale=0.1, max_primitives=4)
    fx.on_event(event_of(vf(((1.0, 0.0, 0.0, 1.0),) * 3, name="A")), 1.0)
    reg = np.eye(4)
    reg[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    fx.registration(reg.tolist(), 1.0)  # 3 more to compile in a tick that compiled 3 of 4
    assert centres(fx)[0] == pytest.approx((10.0, 0.0, 0.0))  # stale
    fx.step((0.0, 0.0, 0.0), 1.001)
    assert centres(fx) == [pytest.approx((0.0, -10.0, 0.0))] * 3


def test_a_mapping_change_within_the_budget_spends_it() -> None:
    fx = fixtures(scale=0.1, max_primitives=4)
    fx.on_event(event_of(vf(((1.0, 0.0, 0.0, 1.0),), name="A")), 1.0)
    fx.on_event(event_of(vf(((1.0, 0.0, 0.0, 1.0),), name="B")), 1.0)
    fx.set_linear([[0.2, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.2]], 1.0)  # 2 + 2: at once
    assert centres(fx) == [pytest.approx((5.0, 0.0, 0.0))] * 2
    with pytest.raises(DefinitionError, match="busy: 4 fixtures compiled this tick"):
        fx.on_event(event_of(vf(((1.0, 0.0, 0.0, 1.0),), name="A")), 1.0)


def test_a_step_without_a_mapping_change_compiles_nothing() -> None:
    fx = fixtures(scale=0.1, max_primitives=4)
    fx.on_event(event_of(vf(((1.0, 0.0, 0.0, 1.0),) * 3, name="A")), 1.0)
    active = fx.active
    fx.step((0.0, 0.0, 0.0), 2.0)
    assert fx.active is active
    fx.on_event(
        event_of(vf(((1.0, 0.0, 0.0, 1.0),), name="B")), 2.0
    )  # the tick's whole budget left
    assert len(fx.active) == 4


def test_a_mapping_change_without_fixtures_is_noted_and_builds_no_set() -> None:
    fx = fixtures()
    active = fx.active
    fx.set_linear([[0.2, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.2]], 1.0)
    assert fx._compiled_version == fx.mapping.version and fx.active is active
    assert fx.version == 0


# ------------------------------------------------------------------ the force a tick
def test_the_force_of_a_damped_plane_uses_the_time_between_steps() -> None:
    """A plane 1 mm (patient) below z = 0, k = 2 N/mm, b = 0.5 N s/mm (master mm at 0.1:
    the tool 1 mm below it in the patient is 10 mm deep on the master)."""
    fx = fixtures(scale=0.1, max_force_n=1e6)
    # the tool's history is kept while there are no fixtures
    assert fx.step((0.0, 0.0, 0.0), 10.0) == (0.0, 0.0, 0.0)
    fx.on_event(event_of(plane("Floor", (0.0, 0.0, -1.0), stiffness="2", damping="0.5")), 10.0)
    f = fx.step((0.0, 0.0, -2.0), 10.002)
    # 10 mm deep: 20 N; the tool moved 20 master mm down in 2 ms: 10000 mm/s, 5000 N of damping
    assert f == pytest.approx((0.0, 0.0, 20.0 + 5000.0)) and fx.raw_force_n == f
    assert fx.tool_mm == (0.0, 0.0, -2.0) and all(type(v) is float for v in fx.tool_mm)
    f = fx.step([0, 0, -2], 10.004)  # still: only the spring
    assert f == pytest.approx((0.0, 0.0, 20.0))
    assert fx.tool_mm == (0.0, 0.0, -2.0) and all(type(v) is float for v in fx.tool_mm)


def test_the_first_step_has_no_velocity() -> None:
    fx = fixtures(scale=0.1, max_force_n=1e6)
    fx.on_event(event_of(plane("Floor", (0.0, 0.0, -1.0), stiffness="2", damping="0.5")), 10.0)
    assert fx.step((0.0, 0.0, -2.0), 10.0) == pytest.approx((0.0, 0.0, 20.0))


def test_the_displayed_force_and_its_peak() -> None:
    fx = fixtures()
    fx.displayed((3.0, 0.0, 4.0))
    assert fx.force_n == (3.0, 0.0, 4.0) and fx.peak_force_n == 5.0
    fx.displayed((0.0, 1.0, 0.0))
    assert fx.force_n == (0.0, 1.0, 0.0) and fx.peak_force_n == 5.0
    fx.displayed((0.0, -6.0, 0.0))
    assert fx.peak_force_n == 6.0


def test_stats_say_what_is_active_and_what_happened() -> None:
    fx = fixtures(scale=0.1, max_force_n=2.0)
    fx.on_event(
        event_of(points([pt("K", (0.0, 0.0, 0.0), radius=1.0)], name="Keep", kind="forbidden")), 1.0
    )
    fx.on_event(event_of(plane("Floor", (0.0, 0.0, -50.0))), 1.0)
    with pytest.raises(DefinitionError):
        fx.on_event(event_of(vf(((0.0, 0.0, 0.0, 0.0),), name="X")), 1.0)
    fx.step((2.0, 0.0, 0.0), 2.0)
    fx.step((0.5, 0.0, 0.0), 2.001)  # into the sphere: a contact, clamped to 2 N
    fx.displayed((1.0, 2.0, 2.0))
    assert fx.stats() == {
        "fixtures": 2,
        "fixture_kinds": {"accessible": 0, "forbidden": 1, "plane": 1, "guide": 0},
        "fixture_sources": ["POINT:Keep", "TRANSFORM:Floor"],
        "fixtures_applied": 2,
        "fixtures_refused": 1,
        "fixture_last_error": fx.last_error,
        "fixture_contacts": 1,
        "fixture_clamped": 1,
        "contact": ["K"],
        "peak_force_n": 3.0,
    }
    fx.displayed((0.123456789, 0.0, 0.0))
    fx.peak_force_n = 3.123456789
    assert fx.stats()["peak_force_n"] == 3.1235


# ------------------------------------------------------------------ what Slicer is shown
def _faces(model: Any) -> list[tuple[int, ...]]:
    return [tuple(c) for c in model.polygons]


def test_a_sphere_is_shown_as_a_closed_outward_mesh_on_its_surface() -> None:
    fx = fixtures(scale=0.1, rotation=R1.tolist())
    c, r = (10.0, -20.0, 30.0), 2.5
    fx.on_event(event_of(points([pt("S", c, radius=r)], kind="forbidden")), 1.0)
    value = fx.model("VirtualFixtures", timestamp=12.5)
    assert value.points_mm.shape == (62, 3)  # MeshOut's points are N x 3 before any packer
    model: Any = mesh_message(value, "VirtualFixtures")
    pts = model.points.astype(float)
    assert pts.shape == (62, 3)  # the poles and 5 rings of 12
    rel = pts - c
    assert np.allclose(np.linalg.norm(rel, axis=1), r, atol=1e-4)  # float32 on the wire
    # in the patient frame (Slicer's): the poles on the patient's z axis, rings at 30 degrees
    assert np.allclose(rel[0], (0, 0, r), atol=1e-4) and np.allclose(rel[-1], (0, 0, -r), atol=1e-4)
    heights = sorted({round(float(z) / r, 4) for z in rel[:, 2]})
    assert heights == sorted({round(math.cos(math.pi * i / 6), 4) for i in range(7)})
    ring = rel[1:13]
    assert np.allclose(
        np.degrees(np.arctan2(ring[:, 1], ring[:, 0])) % 360.0, np.arange(12) * 30.0, atol=1e-3
    )
    faces = _faces(model)
    assert len(faces) == 72 and sorted(len(f) for f in faces) == [3] * 24 + [4] * 48
    # closed: every edge in exactly two faces, once each way (consistently oriented)
    edges: dict[tuple[int, int], int] = {}
    for f in faces:
        for a, b in zip(f, f[1:] + f[:1], strict=True):
            edges[(a, b)] = edges.get((a, b), 0) + 1
    assert all(n == 1 and edges.get((b, a)) == 1 for (a, b), n in edges.items())
    assert len(edges) == 2 * (62 + 72 - 2)  # Euler: V - E + F = 2
    # every face turns outward
    for f in faces:
        p = pts[list(f)]
        nrm = np.cross(p[1] - p[0], p[2] - p[0])
        if np.linalg.norm(nrm) < 1e-9:
            nrm = np.cross(p[2] - p[0], p[3] - p[0])
        assert np.dot(nrm, p.mean(axis=0) - c) > 0.0
    (attr,) = model.attributes
    assert attr.type == CELL_SCALAR and attr.name == "kind"
    assert attr.data.ravel().tolist() == [KIND_CODE["forbidden"]] * 72
    assert model.device_name == "VirtualFixtures" and model.timestamp == 12.5
    assert model.header_version == 2
    assert dict(model.metadata) == {
        "MRMLNodeName": "VirtualFixtures",
        "fixtures": "1",
        "frame": "patient",
    }


@pytest.mark.parametrize("rotated", [False, True], ids=["aligned", "rotated"])
@pytest.mark.parametrize(
    "normal",
    [
        (0.0, 0.0, 1.0),
        (1.0, 0.0, 0.0),
        (0.0, -1.0, 0.0),
        (1.0, 1.0, 0.0),
        (1.0, 0.0, 1.0),
        (-3.0, 0.5, 0.0),
        (-3.0, 0.5, 1.0),
        (0.3, -0.4, 2.0),
    ],
    ids=["z", "x", "y", "xy", "xz", "near-x", "near-x-tilted", "oblique"],
)
def test_a_plane_is_shown_as_a_100_mm_square_facing_its_normal(normal: Any, rotated: bool) -> None:
    """Whatever the normal (along an axis, near x, where the square's first side is built
    from y instead of x, or oblique), in the patient frame as Slicer shows it."""
    fx = fixtures(scale=0.1, rotation=R1.tolist() if rotated else None)
    c = (5.0, 6.0, -7.0)
    fx.on_event(event_of(plane("Wall", c, normal)), 1.0)
    model: Any = mesh_message(fx.model("M"), "M")
    pts = model.points.astype(float)
    assert pts.shape == (4, 3) and _faces(model) == [(0, 1, 2, 3)] and model.lines == ()
    n = np.asarray(normal) / np.linalg.norm(normal)
    rel = pts - c
    assert np.allclose(rel @ n, 0.0, atol=1e-4)  # in the plane
    assert np.allclose(rel.mean(axis=0), 0.0, atol=1e-4)  # centred on its point
    sides = [np.linalg.norm(pts[(i + 1) % 4] - pts[i]) for i in range(4)]
    assert np.allclose(sides, 100.0, atol=1e-3)
    assert np.allclose(
        [np.linalg.norm(pts[2] - pts[0]), np.linalg.norm(pts[3] - pts[1])],
        100.0 * math.sqrt(2.0),
        atol=1e-3,
    )
    turn = np.cross(pts[1] - pts[0], pts[2] - pts[0])
    assert np.allclose(turn / np.linalg.norm(turn), n, atol=1e-5)  # facing the allowed side
    assert model.attributes[0].data.ravel().tolist() == [KIND_CODE["plane"]]


def test_the_square_of_a_normal_of_any_length() -> None:
    corners = np.array(_square((1.0, 2.0, 3.0), (0.0, 0.0, 5.0), 10.0))
    assert np.allclose(corners[:, 2], 3.0) and np.allclose(corners.mean(axis=0), (1.0, 2.0, 3.0))
    sides = [np.linalg.norm(corners[(i + 1) % 4] - corners[i]) for i in range(4)]
    assert np.allclose(sides, 20.0)
    turn = np.cross(corners[1] - corners[0], corners[2] - corners[0])
    assert np.allclose(turn / np.linalg.norm(turn), (0.0, 0.0, 1.0))


def test_guides_are_shown_as_lines_before_the_polygons() -> None:
    fx = fixtures(scale=0.1, rotation=R1.tolist())
    path = [(0.0, 0.0, 0.0), (10.0, 0.0, 0.0), (10.0, 5.0, 2.0)]
    fx.on_event(event_of(points([pt("s", (50.0, 0.0, 0.0), radius=1.0)], name="S")), 1.0)
    fx.on_event(
        event_of(points([pt(str(i), p) for i, p in enumerate(path)], name="G", kind="guide")), 1.0
    )
    model: Any = mesh_message(fx.model("M"), "M")
    assert model.lines == ((62, 63, 64),)
    assert np.allclose(model.points[62:].astype(float), path, atol=1e-4)
    kinds = model.attributes[0].data.ravel().tolist()
    assert kinds == [KIND_CODE["guide"]] + [KIND_CODE["accessible"]] * 72
    assert KIND_CODE == {"accessible": 1.0, "forbidden": 2.0, "plane": 3.0, "guide": 4.0}
    # nothing active: an empty model, no cell data
    empty: Any = mesh_message(fixtures().model("M"), "M")
    assert empty.points.shape == (0, 3) and empty.attributes == ()
    assert empty.metadata["fixtures"] == "0"


def test_the_proxy_is_the_tool_when_free_and_the_contact_point_in_contact() -> None:
    fx = fixtures(scale=0.1, rotation=R1.tolist())
    fx.on_event(
        event_of(
            points(
                [pt("K", (0.0, 0.0, 0.0), radius=1.0), pt("", (30.0, 0.0, 0.0), radius=1.0)],
                name="Keep",
                kind="forbidden",
            )
        ),
        1.0,
    )
    fx.step((2.0, -3.0, 4.0), 2.0)
    fx.displayed((0.5, -0.25, 0.125))
    free: Any = transform_message(fx.proxy("FixtureProxy", timestamp=3.5), "FixtureProxy")
    assert np.allclose(free.matrix[:3, 3], (2.0, -3.0, 4.0), atol=1e-5)
    assert free.device_name == "FixtureProxy" and free.timestamp == 3.5
    assert free.header_version == 2
    assert dict(free.metadata) == {
        "MRMLNodeName": "FixtureProxy",
        "contact": "none",
        "force_n": "0.5000,-0.2500,0.1250",
        "tool_mm": "2.000,-3.000,4.000",
        "frame": "patient",
    }
    fx.step((2.0, 0.0, 0.0), 2.0005)
    fx.step((0.5, 0.0, 0.0), 2.001)  # half-way into K, from +x
    fx.step((30.5, 0.0, 0.0), 2.002)  # and into the unnamed one (a jump)
    inside: Any = transform_message(fx.proxy("FixtureProxy"), "FixtureProxy")
    contacts = fx.active.contacts()
    names = [c.name or c.kind for c in contacts]
    assert inside.metadata["contact"] == ",".join(names)
    first = fx.mapping.master_to_patient(contacts[0].proxy)
    assert np.allclose(inside.matrix[:3, 3], first, atol=1e-4)
    assert inside.metadata["tool_mm"] == "30.500,0.000,0.000"


def test_every_contact_is_named_in_the_proxy() -> None:
    fx = fixtures(scale=0.1)
    fx.on_event(event_of(vf(((0.0, 0.0, 0.0, 1.0),), name="V", kind="forbidden")), 1.0)
    fx.on_event(
        event_of(points([pt("K", (0.0, 0.0, 0.0), radius=1.0)], name="P", kind="forbidden")), 1.0
    )
    fx.step((2.0, 0.0, 0.0), 2.0)
    fx.step((0.5, 0.0, 0.0), 2.001)
    msg: Any = transform_message(fx.proxy("X"), "X")
    assert msg.metadata["contact"] == "V-0,K"
    # the proxy: on the first sphere's surface, where the tool came in (+x), patient mm
    assert np.allclose(msg.matrix[:3, 3], (1.0, 0.0, 0.0), atol=1e-5)
