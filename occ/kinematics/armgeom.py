"""An arm's collision geometry from its URDF, for occ/kinematics/collision.py: the robot's own arm
and the other arms of its cell (peers) are built by the same rules.

- The links' collision geometry (``pin.buildGeomFromUrdf``, meshes found through the URDF's
  package), each mesh as its convex hull when asked (it contains the mesh: no contact missed);
  a URDF without collision geometry gets a capsule per link joining the joint origins (and the
  tip), of a given radius; an optional tool capsule along the tip link's z axis.
- The reach of each joint (what :meth:`CollisionModel.bound` multiplies), the configured base
  link's placement (inverted: a base pose is the base link's, not the URDF root's), the SRDF's
  disabled pairs and the self pairs.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import coal
import numpy as np
import pinocchio as pin

from occ.errors import ConfigError

if TYPE_CHECKING:
    from occ.config import FrameConfig
    from occ.kinematics.frame import Frame

__all__ = [
    "ArmGeometry",
    "ArmLink",
    "load_arm",
    "package_srdf",
    "rotation_to",
    "self_pairs",
    "srdf_disabled",
    "urdf_of",
]


@dataclass(frozen=True)
class ArmLink:
    name: str
    index: int  # in the geometry model
    joint: int


@dataclass(frozen=True)
class ArmGeometry:
    """One arm's collision geometry (what :func:`load_arm` builds)."""

    model: Any  # pin.Model
    geom: Any  # pin.GeometryModel
    links: tuple[ArmLink, ...]
    reach: tuple[float, ...]  # per joint (q index), metres per unit of q
    base_inv: Any  # pin.SE3: the configured base link in the model's root, inverted; or None
    urdf: Path
    capsules: bool  # the URDF had no collision geometry: capsules joined at every joint


def urdf_of(frame_cfg: FrameConfig) -> Path:
    """The URDF a FrameConfig names (a built-in model's shipped file included)."""
    from occ.kinematics.frame import BUILTIN_MODELS, robots_dir

    urdf = frame_cfg.urdf_path()
    if urdf is None:
        assert frame_cfg.model is not None
        urdf = robots_dir() / BUILTIN_MODELS[frame_cfg.model][0]
    return urdf


def load_arm(
    frame_cfg: FrameConfig,
    frame: Frame,
    *,
    convex: bool,
    link_radius: float,
    tool: tuple[float, float] | None = None,
    key: str = "safety.collision",
) -> ArmGeometry:
    """The collision geometry of the arm of ``frame_cfg`` (its kinematics ``frame``): hulls
    with ``convex``, capsules of ``link_radius`` (m) where the URDF has none, the tool capsule
    ``tool`` = (length, radius) in metres. ConfigError naming ``key`` when it does not load."""
    model = frame.model
    urdf = urdf_of(frame_cfg)
    dirs = [str(urdf.parent)]
    if frame_cfg.package is not None:
        from occ.config import package_dir

        dirs.insert(0, str(package_dir(frame_cfg.package).parent))
    try:
        geom = pin.buildGeomFromUrdf(
            model, str(urdf), pin.GeometryType.COLLISION, package_dirs=dirs
        )
    except (RuntimeError, ValueError) as err:
        raise ConfigError(f"{key}: the URDF's collision geometry does not load: {err}") from err
    if convex:
        for g in geom.geometryObjects:
            if isinstance(g.geometry, coal.BVHModelBase):
                g.geometry.buildConvexRepresentation(False)
                g.geometry = g.geometry.convex
    capsules = geom.ngeoms == 0
    if capsules:
        _add_capsules(model, geom, frame.tip_link, link_radius)
    if tool is not None:
        _add_tool(model, geom, frame.tip_link, tool[0], tool[1])
    links = tuple(
        ArmLink("tool" if g.name == "tool" else _link_name(model, g), i, int(g.parentJoint))
        for i, g in enumerate(geom.geometryObjects)
    )
    base_inv = None
    if frame.base_link is not None:
        fid = model.getFrameId(frame.base_link)
        d = model.createData()
        pin.framesForwardKinematics(model, d, pin.neutral(model))
        base_inv = d.oMf[fid].inverse()
    return ArmGeometry(model, geom, links, _reach(model, geom), base_inv, urdf, capsules)


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
        rot = rotation_to(z)
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


def rotation_to(z: np.ndarray) -> np.ndarray:
    """A rotation whose z axis is the unit vector ``z``."""
    a = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(a, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.column_stack((x, y, z))


def package_srdf(urdf: Path) -> Path | None:
    """The package's ``srdf/<urdf stem>.srdf`` beside the URDF's directory, when present."""
    cand = urdf.parent.parent / "srdf" / f"{urdf.stem}.srdf"
    return cand if cand.is_file() else None


def srdf_disabled(path: Path) -> set[frozenset[str]]:
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as err:
        raise ConfigError(f"safety.collision.srdf: cannot read {path}: {err}") from err
    return {
        frozenset((e.get("link1", ""), e.get("link2", ""))) for e in root.iter("disable_collisions")
    }


def self_pairs(
    model: Any, links: Sequence[ArmLink], disabled: set[frozenset[str]]
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
