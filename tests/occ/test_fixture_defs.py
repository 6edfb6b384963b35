"""Fixture definitions (occ/haptics/fixture_defs.py) read alone: what 3D Slicer and scripts send
(VFIXTURE, POINT, TRANSFORM, POLYDATA, ``.mrk.json`` files) becomes exactly these definitions,
a malformed one is refused with a message that names what is wrong, and the patient-to-master
mapping is the linear map it documents, entry by entry (issue 29: the mutation run of
occ/haptics/fixture_defs.py; the master that uses them is tests/occ/test_haptic_master.py)."""

from __future__ import annotations

import json
import locale
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import igtl
from igtl.messages.point import PointElement
from occ.haptics.fixture_defs import (
    Defaults,
    Definition,
    DefinitionError,
    PatientMapping,
    compile_definitions,
    from_event,
    from_markups_file,
    parse_linear,
    to_master,
)
from occ.haptics.fixtures import AccessibleSphere, ForbiddenPlane, ForbiddenSphere, Guide
from occ.net.decoders import event_of
from occ.samples import PoseSample

D = Defaults()


def vf(spheres: Any, hardness: float = 1.0, name: str = "VF", **meta: str) -> igtl.Message:
    return igtl.VirtualFixtureMessage(
        hardness=hardness, spheres=spheres, device_name=name, header_version=2, metadata=meta
    )


def pt(name: str, xyz: Any, alpha: int = 255, radius: float = 0.0) -> PointElement:
    return PointElement(name=name, rgba=(255, 0, 0, alpha), position=xyz, radius=radius)


def points(pts: Any, name: str = "P", **meta: str) -> igtl.Message:
    return igtl.PointMessage(points=tuple(pts), device_name=name, header_version=2, metadata=meta)


def refused(msg: igtl.Message, defaults: Defaults = D) -> str:
    with pytest.raises(DefinitionError) as err:
        from_event(event_of(msg), defaults)
    return str(err.value)


# ------------------------------------------------------------------ VFIXTURE
def test_defaults_are_the_documented_ones() -> None:
    assert Defaults() == Defaults("accessible", "accessible", 5.0, 1.0, 0.0)


def test_vfixture_spheres_become_definitions_named_by_index() -> None:
    got = from_event(
        event_of(vf(((1.0, 2.0, 3.0, 4.0), (-1.0, -2.0, -3.0, 0.5)), hardness=2.5, damping="0.25")),
        D,
    )
    assert got == [
        Definition("accessible", ((1.0, 2.0, 3.0),), 4.0, None, 2.5, 0.25, "VF-0", "patient"),
        Definition("accessible", ((-1.0, -2.0, -3.0),), 0.5, None, 2.5, 0.25, "VF-1", "patient"),
    ]
    # the kind from metadata (any case, spaces around) or from the controller's defaults
    (f,) = from_event(event_of(vf(((0.0, 0.0, 0.0, 1.0),), kind=" Forbidden ")), D)  # type: ignore[misc]
    assert f.kind == "forbidden" and f.damping == 0.0
    (g,) = from_event(event_of(vf(((0.0, 0.0, 0.0, 1.0),))), Defaults(vfixture_kind="forbidden"))  # type: ignore[misc]
    assert g.kind == "forbidden"
    (h,) = from_event(event_of(vf(((0.0, 0.0, 0.0, 1.0),))), Defaults(damping=0.5))  # type: ignore[misc]
    assert h.damping == 0.5
    # a hardness of 0 is a sphere that pushes nothing: allowed; no spheres: none
    (z,) = from_event(event_of(vf(((0.0, 0.0, 0.0, 1.0),), hardness=0.0)), D)  # type: ignore[misc]
    assert z.stiffness == 0.0
    assert from_event(event_of(vf(())), D) == []
    # a v1 sender (no metadata) gets the defaults
    v1 = igtl.VirtualFixtureMessage(
        hardness=1.0, spheres=((0.0, 0.0, 0.0, 1.0),), device_name="Old"
    )
    assert from_event(event_of(v1), D) == [
        Definition("accessible", ((0.0, 0.0, 0.0),), 1.0, None, 1.0, 0.0, "Old-0", "patient")
    ]


