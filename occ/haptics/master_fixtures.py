"""The master's virtual fixtures at run time: definitions in, one force a tick out, models back.

:class:`MasterFixtures` is what the ``teleop-master`` controller holds. It keeps the
definitions by source (:mod:`occ.haptics.fixture_defs`), the patient-to-master mapping, and the
active :class:`~occ.haptics.fixtures.FixtureSet`; all on the loop thread, all bounded:

- a definition message (decoded by the interface thread) is validated and compiled when the
  loop takes it, into a *new* set that replaces the active one in one assignment, so a tick
  sees the old set or the new one, never half of each; an invalid definition raises
  :class:`~occ.haptics.fixture_defs.DefinitionError` (the sender gets an error reply) and the active
  set stays. The work is bounded: only the message's own source is compiled (the others are
  kept compiled), at most ``max_primitives`` in all, and at most ``max_primitives``
  definitions a tick (a burst beyond is refused "busy", to be sent again): a few µs a
  primitive, docs/BENCHMARKS.md;
- a change of the mapping (the slave's ``map``, a registration) marks the compiled fixtures
  stale; :meth:`MasterFixtures.step` recompiles them once, however many changes came in the
  tick;
- :meth:`MasterFixtures.step` (for every new tool position: the slave's measured tip, patient
  frame) returns the force, in the master's axes (N).

Everything is in the patient frame (3D Slicer's RAS, the frame of the slave's ``Tip``) on the
way in and out; the primitives themselves live in the master's force frame
(:class:`~occ.haptics.fixture_defs.PatientMapping`: mm of master motion, the master's axes), where
the tool is mapped too.

Display (3D Slicer): :meth:`model` draws the active fixtures as one POLYDATA
(spheres as triangle meshes, planes as squares, guides as lines; a cell scalar ``kind``: 1
accessible, 2 forbidden, 3 plane, 4 guide) and :meth:`proxy` the contact state as a
TRANSFORM at the first contact's proxy (the tool when free) with metadata ``contact``
(primitive names), ``force_n`` and ``tool_mm``; both with ``MRMLNodeName`` metadata, in the
patient frame.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from occ.errors import caused
from occ.events import Event, MeshOut, TransformOut
from occ.haptics.fixture_defs import (
    Defaults,
    Definition,
    DefinitionError,
    PatientMapping,
    compile_definitions,
    from_event,
    from_markups_file,
)
from occ.haptics.fixtures import (
    AccessibleSphere,
    FixtureSet,
    ForbiddenPlane,
    ForbiddenSphere,
    Guide,
    Primitive,
    Vec3,
)

log = logging.getLogger(__name__)

__all__ = ["MasterFixtures"]

KIND_CODE = {"accessible": 1.0, "forbidden": 2.0, "plane": 3.0, "guide": 4.0}


class MasterFixtures:
    """Definitions, mapping and the active set of one master (see the module docstring)."""

    def __init__(
        self,
        defaults: Defaults,
        mapping: PatientMapping,
        *,
        max_force_n: float = 10.0,
        slide_mm: float = 1.0,
        max_primitives: int = 64,
        max_planes: int = 8,
    ) -> None:
        self.defaults = defaults
        self.mapping = mapping
        self.max_force_n = max_force_n
        self.slide_mm = slide_mm
        self.max_primitives = max_primitives
        self.max_planes = max_planes
        self.groups: dict[str, list[Definition]] = {}
        self.active = FixtureSet(max_force_n=max_force_n, slide_mm=slide_mm)
        self._compiled_version = mapping.version
        #: bumped on every new active set (the display sends models on change)
        self.version = 0
        self.applied = 0
        self.refused = 0
        self.last_error = ""
        self.peak_force_n = 0.0
        self._compiled: dict[str, list[Primitive]] = {}
        self._tick_work = 0  # definitions compiled in the tick at _work_now
        self._work_now = math.nan
        self._last_now = math.nan
        #: the tool (the slave's measured tip) in the patient frame, mm
        self.tool_mm: Vec3 = (0.0, 0.0, 0.0)
        #: the force displayed (N, the master's axes): set by the controller, which may scale
        #: what :meth:`step` returns (a stale or lost tip, the clutch)
        self.force_n: Vec3 = (0.0, 0.0, 0.0)
        #: what :meth:`step` computed last (N), before the controller's gain
        self.raw_force_n: Vec3 = (0.0, 0.0, 0.0)

    # ------------------------------------------------------------------ definitions
    def load_file(self, path: str | Path, **kw: Any) -> int:
        """A Slicer ``.mrk.json`` file as one source (at start, off the loop)."""
        defs = from_markups_file(path, **kw)
        self._new_tick(math.nan)  # at start, off the loop: a budget of its own
        self._tick_work = 0
        self._replace(f"file:{path}", defs)
        return len(defs)

    def _new_tick(self, now: float) -> None:
        """The per-tick work budget starts again on each new tick."""
        if now != self._work_now:
            self._work_now = now
            self._tick_work = 0

    def on_event(self, event: Event, now: float = math.nan) -> str | None:
        """A definition (a decoded input, occ/events.py): applied (a short description) or
        None when ``event`` is no fixture; :class:`DefinitionError` when it is refused (the
        active set unchanged)."""
        self._new_tick(now)
        try:
            defs = from_event(event, self.defaults)
        except DefinitionError as err:
            self._refuse(event, err)
        if defs is None:
            return None
        key = f"{event.kind}:{event.device}"
        try:
            self._replace(key, defs)
        except DefinitionError as err:
            self._refuse(event, err)
        return f"{len(defs)} fixtures from {key}; {len(self.active)} active"

    def _refuse(self, event: Event, err: DefinitionError) -> None:
        self.refused += 1
        self.last_error = f"{event.describe()}: {err}"
        raise caused(
            DefinitionError(f"fixture refused ({self.last_error}); the previous set stays"), err
        ) from err

    def clear(self) -> None:
        self.groups.clear()
        self._compiled.clear()
        self._swap()

    def _replace(self, key: str, defs: list[Definition]) -> None:
        total = sum(len(g) for k, g in self.groups.items() if k != key) + len(defs)
        if total > self.max_primitives:
            raise DefinitionError(
                f"{total} fixtures in all, more than max_primitives {self.max_primitives}"
            )
        planes = sum(
            1 for k, g in self.groups.items() if k != key for d in g if d.kind == "plane"
        ) + sum(1 for d in defs if d.kind == "plane")
        if planes > self.max_planes:
            raise DefinitionError(f"{planes} planes, more than max_planes {self.max_planes}")
        if self._tick_work + len(defs) > self.max_primitives:
            # bounded work a tick: at most one full set's worth of definitions compiled
            raise DefinitionError(
                f"busy: {self._tick_work} fixtures compiled this tick already; send it again"
            )
        self._tick_work += len(defs)
        prims = compile_definitions(defs, self.mapping)
        if defs:
            self.groups[key] = defs
            self._compiled[key] = prims
        else:
            self.groups.pop(key, None)
            self._compiled.pop(key, None)
        self._swap()
        self.applied += 1
        log.info("virtual fixtures: %s -> %d active", key, len(self.active))

    def _swap(self) -> None:
        prims = [p for g in self._compiled.values() for p in g]
        new = FixtureSet(prims, max_force_n=self.max_force_n, slide_mm=self.slide_mm)
        self.active = new.carry_from(self.active)
        self.version += 1

    def _recompile(self) -> None:
        """The mapping changed: the fixtures move in the master's force frame. Done at once
        when this tick's budget allows, else by :meth:`step` (once, whatever the changes)."""
        work = sum(len(g) for g in self.groups.values())
        if self._tick_work + work > self.max_primitives:
            return  # stale until the next step()
        self._compiled_version = self.mapping.version
        if not self.groups:
            return
        self._tick_work += work
        for k, g in self.groups.items():
            self._compiled[k] = compile_definitions(g, self.mapping)
        self._swap()

    # ------------------------------------------------------------------ mapping inputs
    def registration(self, matrix: Sequence[Sequence[float]], now: float = math.nan) -> None:
        """The slave's base pose in the patient frame (a TRANSFORM ``Base``): used for the
        map only when the slave does not report its own (``map``)."""
        self._new_tick(now)
        self.mapping.set_registration(matrix)
        self._recompile()

    def set_linear(self, linear: Sequence[Sequence[float]], now: float = math.nan) -> None:
        """The slave's map (handle mm -> patient mm), from its tip stream's metadata."""
        self._new_tick(now)
        if self.mapping.set_linear(linear):
            self._recompile()

    # ------------------------------------------------------------------ per tick
    def step(self, tool_mm: Sequence[float], now: float) -> Vec3:
        """The force (N, the master's axes) for the tool at ``tool_mm`` (patient frame, mm:
        the slave's measured tip) at time ``now``: :attr:`raw_force_n`. What is displayed
        (:attr:`force_n`, the peak) is the caller's to say, with :meth:`displayed`."""
        self._new_tick(now)
        if self.mapping.version != self._compiled_version:
            self._recompile()
        last = self._last_now
        dt = now - last if last == last else 0.0
        self._last_now = now
        self.tool_mm = (float(tool_mm[0]), float(tool_mm[1]), float(tool_mm[2]))
        tool = self.mapping.point(self.tool_mm)
        if not self.active.primitives:
            self.active.force(tool, dt)  # keeps the tool's history for the next set
            f: Vec3 = (0.0, 0.0, 0.0)
        else:
            f = self.active.force(tool, dt)
        self.raw_force_n = f
        return f

    def displayed(self, f: Vec3) -> None:
        """The force the master displays now (N): what the stats, the contact output and the
        peak report."""
        self.force_n = f
        mag = math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2])
        if mag > self.peak_force_n:
            self.peak_force_n = mag

    def stats(self) -> dict[str, Any]:
        a = self.active
        return {
            "fixtures": len(a),
            "fixture_kinds": {
                k: sum(1 for p in a.primitives if p.kind == k)
                for k in ("accessible", "forbidden", "plane", "guide")
            },
            "fixture_sources": sorted(self.groups),
            "fixtures_applied": self.applied,
            "fixtures_refused": self.refused,
            "fixture_last_error": self.last_error,
            "fixture_contacts": a.contacts_entered,
            "fixture_clamped": a.clamped,
            "contact": [c.name for c in a.contacts()],
            "peak_force_n": round(self.peak_force_n, 4),
        }

    # ------------------------------------------------------------------ display
    def _display_point(self, p: Sequence[float]) -> Vec3:
        return self.mapping.master_to_patient(p)

    def _display_length(self, length: float) -> float:
        return length * self.mapping.factor

    def _display_dir(self, n: Sequence[float]) -> Vec3:
        return self.mapping.patient_direction(n)

    def model(self, device: str, timestamp: float = 0.0) -> MeshOut:
        """The active fixtures as one POLYDATA (see the module docstring)."""
        points: list[Vec3] = []
        lines: list[tuple[int, ...]] = []
        polygons: list[tuple[int, ...]] = []
        line_kind: list[float] = []
        poly_kind: list[float] = []
        for prim in self.active.primitives:
            code = KIND_CODE[prim.kind]
            if isinstance(prim, (AccessibleSphere, ForbiddenSphere)):
                c = self._display_point(prim.centre)
                r = self._display_length(prim.radius)
                base = len(points)
                verts, faces = _sphere_mesh(c, r)
                points.extend(verts)
                for f in faces:
                    polygons.append(tuple(base + i for i in f))
                    poly_kind.append(code)
            elif isinstance(prim, ForbiddenPlane):
                c = self._display_point(prim.point)
                n = self._display_dir(prim.normal)
                base = len(points)
                points.extend(_square(c, n, 50.0))
                polygons.append((base, base + 1, base + 2, base + 3))
                poly_kind.append(code)
            elif isinstance(prim, Guide):
                base = len(points)
                points.extend(self._display_point(p) for p in prim.points)
                lines.append(tuple(range(base, base + len(prim.points))))
                line_kind.append(code)
        # VTK's cell order: vertices, lines, polygons
        kinds = np.array(line_kind + poly_kind, dtype=np.float32)
        return MeshOut(
            np.array(points, dtype=np.float32).reshape(-1, 3),
            timestamp,
            lines=tuple(lines),
            polygons=tuple(polygons),
            cell_scalars=(("kind", kinds),) if len(kinds) else (),
            v2=True,
            meta={
                "MRMLNodeName": device,
                "fixtures": str(len(self.active)),
                "frame": "patient",
            },
        )

    def proxy(self, device: str, timestamp: float = 0.0) -> TransformOut:
        """The contact state: a TRANSFORM at the first contact's proxy (the tool when
        free), metadata ``contact``, ``force_n``, ``tool_mm``."""
        contacts = self.active.contacts()
        x, y, z = self._display_point(contacts[0].proxy) if contacts else self.tool_mm
        f = self.force_n
        t = self.tool_mm
        m = np.eye(4)
        m[:3, 3] = (x, y, z)
        return TransformOut(
            m,
            timestamp,
            v2=True,
            meta={
                "MRMLNodeName": device,
                "contact": ",".join(c.name or c.kind for c in contacts) or "none",
                "force_n": f"{f[0]:.4f},{f[1]:.4f},{f[2]:.4f}",
                "tool_mm": f"{t[0]:.3f},{t[1]:.3f},{t[2]:.3f}",
                "frame": "patient",
            },
        )


