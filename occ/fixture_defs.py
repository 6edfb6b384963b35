"""Virtual-fixture definitions: what 3D Slicer and scripts send, in their own frames, and how
they become the master's primitives (:mod:`occ.fixtures`).

A definition says its kind, geometry, gains and *frame*:

- ``master``: the master's own workspace, mm (the OCC paper's motion test draws its sphere
  there); the default for VFIXTURE;
- ``patient``: 3D Slicer's RAS, mm; the default for Slicer Markups (POINT, TRANSFORM,
  POLYDATA, ``.mrk.json`` files). The master maps these into its frame through
  :class:`PatientMapping` (the slave's registration, the motion scale, the clutch offsets).

Encodings (every metadata key optional; a v1 sender, without metadata, gets the defaults of
the controller's parameters):

===========  ======================================================================
message      fixture
===========  ======================================================================
VFIXTURE     spheres (x, y, z, r mm) with ``hardness`` as stiffness (N/mm); both the
             paper's 8 + 16 n and the 7 + 16 n layouts. Metadata ``kind``:
             ``accessible`` (the paper's meaning, the default) or ``forbidden``;
             ``frame`` (default ``master``), ``damping``.
POINT        Slicer Markups point list: each visible point (alpha > 0) a sphere of the
             point's radius, else metadata ``radius``, else ``fixture_radius_mm``;
             metadata ``kind`` ``accessible``/``forbidden`` or ``guide`` (the points, in
             order, are a polyline: a Markups line or curve), ``stiffness``,
             ``damping``, ``frame`` (default ``patient``).
TRANSFORM    a Markups plane with metadata ``kind=plane``: the translation is a point of
             the plane, the third column of the rotation (the plane node's z axis, its
             normal in Slicer) the outward normal; the half-space behind it is forbidden.
POLYDATA     metadata ``kind=guide``: every line cell a polyline guide; ``kind=plane``:
             every polygon a plane (its first point, the normal of its first three).
===========  ======================================================================

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

from igtl.messages.base import Message

from .fixtures import (
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
    "from_message",
]

Kind = Literal["accessible", "forbidden", "plane", "guide"]
FrameName = Literal["master", "patient"]
KINDS = ("accessible", "forbidden", "plane", "guide")
FRAMES = ("master", "patient")


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
    frame: FrameName = "master"


@dataclass(frozen=True, slots=True)
class Defaults:
    """What a definition without metadata gets (from the controller's parameters)."""

    vfixture_kind: Kind = "accessible"
    vfixture_frame: FrameName = "master"
    point_kind: Kind = "accessible"
    point_frame: FrameName = "patient"
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


def _finite(values: Iterable[float], what: str) -> tuple[float, ...]:
    out = tuple(float(v) for v in values)
    for v in out:
        if not math.isfinite(v):
            raise DefinitionError(f"{what}: not a finite number ({v!r})")
    return out


# ------------------------------------------------------------------------------ messages
def from_message(msg: Message, defaults: Defaults) -> list[Definition] | None:
    """The definitions ``msg`` carries, or None when it is no fixture message (a TRANSFORM
    without ``kind=plane``, say). Raises :class:`DefinitionError` for a bad one."""
    mtype = msg.message_type
    meta = msg.metadata
    name = msg.device_name
    if mtype == "VFIXTURE":
        kind = _choice(meta, "kind", defaults.vfixture_kind, ("accessible", "forbidden"))
        frame = _choice(meta, "frame", defaults.vfixture_frame, FRAMES)
        version = getattr(msg, "version", 1)
        if version != 1:
            raise DefinitionError(f"VFIXTURE version {version} is not known (1 is)")
        hardness = float(getattr(msg, "hardness", 0.0))
        if not math.isfinite(hardness) or hardness < 0.0:
            raise DefinitionError(f"VFIXTURE hardness {hardness!r} must be >= 0")
        damping = _num(meta, "damping", defaults.damping)
        spheres = getattr(msg, "spheres", ())
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
    if mtype == "POINT":
        kind = _choice(meta, "kind", defaults.point_kind, ("accessible", "forbidden", "guide"))
        frame = _choice(meta, "frame", defaults.point_frame, FRAMES)
        k = _num(meta, "stiffness", defaults.stiffness)
        b = _num(meta, "damping", defaults.damping)
        radius = _num(meta, "radius", defaults.point_radius_mm)
        visible = [p for p in getattr(msg, "points", ()) if p.rgba[3] > 0]
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
    if mtype == "TRANSFORM":
        if meta.get("kind", "").strip().lower() != "plane":
            return None
        frame = _choice(meta, "frame", "patient", FRAMES)
        e = _finite(getattr(msg, "elements", ()), f"plane {name!r}")
        # wire order: the 3x3 column by column, then the translation: the z axis is e[6:9]
        point, normal = (e[9], e[10], e[11]), (e[6], e[7], e[8])
        if math.sqrt(sum(v * v for v in normal)) < 1e-9:
            raise DefinitionError(f"plane {name!r}: the rotation's z axis is zero")
        k = _num(meta, "stiffness", defaults.stiffness)
        b = _num(meta, "damping", defaults.damping)
        return [Definition("plane", (point,), 0.0, normal, k, b, name, frame)]  # type: ignore[arg-type]
    if mtype == "POLYDATA":
        kind = meta.get("kind", "").strip().lower()
        if kind not in ("guide", "plane"):
            return None
        frame = _choice(meta, "frame", "patient", FRAMES)
        k = _num(meta, "stiffness", defaults.stiffness)
        b = _num(meta, "damping", defaults.damping)
        poly: Any = msg
        pts = [_finite(p, f"polydata {name!r}") for p in poly.points.tolist()]
        n = len(pts)
        out = []
        cells = poly.lines if kind == "guide" else poly.polygons
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
                a, c, d = (pts[j] for j in cell[:3])
                u = (c[0] - a[0], c[1] - a[1], c[2] - a[2])
                v = (d[0] - a[0], d[1] - a[1], d[2] - a[2])
                nrm = (
                    u[1] * v[2] - u[2] * v[1],
                    u[2] * v[0] - u[0] * v[2],
                    u[0] * v[1] - u[1] * v[0],
                )
                out.append(Definition("plane", (a,), 0.0, nrm, k, b, f"{name}-{i}", frame))  # type: ignore[arg-type]
        return out
    return None


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
        system = str(m.get("coordinateSystem", "LPS")).upper()
        if system not in ("LPS", "RAS"):
            raise DefinitionError(f"{path}: markups[{m_index}]: coordinate system {system!r}")
        flip = -1.0 if system == "LPS" else 1.0
        units = m.get("coordinateUnits", "mm")
        units = units[0] if isinstance(units, list) and units else units
        if units not in ("mm", "um"):
            raise DefinitionError(f"{path}: markups[{m_index}]: coordinate units {units!r}")
        unit = 1e-3 if units == "um" else 1.0

        def ras(p: Any, what: str, flip: float = flip, unit: float = unit) -> Vec3:
            if not isinstance(p, (list, tuple)) or len(p) != 3:
                raise DefinitionError(f"{path}: {what}: expected [x, y, z]")
            x, y, z = _finite(p, f"{path}: {what}")
            return (flip * x * unit, flip * y * unit, z * unit)

        mtype = str(m.get("type", ""))
        label = str(m.get("name", "") or f"markups{m_index}")
        points = []
        for c_index, cp in enumerate(m.get("controlPoints") or []):
            if not isinstance(cp, dict) or "position" not in cp:
                raise DefinitionError(f"{path}: {label}: control point {c_index} has no position")
            if cp.get("visibility", True) is False or cp.get("positionStatus") == "undefined":
                continue
            points.append(
                (
                    str(cp.get("label", "") or f"{label}-{c_index}"),
                    ras(cp["position"], f"{label} point {c_index}"),
                )
            )
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
                continue
            for n, p in points:
                out.append(
                    Definition(kind, (p,), radius_mm, None, stiffness, damping, n, "patient")
                )
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
                ras(m["center"], f"{label} center")
                if "center" in m
                else (points[0][1] if points else None)
            )
            if centre is None or "normal" not in m:
                raise DefinitionError(
                    f"{path}: plane {label!r} needs a center (or a control point) and a normal"
                )
            normal = ras(m["normal"], f"{label} normal", unit=1.0)
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
class PatientMapping:
    """Patient (Slicer RAS, mm) to master (mm), mirroring what the slave does.

    The slave follows ``s = S_ref + scale R (m - M_ref)`` in its base frame, re-taking
    (M_ref, S_ref) whenever following (re)starts (run, clutch released), and its base sits at
    ``registration`` in the patient frame (its base pose, 4x4, mm). So a patient point P is at
    ``m = M_ref + R^T (registration^-1 P - S_ref) / scale`` on the master, and a length ``l``
    at ``l / scale``. The master keeps the same references from its own handle: when
    following stops it notes where the slave stopped (``S_ref + scale R (m - M_ref)``), when it
    resumes that becomes ``S_ref`` and the handle ``M_ref``. ``slave_tip`` (a measured tip, e.g.
    the slave's ``Tip``) re-anchors ``S_ref`` when the slave could not follow exactly (a clamp).
    ``version`` increments on every change, so the controller recompiles patient fixtures.
    """

    def __init__(
        self,
        scale: float,
        rotation: Sequence[Sequence[float]] | None = None,
        registration: Sequence[Sequence[float]] | None = None,
        slave_ref: Vec3 = (0.0, 0.0, 0.0),
        master_ref: Vec3 = (0.0, 0.0, 0.0),
    ) -> None:
        self.scale = 1.0
        self.rotation = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        self.registration = [[1.0 if i == j else 0.0 for j in range(4)] for i in range(4)]
        self._inverse = [row[:] for row in self.registration]
        self.slave_ref = slave_ref
        self.master_ref = master_ref
        self.following = False
        self._slave_hold: Vec3 | None = None
        self.version = 0
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
        self.version += 1

    def set_rotation(self, rotation: Sequence[Sequence[float]]) -> None:
        self.rotation = [[float(v) for v in row] for row in rotation]
        self.version += 1

    def set_registration(self, matrix: Sequence[Sequence[float]]) -> None:
        """The slave's base pose in the patient frame (4x4, translation in mm)."""
        m = [[float(v) for v in row] for row in matrix]
        if len(m) < 3 or any(len(row) != 4 for row in m[:3]):
            raise DefinitionError("registration must be a 4x4 matrix")
        for row in m[:3]:
            _finite(row, "registration")
        r = [row[:3] for row in m[:3]]
        t = [m[0][3], m[1][3], m[2][3]]
        rt = [[r[j][i] for j in range(3)] for i in range(3)]  # rigid: inverse = transpose
        ti = [-sum(rt[i][j] * t[j] for j in range(3)) for i in range(3)]
        self.registration = [*m[:3], [0.0, 0.0, 0.0, 1.0]]
        self._inverse = [[*rt[i], ti[i]] for i in range(3)] + [[0.0, 0.0, 0.0, 1.0]]
        self.version += 1

    def _slave_at(self, m: Sequence[float]) -> Vec3:
        s = self.scale
        d = (m[0] - self.master_ref[0], m[1] - self.master_ref[1], m[2] - self.master_ref[2])
        r = self.rotation
        return (
            self.slave_ref[0] + s * (r[0][0] * d[0] + r[0][1] * d[1] + r[0][2] * d[2]),
            self.slave_ref[1] + s * (r[1][0] * d[0] + r[1][1] * d[1] + r[1][2] * d[2]),
            self.slave_ref[2] + s * (r[2][0] * d[0] + r[2][1] * d[1] + r[2][2] * d[2]),
        )

    def start_following(self, master: Sequence[float]) -> None:
        """Following (re)starts with the handle at ``master`` (mm): the slave re-indexes."""
        if self.following:
            return
        if self._slave_hold is not None:
            self.slave_ref = self._slave_hold
        self.master_ref = (float(master[0]), float(master[1]), float(master[2]))
        self.following = True
        self.version += 1

    def stop_following(self, master: Sequence[float]) -> None:
        """Following stops (clutch pressed, master stopped) with the handle at ``master``."""
        if not self.following:
            return
        self._slave_hold = self._slave_at(master)
        self.following = False

    def slave_tip(self, tip_patient: Sequence[float], master: Sequence[float]) -> None:
        """The slave's tip measured at ``tip_patient`` (patient mm) with the handle at
        ``master``: re-anchor so that the mapping goes through both."""
        base = self._to_base(tip_patient)
        if self.following:
            predicted = self._slave_at(master)
            delta = (base[0] - predicted[0], base[1] - predicted[1], base[2] - predicted[2])
            self.slave_ref = (
                self.slave_ref[0] + delta[0],
                self.slave_ref[1] + delta[1],
                self.slave_ref[2] + delta[2],
            )
        else:
            self._slave_hold = base
            self.slave_ref = base
            self.master_ref = (float(master[0]), float(master[1]), float(master[2]))
        self.version += 1

    # ------------------------------------------------------------------ mapping
    def _to_base(self, p: Sequence[float]) -> Vec3:
        m = self._inverse
        return (
            m[0][0] * p[0] + m[0][1] * p[1] + m[0][2] * p[2] + m[0][3],
            m[1][0] * p[0] + m[1][1] * p[1] + m[1][2] * p[2] + m[1][3],
            m[2][0] * p[0] + m[2][1] * p[1] + m[2][2] * p[2] + m[2][3],
        )

    def point(self, p: Sequence[float]) -> Vec3:
        """A patient point (mm) in the master's frame (mm)."""
        s = self._to_base(p)
        d = (s[0] - self.slave_ref[0], s[1] - self.slave_ref[1], s[2] - self.slave_ref[2])
        r, k = self.rotation, 1.0 / self.scale
        return (
            self.master_ref[0] + k * (r[0][0] * d[0] + r[1][0] * d[1] + r[2][0] * d[2]),
            self.master_ref[1] + k * (r[0][1] * d[0] + r[1][1] * d[1] + r[2][1] * d[2]),
            self.master_ref[2] + k * (r[0][2] * d[0] + r[1][2] * d[1] + r[2][2] * d[2]),
        )

    def direction(self, n: Sequence[float]) -> Vec3:
        """A patient direction in the master's frame (rotated only)."""
        m, r = self._inverse, self.rotation
        b = (
            m[0][0] * n[0] + m[0][1] * n[1] + m[0][2] * n[2],
            m[1][0] * n[0] + m[1][1] * n[1] + m[1][2] * n[2],
            m[2][0] * n[0] + m[2][1] * n[1] + m[2][2] * n[2],
        )
        return (
            r[0][0] * b[0] + r[1][0] * b[1] + r[2][0] * b[2],
            r[0][1] * b[0] + r[1][1] * b[1] + r[2][1] * b[2],
            r[0][2] * b[0] + r[1][2] * b[1] + r[2][2] * b[2],
        )

    def length(self, length: float) -> float:
        return length / self.scale

    def master_to_patient(self, m: Sequence[float]) -> Vec3:
        """Where the slave's tip is (patient mm) for the handle at ``m``, by this mapping."""
        s = self._slave_at(m)
        g = self.registration
        return (
            g[0][0] * s[0] + g[0][1] * s[1] + g[0][2] * s[2] + g[0][3],
            g[1][0] * s[0] + g[1][1] * s[1] + g[1][2] * s[2] + g[1][3],
            g[2][0] * s[0] + g[2][1] * s[1] + g[2][2] * s[2] + g[2][3],
        )


def to_master(d: Definition, mapping: PatientMapping | None) -> Definition:
    """``d`` in the master's frame (unchanged when it is there already)."""
    if d.frame == "master":
        return d
    if mapping is None:
        raise DefinitionError(
            f"fixture {d.name!r} is in the patient frame but the master has no patient mapping"
        )
    return d._replace(
        points=tuple(mapping.point(p) for p in d.points),
        radius=mapping.length(d.radius),
        normal=None if d.normal is None else mapping.direction(d.normal),
        frame="master",
    )


def compile_definitions(
    defs: Iterable[Definition], mapping: PatientMapping | None
) -> list[Primitive]:
    """Primitives in the master's frame; :class:`DefinitionError` when one is not valid."""
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
