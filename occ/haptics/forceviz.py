"""The slave's contact force made visible: what 3D Slicer (and ROS 2, and a recording) is sent.

``teleop-slave`` with ``force`` offers the output source ``force`` (issue 27, "Visible"); what it
sends depends on the output's type:

``TRANSFORM`` (3D Slicer: a linear transform node)
    Origin at the tool tip (the ``Tip`` Slicer shows: patient frame, mm). Its z axis is the
    force's direction, scaled to the force's length in mm (``display_mm_per_n`` x |F|); x and y
    are unit vectors at right angles to it. A model drawn along +z from the origin, 1 mm long
    (a cylinder or an arrow of height 1), put under this transform in Slicer's Data module,
    becomes an arrow from the tip, as long as the force. SlicerOpenIGTLink copies the 3x4
    matrix into the node as it is, scale included (OpenIGTLinkIO's
    ``igtlioTransformConverter::fromIGTL`` and ``vtkMRMLIGTLConnectorNode`` setting it with
    ``SetMatrixTransformToParent``; read 2026-11). Below :data:`MIN_LENGTH_MM` the z axis
    keeps that length so the matrix stays invertible (Slicer inverts transforms, e.g. to move
    a node out from under one); the force itself is in the metadata.
``POLYDATA`` (3D Slicer: a model node, shown at once)
    An arrow mesh in the patient frame: a shaft and a cone from the tip along the force,
    ``display_mm_per_n`` mm per N, closed, faces outward. SlicerOpenIGTLink makes a model node
    with display nodes for a new POLYDATA device and replaces its mesh with each message. No
    force (shorter than :data:`MIN_LENGTH_MM`, or of no finite length) is a mesh without
    points: the arrow disappears, it never stays drawn with a force that is gone.
``SENSOR`` or ``NDARRAY``
    The three components, N, patient frame (SENSOR's unit field N; NDARRAY in header v2:
    metadata ``unit``).

Every one carries, in header v2, the metadata ``force_n`` (``fx,fy,fz``, N, patient frame, 4
decimals: what the return channel sends the master), ``force_mag_n``, ``source`` (the force
source used, ``none`` when no source is healthy), ``frame`` (``patient``) and ``mm_per_n``; with
a 6-axis sensor, ``torque_nm`` too (``tx,ty,tz``, N m about the sensor's origin, patient frame).
``MRMLNodeName`` is the MRML node *tag* (``LinearTransform``, ``Model``): SlicerOpenIGTLink
reads that key as the class of the node to create for a POLYDATA, and sends its own nodes' tags
in it.

Which force: the one the slave sends its master on the return channel (``SlaveForce``'s last
estimate, occ/haptics/forces.py). The estimate is made once per return sample; when none was made
since this output last sent (no master streaming, so no return channel), the source makes one
itself, so Slicer is never shown a force older than its own period.

Pure functions of numbers here (:func:`force_matrix`, :func:`arrow_mesh`); :class:`ForceView`
is the source the controller hands the output scheduler.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from occ.errors import OCCError
from occ.events import MeshOut, TransformOut, VectorOut

if TYPE_CHECKING:
    from occ.net.packers import Target as Output

__all__ = [
    "MIN_LENGTH_MM",
    "TYPES",
    "ForceView",
    "arrow_mesh",
    "check_outputs",
    "force_matrix",
    "parse_force",
]

Vec3 = tuple[float, float, float]

#: an arrow shorter than this (mm) is no arrow (the TRANSFORM keeps this length on its z axis)
MIN_LENGTH_MM = 1e-3
#: sides of the arrow's shaft and cone
SIDES = 12
#: the output types the source ``force`` can be sent as
TYPES = ("TRANSFORM", "POLYDATA", "SENSOR", "NDARRAY")


def _basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors at right angles to the unit vector ``d`` and to each other, (x, y)
    with x cross y = d (a right-handed frame whose z axis is ``d``)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, d)
    x /= np.linalg.norm(x)
    y = np.cross(d, x)
    return x, y


def force_matrix(tip_mm: Vec3, force_n: Vec3, mm_per_n: float) -> np.ndarray:
    """The TRANSFORM's 4x4 (mm): origin ``tip_mm``, z axis the force scaled to its length in
    mm (at least :data:`MIN_LENGTH_MM`), x and y unit and at right angles (module docstring).
    No force (or one whose length is not finite): the identity rotation with z at the minimum
    length."""
    f = np.asarray(force_n, dtype=float)
    mag = float(np.linalg.norm(f))
    length = mag * mm_per_n
    m = np.eye(4)
    if MIN_LENGTH_MM <= length < math.inf:  # not NaN either
        d = f / mag
        x, y = _basis(d)
        m[:3, 0], m[:3, 1], m[:3, 2] = x, y, d * length
    else:
        m[2, 2] = MIN_LENGTH_MM
    m[:3, 3] = tip_mm
    return m


def arrow_mesh(
    tip_mm: Vec3, force_n: Vec3, mm_per_n: float, sides: int = SIDES
) -> tuple[np.ndarray, tuple[tuple[int, ...], ...]]:
    """An arrow from ``tip_mm`` along the force, ``mm_per_n`` mm per N: (points (n, 3) mm,
    polygons). A closed surface, every face counter-clockwise seen from outside: the base cap,
    the shaft, the cone's underside (a ring between shaft and cone) and the cone. The shaft's
    radius is 4 % of the length (0.2 to 1 mm), the cone's 2.5 times that, the cone 30 % of the
    length (at most 8 mm). No points and no faces when the arrow is shorter than
    :data:`MIN_LENGTH_MM` or its length is not finite (a force of NaN, or too large)."""
    f = np.asarray(force_n, dtype=float)
    mag = float(np.linalg.norm(f))
    length = mag * mm_per_n
    if not MIN_LENGTH_MM <= length < math.inf:  # also NaN
        return np.zeros((0, 3)), ()
    d = f / mag
    x, y = _basis(d)
    origin = np.asarray(tip_mm, dtype=float)
    r_shaft = min(max(0.04 * length, 0.2), 1.0)
    r_head = 2.5 * r_shaft
    head = min(0.3 * length, 8.0)
    neck = length - head
    angles = 2.0 * math.pi * np.arange(sides) / sides
    ring = np.outer(np.cos(angles), x) + np.outer(np.sin(angles), y)  # unit, counter-clockwise
    base = origin + r_shaft * ring
    shaft_top = origin + neck * d + r_shaft * ring
    head_base = origin + neck * d + r_head * ring
    apex = origin + length * d
    points = np.vstack([base, shaft_top, head_base, apex, origin])
    b, s, h, a, c = 0, sides, 2 * sides, 3 * sides, 3 * sides + 1
    polys: list[tuple[int, ...]] = []
    for i in range(sides):
        j = (i + 1) % sides
        polys.append((c, b + j, b + i))  # base cap, facing -d
        polys.append((b + i, b + j, s + j, s + i))  # shaft
        polys.append((s + i, s + j, h + j, h + i))  # the cone's underside, facing -d
        polys.append((h + i, h + j, a))  # cone
    return points, tuple(polys)


def parse_force(text: str | None) -> Vec3 | None:
    """``"fx,fy,fz"`` (metadata ``force_n``) as three finite floats, else None."""
    if text is None:
        return None
    parts = text.split(",")
    if len(parts) != 3:
        return None
    try:
        fx, fy, fz = (float(v) for v in parts)
    except ValueError:
        return None
    if not (math.isfinite(fx) and math.isfinite(fy) and math.isfinite(fz)):
        return None
    return (fx, fy, fz)


def check_outputs(config: Any, has_force: bool) -> list[tuple[tuple[str | int, ...], str]]:
    """``teleop-slave``'s check (``occd --check``): every output of source ``force`` needs the
    controller's ``force`` and a type that carries it."""
    problems: list[tuple[tuple[str | int, ...], str]] = []
    for iface in config.interfaces:
        for oc in iface.outputs:
            if oc.source != "force":
                continue
            where = f"interface {iface.name!r}, output {oc.device!r}"
            if not has_force:
                problems.append(
                    (("force",), f"{where}: source 'force' needs the controller's force")
                )
            elif oc.type not in TYPES:
                problems.append(
                    (("force",), f"{where}: source 'force' goes as {', '.join(TYPES)}, "
                     f"not {oc.type}")
                )  # fmt: skip
    return problems