@pytest.mark.parametrize(
    ("msg", "text"),
    [
        (
            vf(((0.0, 0.0, 0.0, 1.0),), kind="sticky"),
            "metadata kind='sticky': expected one of accessible, forbidden",
        ),
        (
            vf(((0.0, 0.0, 0.0, 1.0),), kind="guide"),
            "metadata kind='guide': expected one of accessible, forbidden",
        ),
        (
            igtl.VirtualFixtureMessage(
                hardness=1.0, spheres=((0.0, 0.0, 0.0, 1.0),), version=2, device_name="VF"
            ),
            "VFIXTURE version 2 is not known (1 is)",
        ),
        (vf(((0.0, 0.0, 0.0, 1.0),), hardness=-0.5), "VFIXTURE hardness -0.5 must be >= 0"),
        (vf(((0.0, 0.0, 0.0, 1.0),), hardness=math.nan), "VFIXTURE hardness nan must be >= 0"),
        (vf(((0.0, 0.0, 0.0, 1.0),), hardness=math.inf), "VFIXTURE hardness inf must be >= 0"),
        (
            vf(((0.0, 0.0, 0.0, 1.0), (1.0, 2.0, 3.0, 0.0))),
            "VFIXTURE sphere 1 (1.0, 2.0, 3.0, 0.0): needs finite numbers and a radius > 0",
        ),
        (
            vf(((0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 1.0), (math.nan, 0.0, 0.0, 1.0))),
            "VFIXTURE sphere 2 (nan, 0.0, 0.0, 1.0): needs finite numbers and a radius > 0",
        ),
        (
            vf(((0.0, 0.0, 0.0, -1.0),)),
            "VFIXTURE sphere 0 (0.0, 0.0, 0.0, -1.0): needs finite numbers and a radius > 0",
        ),
        (vf(((0.0, 0.0, 0.0, 1.0),), damping="soft"), "metadata damping='soft' is not a number"),
        (
            vf(((0.0, 0.0, 0.0, 1.0),), damping="-1"),
            "metadata damping='-1' must be a finite number >= 0",
        ),
        (
            vf(((0.0, 0.0, 0.0, 1.0),), damping="inf"),
            "metadata damping='inf' must be a finite number >= 0",
        ),
        (
            vf(((0.0, 0.0, 0.0, 1.0),), damping="nan"),
            "metadata damping='nan' must be a finite number >= 0",
        ),
        (
            vf(((0.0, 0.0, 0.0, 1.0),), frame="master"),
            "metadata frame='master': fixtures are in the patient frame (3D Slicer's RAS, the "
            "frame of the slave's Tip); send them there, without frame or with frame=patient",
        ),
    ],
    ids=[
        "kind",
        "guide-kind",
        "version",
        "hardness",
        "nan-hardness",
        "inf-hardness",
        "zero-radius",
        "nan-centre",
        "negative-radius",
        "damping-text",
        "damping-negative",
        "damping-inf",
        "damping-nan",
        "frame",
    ],
)
def test_a_malformed_vfixture_is_refused_with_what_is_wrong(msg: igtl.Message, text: str) -> None:
    assert refused(msg) == text


def test_the_frame_may_be_named_patient_in_any_case() -> None:
    for frame in ("patient", " Patient "):
        (d,) = from_event(event_of(vf(((0.0, 0.0, 0.0, 1.0),), frame=frame)), D)  # type: ignore[misc]
        assert d.frame == "patient"
    assert "frame='world'" in refused(points([pt("a", (0, 0, 0))], frame="world"))


# ------------------------------------------------------------------ POINT
def test_points_become_spheres_with_their_radius_the_metadata_or_the_default() -> None:
    msg = points(
        [
            pt("a", (1.0, 2.0, 3.0), radius=1.5),
            pt("hidden", (9, 9, 9), alpha=0),
            pt("", (4.0, 5.0, 6.0), alpha=1),
        ],
        name="Targets",
        kind="Forbidden",
        stiffness="0.5",
        damping="0.125",
        radius="2.25",
    )
    assert from_event(event_of(msg), D) == [
        Definition("forbidden", ((1.0, 2.0, 3.0),), 1.5, None, 0.5, 0.125, "a", "patient"),
        # unnamed: the list's name and the point's place among the visible ones
        Definition("forbidden", ((4.0, 5.0, 6.0),), 2.25, None, 0.5, 0.125, "Targets-1", "patient"),
    ]
    # no metadata: the controller's defaults
    mine = Defaults(point_kind="forbidden", point_radius_mm=3.0, stiffness=0.75, damping=0.5)
    assert from_event(event_of(points([pt("b", (0.0, 0.0, 0.0))])), mine) == [
        Definition("forbidden", ((0.0, 0.0, 0.0),), 3.0, None, 0.75, 0.5, "b", "patient")
    ]
    assert from_event(event_of(points([pt("b", (0.0, 0.0, 0.0))])), D)[0].radius == 5.0  # type: ignore[index]


def test_points_as_a_guide_in_their_order() -> None:
    msg = points(
        [
            pt("a", (0.0, 0.0, 0.0)),
            pt("skip", (5, 5, 5), alpha=0),
            pt("b", (0.0, 0.0, 10.0)),
            pt("c", (10.0, 0.0, 10.0)),
        ],
        name="Path",
        kind="guide",
        stiffness="0.5",
        damping="0.25",
    )
    assert from_event(event_of(msg), D) == [
        Definition(
            "guide",
            ((0.0, 0.0, 0.0), (0.0, 0.0, 10.0), (10.0, 0.0, 10.0)),
            0.0,
            None,
            0.5,
            0.25,
            "Path",
            "patient",
        )
    ]
    two = points([pt("a", (0.0, 0.0, 0.0)), pt("b", (0.0, 0.0, 1.0))], kind="guide")
    assert len(from_event(event_of(two), D)[0].points) == 2  # type: ignore[index]
    # every point hidden: no guide (the node is empty), not an error
    assert from_event(event_of(points([pt("a", (0, 0, 0), alpha=0)], kind="guide")), D) == []


