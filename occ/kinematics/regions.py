"""Forbidden regions of the whole-arm collision check (occ/kinematics/collision.py): spheres,
half-spaces behind a plane and triangle meshes, placed in the patient frame (3D Slicer's RAS;
given in mm, kept in metres), from the YAML (``safety.collision.regions``) or from 3D Slicer
(:func:`regions_from_event`).

Meshes in parts
    coal builds a mesh's bounding-volume hierarchy in one call that holds the interpreter lock
    throughout: ~2 us a triangle, 0.4 s for a 200k-triangle Slicer model, during which the
    loop thread cannot run whatever thread builds it. So a mesh of more than
    :data:`MESH_PART` triangles is cut into spatially compact parts (median splits of the
    triangles' centroids along the longest axis), each with its own hierarchy and bounding
    ball, built one after the other with the lock given up between two (``pause``): a part
    holds it ~1 ms (a ticking thread waited at most 5.3 ms during a 200k-triangle build,
    against 0.4 s in one call: docs/BENCHMARKS.md). The check treats the parts as one region:
    the parts whose balls are near a link are asked, the others' balls bound their distance
    from below (occ/kinematics/collision.py ``Checker``). A Slicer mesh is built on the
    operator desk's worker, never on the loop thread (occ/net/operators.py), and takes effect
    when built.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import coal
import numpy as np

if TYPE_CHECKING:
    from occ.config import RegionConfig

__all__ = [
    "MAX_TRIANGLES",
    "MESH_PART",
    "REGION_KIND",
    "Region",
    "RegionError",
    "mesh_region",
    "plane_region",
    "region_event",
    "region_from_config",
    "regions_from_event",
    "sphere_region",
]

MM = 1e-3
#: the Slicer metadata ``kind`` of a forbidden region for the collision check
REGION_KIND = "forbidden-region"
#: the largest Slicer mesh taken as a region (triangles)
MAX_TRIANGLES = 200_000
#: a mesh of more triangles is built in parts of at most this many (module docstring): each
#: part's build holds the interpreter lock ~1 ms
MESH_PART = 512
#: triangles converted to an array at a time between two pauses (a Slicer model's cells)
_CELLS_AT_ONCE = 8192


class RegionError(ValueError):
    """A region definition that cannot be used (the message says why)."""


@dataclass(frozen=True)
class Region:
    """A forbidden region, placed in the patient frame (metres)."""

    name: str
    kind: str  # sphere, plane, mesh
    geometry: Any  # a coal.CollisionGeometry; None for a mesh in parts
    placement: Any  # coal.Transform3s
    exclude: frozenset[str] = frozenset()
    source: str = "config"  # the Slicer node it came from, or "config"
    #: the broad phase's bound (occ/kinematics/collision.py, "Cost"): a ball around it
    #: (centre x, y, z, 0, radius), or a plane's (nx, ny, nz, d, NaN)
    bound: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, math.inf)
    #: a mesh in parts (module docstring): each part's hierarchy, and their balls as rows
    #: (centre x, y, z, radius) of an array
    parts: tuple[Any, ...] = ()
    part_balls: Any = None

    def __post_init__(self) -> None:
        g = self.geometry
        if isinstance(g, coal.Halfspace):
            n = g.n
            b = (float(n[0]), float(n[1]), float(n[2]), float(g.d), math.nan)
            object.__setattr__(self, "bound", b)
            return
        if g is None:  # in parts: the ball around the parts' balls
            balls = np.asarray(self.part_balls, dtype=float)
            lo = (balls[:, :3] - balls[:, 3:]).min(axis=0)
            hi = (balls[:, :3] + balls[:, 3:]).max(axis=0)
            c = (lo + hi) / 2.0
            r = float((np.linalg.norm(balls[:, :3] - c, axis=1) + balls[:, 3]).max())
            object.__setattr__(self, "bound", (float(c[0]), float(c[1]), float(c[2]), 0.0, r))
            return
        g.computeLocalAABB()
        c = self.placement.transform(np.asarray(g.aabb_center, dtype=float))
        r = float(g.aabb_radius)
        object.__setattr__(self, "bound", (float(c[0]), float(c[1]), float(c[2]), 0.0, r))

    @property
    def triangles(self) -> int:
        """A mesh's triangles (all its parts'); 0 for a sphere or a plane."""
        if self.kind != "mesh":
            return 0
        return sum(int(g.num_tris) for g in (self.parts or (self.geometry,)))


def sphere_region(
    name: str,
    centre_mm: Sequence[float],
    radius_mm: float,
    *,
    exclude: Sequence[str] = (),
    source: str = "config",
) -> Region:
    c = _finite(centre_mm, name, "centre")
    if not (math.isfinite(radius_mm) and radius_mm > 0.0):
        raise RegionError(f"region {name!r}: radius {radius_mm} must be > 0")
    tf = coal.Transform3s(np.eye(3), np.asarray(c) * MM)
    return Region(name, "sphere", coal.Sphere(radius_mm * MM), tf, frozenset(exclude), source)


def plane_region(
    name: str,
    point_mm: Sequence[float],
    normal: Sequence[float],
    *,
    exclude: Sequence[str] = (),
    source: str = "config",
) -> Region:
    """The half-space behind a plane: the side opposite ``normal`` is forbidden."""
    p = np.asarray(_finite(point_mm, name, "point")) * MM
    n = np.asarray(_finite(normal, name, "normal"))
    norm = float(np.linalg.norm(n))
    if norm < 1e-12:
        raise RegionError(f"region {name!r}: the normal is zero")
    n = n / norm
    # coal's Halfspace(n, d) is {x: n.x <= d}: the forbidden side
    hs = coal.Halfspace(n, float(n @ p))
    return Region(name, "plane", hs, coal.Transform3s(), frozenset(exclude), source)


def mesh_region(
    name: str,
    vertices_mm: Any,
    triangles: Any,
    *,
    exclude: Sequence[str] = (),
    source: str = "config",
    pause: Callable[[], None] | None = None,
) -> Region:
    """A triangle mesh (vertices in patient mm, triangles as vertex index triples); in parts
    when it has more than :data:`MESH_PART` triangles, ``pause`` called between two (module
    docstring: a worker gives up the interpreter lock there)."""
    v = np.asarray(vertices_mm, dtype=float).reshape(-1, 3)
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if len(t) == 0:
        raise RegionError(f"region {name!r}: the mesh has no triangles")
    if len(t) > MAX_TRIANGLES:
        raise RegionError(f"region {name!r}: {len(t)} triangles (at most {MAX_TRIANGLES})")
    if not np.isfinite(v).all():
        raise RegionError(f"region {name!r}: a vertex is not a finite number")
    if t.min() < 0 or t.max() >= len(v):
        raise RegionError(f"region {name!r}: a triangle refers to a missing point")
    v = v * MM
    ex = frozenset(exclude)
    if len(t) <= MESH_PART:
        return Region(name, "mesh", _bvh(v, t), coal.Transform3s(), ex, source)
    parts, balls = [], []
    for chunk in _split(v, t):
        used, local = np.unique(t[chunk], return_inverse=True)
        pv = v[used]
        parts.append(_bvh(pv, local.reshape(-1, 3)))
        lo, hi = pv.min(axis=0), pv.max(axis=0)
        c = (lo + hi) / 2.0
        balls.append((*c.tolist(), float(np.linalg.norm(pv - c, axis=1).max())))
        if pause is not None:
            pause()
    return Region(
        name,
        "mesh",
        None,
        coal.Transform3s(),
        ex,
        source,
        parts=tuple(parts),
        part_balls=np.asarray(balls, dtype=float),
    )


def _bvh(vertices_m: np.ndarray, triangles: np.ndarray) -> Any:
    bvh = coal.BVHModelOBBRSS()
    bvh.beginModel(len(triangles), len(vertices_m))
    bvh.addVertices(vertices_m)
    bvh.addTriangles(triangles)
    bvh.endModel()
    return bvh


def _split(v: np.ndarray, t: np.ndarray) -> list[np.ndarray]:
    """The triangles' indices in parts of at most :data:`MESH_PART`, each spatially compact:
    median splits of their centroids along the longest axis of the part's centroid box."""
    centroids = v[t].mean(axis=1)
    out = []
    todo = [np.arange(len(t))]
    while todo:
        idx = todo.pop()
        if len(idx) <= MESH_PART:
            out.append(idx)
            continue
        c = centroids[idx]
        axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        half = len(idx) // 2
        order = np.argpartition(c[:, axis], half)
        todo += [idx[order[:half]], idx[order[half:]]]
    return out