class ForceView:
    """The output source ``force`` of ``teleop-slave`` (module docstring). ``force`` is the
    controller's ``SlaveForce``, ``data`` its ``RobotData``, ``ctx`` its context."""

    def __init__(self, force: Any, data: Any, ctx: Any, mm_per_n: float) -> None:
        self.force = force
        self.data = data
        self.ctx = ctx
        self.mm_per_n = mm_per_n
        self._seen: dict[int, int] = {}  # per output: the estimates made when it last sent
        #: estimates this source made itself (no return channel running)
        self.own_estimates = 0
        self.sent = 0

    def current(self, out: Output, now: float) -> Vec3:
        """The force to show now: the return channel's last estimate, or a new one when none
        was made since this output last sent."""
        force, data, ctx = self.force, self.data, self.ctx
        made = force.estimates_made
        if made == 0 or self._seen.get(id(out)) == made:
            self.own_estimates += 1
            force.estimate(
                now, ctx.frame, data.q, data.qdot, data.effort, data.base,
                lambda: data.tip[:3, :3],
            )  # fmt: skip
            made = force.estimates_made
        self._seen[id(out)] = made
        fx, fy, fz = force.force_n
        return (float(fx), float(fy), float(fz))

    def meta(self, f: Vec3, tag: str | None = None) -> Mapping[str, str]:
        mag = math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2])
        out = {
            "force_n": f"{f[0]:.4f},{f[1]:.4f},{f[2]:.4f}",
            "force_mag_n": f"{mag:.4f}",
            "source": self.force.used or "none",
            "frame": "patient",
            "mm_per_n": f"{self.mm_per_n:g}",
        }
        t = self.force.torque_nm
        if t is not None:  # a 6-axis sensor's torque (N m, patient frame): old readers skip it
            out["torque_nm"] = f"{t[0]:.5f},{t[1]:.5f},{t[2]:.5f}"
        if tag is not None:
            out["MRMLNodeName"] = tag
        return out

    def __call__(self, out: Output, now: float) -> VectorOut | TransformOut | MeshOut:
        if out.type not in TYPES:
            raise OCCError(f"output source 'force' goes as {', '.join(TYPES)}, not {out.type}")
        f = self.current(out, now)
        stamp = self.ctx.clock.wall_time()
        v2 = out.header_version == 2
        self.sent += 1
        if out.type in ("SENSOR", "NDARRAY"):
            return VectorOut(f, stamp, "N", self.meta(f))
        tip = self.data.world_tip()
        tip_mm = (tip[0, 3] * 1e3, tip[1, 3] * 1e3, tip[2, 3] * 1e3)
        if out.type == "TRANSFORM":
            return TransformOut(
                force_matrix(tip_mm, f, self.mm_per_n),
                stamp,
                self.meta(f, "LinearTransform") if v2 else None,
            )
        points, polys = arrow_mesh(tip_mm, f, self.mm_per_n)
        return MeshOut(
            points.astype(np.float32),
            stamp,
            polygons=polys,
            meta=self.meta(f, "Model") if v2 else None,
        )

    def stats(self) -> dict[str, Any]:
        return {"sent": self.sent, "own_estimates": self.own_estimates}
