"""Virtual-fixture definitions: what 3D Slicer and scripts send, and how they become the
master's primitives (:mod:`occ.haptics.fixtures`).

**One frame: the patient frame.** Every definition is in 3D Slicer's RAS, mm: the frame of the
``Tip`` TRANSFORM the slave sends to Slicer (its base pose times its forward kinematics). VFIXTURE,
POINT, TRANSFORM, POLYDATA and ``.mrk.json`` files alike; a Markups point placed at the ``Tip``
Slicer shows is at the tool. The master computes the force where the slave's tool *is*: its
measured tip, sent back on the return channel (``SlaveTip``), mapped with the fixtures into the
master's force frame by :class:`PatientMapping`. Metadata ``frame`` may say ``patient``; any
other value is refused (the master's own workspace is no frame for fixtures any more: a sphere
drawn there would not follow the clutch).

Encodings (every metadata key optional; a v1 sender, without metadata, gets the defaults of
the controller's parameters):

===========  ======================================================================
message      fixture (patient frame, mm)
===========  ======================================================================
VFIXTURE     spheres (x, y, z, r mm) with ``hardness`` as stiffness (N per mm of master
             motion); both the paper's 8 + 16 n and the 7 + 16 n layouts. Metadata
             ``kind``: ``accessible`` (the paper's meaning, the default) or
             ``forbidden``; ``damping``.
POINT        Slicer Markups point list: each visible point (alpha > 0) a sphere of the
             point's radius, else metadata ``radius``, else ``fixture_radius_mm``;
             metadata ``kind`` ``accessible``/``forbidden`` or ``guide`` (the points, in
             order, are a polyline: a Markups line or curve), ``stiffness``,
             ``damping``.
TRANSFORM    a Markups plane with metadata ``kind=plane``: the translation is a point of
             the plane, the third column of the rotation (the plane node's z axis, its
             normal in Slicer) the outward normal; the half-space behind it is forbidden.
POLYDATA     metadata ``kind=guide``: every line cell a polyline guide; ``kind=plane``:
             every polygon a plane (its first point, the normal of its first three).
===========  ======================================================================

Radii are patient mm; stiffness is N per mm of *master* motion (what the hand feels: a 1 mm
deep contact in the patient at 10:1 is 10 mm of master motion).

One definition message replaces the fixtures of its *source* (message type + device name):
Slicer sends each Markups node under its own name, so a point list, a plane and a VFIXTURE
coexist, and re-sending a node replaces only its fixtures (an empty one removes them). Limits:
``max_primitives`` in all and ``max_planes`` planes (the SAW's fixed number of forbidden
planes); a definition over either, or with a bad number, is refused whole.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np

from occ.events import Event, Mesh, PointList, SphereList
from occ.haptics.fixtures import (
    AccessibleSphere,
    ForbiddenPlane,
    ForbiddenSphere,
    Guide,
    Primitive,
    Vec3,
)

__all__ = [
    "Defaults",
    "Definition",
    "DefinitionError",
    "PatientMapping",
    "compile_definitions",
    "from_markups_file",
    "from_event",
    "parse_linear",
]

Kind = Literal["accessible", "forbidden", "plane", "guide"]
FrameName = Literal["patient"]
KINDS = ("accessible", "forbidden", "plane", "guide")
#: the one frame of fixture definitions (see the module docstring)
FRAMES = ("patient",)


class DefinitionError(ValueError):
    """A fixture definition that cannot be used (the sender is told why)."""


class Definition(NamedTuple):
    """One fixture in its own frame: a sphere (``points`` = its centre, ``radius``), a plane
    (``points`` = one point, ``normal``) or a guide (``points`` = the path). A named tuple:
    a definition of 64 spheres is built on the loop thread."""

    kind: Kind
    points: tuple[Vec3, ...]
    radius: float = 0.0
    normal: Vec3 | None = None
    stiffness: float = 1.0
    damping: float = 0.0
    name: str = ""
    frame: FrameName = "patient"


@dataclass(frozen=True, slots=True)
class Defaults:
    """What a definition without metadata gets (from the controller's parameters)."""

    vfixture_kind: Kind = "accessible"
    point_kind: Kind = "accessible"
    point_radius_mm: float = 5.0
    stiffness: float = 1.0
    damping: float = 0.0


def _num(meta: Mapping[str, str], key: str, default: float) -> float:
    raw = meta.get(key)
    if raw is None:
        return default
    try:
        v = float(raw)
    except ValueError as err:
        raise DefinitionError(f"metadata {key}={raw!r} is not a number") from err
    if not math.isfinite(v) or v < 0.0:
        raise DefinitionError(f"metadata {key}={raw!r} must be a finite number >= 0")
    return v


def _choice(meta: Mapping[str, str], key: str, default: str, allowed: Sequence[str]) -> str:
    raw = meta.get(key)
    if raw is None:
        return default
    v = raw.strip().lower()
    if v not in allowed:
        raise DefinitionError(f"metadata {key}={raw!r}: expected one of {', '.join(allowed)}")
    return v


def _frame(meta: Mapping[str, str]) -> FrameName:
    """Metadata ``frame``: absent or ``patient`` (the one frame); anything else refused."""
    raw = meta.get("frame")
    if raw is None or raw.strip().lower() == "patient":
        return "patient"
    raise DefinitionError(
        f"metadata frame={raw!r}: fixtures are in the patient frame (3D Slicer's RAS, the "
        "frame of the slave's Tip); send them there, without frame or with frame=patient"
    )


def _finite(values: Iterable[float], what: str) -> tuple[float, ...]:
    out = tuple(float(v) for v in values)
    for v in out:
        if not math.isfinite(v):
            raise DefinitionError(f"{what}: not a finite number ({v!r})")
    return out


# ------------------------------------------------------------------------------ inputs
def from_event(event: Event | Any, defaults: Defaults) -> list[Definition] | None:
    """The definitions an input (occ/events.py) carries, or None when it is no fixture (a
    TRANSFORM without ``kind=plane``, say). Raises :class:`DefinitionError` for a bad one."""
    if isinstance(event, SphereList):
        return _spheres(event, defaults)
    if isinstance(event, PointList):
        return _points(event, defaults)
    if isinstance(event, Mesh):
        return _mesh(event, defaults)
    if getattr(event, "kind", "") == "TRANSFORM":  # a pose sample (occ/samples.py)
        return _plane(event, defaults)
    return None


def _spheres(event: SphereList, defaults: Defaults) -> list[Definition]:
    """VFIXTURE: the OCC paper's spheres."""
    meta, name = event.meta, event.device
    kind = _choice(meta, "kind", defaults.vfixture_kind, ("accessible", "forbidden"))
    frame = _frame(meta)
    version = event.version
    if version != 1:
        raise DefinitionError(f"VFIXTURE version {version} is not known (1 is)")
    hardness = event.hardness
    if not math.isfinite(hardness) or hardness < 0.0:
        raise DefinitionError(f"VFIXTURE hardness {hardness!r} must be >= 0")
    damping = _num(meta, "damping", defaults.damping)
    spheres = event.spheres
    # one vectorised check for the whole message: this runs on the loop thread
    arr = np.asarray(spheres, dtype=float).reshape(-1, 4)
    if arr.size and not (np.isfinite(arr).all() and (arr[:, 3] > 0.0).all()):
        i = int(np.flatnonzero(~(np.isfinite(arr).all(axis=1) & (arr[:, 3] > 0.0)))[0])
        raise DefinitionError(
            f"VFIXTURE sphere {i} {tuple(spheres[i])}: needs finite numbers and a radius > 0"
        )
    return [
        Definition(kind, ((x, y, z),), r, None, hardness, damping, f"{name}-{i}", frame)  # type: ignore[arg-type]
        for i, (x, y, z, r) in enumerate(spheres)
    ]


def _points(event: PointList, defaults: Defaults) -> list[Definition]:
    """POINT: a Markups point list, spheres or a guide."""
    meta, name = event.meta, event.device
    kind = _choice(meta, "kind", defaults.point_kind, ("accessible", "forbidden", "guide"))
    frame = _frame(meta)
    k = _num(meta, "stiffness", defaults.stiffness)
    b = _num(meta, "damping", defaults.damping)
    radius = _num(meta, "radius", defaults.point_radius_mm)
    visible = [p for p in event.points if p.visible]
    if kind == "guide":
        if not visible:
            return []
        path = tuple(_finite(p.position, f"point {p.name!r}") for p in visible)
        if len(path) < 2:
            raise DefinitionError("a guide needs at least two visible points")
        return [Definition("guide", path, 0.0, None, k, b, name, frame)]  # type: ignore[arg-type]
    out = []
    for i, p in enumerate(visible):
        c = _finite(p.position, f"point {p.name!r}")
        r = float(p.radius) if p.radius > 0.0 else radius
        if not (r > 0.0 and math.isfinite(r)):
            raise DefinitionError(f"point {p.name!r}: radius {r} must be > 0")
        out.append(
            Definition(kind, (c,), r, None, k, b, p.name or f"{name}-{i}", frame)  # type: ignore[arg-type]
        )
    return out


def _plane(sample: Any, defaults: Defaults) -> list[Definition] | None:
    """TRANSFORM with ``kind=plane``: a Markups plane (its matrix as sent)."""
    meta, name = sample.meta, sample.device
    if meta.get("kind", "").strip().lower() != "plane":
        return None
    frame = _frame(meta)
    m = sample.matrix
    # the upper 3x4 in wire order (column by column): the z axis is e[6:9]
    e = _finite(() if m is None else m[:3, :].T.ravel().tolist(), f"plane {name!r}")
    point, normal = (e[9], e[10], e[11]), (e[6], e[7], e[8])
    if math.sqrt(sum(v * v for v in normal)) < 1e-9:
        raise DefinitionError(f"plane {name!r}: the rotation's z axis is zero")
    k = _num(meta, "stiffness", defaults.stiffness)
    b = _num(meta, "damping", defaults.damping)
    return [Definition("plane", (point,), 0.0, normal, k, b, name, frame)]  # type: ignore[arg-type]


def _mesh(event: Mesh, defaults: Defaults) -> list[Definition] | None:
    """POLYDATA with ``kind=guide`` (line cells) or ``kind=plane`` (polygons)."""
    meta, name = event.meta, event.device
    kind = meta.get("kind", "").strip().lower()
    if kind not in ("guide", "plane"):
        return None
    frame = _frame(meta)
    k = _num(meta, "stiffness", defaults.stiffness)
    b = _num(meta, "damping", defaults.damping)
    pts = [_finite(p, f"polydata {name!r}") for p in event.points.tolist()]
    n = len(pts)
    out = []
    cells = event.lines if kind == "guide" else event.polygons
    for i, cell in enumerate(cells):
        if any(j >= n for j in cell):
            raise DefinitionError(f"polydata {name!r}: cell {i} refers to a missing point")
        if kind == "guide":
            if len(cell) < 2:
                raise DefinitionError(f"polydata {name!r}: line {i} has fewer than 2 points")
            path = tuple(pts[j] for j in cell)
            out.append(Definition("guide", path, 0.0, None, k, b, f"{name}-{i}", frame))  # type: ignore[arg-type]
        else:
            if len(cell) < 3:
                raise DefinitionError(f"polydata {name!r}: polygon {i} has fewer than 3 points")
            out.append(_polygon_plane(pts, cell, k, b, f"{name}-{i}", frame))
    return out


def _polygon_plane(
    pts: list[tuple[float, ...]], cell: Sequence[int], k: float, b: float, name: str, frame: str
) -> Definition:
    """A plane through a polygon's first point, the normal of its first three."""
    a, c, d = (pts[j] for j in cell[:3])
    u = (c[0] - a[0], c[1] - a[1], c[2] - a[2])
    v = (d[0] - a[0], d[1] - a[1], d[2] - a[2])
    nrm = (
        u[1] * v[2] - u[2] * v[1],
        u[2] * v[0] - u[0] * v[2],
        u[0] * v[1] - u[1] * v[0],
    )
    return Definition("plane", (a,), 0.0, nrm, k, b, name, frame)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------ files
def from_markups_file(
    path: str | Path,
    *,
    kind: Kind = "accessible",
    radius_mm: float = 5.0,
    stiffness: float = 1.0,
    damping: float = 0.0,
) -> list[Definition]:
    """A 3D Slicer markups file (``.mrk.json``) as definitions in the patient frame (RAS).

    Fiducial point lists become spheres of ``kind`` (``accessible``/``forbidden``; the
    point's own radius is not stored by Slicer, so ``radius_mm``) or, with ``kind: guide``, one
    polyline; lines and curves become guides; planes become forbidden planes (their first
    control point or ``center`` and ``normal``). Coordinates in ``LPS`` (Slicer's file default)
    are turned into RAS (x and y negated); ``RAS`` files are taken as they are; ``um`` units
    become mm. Hidden and undefined control points are left out."""
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        raise DefinitionError(f"{path}: cannot read a markups file: {err}") from err
    out: list[Definition] = []
    markups = doc.get("markups") if isinstance(doc, dict) else None
    if not isinstance(markups, list):
        raise DefinitionError(f"{path}: no 'markups' list (is it a Slicer .mrk.json file?)")
    for m_index, m in enumerate(markups):
        if not isinstance(m, dict):
            raise DefinitionError(f"{path}: markups[{m_index}] is not an object")
        frame = _markup_frame(path, m, m_index)
        label = str(m.get("name", "") or f"markups{m_index}")
        points = _markup_points(path, m, label, frame)
        fixture = (kind, radius_mm, stiffness, damping)
        out.extend(_markup_definitions(path, m, label, points, frame, fixture))
    return out


def _markup_frame(path: str | Path, m: dict[str, Any], m_index: int) -> tuple[float, float]:
    """A markup's coordinate system and units: (the sign of x and y, the factor to mm)."""
    system = str(m.get("coordinateSystem", "LPS")).upper()
    if system not in ("LPS", "RAS"):
        raise DefinitionError(f"{path}: markups[{m_index}]: coordinate system {system!r}")
    flip = -1.0 if system == "LPS" else 1.0
    units = m.get("coordinateUnits", "mm")
    units = units[0] if isinstance(units, list) and units else units
    if units not in ("mm", "um"):
        raise DefinitionError(f"{path}: markups[{m_index}]: coordinate units {units!r}")
    return flip, (1e-3 if units == "um" else 1.0)


def _ras(path: str | Path, p: Any, what: str, frame: tuple[float, float]) -> Vec3:
    """A file's ``[x, y, z]`` in RAS millimetres (``frame``: :func:`_markup_frame`)."""
    flip, unit = frame
    if not isinstance(p, (list, tuple)) or len(p) != 3:
        raise DefinitionError(f"{path}: {what}: expected [x, y, z]")
    x, y, z = _finite(p, f"{path}: {what}")
    return (flip * x * unit, flip * y * unit, z * unit)


def _markup_points(
    path: str | Path, m: dict[str, Any], label: str, frame: tuple[float, float]
) -> list[tuple[str, Vec3]]:
    """A markup's visible, defined control points: (label, RAS point)."""
    points = []
    for c_index, cp in enumerate(m.get("controlPoints") or []):
        if not isinstance(cp, dict) or "position" not in cp:
            raise DefinitionError(f"{path}: {label}: control point {c_index} has no position")
        if cp.get("visibility", True) is False or cp.get("positionStatus") == "undefined":
            continue
        points.append(
            (
                str(cp.get("label", "") or f"{label}-{c_index}"),
                _ras(path, cp["position"], f"{label} point {c_index}", frame),
            )
        )
    return points


def _markup_definitions(
    path: str | Path,
    m: dict[str, Any],
    label: str,
    points: list[tuple[str, Vec3]],
    frame: tuple[float, float],
    fixture: tuple[Kind, float, float, float],
) -> list[Definition]:
    """What one markup defines, by its type; ``fixture`` is (kind, radius_mm, stiffness,
    damping) as :func:`from_markups_file` was given them."""
    kind, radius_mm, stiffness, damping = fixture
    mtype = str(m.get("type", ""))
    out: list[Definition] = []
    if mtype == "Fiducial":
        if kind == "guide":
            if len(points) >= 2:
                out.append(
                    Definition(
                        "guide",
                        tuple(p for _, p in points),
                        0.0,
                        None,
                        stiffness,
                        damping,
                        label,
                        "patient",
                    )
                )
            return out
        for n, p in points:
            out.append(Definition(kind, (p,), radius_mm, None, stiffness, damping, n, "patient"))
    elif mtype in ("Line", "Curve", "ClosedCurve"):
        path_pts = tuple(p for _, p in points)
        if mtype == "ClosedCurve" and path_pts:
            path_pts = (*path_pts, path_pts[0])
        if len(path_pts) >= 2:
            out.append(
                Definition("guide", path_pts, 0.0, None, stiffness, damping, label, "patient")
            )
    elif mtype == "Plane":
        centre = (
            _ras(path, m["center"], f"{label} center", frame)
            if "center" in m
            else (points[0][1] if points else None)
        )
        if centre is None or "normal" not in m:
            raise DefinitionError(
                f"{path}: plane {label!r} needs a center (or a control point) and a normal"
            )
        normal = _ras(path, m["normal"], f"{label} normal", (frame[0], 1.0))
        out.append(
            Definition("plane", (centre,), 0.0, normal, stiffness, damping, label, "patient")
        )
    else:
        raise DefinitionError(
            f"{path}: markups type {mtype!r} is not a fixture "
            "(Fiducial, Line, Curve, ClosedCurve, Plane are)"
        )
    return out


# ------------------------------------------------------------------------------ frames
def parse_linear(text: str) -> tuple[tuple[float, float, float], ...]:
    """The ``map`` metadata of the slave's tip stream: 9 numbers, row by row, the 3x3 matrix
    that turns a handle displacement (master mm) into the tip's displacement in the patient
    frame (mm). :class:`DefinitionError` when it is no scaled rotation."""
    parts = text.replace(",", " ").split()
    if len(parts) != 9:
        raise DefinitionError(f"map {text!r}: expected 9 numbers, got {len(parts)}")
    try:
        v = [float(x) for x in parts]
    except ValueError as err:
        raise DefinitionError(f"map {text!r}: not numbers") from err
    rows = ((v[0], v[1], v[2]), (v[3], v[4], v[5]), (v[6], v[7], v[8]))
    _check_linear(rows)
    return rows


def _det3(m: Sequence[Sequence[float]]) -> float:
    return (
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    )


def _check_linear(m: Sequence[Sequence[float]]) -> float:
    """The scale ``s`` of ``m`` when it is ``s`` times a rotation (what a slave's motion
    scaling, master-to-slave rotation and base rotation make), else DefinitionError."""
    for row in m:
        _finite(row, "map")
    det = _det3(m)
    if not det > 0.0:
        raise DefinitionError("map: not a scaled rotation (determinant <= 0)")
    s = det ** (1.0 / 3.0)
    for i in range(3):
        for j in range(3):
            dot = sum(m[k][i] * m[k][j] for k in range(3))
            want = s * s if i == j else 0.0
            if abs(dot - want) > 1e-3 * s * s:
                raise DefinitionError("map: not a scaled rotation (columns not orthogonal)")
    return s


class PatientMapping:
    """The patient frame (3D Slicer RAS, mm: the frame of the slave's ``Tip``) seen from the
    master's hand: a linear map, no offsets.

    When the handle moves by ``dm`` (mm) the slave's tip moves by ``L dm`` in the patient frame,
    with ``L = G * scale * R``: the rotation ``G`` of the slave's base in the patient frame (its
    registration), its motion scaling and its master-to-slave rotation ``R``. Fixtures (patient
    mm) and the tool (the slave's measured tip, patient mm, sent back on the return channel)
    are both mapped by ``L^-1`` (:meth:`point`); in that frame lengths are mm of master motion
    and directions the master's axes, so the force computed there is the force to display and a
    stiffness is N per mm of master motion, whatever the scale. Where the handle is does not
    enter (the tool is where the slave measures it), so the clutch, re-indexing and a
    hand-over move nothing here.

    ``L`` comes from the slave itself (the ``map`` metadata of its tip stream:
    :meth:`set_linear`) or, for a slave that does not send it, from the master's parameters
    (``scale``, ``rotation``) and a registration TRANSFORM (``set_registration``; only its
    rotation matters). ``version`` increments on every change, so patient fixtures are
    recompiled.
    """

    def __init__(
        self,
        scale: float,
        rotation: Sequence[Sequence[float]] | None = None,
        registration: Sequence[Sequence[float]] | None = None,
    ) -> None:
        self.scale = 1.0
        self.rotation = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        self.registration = [[1.0 if i == j else 0.0 for j in range(4)] for i in range(4)]
        #: where L came from: ``params`` (scale, rotation, registration) or ``slave`` (its map)
        self.source = "params"
        self.linear: list[list[float]] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        self._inverse = [row[:] for row in self.linear]
        self.version = 0
        self._from_slave: tuple[tuple[float, ...], ...] | None = None
        self.set_scale(scale)
        if rotation is not None:
            self.set_rotation(rotation)
        if registration is not None:
            self.set_registration(registration)

    # ------------------------------------------------------------------ changes
    def set_scale(self, scale: float) -> None:
        if not (math.isfinite(scale) and scale > 0.0):
            raise DefinitionError(f"scale must be > 0, got {scale!r}")
        self.scale = float(scale)
        self._from_params()

    def set_rotation(self, rotation: Sequence[Sequence[float]]) -> None:
        self.rotation = [[float(v) for v in row] for row in rotation]
        self._from_params()

    def set_registration(self, matrix: Sequence[Sequence[float]]) -> None:
        """The slave's base pose in the patient frame (4x4, translation in mm; only its
        rotation enters the map)."""
        m = [[float(v) for v in row] for row in matrix]
        if len(m) < 3 or any(len(row) != 4 for row in m[:3]):
            raise DefinitionError("registration must be a 4x4 matrix")
        for row in m[:3]:
            _finite(row, "registration")
        self.registration = [*m[:3], [0.0, 0.0, 0.0, 1.0]]
        self._from_params()

    def _from_params(self) -> None:
        if self._from_slave is not None:
            self.version += 1  # noted; the slave's own map stays in force
            return
        g = [row[:3] for row in self.registration[:3]]
        r, s = self.rotation, self.scale
        lin = [[s * sum(g[i][k] * r[k][j] for k in range(3)) for j in range(3)] for i in range(3)]
        self._set(lin)
        self.source = "params"

    def set_linear(self, linear: Sequence[Sequence[float]]) -> bool:
        """``L`` as the slave reports it (its ``map``): True when it changed the mapping."""
        key = tuple(tuple(float(v) for v in row) for row in linear)
        if key == self._from_slave:
            return False
        self._from_slave = key
        self._set([list(row) for row in key])
        self.source = "slave"
        return True

    def _set(self, lin: list[list[float]]) -> None:
        s = _check_linear(lin)
        # L = s Q with Q a rotation: L^-1 = Q^T / s = L^T / s^2
        self.linear = lin
        self._inverse = [[lin[j][i] / (s * s) for j in range(3)] for i in range(3)]
        self._scale_now = s
        self.version += 1

    # ------------------------------------------------------------------ mapping
    @property
    def factor(self) -> float:
        """Patient mm per mm of master motion (the slave's motion scaling)."""
        return self._scale_now

    def point(self, p: Sequence[float]) -> Vec3:
        """A patient point (mm) in the master's force frame (mm of master motion)."""
        m = self._inverse
        return (
            m[0][0] * p[0] + m[0][1] * p[1] + m[0][2] * p[2],
            m[1][0] * p[0] + m[1][1] * p[1] + m[1][2] * p[2],
            m[2][0] * p[0] + m[2][1] * p[1] + m[2][2] * p[2],
        )

    def direction(self, n: Sequence[float]) -> Vec3:
        """A plane's normal (patient) in the force frame: ``L^T n``, unit length."""
        m = self.linear
        v = (
            m[0][0] * n[0] + m[1][0] * n[1] + m[2][0] * n[2],
            m[0][1] * n[0] + m[1][1] * n[1] + m[2][1] * n[2],
            m[0][2] * n[0] + m[1][2] * n[1] + m[2][2] * n[2],
        )
        k = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) or 1.0
        return (v[0] / k, v[1] / k, v[2] / k)

    def force(self, f: Sequence[float]) -> Vec3:
        """A force on the slave's instrument (N, patient frame) in the master's axes, unscaled:
        ``Q^T f`` with ``Q = L / s`` the rotation of the map (the motion scaling is not a force
        scaling; the master applies its own)."""
        m, k = self.linear, 1.0 / self._scale_now
        return (
            k * (m[0][0] * f[0] + m[1][0] * f[1] + m[2][0] * f[2]),
            k * (m[0][1] * f[0] + m[1][1] * f[1] + m[2][1] * f[2]),
            k * (m[0][2] * f[0] + m[1][2] * f[1] + m[2][2] * f[2]),
        )

    def length(self, length: float) -> float:
        """A patient length (mm) in mm of master motion."""
        return length / self._scale_now

    def master_to_patient(self, m: Sequence[float]) -> Vec3:
        """A point of the force frame back in the patient frame (the display)."""
        g = self.linear
        return (
            g[0][0] * m[0] + g[0][1] * m[1] + g[0][2] * m[2],
            g[1][0] * m[0] + g[1][1] * m[1] + g[1][2] * m[2],
            g[2][0] * m[0] + g[2][1] * m[1] + g[2][2] * m[2],
        )

    def patient_direction(self, n: Sequence[float]) -> Vec3:
        """A normal of the force frame back in the patient frame (the display), unit."""
        m = self._inverse
        v = (
            m[0][0] * n[0] + m[1][0] * n[1] + m[2][0] * n[2],
            m[0][1] * n[0] + m[1][1] * n[1] + m[2][1] * n[2],
            m[0][2] * n[0] + m[1][2] * n[1] + m[2][2] * n[2],
        )
        k = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) or 1.0
        return (v[0] / k, v[1] / k, v[2] / k)


