"""Whole-arm collision checking (issue 28): the arm's links and its tool against forbidden
regions and against each other, with coal (the collision library under pinocchio).

What is checked
    The links' collision geometry from the robot's URDF (``pin.buildGeomFromUrdf``, the meshes
    found through the package's share directory), each mesh as its convex hull by default (it
    contains the mesh, so no contact is missed; a hull pair costs ~2 us where the mesh's BVH
    costs 20-40); a URDF without collision geometry gets a capsule per link, between its
    joint's origin and the next joint's (and the tip), of ``link_radius_mm``. The tool is a
    capsule along the tip link's z axis. Forbidden regions live in the patient frame (3D
    Slicer's RAS, mm, the frame of the robot's ``Tip``): spheres, half-spaces behind a plane
    and triangle meshes (a coal BVH); a link pose there is the robot's base pose
    (``RobotData.base``) times forward kinematics. Self-collision: every pair of links that
    are not adjacent (same joint, or parent and child), minus the SRDF's
    ``disable_collisions`` pairs (the package's ``srdf/<urdf name>.srdf`` when there is one);
  none for capsules (they meet at every joint by construction).

What a check says
    :meth:`Checker.check` (``q``, base) gives every pair closer than its margin as a
    :class:`Contact` (link, region or ``self:<link>``, signed distance: negative is
    penetration), nearest first; :meth:`Checker.clearance` the nearest pair and the smallest
    slack (distance minus the pair's margin) in one pass, which is what the plan check and the
    run-time guard use.

Cost
    A pair costs a coal distance call (~2 us between two hulls or a hull and a sphere or a
    plane; tens to hundreds of us against a Slicer mesh of a thousand triangles) only when
    the two could be within ``margin + BROAD_PAD_M`` (50 mm): a ball around each link and each
    region (a plane's signed distance) settles the others, their distance then a lower bound
    (all a clearance needs). A link near a mesh region is asked whether it is within
    ``margin`` plus 50, 25, 12.5 or 0 mm of it (collision queries with a security margin,
    ~10 us each where the mesh's exact distance costs 200-600 us), its distance then the
    largest of those it exceeds; only inside the margin is the exact distance computed (for
    the report). A coal call holds the interpreter lock while it runs, so its cost is what the
    loop may wait for (docs/BENCHMARKS.md, "Collision checking").

How far a link can move: :meth:`CollisionModel.bound`
    ``sum_i |dq_i| R_i``, with ``R_i`` the reach of joint ``i`` (the farthest any point of the
    geometry after it can be from its axis, over every configuration: chain lengths plus the
    geometry's bounding radius; 1 for a prismatic joint), bounds how far any point of any link
    moves between two configurations along the straight segment joining them. A check at ``q``
    with slack ``s`` therefore clears every configuration within bound ``s`` of it (a convex
    set: the segment between two such is in it too). The keyframe plan check advances by it
    (conservative advancement: a sample is checked only when the bound since the last check
    reaches that check's slack), and the run-time guard lets the loop move only within half
    the last verdict's clearance.

Run time: :class:`CollisionGuard`
    The loop never computes a distance. Each tick it offers the setpoint it just wrote to the
    guard (``publish``: O(1), a job for the guard's own worker thread when it is idle); the
    worker checks it and posts a *verdict* (the configuration, its clearance, its slack, the
    nearest pair) by swapping one reference. The loop then:

    - *admits* each new setpoint only when its bound from the last verdict's configuration is
      under half that verdict's clearance (:meth:`CollisionGuard.admit`); otherwise it holds
      the previous setpoint (a late verdict holds the robot, the way a late stream does, and
      the re-entry after it is rate-limited). So whatever the worker's timing, no link gets
      closer than half the clearance the last verdict saw, and a verdict inside the margin
      stops the robot at least a quarter of the margin away;
    - *stops* when a verdict's slack is negative (a link inside its margin):
      ``CollisionGuard.poll`` returns the reason and the robot raises its safety stop
      (STOPPED, or FAULT with ``policy: fault``) with an ALERT ``COLLISION`` naming the link,
      the region and the distance. A Run started inside the margin may move only away: the
      run's threshold is the best slack seen since it started, minus ``ESCAPE_TOLERANCE_M``,
      until the slack is positive again.

    In simulated time (``inline=True``) the check runs in ``publish`` itself, so runs are exact.
"""