@pytest.mark.parametrize(
    ("msg", "text"),
    [
        (
            points([pt("a", (0.0, 0.0, 0.0))], kind="guide"),
            "a guide needs at least two visible points",
        ),
        (
            points([pt("a", (0.0, 0.0, 0.0)), pt("b", (0.0, 0.0, 0.0), alpha=0)], kind="guide"),
            "a guide needs at least two visible points",
        ),
        (
            points([pt("a", (0.0, 0.0, 0.0)), pt("b", (0.0, math.inf, 0.0))], kind="guide"),
            "point 'b': not a finite number (inf)",
        ),
        (points([pt("a", (0.0, math.nan, 0.0))]), "point 'a': not a finite number (nan)"),
        (points([pt("a", (0.0, 0.0, 0.0))], radius="0"), "point 'a': radius 0.0 must be > 0"),
        (
            points([pt("a", (0.0, 0.0, 0.0))], kind="plane"),
            "metadata kind='plane': expected one of accessible, forbidden, guide",
        ),
        (
            points([pt("a", (0.0, 0.0, 0.0))], stiffness="stiff"),
            "metadata stiffness='stiff' is not a number",
        ),
        (points([pt("a", (0.0, 0.0, 0.0))], damping="x"), "metadata damping='x' is not a number"),
        (
            points([pt("a", (0.0, 0.0, 0.0))], radius="-2"),
            "metadata radius='-2' must be a finite number >= 0",
        ),
    ],
    ids=[
        "guide-one",
        "guide-one-visible",
        "guide-inf",
        "nan",
        "zero-radius",
        "kind",
        "stiffness",
        "damping",
        "radius",
    ],
)
def test_a_malformed_point_list_is_refused_with_what_is_wrong(msg: igtl.Message, text: str) -> None:
    assert refused(msg) == text


def test_a_point_with_no_radius_anywhere_is_refused() -> None:
    assert refused(points([pt("a", (0.0, 0.0, 0.0))]), Defaults(point_radius_mm=0.0)) == (
        "point 'a': radius 0.0 must be > 0"
    )


# ------------------------------------------------------------------ TRANSFORM: a plane
def test_a_plane_is_the_translation_and_the_rotations_third_column() -> None:
    # twelve different numbers in wire order (the 3x3 column by column, the translation)
    e = tuple(float(v) for v in range(1, 13))
    msg = igtl.TransformMessage(
        elements=e,
        device_name="Wall",
        header_version=2,
        metadata={"kind": " Plane ", "stiffness": "3", "damping": "0.5"},
    )
    assert from_event(event_of(msg), D) == [
        Definition(
            "plane", ((10.0, 11.0, 12.0),), 0.0, (7.0, 8.0, 9.0), 3.0, 0.5, "Wall", "patient"
        )
    ]
    plain = igtl.TransformMessage(
        elements=e, device_name="Wall", header_version=2, metadata={"kind": "plane"}
    )
    (d,) = from_event(event_of(plain), Defaults(stiffness=0.25, damping=0.125))  # type: ignore[misc]
    assert (d.stiffness, d.damping) == (0.25, 0.125)
    # a TRANSFORM without kind=plane is no fixture (a tracker, the slave's base, ...)
    assert from_event(event_of(igtl.TransformMessage(elements=e, device_name="Base")), D) is None
    other = igtl.TransformMessage(
        elements=e, device_name="T", header_version=2, metadata={"kind": "guide"}
    )
    assert from_event(event_of(other), D) is None
    # a tiny but non-zero z axis is a direction
    tiny = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 2e-9, 0.0, 0.0, 0.0)
    small = igtl.TransformMessage(
        elements=tiny, device_name="T", header_version=2, metadata={"kind": "plane"}
    )
    assert from_event(event_of(small), D)[0].normal == (0.0, 0.0, pytest.approx(2e-9))  # type: ignore[index]


def test_a_plane_z_axis_of_exactly_1e_9_mm_is_a_direction_and_a_shorter_one_is_zero() -> None:
    """The zero test is ``< 1e-9``: a float64 matrix (a sample built in the process, not the
    float32 wire) puts the boundary exactly there."""

    def sample(z: float) -> PoseSample:
        m = np.eye(4)
        m[:3, 2] = (0.0, 0.0, z)
        return PoseSample("i", None, "Wall", (0.0, 0.0, 0.0), kind="TRANSFORM",
                          meta={"kind": "plane"}, matrix=m)  # fmt: skip

    (d,) = from_event(sample(1e-9), D)  # type: ignore[misc]
    assert d.normal == (0.0, 0.0, 1e-9)
    # compiled for the master, its direction is made unit
    (p,) = compile_definitions([d], PatientMapping(0.1))
    assert isinstance(p, ForbiddenPlane) and tuple(p.normal) == (0.0, 0.0, 1.0)
    with pytest.raises(DefinitionError, match="the rotation's z axis is zero"):
        from_event(sample(math.nextafter(1e-9, 0.0)), D)