def region_from_config(rc: RegionConfig) -> Region:
    """A region of the YAML (``safety.collision.regions``)."""
    ex = tuple(rc.exclude_links)
    if rc.kind == "sphere":
        return sphere_region(rc.name, rc.point_mm, rc.radius_mm, exclude=ex)
    if rc.kind == "plane":
        return plane_region(rc.name, rc.point_mm, rc.normal, exclude=ex)
    assert rc.file is not None
    try:
        loaded = coal.MeshLoader().load(str(rc.file), np.ones(3))
    except Exception as err:  # noqa: BLE001 - coal raises what assimp says
        raise RegionError(f"region {rc.name!r}: cannot read {rc.file}: {err}") from err
    vertices = np.asarray(loaded.vertices(), dtype=float) + np.asarray(rc.point_mm)
    tris = np.array(
        [[tr[0], tr[1], tr[2]] for tr in (loaded.tri_indices(i) for i in range(loaded.num_tris))]
    )
    return mesh_region(rc.name, vertices, tris, exclude=ex)


def _finite(values: Sequence[float], name: str, what: str) -> tuple[float, float, float]:
    try:
        x, y, z = (float(v) for v in values)
    except (TypeError, ValueError):
        raise RegionError(f"region {name!r}: the {what} needs three numbers") from None
    if not all(math.isfinite(v) for v in (x, y, z)):
        raise RegionError(f"region {name!r}: the {what} is not finite")
    return (x, y, z)