from __future__ import annotations

import logging
import math
import threading
import xml.etree.ElementTree as ET
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import coal
import numpy as np
import pinocchio as pin

from occ.core.supervision import Worker
from occ.errors import ConfigError

if TYPE_CHECKING:
    from occ.config import CollisionConfig, FrameConfig, RegionConfig
    from occ.core.data import RobotData
    from occ.core.safety import RobotState
    from occ.kinematics.frame import Frame

__all__ = [
    "CollisionGuard",
    "CollisionModel",
    "Checker",
    "Contact",
    "Region",
    "RegionError",
    "mesh_region",
    "plane_region",
    "regions_from_event",
    "sphere_region",
]

log = logging.getLogger(__name__)

MM = 1e-3
#: the Slicer metadata ``kind`` of a forbidden region for the collision check
REGION_KIND = "forbidden-region"
#: the largest Slicer mesh taken as a region (triangles)
MAX_TRIANGLES = 200_000
#: a pair whose bounding balls are farther apart than its margin plus this is not computed
#: exactly: the balls' distance stands for it (a lower bound)
BROAD_PAD_M = 0.05
#: a mesh region's near pairs: is the distance under margin + each of these x BROAD_PAD_M?
#: (a collision query with that security margin costs ~10 us where the distance costs
#: 200-600 us against a thousand triangles); the exact distance only inside the margin
MESH_LEVELS = (1.0, 0.5, 0.25, 0.125, 0.0)
#: after a Run inside the margin, how much closer than its best the arm may come (m)
ESCAPE_TOLERANCE_M = 0.5e-3


class RegionError(ValueError):
    """A region definition that cannot be used (the message says why)."""


@dataclass(frozen=True, slots=True)
class Contact:
    """A link (or the tool) closer to a region or another link than the margin."""

    link: str
    region: str  # a region's name, or ``self:<link>``
    distance: float  # metres; negative: penetration

    def describe(self) -> str:
        what = (
            f"link {self.region[5:]!r}"
            if self.region.startswith("self:")
            else f"forbidden region {self.region!r}"
        )
        if self.distance < 0.0:
            return f"link {self.link!r} penetrates {what} by {-self.distance / MM:.2f} mm"
        return f"link {self.link!r} is {self.distance / MM:.2f} mm from {what}"


@dataclass(frozen=True)
class Region:
    """A forbidden region, placed in the patient frame (metres)."""

    name: str
    kind: str  # sphere, plane, mesh
    geometry: Any  # a coal.CollisionGeometry
    placement: Any  # coal.Transform3s
    exclude: frozenset[str] = frozenset()
    source: str = "config"  # the Slicer node it came from, or "config"
    #: the broad phase's bound (module docstring, "Cost"): a ball around it (centre x, y, z,
    #: 0, radius), or a plane's (nx, ny, nz, d, NaN)
    bound: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, math.inf)

    def __post_init__(self) -> None:
        g = self.geometry
        if isinstance(g, coal.Halfspace):
            n = g.n
            b = (float(n[0]), float(n[1]), float(n[2]), float(g.d), math.nan)
            object.__setattr__(self, "bound", b)
            return
        g.computeLocalAABB()
        c = self.placement.transform(np.asarray(g.aabb_center, dtype=float))
        r = float(g.aabb_radius)
        object.__setattr__(self, "bound", (float(c[0]), float(c[1]), float(c[2]), 0.0, r))


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
) -> Region:
    """A triangle mesh (vertices in patient mm, triangles as vertex index triples)."""
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
    bvh = coal.BVHModelOBBRSS()
    bvh.beginModel(len(t), len(v))
    bvh.addVertices(v * MM)
    bvh.addTriangles(t)
    bvh.endModel()
    return Region(name, "mesh", bvh, coal.Transform3s(), frozenset(exclude), source)


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