@pytest.mark.parametrize(
    ("elements", "meta", "text"),
    [
        (
            (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 2.0, 3.0),
            {},
            "plane 'Wall': the rotation's z axis is zero",
        ),
        (
            (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, math.nan, 2.0, 3.0),
            {},
            "plane 'Wall': not a finite number (nan)",
        ),
        (
            (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 2.0, 3.0),
            {"stiffness": "-1"},
            "metadata stiffness='-1' must be a finite number >= 0",
        ),
        ((1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 2.0, 3.0), {"frame": "master"}, None),
    ],
    ids=["zero-normal", "nan", "stiffness", "frame"],
)
def test_a_malformed_plane_is_refused(
    elements: Any, meta: dict[str, str], text: str | None
) -> None:
    msg = igtl.TransformMessage(
        elements=elements, device_name="Wall", header_version=2, metadata={"kind": "plane", **meta}
    )
    got = refused(msg)
    assert got == text if text else got.startswith("metadata frame='master'")


# ------------------------------------------------------------------ POLYDATA
def poly(kind: str | None, pts: Any, lines: Any = (), polygons: Any = (), **meta: str) -> Any:
    m = dict(meta)
    if kind is not None:
        m["kind"] = kind
    return igtl.PolyDataMessage(
        points=np.array(pts, dtype=float).reshape(-1, 3),
        lines=lines,
        polygons=polygons,
        device_name="Model",
        header_version=2,
        metadata=m,
    )


PTS = [(0.5, -1.0, 2.0), (2.5, 1.5, -0.25), (-1.5, 3.0, 0.75), (1.0, 1.25, 4.0)]


def test_polydata_lines_are_guides_and_polygons_planes() -> None:
    got = from_event(event_of(poly(" Guide ", PTS, lines=((0, 1), (3, 2, 1)), stiffness="0.5")), D)
    assert got == [
        Definition("guide", (PTS[0], PTS[1]), 0.0, None, 0.5, 0.0, "Model-0", "patient"),
        Definition("guide", (PTS[3], PTS[2], PTS[1]), 0.0, None, 0.5, 0.0, "Model-1", "patient"),
    ]
    # a polygon's plane: its first point, the normal (p1 - p0) x (p2 - p0) of its first three
    got = from_event(
        event_of(poly("plane", PTS, polygons=((1, 2, 3), (0, 1, 2, 3)), damping="0.5")), D
    )

    def normal(a: int, b: int, c: int) -> tuple[float, float, float]:
        x, y, z = np.cross(np.subtract(PTS[b], PTS[a]), np.subtract(PTS[c], PTS[a])).tolist()
        return (x, y, z)

    assert got == [
        Definition("plane", (PTS[1],), 0.0, normal(1, 2, 3), 1.0, 0.5, "Model-0", "patient"),
        Definition("plane", (PTS[0],), 0.0, normal(0, 1, 2), 1.0, 0.5, "Model-1", "patient"),
    ]
    # every coordinate different and non-zero: each term of the cross product counts
    assert all(abs(c) > 0.1 for c in normal(1, 2, 3) + normal(0, 1, 2))
    # the lines of a plane model and the polygons of a guide model are not read
    assert from_event(event_of(poly("plane", PTS, lines=((0, 1),))), D) == []
    assert from_event(event_of(poly("guide", PTS, polygons=((0, 1, 2),))), D) == []
    # without kind guide or plane a model is no fixture (Slicer sends models for display)
    assert from_event(event_of(poly(None, PTS, lines=((0, 1),))), D) is None
    assert from_event(event_of(poly("sphere", PTS, lines=((0, 1),))), D) is None
    # no fixture message at all
    assert from_event(event_of(igtl.StringMessage(string="x", device_name="S")), D) is None


@pytest.mark.parametrize(
    ("msg", "text"),
    [
        (poly("guide", PTS, lines=((0, 4),)), "polydata 'Model': cell 0 refers to a missing point"),
        (
            poly("plane", PTS, polygons=((0, 1, 2), (0, 1, 7))),
            "polydata 'Model': cell 1 refers to a missing point",
        ),
        (
            poly("guide", PTS, lines=((0, 1), (2,))),
            "polydata 'Model': line 1 has fewer than 2 points",
        ),
        (
            poly("plane", PTS, polygons=((0, 1),)),
            "polydata 'Model': polygon 0 has fewer than 3 points",
        ),
        (
            poly("guide", [(0.0, 0.0, 0.0), (math.inf, 0.0, 0.0)], lines=((0, 1),)),
            "polydata 'Model': not a finite number (inf)",
        ),
        (poly("guide", PTS, lines=((0, 1),), damping="?"), "metadata damping='?' is not a number"),
        (poly("plane", PTS, polygons=((0, 1, 2),), frame="master"), "frame"),
    ],
    ids=[
        "missing-point",
        "missing-in-polygon",
        "short-line",
        "short-polygon",
        "inf",
        "damping",
        "frame",
    ],
)
def test_a_malformed_model_is_refused(msg: igtl.Message, text: str) -> None:
    got = refused(msg)
    assert got == text if text != "frame" else got.startswith("metadata frame='master'")


# ------------------------------------------------------------------ .mrk.json files
def write(tmp_path: Path, markups: Any, name: str = "plan.mrk.json") -> Path:
    path = tmp_path / name
    path.write_text(markups if isinstance(markups, str) else json.dumps({"markups": markups}))
    return path