def region_event(event: Any) -> str | None:
    """The definition's name when ``event`` (a decoded message) defines a forbidden region
    (metadata ``kind=forbidden-region``), else None: a test that costs nothing."""
    meta = event.meta or {}
    if meta.get("kind", "").strip().lower() != REGION_KIND:
        return None
    return str(event.device or "region")


def regions_from_event(
    event: Any, pause: Callable[[], None] | None = None
) -> tuple[str, list[Region]] | None:
    """Forbidden regions from 3D Slicer: a message with metadata ``kind=forbidden-region``, or
    None for any other. A Markups point list (POINT): a sphere per visible point (its radius,
    else metadata ``radius``, else 10 mm); a Markups plane (TRANSFORM): the half-space behind
    it, its z axis the normal out of the forbidden side (as the fixtures' planes); a model
    (POLYDATA): its polygons, triangulated, as a mesh. Returns (the definition's name: the
    device name, its regions: none removes it). RegionError for one that cannot be used.
    ``pause``: called now and then while a mesh is made (its parts, module docstring)."""
    name = region_event(event)
    if name is None:
        return None
    meta = event.meta or {}
    mtype = event.kind
    if mtype == "POINT":
        try:
            radius = float(meta.get("radius", 10.0))
        except ValueError:
            raise RegionError(
                f"region {name!r}: radius {meta.get('radius')!r} is no number"
            ) from None
        out = []
        for i, p in enumerate(x for x in event.points if x.visible):
            r = float(p.radius) if p.radius > 0.0 else radius
            out.append(sphere_region(f"{name}:{i}", p.position, r, source=name))
        return name, out
    if mtype == "TRANSFORM":
        m = np.asarray(event.matrix, dtype=float)
        if m.shape != (4, 4) or not np.isfinite(m).all():
            raise RegionError(f"region {name!r}: not a transform")
        point, normal = m[:3, 3].tolist(), m[:3, 2].tolist()
        return name, [plane_region(name, point, normal, source=name)]
    if mtype == "POLYDATA":
        return name, _mesh_from_cells(name, event, pause)
    raise RegionError(f"region {name!r}: a {mtype} defines no region (POINT, TRANSFORM, POLYDATA)")


def _mesh_from_cells(name: str, event: Any, pause: Callable[[], None] | None) -> list[Region]:
    """A Slicer model's polygons (fans) and strips (alternating winding) as one mesh region."""
    if len(event.polygons) > MAX_TRIANGLES:
        raise RegionError(
            f"region {name!r}: {len(event.polygons)} polygons (at most {MAX_TRIANGLES} triangles)"
        )
    pts = np.asarray(event.points, dtype=float).reshape(-1, 3)
    tris: list[tuple[int, int, int]] = []
    for i, cell in enumerate(event.polygons):
        if len(cell) < 3:
            raise RegionError(f"region {name!r}: polygon {i} has fewer than 3 points")
        tris.extend((cell[0], cell[k], cell[k + 1]) for k in range(1, len(cell) - 1))
    for strip in event.strips:
        for k in range(len(strip) - 2):
            a, b, c = strip[k], strip[k + 1], strip[k + 2]
            tris.append((a, b, c) if k % 2 == 0 else (b, a, c))
    if not tris:
        return []
    if len(tris) > MAX_TRIANGLES:
        raise RegionError(f"region {name!r}: {len(tris)} triangles (at most {MAX_TRIANGLES})")
    # one array conversion holds the interpreter lock: a slice at a time
    blocks = []
    for k in range(0, len(tris), _CELLS_AT_ONCE):
        blocks.append(np.asarray(tris[k : k + _CELLS_AT_ONCE], dtype=np.int64).reshape(-1, 3))
        if pause is not None:
            pause()
    return [mesh_region(name, pts, np.concatenate(blocks), source=name, pause=pause)]