def regions_from_event(event: Any) -> tuple[str, list[Region]] | None:
    """Forbidden regions from 3D Slicer: a message with metadata ``kind=forbidden-region``, or
    None for any other. A Markups point list (POINT): a sphere per visible point (its radius,
    else metadata ``radius``, else 10 mm); a Markups plane (TRANSFORM): the half-space behind
    it, its z axis the normal out of the forbidden side (as the fixtures' planes); a model
    (POLYDATA): its polygons, triangulated, as a mesh. Returns (the definition's name: the
    device name, its regions: none removes it). RegionError for one that cannot be used."""
    meta = event.meta or {}
    if meta.get("kind", "").strip().lower() != REGION_KIND:
        return None
    name = event.device or "region"
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
            return name, []
        return name, [mesh_region(name, pts, tris, source=name)]
    raise RegionError(f"region {name!r}: a {mtype} defines no region (POINT, TRANSFORM, POLYDATA)")


# ------------------------------------------------------------------------------ the model
@dataclass(frozen=True)
class _Link:
    name: str
    index: int  # in the geometry model
    joint: int


@dataclass
class CollisionModel:
    """The arm's collision geometry, its self-collision pairs, and the forbidden regions (an
    immutable tuple swapped whole: :meth:`set_regions`). Thread-safe to share; each thread
    checks with its own :meth:`checker`."""

    model: Any  # pin.Model
    geom: Any  # pin.GeometryModel
    links: tuple[_Link, ...]
    self_pairs: tuple[tuple[int, int], ...]
    reach: tuple[float, ...]  # per joint (q index), metres per unit of q
    margin: float  # metres
    self_margin: float
    base_inv: Any = None  # pin.SE3: the configured base link in the model's root, inverted
    regions: tuple[Region, ...] = ()
    #: bumped by every change of the regions (a plan checked against older ones is stale)
    version: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    # ------------------------------------------------------------------ build
    @classmethod
    def build(
        cls,
        cfg: CollisionConfig,
        frame_cfg: FrameConfig,
        frame: Frame,
    ) -> CollisionModel:
        """From the configuration: the URDF's collision geometry (capsules where it has
        none), the tool, the self pairs, the configured regions. ConfigError naming the key."""
        from occ.kinematics.frame import BUILTIN_MODELS, robots_dir

        model = frame.model
        urdf = frame_cfg.urdf_path()
        if urdf is None:
            assert frame_cfg.model is not None
            urdf = robots_dir() / BUILTIN_MODELS[frame_cfg.model][0]
        dirs = [str(urdf.parent)]
        if frame_cfg.package is not None:
            from occ.config import package_dir

            dirs.insert(0, str(package_dir(frame_cfg.package).parent))
        try:
            geom = pin.buildGeomFromUrdf(
                model, str(urdf), pin.GeometryType.COLLISION, package_dirs=dirs
            )
        except (RuntimeError, ValueError) as err:
            raise ConfigError(
                f"safety.collision: the URDF's collision geometry does not load: {err}"
            ) from err
        if cfg.convex:
            for g in geom.geometryObjects:
                if isinstance(g.geometry, coal.BVHModelBase):
                    g.geometry.buildConvexRepresentation(False)
                    g.geometry = g.geometry.convex
        capsules = geom.ngeoms == 0
        if capsules:
            _add_capsules(model, geom, frame.tip_link, cfg.link_radius_mm * MM)
        if cfg.tool is not None:
            _add_tool(model, geom, frame.tip_link, cfg.tool.length_mm * MM, cfg.tool.radius_mm * MM)
        links = tuple(
            _Link("tool" if g.name == "tool" else _link_name(model, g), i, int(g.parentJoint))
            for i, g in enumerate(geom.geometryObjects)
        )
        names = {lk.name for lk in links}
        for i, rc in enumerate(cfg.regions):
            for ex in rc.exclude_links:
                if ex not in names:
                    raise ConfigError(
                        f"safety.collision.regions[{i}].exclude_links: no link {ex!r} with "
                        f"collision geometry (links: {', '.join(sorted(names))})"
                    )
        base_inv = None
        if frame.base_link is not None:
            fid = model.getFrameId(frame.base_link)
            d = model.createData()
            pin.framesForwardKinematics(model, d, pin.neutral(model))
            base_inv = d.oMf[fid].inverse()
        pairs: tuple[tuple[int, int], ...] = ()
        # capsules between joint origins meet at every joint (an RCM's tool passes through the
        # column's top): their self pairs would be contacts by construction, so none
        if cfg.self_collision and not capsules:
            srdf = Path(str(cfg.srdf)) if cfg.srdf is not None else _package_srdf(urdf)
            pairs = _self_pairs(model, links, _srdf_disabled(srdf) if srdf else set())
        try:
            regions = tuple(region_from_config(rc) for rc in cfg.regions)
        except RegionError as err:
            raise ConfigError(f"safety.collision.regions: {err}") from err
        return cls(
            model=model,
            geom=geom,
            links=links,
            self_pairs=pairs,
            reach=_reach(model, geom),
            margin=cfg.margin_mm * MM,
            self_margin=cfg.self_margin_mm * MM,
            base_inv=base_inv,
            regions=regions,
        )

    # ------------------------------------------------------------------ regions
    def define(self, source: str, regions: Sequence[Region]) -> int:
        """Replace every region from ``source`` (a Slicer node's name) with ``regions`` (none:
        removed); the new version number. Thread-safe: a check in progress keeps the tuple it
        read."""
        with self._lock:
            keep = tuple(r for r in self.regions if r.source != source)
            self.regions = keep + tuple(regions)
            self.version += 1
            return self.version

    def checker(self) -> Checker:
        """A checker with its own pinocchio and coal data, for one thread."""
        return Checker(self)

    def bound(self, qa: Sequence[float], qb: Sequence[float]) -> float:
        """An upper bound of how far any point of any link moves between ``qa`` and ``qb``
        (metres; along the straight segment between them)."""
        s = 0.0
        for a, b, r in zip(qa, qb, self.reach, strict=True):
            s += abs(a - b) * r
        return s

    def step_bound(self, velocities: Sequence[float], period: float) -> float:
        """How far a link point can move in one period at ``velocities`` (m)."""
        return sum(v * period * r for v, r in zip(velocities, self.reach, strict=True))

    def describe(self) -> dict[str, Any]:
        return {
            "links": [lk.name for lk in self.links],
            "self_pairs": len(self.self_pairs),
            "regions": [r.name for r in self.regions],
            "margin_mm": round(self.margin / MM, 3),
            "self_margin_mm": round(self.self_margin / MM, 3),
            "reach_m": [round(r, 4) for r in self.reach],
        }

    def path_check(self) -> PathCheck:
        """The keyframe controller's whole-arm check of a plan (``add_forbidden_check``)."""
        return PathCheck(self)