def _sphere_mesh(
    c: Vec3, r: float, n_lat: int = 6, n_lon: int = 12
) -> tuple[list[Vec3], list[tuple[int, ...]]]:
    """A UV sphere: poles plus rings, triangles at the poles and quads between."""
    verts: list[Vec3] = [(c[0], c[1], c[2] + r)]
    for i in range(1, n_lat):
        th = math.pi * i / n_lat
        for j in range(n_lon):
            ph = 2.0 * math.pi * j / n_lon
            verts.append(
                (
                    c[0] + r * math.sin(th) * math.cos(ph),
                    c[1] + r * math.sin(th) * math.sin(ph),
                    c[2] + r * math.cos(th),
                )
            )
    verts.append((c[0], c[1], c[2] - r))
    south = len(verts) - 1
    faces: list[tuple[int, ...]] = []
    for j in range(n_lon):
        faces.append((0, 1 + j, 1 + (j + 1) % n_lon))
    for i in range(n_lat - 2):
        a0 = 1 + i * n_lon
        b0 = a0 + n_lon
        for j in range(n_lon):
            k = (j + 1) % n_lon
            faces.append((a0 + j, b0 + j, b0 + k, a0 + k))
    last = 1 + (n_lat - 2) * n_lon
    for j in range(n_lon):
        faces.append((last + j, south, last + (j + 1) % n_lon))
    return verts, faces


def _square(c: Vec3, n: Vec3, half: float) -> list[Vec3]:
    """Four corners of a square of side 2 ``half`` centred at ``c``, normal ``n``."""
    nn = math.sqrt(sum(v * v for v in n)) or 1.0
    nx, ny, nz = (v / nn for v in n)
    # any vector not parallel to n
    ax, ay, az = (1.0, 0.0, 0.0) if abs(nx) < 0.9 else (0.0, 1.0, 0.0)
    ux, uy, uz = ny * az - nz * ay, nz * ax - nx * az, nx * ay - ny * ax
    un = math.sqrt(ux * ux + uy * uy + uz * uz)
    ux, uy, uz = ux / un, uy / un, uz / un
    vx, vy, vz = ny * uz - nz * uy, nz * ux - nx * uz, nx * uy - ny * ux
    out = []
    for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        out.append(
            (
                c[0] + half * (su * ux + sv * vx),
                c[1] + half * (su * uy + sv * vy),
                c[2] + half * (su * uz + sv * vz),
            )
        )
    return out
