"""Simulated tissue: what the slave's instrument presses on, acting on the simulated drives.

A simulated slave in free space never touches anything, so no force exists to feed back
(issue 27). The config's ``environment`` puts tissue in the patient frame (the frame of 3D
Slicer's ``Tip``, mm), and 3D Slicer can add or move it at run time (:func:`tissue_from_event`:
a Markups point list or plane with the attribute ``kind=tissue``, sent to the slave's operator
port):

``wall``
    tissue behind a plane: a point on its surface and the normal pointing out of it;
``sphere``
    tissue inside a ball: its centre and radius (an organ, a tumour).

Each is a unilateral spring-damper on the penetration depth ``d`` (mm) along the surface
normal ``n`` (out of the tissue)::

    F = max(0, k d + b d') n        (N; d > 0 only)

the Kelvin-Voigt model clamped so that tissue pushes the tool out and never pulls it in (the
same non-negativity Hunt and Crossley's model has, without its depth-dependent damping). The
forces of all shapes add up.

The force acts on the robot the way real tissue does: :class:`Environment` turns it into the
joint efforts ``tau = J(q)^T F`` (the robot's kinematic model, base-frame Jacobian, with the
force rotated from the patient frame into the base frame), which the ``sim`` driver adds to its
joint dynamics. A position servo then holds the tool in the tissue against that load: it
yields by ``tau / kp`` (tenths of a millimetre at the shipped slave's stiffness), and the effort
it reports is the one that balances the load, as a real drive's current does. The slave's
force source ``effort`` (teleop-slave ``force``) estimates the tip force from those efforts;
:attr:`Environment.force_n` is the truth it is measured against.

Loop thread only (the ``sim`` driver calls :meth:`Environment.efforts` from its integrator).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from occ.config import ContactConfig

__all__ = ["Contact", "Environment"]

Vec3 = tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class Contact:
    """One shape of tissue (patient frame, mm; see the module docstring)."""

    name: str
    kind: str  # "wall" or "sphere"
    point: Vec3
    normal: Vec3  # unit, out of the tissue (wall)
    radius: float
    stiffness: float  # N/mm
    damping: float  # N s/mm

    @classmethod
    def from_config(cls, c: ContactConfig) -> Contact:
        nx, ny, nz = c.normal
        k = math.sqrt(nx * nx + ny * ny + nz * nz)
        return cls(
            c.name, c.kind, tuple(c.point_mm), (nx / k, ny / k, nz / k),  # type: ignore[arg-type]
            c.radius_mm, c.stiffness, c.damping,
        )  # fmt: skip

    def depth(self, p: Sequence[float]) -> tuple[float, Vec3]:
        """Penetration depth (mm, > 0 inside the tissue) of point ``p`` and the outward normal
        there."""
        if self.kind == "wall":
            n = self.normal
            d = -sum((p[i] - self.point[i]) * n[i] for i in range(3))
            return d, n
        r = [p[i] - self.point[i] for i in range(3)]
        dist = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
        if dist == 0.0:
            return self.radius, (0.0, 0.0, 1.0)  # the centre: any direction is out
        return self.radius - dist, (r[0] / dist, r[1] / dist, r[2] / dist)

    def force(self, p: Sequence[float], v: Sequence[float]) -> tuple[Vec3, float]:
        """The force on the tool (N, patient frame) at ``p`` (mm) moving at ``v`` (mm/s), and
        the penetration depth (mm; <= 0: no contact, no force)."""
        d, n = self.depth(p)
        if d <= 0.0:
            return (0.0, 0.0, 0.0), d
        rate = -(v[0] * n[0] + v[1] * n[1] + v[2] * n[2])  # deeper per second
        mag = self.stiffness * d + self.damping * rate
        if mag <= 0.0:
            return (0.0, 0.0, 0.0), d
        return (mag * n[0], mag * n[1], mag * n[2]), d


def tissue_from_event(event: Any) -> tuple[str, list[Contact]] | None:
    """Tissue defined in 3D Slicer: a message with metadata ``kind=tissue``, or None for any
    other. A Markups point list (POINT) is spheres (each visible point's radius, else
    ``radius`` metadata, else 10 mm); a Markups plane sent as a TRANSFORM is a wall through its
    origin whose normal (out of the tissue) is the transform's z axis, as a forbidden plane's
    is for the fixtures. ``stiffness`` (N/mm, default 0.5) and ``damping`` (N s/mm) from the
    metadata. Returns (the definition's name: its device name, the contacts; none when every
    point was removed). ValueError for a definition that is no tissue."""
    meta = event.meta or {}
    if meta.get("kind") != "tissue":
        return None
    name = event.device or "tissue"

    def number(key: str, default: float, low: float) -> float:
        try:
            v = float(meta.get(key, default))
        except ValueError:
            raise ValueError(f"tissue {name!r}: {key} {meta.get(key)!r} is not a number") from None
        if not (math.isfinite(v) and v >= low):
            raise ValueError(f"tissue {name!r}: {key} {v} must be >= {low}")
        return v

    k = number("stiffness", 0.5, 0.0)
    b = number("damping", 0.0, 0.0)
    if event.kind == "POINT":
        radius = number("radius", 10.0, 1e-9)
        out = []
        for i, p in enumerate(x for x in event.points if x.visible):
            r = float(p.radius) if p.radius > 0.0 else radius
            c = tuple(float(v) for v in p.position)
            if not all(math.isfinite(v) for v in (*c, r)):
                raise ValueError(f"tissue {name!r}: point {i} is not a point")
            out.append(Contact(f"{name}:{i}", "sphere", c, (0.0, 0.0, 1.0), r, k, b))  # type: ignore[arg-type]
        return name, out
    if event.kind == "TRANSFORM":
        m = np.asarray(event.matrix, dtype=float)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise ValueError(f"tissue {name!r}: not a transform")
        n = m[:3, 2]
        norm = float(np.linalg.norm(n))
        if norm == 0.0:
            raise ValueError(f"tissue {name!r}: the plane's z axis is zero")
        point = tuple(float(v) for v in m[:3, 3])
        normal = tuple(float(v) / norm for v in n)
        return name, [Contact(name, "wall", point, normal, 0.0, k, b)]  # type: ignore[arg-type]
    raise ValueError(f"tissue {name!r}: a {event.kind} defines no tissue (POINT, TRANSFORM)")


class Environment:
    """The simulated world of one robot: its tissue and what it does to the joints.

    ``base()`` gives the robot's base pose in the patient frame (4x4, metres), read at each
    evaluation (a tracker may move it); ``frame`` is the robot's kinematic model.
    """

    def __init__(
        self,
        contacts: Sequence[Contact],
        frame: Any,
        base: Callable[[], np.ndarray],
    ) -> None:
        self.contacts = list(contacts)
        self.frame = frame
        self._base = base
        #: the last contact force on the tool (N, patient frame) and each shape's depth (mm)
        self.force_n: Vec3 = (0.0, 0.0, 0.0)
        self.depth_mm: dict[str, float] = {c.name: -math.inf for c in self.contacts}
        self.in_contact = False
        self.evaluations = 0
        self.definitions = 0
        self.peak_force_n = 0.0

    def tip(self, q: Sequence[float]) -> tuple[Vec3, np.ndarray]:
        """The tool tip in the patient frame (mm) at joint positions ``q``, and the base pose."""
        b = self._base()
        x, y, z = self.frame.tip_position(q)
        p = b[:3, :3] @ np.array([x, y, z]) + b[:3, 3]
        return (float(p[0] * 1e3), float(p[1] * 1e3), float(p[2] * 1e3)), b

    def efforts(self, q: Sequence[float], qd: Sequence[float]) -> list[float] | None:
        """The joint efforts the tissue applies at ``q`` moving at ``qd`` (``J^T F``), or None
        when the tool touches nothing (the common case: no Jacobian computed)."""
        self.evaluations += 1
        p, b = self.tip(q)
        jac: np.ndarray | None = None
        v: Vec3 = (0.0, 0.0, 0.0)
        fx = fy = fz = 0.0
        touching = False
        for c in self.contacts:
            d, _n = c.depth(p)
            self.depth_mm[c.name] = d
            if d <= 0.0:
                continue
            if jac is None:  # the tip velocity (patient mm/s), for the damping
                jac = self.frame.jacobian(q)[:3]
                vb = b[:3, :3] @ (jac @ np.asarray(qd, dtype=float)) * 1e3
                v = (float(vb[0]), float(vb[1]), float(vb[2]))
            f, _d = c.force(p, v)
            fx, fy, fz = fx + f[0], fy + f[1], fz + f[2]
            touching = True
        self.force_n = (fx, fy, fz)
        self.in_contact = touching
        if not touching or jac is None:
            return None
        mag = math.sqrt(fx * fx + fy * fy + fz * fz)
        if mag > self.peak_force_n:
            self.peak_force_n = mag
        fb = b[:3, :3].T @ np.array([fx, fy, fz])  # into the base frame
        return [float(t) for t in jac.T @ fb]

    def define(self, name: str, contacts: Sequence[Contact]) -> None:
        """Replace the tissue named ``name`` (a Slicer definition: its contacts ``name`` and
        ``name:i``) with ``contacts`` (none: removed)."""
        keep = [c for c in self.contacts if c.name != name and not c.name.startswith(name + ":")]
        self.contacts = keep + list(contacts)
        self.depth_mm = {c.name: -math.inf for c in self.contacts}
        self.definitions += 1

    def stats(self) -> dict[str, Any]:
        return {
            "contacts": [c.name for c in self.contacts],
            "definitions": self.definitions,
            "force_n": [round(v, 4) for v in self.force_n],
            "in_contact": self.in_contact,
            "depth_mm": {k: round(v, 4) for k, v in self.depth_mm.items() if math.isfinite(v)},
            "peak_force_n": round(self.peak_force_n, 4),
        }