def _link_name(model: Any, g: Any) -> str:
    name = str(model.frames[g.parentFrame].name) if g.parentFrame < len(model.frames) else ""
    return name or str(g.name)


def _add_capsules(model: Any, geom: Any, tip_link: str, radius: float) -> None:
    """A capsule per link between joint origins (and to the tip) where the URDF has no
    collision geometry."""
    body_of: dict[int, int] = {}
    for fid, f in enumerate(model.frames):
        if f.type == pin.FrameType.BODY and int(f.parentJoint) not in body_of:
            body_of[int(f.parentJoint)] = fid
    segments: list[tuple[int, np.ndarray]] = []
    for j in range(1, model.njoints):
        segments.append((int(model.parents[j]), np.asarray(model.jointPlacements[j].translation)))
    tip = model.frames[model.getFrameId(tip_link)]
    segments.append((int(tip.parentJoint), np.asarray(tip.placement.translation)))
    for k, (parent, t) in enumerate(segments):
        length = float(np.linalg.norm(t))
        if length < 1e-6:
            continue
        z = t / length
        rot = _rotation_to(z)
        placement = pin.SE3(rot, t / 2.0)
        fid = body_of.get(parent, 0)
        obj = pin.GeometryObject(
            f"{model.frames[fid].name}_capsule{k}",
            parent,
            fid,
            placement,
            coal.Capsule(radius, length),
        )
        geom.addGeometryObject(obj)


def _add_tool(model: Any, geom: Any, tip_link: str, length: float, radius: float) -> None:
    fid = model.getFrameId(tip_link)
    tip = model.frames[fid]
    placement = tip.placement * pin.SE3(np.eye(3), np.array([0.0, 0.0, length / 2.0]))
    obj = pin.GeometryObject(
        "tool", int(tip.parentJoint), fid, placement, coal.Capsule(radius, length)
    )
    obj_index = geom.addGeometryObject(obj)
    assert obj_index >= 0