def cps(*positions: Any, **extra: Any) -> list[dict[str, Any]]:
    return [{"position": list(p), **extra} for p in positions]


def test_a_markups_file_default_is_accessible_spheres_of_5_mm(tmp_path: Path) -> None:
    path = write(tmp_path, [{"type": "Fiducial", "controlPoints": cps((1, 2, 3))}])
    # no coordinate system: LPS (Slicer's default for files); no name: markups + its index
    assert from_markups_file(path) == [
        Definition("accessible", ((-1.0, -2.0, 3.0),), 5.0, None, 1.0, 0.0, "markups0-0", "patient")
    ]


def test_a_markups_file_in_ras_and_um_with_every_type(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        [
            {
                "type": "Fiducial",
                "name": "T",
                "coordinateSystem": "ras",
                "coordinateUnits": ["um"],
                "controlPoints": [
                    {"label": "t1", "position": [1000, 2000, 3000]},
                    {"position": [4000, 5000, 6000]},
                    {"label": "off", "position": [0, 0, 0], "positionStatus": "undefined"},
                    {"label": "t4", "position": [7000, 8000, 9000]},
                ],
            },
            {
                "type": "Curve",
                "name": "C",
                "coordinateUnits": "mm",
                "controlPoints": cps((1, 1, 1), (2, 2, 2), (3, 3, 3)),
            },
            {
                "type": "ClosedCurve",
                "name": "Loop",
                "coordinateSystem": "RAS",
                "controlPoints": cps((0, 0, 0), (1, 0, 0), (0, 1, 0)),
            },
            {"type": "Line", "name": "Short", "controlPoints": cps((0, 0, 0))},
            {
                "type": "Plane",
                "name": "P",
                "coordinateSystem": "RAS",
                "coordinateUnits": "um",
                "normal": [0, 0, 2],
                "controlPoints": cps((1000, 0, 0)),
            },
        ],
    )
    got = from_markups_file(path, kind="forbidden", radius_mm=2.0, stiffness=0.5, damping=0.25)
    assert got == [
        Definition("forbidden", ((1.0, 2.0, 3.0),), 2.0, None, 0.5, 0.25, "t1", "patient"),
        Definition("forbidden", ((4.0, 5.0, 6.0),), 2.0, None, 0.5, 0.25, "T-1", "patient"),
        Definition("forbidden", ((7.0, 8.0, 9.0),), 2.0, None, 0.5, 0.25, "t4", "patient"),
        Definition(
            "guide",
            ((-1.0, -1.0, 1.0), (-2.0, -2.0, 2.0), (-3.0, -3.0, 3.0)),
            0.0,
            None,
            0.5,
            0.25,
            "C",
            "patient",
        ),
        Definition(
            "guide",
            ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 0.0)),
            0.0,
            None,
            0.5,
            0.25,
            "Loop",
            "patient",
        ),
        # a line of one defined point is no guide: left out
        # a plane's normal is a direction: not scaled by the units
        Definition("plane", ((1.0, 0.0, 0.0),), 0.0, (0.0, 0.0, 2.0), 0.5, 0.25, "P", "patient"),
    ]


def test_a_markups_fiducial_list_as_a_guide(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        [
            {
                "type": "Fiducial",
                "name": "G",
                "coordinateSystem": "RAS",
                "controlPoints": cps((0, 0, 0), (0, 0, 5)),
            },
            {"type": "Fiducial", "name": "One", "controlPoints": cps((0, 0, 0))},
            {
                "type": "Fiducial",
                "name": "After",
                "coordinateSystem": "RAS",
                "controlPoints": cps((1, 0, 0), (2, 0, 0)) + cps((3, 0, 0), visibility=False),
            },
        ],
    )
    assert from_markups_file(path, kind="guide", stiffness=2.0) == [
        Definition(
            "guide", ((0.0, 0.0, 0.0), (0.0, 0.0, 5.0)), 0.0, None, 2.0, 0.0, "G", "patient"
        ),
        # one point is no guide; the next markups are still read
        Definition(
            "guide", ((1.0, 0.0, 0.0), (2.0, 0.0, 0.0)), 0.0, None, 2.0, 0.0, "After", "patient"
        ),
    ]


def test_a_markups_plane_takes_its_center_else_its_first_point(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        [
            {
                "type": "Plane",
                "name": "A",
                "center": [1, 2, 3],
                "normal": [0, 0, 1],
                "controlPoints": cps((9, 9, 9)),
            },
            {
                "type": "Plane",
                "name": "B",
                "normal": [1, 0, 0],
                "controlPoints": cps((4, 5, 6), (7, 8, 9)),
            },
        ],
    )
    assert from_markups_file(path) == [
        Definition("plane", ((-1.0, -2.0, 3.0),), 0.0, (-0.0, -0.0, 1.0), 1.0, 0.0, "A", "patient"),
        Definition("plane", ((-4.0, -5.0, 6.0),), 0.0, (-1.0, -0.0, 0.0), 1.0, 0.0, "B", "patient"),
    ]


