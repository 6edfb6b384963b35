"""Virtual fixtures: the force a haptic master displays to keep the tool where it may go.

Pure computation on plain floats (no robot, no loop, no IGTL): the master controller calls
:meth:`FixtureSet.force` once a tick with the tool position (mm, the master's frame) and the
tick's duration, and writes the returned force (N) to its haptic driver. Definitions (what
3D Slicer or a script sends, in the master's or the patient's frame) become a set in
:mod:`occ.haptics.fixture_defs`; this module only knows primitives in the master's frame.

Primitives (every one with a stiffness ``k`` in N/mm and an optional damping ``b`` in N s/mm)

- **accessible sphere** (the OCC paper, Arata et al. 2010): the *accessible area* is the union
  of every accessible sphere of the set. Inside it no force; outside, a spring toward its
  surface. For one sphere with centre Ps and radius r, the tool at Pe and D = Ps - Pe, this is
  the paper's law: f = k (|D| - r) when |D| > r, F = f D / |D|.
- **forbidden sphere**: a region the tool must not enter; a spring out of it while inside.
- **forbidden plane** (the SAW's forbidden-region fixtures bounded by planes): a point and an
  outward unit normal; the half-space behind the plane is forbidden.
- **guide** (the SAW's guidance fixtures): a line (two points) or a polyline the tool is
  pulled onto: a spring toward the nearest point of the path.

The proxy (god-object)
    Each contact keeps a proxy point that stays on the allowed side, and the force is the
    spring between the proxy and the tool, ``k (proxy - tool)``. When the tool leaves the
    accessible area the proxy starts where the tool left it (the exit point on the segment from
    the last free position to the tool: the paper's proxy-based entry point), and from then on
    slides toward the nearest point of *its* sphere, by at most ``slide_mm`` per tick. It
    changes sphere only when it lies inside another one whose surface is nearer the tool, so the
    force stays continuous and points back to where the tool left, instead of jumping to
    whichever sphere happens to be nearest (the naive rule: across the bisector between two
    spheres its direction flips in one tick). The slide limit spreads a change of contact
    sphere, or a corner of a guide, over several ticks: the force moves by at most ``k`` x
    ``slide_mm`` per tick beyond what the tool's own motion causes. A forbidden sphere's proxy
    enters at the first intersection of that segment with the sphere and slides on its surface
    the same way (the tool pushed past the centre does not pop through in one tick). A plane
    needs no memory: its proxy is the tool's projection onto it.

Damping acts along the spring only and only in contact (free motion stays free): the normal
component of the tool's velocity (from two successive positions) times ``b``, opposed.
The sum over every contact is clamped to ``max_force_n`` (default 10 N, the paper's figure:
its motion test displayed at most 10 N).

Cost: per tick, a few float operations per primitive (``benchmarks/bench_fixtures.py``;
docs/BENCHMARKS.md has the figures for 1, 10 and 100 primitives).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar, Literal, NamedTuple, Self

__all__ = [
    "AccessibleSphere",
    "Contact",
    "FixtureSet",
    "ForbiddenPlane",
    "ForbiddenSphere",
    "Guide",
    "Primitive",
    "Vec3",
]

Vec3 = tuple[float, float, float]
Kind = Literal["accessible", "forbidden", "plane", "guide"]

#: Default clamp of the displayed force (N): the OCC paper's motion test peaked at 10 N.
DEFAULT_MAX_FORCE_N = 10.0
#: Default longest proxy slide per tick (mm): 1 mm a tick is 1 m/s at 1 kHz, far above a hand.
DEFAULT_SLIDE_MM = 1.0
_EPS = 1e-9


def _bad(what: str, why: str) -> ValueError:
    return ValueError(f"{what}: {why}")


def _gains(k: float, b: float, what: str) -> tuple[float, float]:
    k, b = float(k), float(b)
    if not (0.0 <= k < math.inf and 0.0 <= b < math.inf):
        raise _bad(what, f"stiffness and damping must be finite and >= 0 (got {k}, {b})")
    return k, b


def _vec(v: Sequence[float], what: str) -> Vec3:
    if len(v) != 3:
        raise _bad(what, f"expected (x, y, z), got {tuple(v)!r}")
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise _bad(what, f"not finite: {(x, y, z)!r}")
    return (x, y, z)


# Primitives are named tuples (immutable, compared by value, and cheap to build: a definition
# of 64 spheres is compiled on the loop thread), validated in __new__.
class _SphereFields(NamedTuple):
    centre: Vec3
    radius: float
    stiffness: float
    damping: float
    name: str


class _Sphere(_SphereFields):
    __slots__ = ()
    kind: ClassVar[Kind]

    def __new__(
        cls,
        centre: Sequence[float],
        radius: float,
        stiffness: float = 1.0,
        damping: float = 0.0,
        name: str = "",
    ) -> Self:
        what = f"sphere {name!r}"
        c = _vec(centre, what)
        r = float(radius)
        if not 0.0 < r < math.inf:
            raise _bad(what, f"radius must be > 0, got {radius!r}")
        k, b = _gains(stiffness, damping, what)
        return super().__new__(cls, c, r, k, b, name)

    @classmethod
    def _trusted(
        cls, centre: Vec3, radius: float, stiffness: float, damping: float, name: str
    ) -> Self:
        """Built from numbers already checked (occ.haptics.fixture_defs), without checking again."""
        return tuple.__new__(cls, (centre, radius, stiffness, damping, name))


class AccessibleSphere(_Sphere):
    """Part of the accessible area (the union of all such spheres). Lengths in mm, stiffness
    N/mm, damping N s/mm."""

    __slots__ = ()
    kind: ClassVar[Kind] = "accessible"


class ForbiddenSphere(_Sphere):
    """A sphere the tool must not enter."""

    __slots__ = ()
    kind: ClassVar[Kind] = "forbidden"


class _PlaneFields(NamedTuple):
    point: Vec3
    normal: Vec3
    stiffness: float
    damping: float
    name: str


class ForbiddenPlane(_PlaneFields):
    """The half-space behind ``point`` along ``-normal`` is forbidden (the normal points to
    the allowed side; it is normalised here)."""

    __slots__ = ()
    kind: ClassVar[Kind] = "plane"

    def __new__(
        cls,
        point: Sequence[float],
        normal: Sequence[float],
        stiffness: float = 1.0,
        damping: float = 0.0,
        name: str = "",
    ) -> Self:
        what = f"plane {name!r}"
        p = _vec(point, what)
        nx, ny, nz = _vec(normal, what)
        n = math.sqrt(nx * nx + ny * ny + nz * nz)
        if not n > 1e-9:
            raise _bad(what, "the normal is zero")
        k, b = _gains(stiffness, damping, what)
        return super().__new__(cls, p, (nx / n, ny / n, nz / n), k, b, name)


class _GuideFields(NamedTuple):
    points: tuple[Vec3, ...]
    stiffness: float
    damping: float
    name: str


class Guide(_GuideFields):
    """A line (two points) or polyline (more) the tool is pulled onto. Points in mm."""

    __slots__ = ()
    kind: ClassVar[Kind] = "guide"

    def __new__(
        cls,
        points: Sequence[Sequence[float]],
        stiffness: float = 1.0,
        damping: float = 0.0,
        name: str = "",
    ) -> Self:
        what = f"guide {name!r}"
        pts = tuple(_vec(p, what) for p in points)
        if len(pts) < 2:
            raise _bad(what, "needs at least two points (x, y, z)")
        if all(p == pts[0] for p in pts):
            raise _bad(what, "its points are all the same")
        k, b = _gains(stiffness, damping, what)
        return super().__new__(cls, pts, k, b, name)


Primitive = AccessibleSphere | ForbiddenSphere | ForbiddenPlane | Guide


@dataclass(slots=True)
class Contact:
    """One contact's state, for display and tests: which primitive, its proxy (mm), the
    force it adds (N, before the clamp)."""

    name: str
    kind: str
    proxy: Vec3
    force: Vec3


# ------------------------------------------------------------------------------ geometry
def _project_sphere(x: float, y: float, z: float, s: tuple[float, ...]) -> Vec3 | None:
    """The point of sphere ``s`` (cx, cy, cz, r, ...) nearest to (x, y, z); None at the
    centre (every point is as near)."""
    cx, cy, cz, r = s[0], s[1], s[2], s[3]
    dx, dy, dz = x - cx, y - cy, z - cz
    d = math.sqrt(dx * dx + dy * dy + dz * dz)
    if d < _EPS:
        return None
    f = r / d
    return (cx + dx * f, cy + dy * f, cz + dz * f)


def _exit_t(p: Vec3, q: Vec3, s: tuple[float, ...], first: bool) -> float:
    """Parameter t in [0, 1] where the segment p -> q crosses sphere ``s``: the larger root
    (leaving it, ``first`` False) or the smaller (entering it, ``first`` True)."""
    cx, cy, cz, r = s[0], s[1], s[2], s[3]
    dx, dy, dz = q[0] - p[0], q[1] - p[1], q[2] - p[2]
    fx, fy, fz = p[0] - cx, p[1] - cy, p[2] - cz
    a = dx * dx + dy * dy + dz * dz
    if a < _EPS:
        return 0.0
    b = 2.0 * (fx * dx + fy * dy + fz * dz)
    c = fx * fx + fy * fy + fz * fz - r * r
    disc = b * b - 4.0 * a * c
    if disc < 0.0:
        return 0.0 if first else 1.0
    sq = math.sqrt(disc)
    t = (-b - sq) / (2.0 * a) if first else (-b + sq) / (2.0 * a)
    return 0.0 if t < 0.0 else 1.0 if t > 1.0 else t


def _slide(p: Vec3, target: Vec3, step: float) -> Vec3:
    """``p`` moved toward ``target`` by at most ``step``."""
    dx, dy, dz = target[0] - p[0], target[1] - p[1], target[2] - p[2]
    d = math.sqrt(dx * dx + dy * dy + dz * dz)
    if d <= step:
        return target
    f = step / d
    return (p[0] + dx * f, p[1] + dy * f, p[2] + dz * f)


# ------------------------------------------------------------------------------ the set
class FixtureSet:
    """An immutable set of primitives plus the proxies of its contacts.

    ``force(tool, dt)`` is the per-tick call: it updates the proxies and returns the force (N)
    to display, clamped to ``max_force_n``. A new definition means a new set (built off the
    tick or bounded by the number of primitives); the controller swaps it in between ticks,
    so a tick always sees one whole set. ``carry_from`` hands the previous set's last tool
    position on, so a swap needs no new entry point.
    """

    __slots__ = (
        "primitives",
        "max_force_n",
        "slide_mm",
        "_acc",
        "_forb",
        "_planes",
        "_guides",
        "_acc_contact",
        "_acc_proxy",
        "_forb_proxy",
        "_guide_proxy",
        "_last",
        "force_n",
        "contacts_entered",
        "clamped",
        "label",
    )

    def __init__(
        self,
        primitives: Sequence[Primitive] = (),
        *,
        max_force_n: float = DEFAULT_MAX_FORCE_N,
        slide_mm: float = DEFAULT_SLIDE_MM,
        label: str = "",
    ) -> None:
        if not (max_force_n > 0.0 and math.isfinite(max_force_n)):
            raise ValueError(f"max_force_n must be > 0, got {max_force_n!r}")
        if not slide_mm > 0.0:
            raise ValueError(f"slide_mm must be > 0, got {slide_mm!r}")
        self.primitives: tuple[Primitive, ...] = tuple(primitives)
        self.max_force_n = float(max_force_n)
        self.slide_mm = float(slide_mm)
        self.label = label
        # flat float tuples: the tick reads these, not the dataclasses
        self._acc = [
            (*p.centre, p.radius, p.stiffness, p.damping)
            for p in self.primitives
            if isinstance(p, AccessibleSphere)
        ]
        self._forb = [
            (*p.centre, p.radius, p.stiffness, p.damping)
            for p in self.primitives
            if isinstance(p, ForbiddenSphere)
        ]
        self._planes = [
            (*p.point, *p.normal, p.stiffness, p.damping)
            for p in self.primitives
            if isinstance(p, ForbiddenPlane)
        ]
        self._guides: list[tuple[list[tuple[float, ...]], float, float]] = []
        for p in self.primitives:
            if isinstance(p, Guide):
                segs: list[tuple[float, ...]] = []
                for a, c in zip(p.points, p.points[1:], strict=False):
                    d = (c[0] - a[0], c[1] - a[1], c[2] - a[2])
                    dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
                    if dd > 0.0:
                        segs.append((*a, *d, dd))
                self._guides.append((segs, p.stiffness, p.damping))
        self._acc_contact = -1  # index into _acc of the proxy's sphere, -1 = free
        self._acc_proxy: Vec3 | None = None
        self._forb_proxy: list[Vec3 | None] = [None] * len(self._forb)
        self._guide_proxy: list[Vec3 | None] = [None] * len(self._guides)
        self._last: Vec3 | None = None
        #: the last force returned (N)
        self.force_n: Vec3 = (0.0, 0.0, 0.0)
        #: how many times a contact began (counted per primitive kind together)
        self.contacts_entered = 0
        #: ticks on which the clamp limited the force
        self.clamped = 0

    def __len__(self) -> int:
        return len(self.primitives)

    def carry_from(self, previous: FixtureSet | None) -> FixtureSet:
        """Start from ``previous``'s last tool position (a swap keeps the tool's history: a
        tool already outside the new accessible area gets its nearest surface, not an entry
        point from nowhere)."""
        if previous is not None:
            self._last = previous._last
        return self

    # ------------------------------------------------------------------ per tick
    def force(self, tool: Sequence[float], dt: float) -> Vec3:
        """The force (N) for the tool at ``tool`` (mm, master frame), ``dt`` s after the
        previous call; proxies move."""
        x, y, z = float(tool[0]), float(tool[1]), float(tool[2])
        last = self._last
        if last is not None and dt > 0.0:
            vx, vy, vz = (x - last[0]) / dt, (y - last[1]) / dt, (z - last[2]) / dt
        else:
            vx = vy = vz = 0.0
        fx = fy = fz = 0.0
        if self._acc:
            f = self._accessible(x, y, z, vx, vy, vz, last)
            fx, fy, fz = fx + f[0], fy + f[1], fz + f[2]
        forb_proxy = self._forb_proxy
        for i, s in enumerate(self._forb):
            dx, dy, dz = x - s[0], y - s[1], z - s[2]
            if dx * dx + dy * dy + dz * dz >= s[3] * s[3]:  # outside, free: inlined, the usual case
                forb_proxy[i] = None
                continue
            f = self._forbidden(i, s, x, y, z, vx, vy, vz, last)
            fx, fy, fz = fx + f[0], fy + f[1], fz + f[2]
        for px, py, pz, nx, ny, nz, k, b in self._planes:
            depth = (x - px) * nx + (y - py) * ny + (z - pz) * nz
            if depth < 0.0:
                vn = vx * nx + vy * ny + vz * nz
                m = -k * depth - b * vn
                fx, fy, fz = fx + m * nx, fy + m * ny, fz + m * nz
        for i, g in enumerate(self._guides):
            f = self._guide(i, g, x, y, z, vx, vy, vz)
            fx, fy, fz = fx + f[0], fy + f[1], fz + f[2]
        self._last = (x, y, z)
        mag = math.sqrt(fx * fx + fy * fy + fz * fz)
        cap = self.max_force_n
        if mag > cap:
            sc = cap / mag
            fx, fy, fz = fx * sc, fy * sc, fz * sc
            self.clamped += 1
        self.force_n = (fx, fy, fz)
        return self.force_n

    def _spring(
        self,
        p: Vec3,
        x: float,
        y: float,
        z: float,
        k: float,
        b: float,
        vx: float,
        vy: float,
        vz: float,
    ) -> Vec3:
        """k (p - x) plus damping of the velocity along it."""
        ex, ey, ez = p[0] - x, p[1] - y, p[2] - z
        fx, fy, fz = k * ex, k * ey, k * ez
        if b > 0.0:
            e = math.sqrt(ex * ex + ey * ey + ez * ez)
            if e > _EPS:
                nx, ny, nz = ex / e, ey / e, ez / e
                m = -b * (vx * nx + vy * ny + vz * nz)
                fx, fy, fz = fx + m * nx, fy + m * ny, fz + m * nz
        return (fx, fy, fz)

    def _accessible(
        self, x: float, y: float, z: float, vx: float, vy: float, vz: float, last: Vec3 | None
    ) -> Vec3:
        acc = self._acc
        for s in acc:
            dx, dy, dz = x - s[0], y - s[1], z - s[2]
            if dx * dx + dy * dy + dz * dz <= s[3] * s[3]:
                self._acc_contact = -1
                self._acc_proxy = (x, y, z)
                return (0.0, 0.0, 0.0)
        tool = (x, y, z)
        i = self._acc_contact
        p = self._acc_proxy
        if i < 0:
            self.contacts_entered += 1
            # the tool has just left: the proxy starts at the exit point on the segment from
            # its last free position (the paper's proxy-based entry point)
            start = p if p is not None else last
            best_t = -1.0
            if start is not None:
                for j, s in enumerate(acc):
                    dx, dy, dz = start[0] - s[0], start[1] - s[1], start[2] - s[2]
                    if dx * dx + dy * dy + dz * dz <= s[3] * s[3] * (1.0 + 1e-9):
                        t = _exit_t(start, tool, s, first=False)
                        if t > best_t:
                            best_t, i = t, j
            if i >= 0 and start is not None:
                p = (
                    start[0] + best_t * (x - start[0]),
                    start[1] + best_t * (y - start[1]),
                    start[2] + best_t * (z - start[2]),
                )
            else:
                # no free history (a set swapped in while the tool is outside): the nearest
                # surface
                best = math.inf
                for j, s in enumerate(acc):
                    d = math.sqrt((x - s[0]) ** 2 + (y - s[1]) ** 2 + (z - s[2]) ** 2) - s[3]
                    if d < best:
                        best, i = d, j
                p = _project_sphere(x, y, z, acc[i]) or (x, y, z)
        assert p is not None
        # slide on the contact sphere; hand over to another sphere only from inside it, when
        # its surface is nearer the tool
        target = _project_sphere(x, y, z, acc[i]) or p
        best = (x - target[0]) ** 2 + (y - target[1]) ** 2 + (z - target[2]) ** 2
        for j, s in enumerate(acc):
            if j == i:
                continue
            dx, dy, dz = p[0] - s[0], p[1] - s[1], p[2] - s[2]
            if dx * dx + dy * dy + dz * dz <= s[3] * s[3] * (1.0 + 1e-9):
                q = _project_sphere(x, y, z, s)
                if q is None:
                    continue
                e = (x - q[0]) ** 2 + (y - q[1]) ** 2 + (z - q[2]) ** 2
                if e < best - 1e-12:
                    best, target, i = e, q, j
        p = _slide(p, target, self.slide_mm)
        self._acc_contact = i
        self._acc_proxy = p
        s = acc[i]
        return self._spring(p, x, y, z, s[4], s[5], vx, vy, vz)

    def _forbidden(
        self,
        i: int,
        s: tuple[float, ...],
        x: float,
        y: float,
        z: float,
        vx: float,
        vy: float,
        vz: float,
        last: Vec3 | None,
    ) -> Vec3:
        # called only with the tool inside (force() tests that, inlined)
        cx, cy, cz, r = s[0], s[1], s[2], s[3]
        tool = (x, y, z)
        p = self._forb_proxy[i]
        if p is None:
            self.contacts_entered += 1
            if last is not None:
                t = _exit_t(last, tool, s, first=True)
                p = (
                    last[0] + t * (x - last[0]),
                    last[1] + t * (y - last[1]),
                    last[2] + t * (z - last[2]),
                )
            else:
                p = _project_sphere(x, y, z, s) or (cx, cy, cz + r)
            p = _project_sphere(*p, s) or p
        target = _project_sphere(x, y, z, s) or p
        p = _slide(p, target, self.slide_mm)
        p = _project_sphere(*p, s) or p  # a chord cuts through the sphere: back on it
        self._forb_proxy[i] = p
        return self._spring(p, x, y, z, s[4], s[5], vx, vy, vz)

    def _guide(
        self,
        i: int,
        g: tuple[list[tuple[float, ...]], float, float],
        x: float,
        y: float,
        z: float,
        vx: float,
        vy: float,
        vz: float,
    ) -> Vec3:
        segs, k, b = g
        # the nearest point of the path, inlined: a guide pulls every tick
        best = math.inf
        tx = ty = tz = 0.0
        for ax, ay, az, dx, dy, dz, dd in segs:
            t = ((x - ax) * dx + (y - ay) * dy + (z - az) * dz) / dd
            t = 0.0 if t < 0.0 else 1.0 if t > 1.0 else t
            px, py, pz = ax + t * dx, ay + t * dy, az + t * dz
            ex, ey, ez = x - px, y - py, z - pz
            e = ex * ex + ey * ey + ez * ez
            if e < best:
                best, tx, ty, tz = e, px, py, pz
        p = self._guide_proxy[i]
        if p is None:
            p = (tx, ty, tz)
        else:
            ex, ey, ez = tx - p[0], ty - p[1], tz - p[2]
            d = math.sqrt(ex * ex + ey * ey + ez * ez)
            step = self.slide_mm
            if d <= step:
                p = (tx, ty, tz)
            else:
                f = step / d
                p = (p[0] + ex * f, p[1] + ey * f, p[2] + ez * f)
        self._guide_proxy[i] = p
        if b == 0.0:
            return (k * (p[0] - x), k * (p[1] - y), k * (p[2] - z))
        return self._spring(p, x, y, z, k, b, vx, vy, vz)

    # ------------------------------------------------------------------ inspection
    def contacts(self) -> list[Contact]:
        """The contacts of the last call (for display: Slicer's proxy model, stats)."""
        out: list[Contact] = []
        last = self._last
        if last is None:
            return out
        x, y, z = last
        acc_prims = [p for p in self.primitives if isinstance(p, AccessibleSphere)]
        if self._acc_contact >= 0 and self._acc_proxy is not None:
            s = self._acc[self._acc_contact]
            p = self._acc_proxy
            out.append(
                Contact(
                    acc_prims[self._acc_contact].name,
                    "accessible",
                    p,
                    (s[4] * (p[0] - x), s[4] * (p[1] - y), s[4] * (p[2] - z)),
                )
            )
        forb_prims = [p for p in self.primitives if isinstance(p, ForbiddenSphere)]
        for i, fp in enumerate(self._forb_proxy):
            if fp is not None:
                p = fp
                k = self._forb[i][4]
                out.append(
                    Contact(
                        forb_prims[i].name,
                        "forbidden",
                        p,
                        (k * (p[0] - x), k * (p[1] - y), k * (p[2] - z)),
                    )
                )
        planes = [p for p in self.primitives if isinstance(p, ForbiddenPlane)]
        for prim, (px, py, pz, nx, ny, nz, k, _b) in zip(planes, self._planes, strict=True):
            depth = (x - px) * nx + (y - py) * ny + (z - pz) * nz
            if depth < 0.0:
                proxy = (x - depth * nx, y - depth * ny, z - depth * nz)
                out.append(
                    Contact(
                        prim.name,
                        "plane",
                        proxy,
                        (-k * depth * nx, -k * depth * ny, -k * depth * nz),
                    )
                )
        guides = [p for p in self.primitives if isinstance(p, Guide)]
        for i, gp in enumerate(self._guide_proxy):
            if gp is not None:
                p = gp
                k = self._guides[i][1]
                out.append(
                    Contact(
                        guides[i].name, "guide", p, (k * (p[0] - x), k * (p[1] - y), k * (p[2] - z))
                    )
                )
        return out

    def inside_accessible(self, point: Sequence[float]) -> bool:
        """Whether ``point`` (mm) lies in the accessible area (True when there is none)."""
        if not self._acc:
            return True
        x, y, z = point[0], point[1], point[2]
        return any(
            (x - s[0]) ** 2 + (y - s[1]) ** 2 + (z - s[2]) ** 2 <= s[3] * s[3] for s in self._acc
        )


def forbidden_hit(
    primitives: Sequence[ForbiddenSphere | ForbiddenPlane], point_mm: Sequence[float]
) -> str | None:
    """The first forbidden sphere or plane containing ``point_mm`` (same frame and units as
    the primitives), described for an error message, or None when the point is free. For
    planners (a keyframe plan's collision check), not the per-tick force."""
    x, y, z = point_mm[0], point_mm[1], point_mm[2]
    for f in primitives:
        if isinstance(f, ForbiddenSphere):
            (cx, cy, cz), r = f.centre, f.radius
            if (x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2 < r * r:
                return f"forbidden sphere {f.name!r}" if f.name else "a forbidden sphere"
        else:
            (px, py, pz), (nx, ny, nz) = f.point, f.normal
            if (x - px) * nx + (y - py) * ny + (z - pz) * nz < 0.0:
                return f"forbidden plane {f.name!r}" if f.name else "a forbidden plane"
    return None