def _rotation_to(z: np.ndarray) -> np.ndarray:
    """A rotation whose z axis is the unit vector ``z``."""
    a = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(a, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.column_stack((x, y, z))


def _package_srdf(urdf: Path) -> Path | None:
    """The package's ``srdf/<urdf stem>.srdf`` beside the URDF's directory, when present."""
    cand = urdf.parent.parent / "srdf" / f"{urdf.stem}.srdf"
    return cand if cand.is_file() else None


def _srdf_disabled(path: Path) -> set[frozenset[str]]:
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as err:
        raise ConfigError(f"safety.collision.srdf: cannot read {path}: {err}") from err
    return {
        frozenset((e.get("link1", ""), e.get("link2", ""))) for e in root.iter("disable_collisions")
    }


def _self_pairs(
    model: Any, links: Sequence[_Link], disabled: set[frozenset[str]]
) -> tuple[tuple[int, int], ...]:
    """Pairs of links neither on the same joint nor parent and child, nor disabled."""
    parents = model.parents
    out = []
    for i, a in enumerate(links):
        for b in links[i + 1 :]:
            if a.joint == b.joint or parents[a.joint] == b.joint or parents[b.joint] == a.joint:
                continue
            if frozenset((a.name, b.name)) in disabled:
                continue
            out.append((a.index, b.index))
    return tuple(out)


def _reach(model: Any, geom: Any) -> tuple[float, ...]:
    """Per joint (q order): the farthest any geometry point after it can be from its origin,
    over every configuration (a revolute joint moves such a point by at most that times its
    angle); 1 for a prismatic joint."""
    # the largest distance from joint j's origin to each geometry, by chain lengths
    radius = []
    for g in geom.geometryObjects:
        g.geometry.computeLocalAABB()
        radius.append(
            float(g.geometry.aabb_radius) + float(np.linalg.norm(g.placement.translation))
        )
    out = []
    for j in range(1, model.njoints):
        kind = str(model.joints[j].shortname())
        if "Prismatic" in kind or kind.startswith("JointModelP"):
            out.append(1.0)
            continue
        r = 0.0
        for gi, g in enumerate(geom.geometryObjects):
            k = int(g.parentJoint)
            chain = 0.0
            while k > j:
                chain += float(np.linalg.norm(model.jointPlacements[k].translation))
                k = int(model.parents[k])
            if k == j:
                r = max(r, chain + radius[gi])
        out.append(r)
    return tuple(out)


# ------------------------------------------------------------------------------ checks
class Checker:
    """Distances on one thread (its own pinocchio and coal data)."""

    def __init__(self, cm: CollisionModel) -> None:
        self.cm = cm
        self.data = cm.model.createData()
        self.gdata = pin.GeometryData(cm.geom)
        self._req = coal.DistanceRequest()
        self._res = coal.DistanceResult()
        self._creq = coal.CollisionRequest()
        self._cres = coal.CollisionResult()
        self._world = [coal.Transform3s() for _ in cm.links]
        self._centres: list[tuple[float, float, float]] = [(0.0, 0.0, 0.0)] * len(cm.links)
        objs = cm.geom.geometryObjects
        self._local = []
        self._radius = []
        for lk in cm.links:
            geo = objs[lk.index].geometry
            geo.computeLocalAABB()
            self._local.append(np.asarray(geo.aabb_center, dtype=float))
            self._radius.append(float(geo.aabb_radius))
        #: pairs whose distance coal computed, and pairs the broad phase settled (last check)
        self.exact = 0
        self.bounded = 0
        self.checks = 0

    def _place(self, q: Sequence[float], base: np.ndarray | None) -> list[Any]:
        cm = self.cm
        qa = np.asarray(q, dtype=float)
        pin.updateGeometryPlacements(cm.model, self.data, cm.geom, self.gdata, qa)
        world = pin.SE3(np.asarray(base, dtype=float)) if base is not None else None
        if cm.base_inv is not None:
            world = cm.base_inv if world is None else world * cm.base_inv
        out = self._world
        centres = self._centres
        local = self._local
        for i, m in enumerate(self.gdata.oMg):
            w = world * m if world is not None else m
            out[i] = coal.Transform3s(w)
            x, y, z = w.act(local[i]).tolist()
            centres[i] = (x, y, z)
        return out

    def pairs(
        self, q: Sequence[float], base: np.ndarray | None = None
    ) -> list[tuple[float, float, str, str]]:
        """Every checked pair at ``q``: (slack = distance - margin, distance, link, region)."""
        self.checks += 1
        cm = self.cm
        tf = self._place(q, base)
        req, res = self._req, self._res
        dist = coal.distance
        objs = cm.geom.geometryObjects
        centres, radius = self._centres, self._radius
        out = []
        exact = bounded = 0
        regions = cm.regions  # one read: a definition swapped meanwhile is for the next check
        near = cm.margin + BROAD_PAD_M
        for lk in cm.links:
            i = lk.index
            g = objs[i].geometry
            cx, cy, cz = centres[i]
            rl = radius[i]
            for r in regions:
                if lk.name in r.exclude:
                    continue
                bx, by, bz, bd, br = r.bound
                if br != br:  # a plane: the ball's signed distance to it
                    low = cx * bx + cy * by + cz * bz - bd - rl
                else:
                    low = math.sqrt((cx - bx) ** 2 + (cy - by) ** 2 + (cz - bz) ** 2) - rl - br
                if low > near:
                    d = low  # a lower bound: far enough not to need the exact distance
                    bounded += 1
                elif r.kind == "mesh":
                    d = self._mesh(g, tf[i], r)
                    exact += 1
                else:
                    res.clear()
                    d = dist(g, tf[i], r.geometry, r.placement, req, res)
                    exact += 1
                out.append((d - cm.margin, d, lk.name, r.name))
        near = cm.self_margin + BROAD_PAD_M
        for a, b in cm.self_pairs:
            (ax, ay, az), (bx, by, bz) = centres[a], centres[b]
            low = math.sqrt((ax - bx) ** 2 + (ay - by) ** 2 + (az - bz) ** 2)
            low -= radius[a] + radius[b]
            if low > near:
                d = low
                bounded += 1
            else:
                res.clear()
                d = dist(objs[a].geometry, tf[a], objs[b].geometry, tf[b], req, res)
                exact += 1
            out.append((d - cm.self_margin, d, cm.links[a].name, f"self:{cm.links[b].name}"))
        self.exact, self.bounded = exact, bounded
        return out

    def _mesh(self, g: Any, tf: Any, r: Region) -> float:
        """A link near a mesh region: the largest of ``margin + level x BROAD_PAD_M`` the
        distance is known to exceed (collision queries with that security margin), or the
        exact distance when it is inside the margin."""
        creq, cres = self._creq, self._cres
        margin = self.cm.margin
        for level in MESH_LEVELS:
            creq.security_margin = margin + level * BROAD_PAD_M
            cres.clear()
            if not coal.collide(g, tf, r.geometry, r.placement, creq, cres):
                return creq.security_margin  # type: ignore[no-any-return]
        res = self._res
        res.clear()
        return coal.distance(g, tf, r.geometry, r.placement, self._req, res)  # type: ignore[no-any-return]

    def check(self, q: Sequence[float], base: np.ndarray | None = None) -> list[Contact]:
        """Every pair closer than its margin at ``q`` (``base``: world <- base, metres; None:
        the identity), nearest first."""
        hits = [Contact(lk, rg, d) for s, d, lk, rg in self.pairs(q, base) if s < 0.0]
        hits.sort(key=lambda c: c.distance)
        return hits

    def clearance(
        self, q: Sequence[float], base: np.ndarray | None = None
    ) -> tuple[float, float, Contact | None]:
        """(the smallest slack, the smallest distance, the pair with the smallest slack) at
        ``q``; (inf, inf, None) when nothing is checked."""
        slack = gap = math.inf
        worst: Contact | None = None
        for s, d, lk, rg in self.pairs(q, base):
            if s < slack:
                slack, worst = s, Contact(lk, rg, d)
            if d < gap:
                gap = d
        return slack, gap, worst


class PathCheck:
    """A keyframe plan's whole-arm check (``KeyframeController.add_forbidden_check``):
    ``check_path(qs, base, pace)`` over the plan's samples, one per loop period, advancing by
    the motion bound (module docstring); None when clear, else (the first sample inside a
    margin, what it hits). Runs on the planner thread with a checker of its own."""

    def __init__(self, cm: CollisionModel) -> None:
        self.cm = cm
        self._checker: Checker | None = None
        self.checked = 0  # samples checked in the last plan

    def check_path(
        self,
        qs: Sequence[Sequence[float]],
        base: np.ndarray,
        pace: Callable[[], None] | None = None,
    ) -> tuple[int, str] | None:
        cm = self.cm
        if self._checker is None:
            self._checker = cm.checker()
        checker = self._checker
        n = len(qs)
        i = 0
        self.checked = 0
        while i < n:
            if pace is not None:
                pace()
            slack, _gap, worst = checker.clearance(qs[i], base)
            self.checked += 1
            if worst is not None and slack < 0.0:
                margin = cm.self_margin if worst.region.startswith("self:") else cm.margin
                return i, f"{worst.describe()} (margin {margin / MM:g} mm)"
            if not math.isfinite(slack):
                return None
            qi = qs[i]
            j = i + 1
            bound = cm.bound
            while j < n and bound(qs[j], qi) < slack:
                j += 1
            i = j
        return None


# ------------------------------------------------------------------------------ run time
@dataclass(frozen=True, slots=True)
class Verdict:
    q: tuple[float, ...]
    base: Any  # the base pose object the check used (identity-compared)
    slack: float
    gap: float
    worst: Contact | None
    version: int


class CollisionGuard:
    """The run-time check (module docstring, "Run time"). The loop calls :meth:`publish`
    (after writing a setpoint), :meth:`admit` (before) and :meth:`poll` (each tick); the
    worker thread calls nothing else."""

    def __init__(
        self,
        cm: CollisionModel,
        *,
        inline: bool = False,
        runtime: bool = True,
        runtime_hz: float | None = None,
        fifo_priority: int | None = None,
        name: str = "occ-collision",
    ) -> None:
        self.cm = cm
        self.inline = inline
        #: what a collision stop is (``safety.collision.policy``)
        self.policy = "hold"
        #: check setpoints at run time (``safety.collision.runtime``); plans are checked anyway
        self.runtime = runtime
        self._every = 1.0 / runtime_hz if runtime_hz else 0.0
        self._next = -math.inf
        self._checker = cm.checker()
        self._worker: Worker | None = (
            None if inline or not runtime else Worker(name, depth=2, fifo_priority=fifo_priority)
        )
        self._busy = False
        self.verdict: Verdict | None = None
        self._threshold = 0.0  # the run's stop threshold on the slack (escape: below 0)
        self._best = math.inf
        self._stopped_for: Verdict | None = None
        self.running = False
        # statistics
        self.verdicts = 0
        self.holds = 0  # setpoints not admitted (no verdict covering them)
        self.stops = 0
        self.last_contact = ""
        self.min_slack = math.inf
        self.worker_failed = ""

    @classmethod
    def build(
        cls,
        cc: CollisionConfig | None,
        frame_cfg: FrameConfig,
        frame: Frame,
        velocities: Sequence[float],
        period: float,
        *,
        real: bool,
        fifo_priority: int | None,
        name: str,
    ) -> CollisionGuard | None:
        """The collision model (the URDF, ``safety.collision`` ``cc``) and its run-time guard
        (inline in simulated time, a worker thread ``name`` of its own on the real clock,
        ``real``); None without ``cc``. ConfigError for a margin a link can cross in one tick
        (``velocities``: the joints' limits, ``period``: the loop's)."""
        if cc is None:
            return None
        cm = CollisionModel.build(cc, frame_cfg, frame)
        step = cm.step_bound(velocities, period)
        if step >= 2.0 * cm.margin:
            # a plan is checked at the loop's samples: between two, a link moves at most
            # `step`, so a margin over half of it keeps every link out of every region
            raise ConfigError(
                f"safety.collision.margin_mm: must exceed half of what a link can move in one "
                f"tick at the velocity limits ({step * 500:.3g} mm), got {cm.margin * 1e3:g}"
            )
        guard = cls(
            cm,
            inline=not real,
            runtime=cc.runtime,
            runtime_hz=cc.runtime_hz,
            fifo_priority=fifo_priority,
            name=name,
        )
        guard.policy = cc.policy
        return guard

    def admitter(self, data: RobotData) -> Callable[[Sequence[float]], bool] | None:
        """What the loop's motion asks before writing a setpoint (:meth:`admit`, with the
        robot's base pose), or None when run-time checking is off."""
        if not self.runtime:
            return None
        return lambda sp: self.admit(sp, data.base)

    def after_control(self, state: RobotState, data: RobotData, now: float) -> str | None:
        """Each tick after the drives were written: entering or leaving RUNNING noted
        (:meth:`on_running`), the reason to stop now if a verdict says so (:meth:`poll`), and
        the new setpoint handed to the worker (run-time checking on, the drives powered)."""
        running = state.value == "RUNNING"
        if running != self.running:
            self.on_running(running)
        why = self.poll()
        if self.runtime and state.value in ("ENABLED", "RUNNING", "STOPPED"):  # powered
            self.publish(data.commanded(), data.base, now)
        return why

    def start(self) -> None:
        if self._worker is not None:
            self._worker.start()

    def stop(self) -> None:
        if self._worker is not None:
            self._worker.stop()

    # ---------------------------------------------------------------- loop thread
    def publish(self, q: Sequence[float], base: Any, now: float | None = None) -> None:
        """The setpoint the drives now hold: checked next (if the worker is idle and, with
        ``runtime_hz``, a verdict is due at ``now``)."""
        if self._busy:
            return
        if now is not None and self._every:
            if now < self._next:
                return
            self._next = now + self._every
        snap = tuple(q)
        if self.inline:
            self._job(snap, base)
            return
        self._busy = True
        assert self._worker is not None
        if not self._worker.submit(lambda: self._job(snap, base)):
            self._busy = False

    def admit(self, sp: Sequence[float], base: Any) -> bool:
        """May the loop write ``sp``? Only within half the last verdict's clearance of its
        configuration (and with the base pose it used)."""
        v = self.verdict
        if (
            v is None
            or v.version != self.cm.version
            or (v.base is not base and not np.array_equal(v.base, base))
        ):  # no verdict for these regions and this base pose (a tracker moved it): hold
            self.holds += 1
            return False
        if self.cm.bound(sp, v.q) < 0.5 * v.gap:
            return True
        self.holds += 1
        return False

    def on_running(self, running: bool) -> None:
        """The robot enters (True) or leaves RUNNING: a run starts with the current slack as
        its best, so one started inside the margin may move away."""
        self.running = running
        v = self.verdict
        self._best = v.slack if (running and v is not None) else math.inf
        self._stopped_for = None

    def poll(self) -> str | None:
        """The reason to stop now (a verdict inside the margin while running), once per
        verdict; None otherwise."""
        v = self.verdict
        if v is None or not self.running or v is self._stopped_for or v.worst is None:
            return None
        if v.slack > self._best:
            self._best = v.slack
        threshold = min(0.0, self._best - ESCAPE_TOLERANCE_M)
        if v.slack >= threshold:
            return None
        self._stopped_for = v
        self.stops += 1
        w = v.worst
        margin = self.cm.self_margin if w.region.startswith("self:") else self.cm.margin
        self.last_contact = f"{w.describe()} (margin {margin / MM:g} mm)"
        return f"collision: {self.last_contact}"

    # ---------------------------------------------------------------- worker thread
    def _job(self, q: tuple[float, ...], base: Any) -> None:
        try:
            version = self.cm.version
            slack, gap, worst = self._checker.clearance(q, base)
            self.verdict = Verdict(q, base, slack, gap, worst, version)
            self.verdicts += 1
            if slack < self.min_slack:
                self.min_slack = slack
        except Exception as err:  # noqa: BLE001 - no verdict: the loop holds, and says why
            self.worker_failed = f"{type(err).__name__}: {err}"
            raise
        finally:
            self._busy = False

    def stats(self) -> dict[str, Any]:
        v = self.verdict
        return {
            **self.cm.describe(),
            "verdicts": self.verdicts,
            "holds": self.holds,
            "stops": self.stops,
            "last_contact": self.last_contact,
            "clearance_mm": None if v is None or not math.isfinite(v.gap) else round(v.gap / MM, 3),
            "min_slack_mm": None
            if not math.isfinite(self.min_slack)
            else round(self.min_slack / MM, 3),
            "worker_failed": self.worker_failed,
        }