@pytest.mark.parametrize(
    ("markups", "text"),
    [
        (
            "{not json",
            "cannot read a markups file: Expecting property name enclosed in double "
            "quotes: line 1 column 2 (char 1)",
        ),
        ("[1, 2]", "no 'markups' list (is it a Slicer .mrk.json file?)"),
        ('{"markups": {}}', "no 'markups' list (is it a Slicer .mrk.json file?)"),
        ([{"type": "Fiducial"}, 3], "markups[1] is not an object"),
        ([{"type": "Fiducial", "coordinateSystem": "XYZ"}], "markups[0]: coordinate system 'XYZ'"),
        ([{"type": "Fiducial", "coordinateUnits": "cm"}], "markups[0]: coordinate units 'cm'"),
        (
            [{"type": "Fiducial", "coordinateUnits": ["cm", "um"]}],
            "markups[0]: coordinate units 'cm'",
        ),
        (
            [{"type": "Fiducial", "name": "F", "controlPoints": [{"label": "x"}]}],
            "F: control point 0 has no position",
        ),
        (
            [{"type": "Fiducial", "name": "F", "controlPoints": cps((0, 0, 0)) + [[1, 2, 3]]}],
            "F: control point 1 has no position",
        ),
        (
            [{"type": "Fiducial", "name": "F", "controlPoints": cps((0, 0, 0), (1, 2))}],
            "F point 1: expected [x, y, z]",
        ),
        (
            [{"type": "Fiducial", "name": "F", "controlPoints": [{"position": "1,2,3"}]}],
            "F point 0: expected [x, y, z]",
        ),
        (
            [{"type": "Fiducial", "name": "F", "controlPoints": cps((0, 0, "NaN"))}],
            "F point 0: not a finite number (nan)",
        ),
        (
            [{"type": "Plane", "name": "W", "controlPoints": cps((0, 0, 0))}],
            "plane 'W' needs a center (or a control point) and a normal",
        ),
        (
            [{"type": "Plane", "name": "W", "normal": [0, 0, 1], "controlPoints": []}],
            "plane 'W' needs a center (or a control point) and a normal",
        ),
        (
            [{"type": "Plane", "name": "W", "center": [0, 0], "normal": [0, 0, 1]}],
            "W center: expected [x, y, z]",
        ),
        (
            [{"type": "Plane", "name": "W", "center": [0, 0, 0], "normal": [0, 1]}],
            "W normal: expected [x, y, z]",
        ),
        (
            [{"type": "Angle", "name": "A"}],
            "markups type 'Angle' is not a fixture (Fiducial, Line, Curve, ClosedCurve, Plane are)",
        ),
        (
            [{"name": "A"}],
            "markups type '' is not a fixture (Fiducial, Line, Curve, ClosedCurve, Plane are)",
        ),
    ],
    ids=[
        "json",
        "list",
        "dict",
        "entry",
        "system",
        "units",
        "units-list",
        "no-position",
        "not-object",
        "two-numbers",
        "text",
        "nan",
        "plane-no-normal",
        "plane-no-point",
        "plane-center",
        "plane-normal",
        "angle",
        "no-type",
    ],
)
def test_a_malformed_markups_file_is_refused_with_its_path_and_what_is_wrong(
    tmp_path: Path, markups: Any, text: str
) -> None:
    path = write(tmp_path, markups)
    with pytest.raises(DefinitionError) as err:
        from_markups_file(path)
    msg = str(err.value)
    assert msg.startswith(f"{path}: ") and msg.endswith(text), msg


def test_a_markups_file_is_read_as_utf_8_whatever_the_locale(tmp_path: Path) -> None:
    """Slicer writes its files in UTF-8; a daemon started under another locale (``C`` here,
    ASCII) still reads a non-ASCII label."""
    path = tmp_path / "plan.mrk.json"
    doc = {
        "markups": [
            {
                "type": "Fiducial",
                "coordinateSystem": "RAS",
                "controlPoints": [{"label": "Läsion", "position": [1, 2, 3]}],
            }
        ]
    }
    path.write_bytes(json.dumps(doc, ensure_ascii=False).encode("utf-8"))
    old = locale.setlocale(locale.LC_CTYPE)
    try:
        locale.setlocale(locale.LC_CTYPE, "C")
        (d,) = from_markups_file(path)
    finally:
        locale.setlocale(locale.LC_CTYPE, old)
    assert d.name == "Läsion" and d.points == ((1.0, 2.0, 3.0),)


def test_a_missing_markups_file_is_refused(tmp_path: Path) -> None:
    with pytest.raises(DefinitionError, match=r"nope\.mrk\.json: cannot read a markups file: "):
        from_markups_file(tmp_path / "nope.mrk.json")


# ------------------------------------------------------------------ the slave's map
def rotation(axis: Any, angle: float) -> np.ndarray:
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


R1 = rotation((1.0, 2.0, 3.0), 0.7)  # every entry different
R2 = rotation((-2.0, 1.0, 0.5), 1.1)


def test_parse_linear_reads_nine_numbers_row_by_row() -> None:
    m = 0.1 * R1
    text = ", ".join(repr(v) for v in m.ravel().tolist())
    got = parse_linear(text)
    assert np.array_equal(np.array(got), m)
    assert parse_linear("2 0 0  0 2 0  0 0 2") == (
        (2.0, 0.0, 0.0),
        (0.0, 2.0, 0.0),
        (0.0, 0.0, 2.0),
    )