def to_master(d: Definition, mapping: PatientMapping | None) -> Definition:
    """``d`` (patient frame) in the master's force frame (see :class:`PatientMapping`);
    unchanged without a mapping (unit tests of the primitives)."""
    if mapping is None:
        return d
    return d._replace(
        points=tuple(mapping.point(p) for p in d.points),
        radius=mapping.length(d.radius),
        normal=None if d.normal is None else mapping.direction(d.normal),
    )


def compile_definitions(
    defs: Iterable[Definition], mapping: PatientMapping | None
) -> list[Primitive]:
    """Primitives in the master's force frame; :class:`DefinitionError` when one is not
    valid."""
    out: list[Primitive] = []
    for d in defs:
        m = to_master(d, mapping)
        try:
            if m.kind in ("accessible", "forbidden"):
                # the bulk of a definition: its numbers were checked when it was read (finite,
                # radius > 0, gains >= 0) and the mapping keeps them so; built without a second
                # check (a definition of 64 spheres is compiled on the loop thread)
                cls = AccessibleSphere if m.kind == "accessible" else ForbiddenSphere
                out.append(cls._trusted(m.points[0], m.radius, m.stiffness, m.damping, m.name))
            elif m.kind == "plane":
                assert m.normal is not None
                out.append(ForbiddenPlane(m.points[0], m.normal, m.stiffness, m.damping, m.name))
            else:
                out.append(Guide(m.points, m.stiffness, m.damping, m.name))
        except ValueError as err:
            raise DefinitionError(str(err)) from err
    return out