@pytest.mark.parametrize(
    ("text", "error"),
    [
        ("1 0 0 0 1 0 0 0", "map '1 0 0 0 1 0 0 0': expected 9 numbers, got 8"),
        ("1 0 0 0 1 0 0 0 1 0", "map '1 0 0 0 1 0 0 0 1 0': expected 9 numbers, got 10"),
        ("1 0 0 0 1 0 0 0 x", "map '1 0 0 0 1 0 0 0 x': not numbers"),
        ("1 0 0 0 1 0 0 0 nan", "map: not a finite number (nan)"),
        ("1 0 0 0 1 0 0 0 -1", "map: not a scaled rotation (determinant <= 0)"),
        ("0 0 0 0 0 0 0 0 0", "map: not a scaled rotation (determinant <= 0)"),
        ("1 0 0 0 2 0 0 0 1", "map: not a scaled rotation (columns not orthogonal)"),
        ("1 0.1 0 0 1 0 0 0 1", "map: not a scaled rotation (columns not orthogonal)"),
        ("1 0 0 0.1 1 0 0 0 1", "map: not a scaled rotation (columns not orthogonal)"),
        ("1 0 0 0 1 0 0.1 0 1", "map: not a scaled rotation (columns not orthogonal)"),
        ("1 0 0 0 1 0.1 0 0 1", "map: not a scaled rotation (columns not orthogonal)"),
    ],
)
def test_a_map_that_is_no_scaled_rotation_is_refused(text: str, error: str) -> None:
    with pytest.raises(DefinitionError) as err:
        parse_linear(text)
    assert str(err.value) == error


def test_the_map_tolerates_a_float32_rotation_but_not_a_shear() -> None:
    # what a sender's float32 rounding gives: accepted
    m = (0.1 * R1).astype(np.float32).astype(float)
    parse_linear(" ".join(repr(v) for v in m.ravel().tolist()))
    # 1e-3 of s^2 is the tolerance on the columns' dot products, relative to the scale
    # at the tolerance exactly (s = 1): still a rotation
    parse_linear("1 0.001 0  0 1 0  0 0 1")
    for s in (0.1, 10.0):
        ok = np.array([[1.0, 0.0009, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) * s
        parse_linear(" ".join(repr(v) for v in ok.ravel().tolist()))
        bad = np.array([[1.0, 0.0011, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) * s
        with pytest.raises(DefinitionError, match="columns not orthogonal"):
            parse_linear(" ".join(repr(v) for v in bad.ravel().tolist()))


def test_the_patient_mapping_is_the_linear_map_entry_by_entry() -> None:
    """``L = G s R`` (registration's rotation, scale, master-to-slave rotation); fixtures and
    the tool by ``L^-1``, normals by ``L^T`` made unit, forces by ``Q^T`` (``Q = L/s``), back
    to the patient by ``L`` and ``L^-T`` (normals unit)."""
    g = np.eye(4)
    g[:3, :3] = R2
    g[:3, 3] = (100.0, -20.0, 5.0)  # a translation: never enters
    m = PatientMapping(0.25, rotation=R1.tolist(), registration=g.tolist())
    lin = R2 @ (0.25 * R1)
    assert m.source == "params" and m.factor == pytest.approx(0.25, abs=1e-12)
    assert np.allclose(m.linear, lin, atol=1e-12)
    p, n = (3.0, -7.0, 11.0), (0.2, -0.5, 0.9)
    inv = np.linalg.inv(lin)
    assert np.allclose(m.point(p), inv @ p, atol=1e-9)
    t = lin.T @ n
    assert np.allclose(m.direction(n), t / np.linalg.norm(t), atol=1e-12)
    assert np.allclose(m.force(p), (lin / 0.25).T @ p, atol=1e-9)
    assert m.length(2.0) == pytest.approx(8.0)
    assert np.allclose(m.master_to_patient(p), lin @ p, atol=1e-12)
    b = inv.T @ n  # the inverse of direction(): normals go by the inverse transpose
    assert np.allclose(m.patient_direction(n), b / np.linalg.norm(b), atol=1e-12)
    # a zero direction stays zero (no division by zero)
    assert m.direction((0.0, 0.0, 0.0)) == (0.0, 0.0, 0.0)
    assert m.patient_direction((0.0, 0.0, 0.0)) == (0.0, 0.0, 0.0)


def test_the_mapping_changes_and_the_slaves_own_map_wins() -> None:
    m = PatientMapping(0.5)
    assert m.linear == [[0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 0.5]] and m.version == 1
    m.set_rotation(R1.tolist())
    assert np.allclose(m.linear, 0.5 * R1) and m.version == 2
    m.set_scale(2.0)
    assert np.allclose(m.linear, 2.0 * R1) and m.scale == 2.0 and m.version == 3
    reg = np.eye(4)
    reg[:3, :3] = R2
    reg[3] = (9.0, 9.0, 9.0, 9.0)  # the last row is not read
    m.set_registration(reg.tolist())
    assert np.allclose(m.linear, R2 @ (2.0 * R1)) and m.version == 4
    assert m.registration[3] == [0.0, 0.0, 0.0, 1.0]
    # the slave's map: in force from then on, parameters noted (version) but not applied
    own = (0.1 * R2).tolist()
    assert m.set_linear(own) is True and m.source == "slave" and m.version == 5
    assert m.set_linear([list(r) for r in own]) is False and m.version == 5
    m.set_scale(4.0)
    assert np.allclose(m.linear, own) and m.source == "slave" and m.version == 6
    assert m.factor == pytest.approx(0.1)
    assert np.allclose(m.point((1.0, 2.0, 3.0)), np.linalg.inv(0.1 * R2) @ (1.0, 2.0, 3.0))
    assert m.set_linear((0.2 * R2).tolist()) is True and m.version == 7


@pytest.mark.parametrize("scale", [0.0, -1.0, math.nan, math.inf])
def test_a_bad_scale_is_refused(scale: float) -> None:
    with pytest.raises(DefinitionError) as err:
        PatientMapping(scale)
    assert str(err.value) == f"scale must be > 0, got {scale!r}"


@pytest.mark.parametrize(
    ("matrix", "text"),
    [
        (np.eye(3).tolist(), "registration must be a 4x4 matrix"),
        ([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]], "registration must be a 4x4 matrix"),
        (
            [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
            "registration must be a 4x4 matrix",
        ),
        (
            [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, math.nan], [0.0, 0.0, 1.0, 0.0]],
            "registration: not a finite number (nan)",
        ),
        (
            [[1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]],
            "map: not a scaled rotation (determinant <= 0)",
        ),
    ],
    ids=["3x3", "two-rows", "short-row", "nan", "mirror"],
)
def test_a_bad_registration_is_refused(matrix: Any, text: str) -> None:
    m = PatientMapping(1.0)
    with pytest.raises(DefinitionError) as err:
        m.set_registration(matrix)
    assert str(err.value) == text


def test_a_registration_of_three_rows_is_taken_and_a_fourth_is_not_read() -> None:
    m = PatientMapping(1.0)
    m.set_registration([[*r, 0.0] for r in R2.tolist()])
    assert np.allclose(m.linear, R2)
    for last in ([math.nan] * 4, [0.0, 0.0, 1.0]):
        m.set_registration([[*r, 5.0] for r in R1.tolist()] + [last])
        assert np.allclose(m.linear, R1) and m.registration[3] == [0.0, 0.0, 0.0, 1.0]


# ------------------------------------------------------------------ into the master's frame
def test_definitions_compile_into_the_masters_frame() -> None:
    m = PatientMapping(0.5, rotation=R1.tolist())
    defs = [
        Definition("accessible", ((1.0, 2.0, 3.0),), 2.0, None, 0.5, 0.25, "a"),
        Definition("forbidden", ((4.0, 5.0, 6.0),), 1.0, None, 2.0, 0.0, "f"),
        Definition("plane", ((0.0, 0.0, 1.0),), 0.0, (0.0, 0.0, 3.0), 1.5, 0.5, "p"),
        Definition("guide", ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)), 0.0, None, 0.75, 0.125, "g"),
    ]
    a, f, p, g = compile_definitions(defs, m)
    inv = np.linalg.inv(0.5 * R1)
    assert type(a) is AccessibleSphere and type(f) is ForbiddenSphere
    assert np.allclose(a.centre, inv @ (1.0, 2.0, 3.0)) and a.radius == pytest.approx(4.0)
    assert (a.stiffness, a.damping, a.name) == (0.5, 0.25, "a")
    assert np.allclose(f.centre, inv @ (4.0, 5.0, 6.0)) and f.radius == pytest.approx(2.0)
    assert (f.stiffness, f.damping, f.name) == (2.0, 0.0, "f")
    assert type(p) is ForbiddenPlane and np.allclose(p.point, inv @ (0.0, 0.0, 1.0))
    assert np.allclose(p.normal, R1.T @ (0.0, 0.0, 1.0)) and (p.stiffness, p.damping) == (1.5, 0.5)
    assert p.name == "p"
    assert type(g) is Guide and np.allclose(g.points, np.array([(0, 0, 0), inv @ (1.0, 1.0, 1.0)]))
    assert (g.stiffness, g.damping, g.name) == (0.75, 0.125, "g")
    # without a mapping: as defined
    assert to_master(defs[2], None) is defs[2]
    (same,) = compile_definitions(defs[:1], None)
    assert same == AccessibleSphere((1.0, 2.0, 3.0), 2.0, 0.5, 0.25, "a")
    assert to_master(defs[0], m).normal is None


def test_a_definition_the_primitives_refuse_is_a_definition_error() -> None:
    same = Definition("guide", ((1.0, 1.0, 1.0), (1.0, 1.0, 1.0)), 0.0, None, 1.0, 0.0, "g")
    with pytest.raises(DefinitionError, match="its points are all the same") as err:
        compile_definitions([same], None)
    assert isinstance(err.value.__cause__, ValueError)
    flat = Definition("plane", ((0.0, 0.0, 0.0),), 0.0, (1e-12, 0.0, 0.0), 1.0, 0.0, "p")
    with pytest.raises(DefinitionError, match="the normal is zero"):
        compile_definitions([flat], None)
