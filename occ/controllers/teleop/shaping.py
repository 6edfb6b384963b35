"""The slave's contact shaping at the instrument: the master's mapped target turned into the tip
to command, within the force limit (``max_tissue_force_n``) and the energy the hand put in (the
slave's passivity port), the gap they left given back; and the release of a stop in contact."""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING, Any

from occ.controllers.teleop.common import LIMIT_GAIN, MM, STATUS_OK
from occ.haptics.passivity import SlavePort, parse_energy

if TYPE_CHECKING:
    from occ.controllers import ControllerContext
    from occ.core.data import RobotData
    from occ.haptics.forces import SlaveForce

log = logging.getLogger("occ.controllers.teleop.slave")

Vec3 = tuple[float, float, float]


class ContactShaper:
    """The tip commanded (base frame, m) against the one the master's motion maps to, the
    instrument's force limit and release, the slave's passivity port (the controller owns one).
    ``p`` the slave's parameters (SlaveParams)."""

    def __init__(self, p: Any) -> None:
        #: the force limit at the instrument (N; None: none)
        self.max_tissue_force = p.max_tissue_force_n if p.force is not None else None
        #: the slave's port of the two-port passivity scheme (occ/haptics/passivity.py): on
        #: while the followed stream carries the master's energy
        self.port = SlavePort()
        self.port_on = p.passivity
        self.port_active = False
        self.bad_energy = 0
        self._drift_speed = p.drift_return_mm_s * MM
        #: the master's target mapped (base frame, m), the tip commanded, and the gap the
        #: port and the force limit left between them (commanded - mapped)
        self.raw: Vec3 | None = None
        self.cmd: Vec3 | None = None
        self._offset: Vec3 = (0.0, 0.0, 0.0)
        self._t_shape = math.nan
        self.offset_max_mm = 0.0
        self.limit_ticks = 0
        self.limit_hits = 0
        self._limiting = False
        #: a latched stop in contact lets go of the tissue (see :meth:`release`)
        self._release_speed = p.release_speed_mm_s * MM
        self._release_force = p.release_force_n
        self._release_max = p.release_max_mm * MM
        self.releasing = False
        self.released_mm = 0.0
        self.releases = 0
        self._release_done = False
        self.force: SlaveForce | None = None
        self.data: RobotData | None = None
        self.ctx: ControllerContext | None = None

    def bind(self, force: SlaveForce | None, data: RobotData, ctx: ControllerContext) -> None:
        self.force, self.data, self.ctx = force, data, ctx

    def reindex(self, here: Vec3, now: float) -> None:
        """A re-index with the tip at ``here``: no gap, and a new session for the port (nothing
        the tissue stored before is counted)."""
        self.raw = self.cmd = here
        self._offset = (0.0, 0.0, 0.0)
        self._t_shape = now
        self.port.reset()

    def master_energy(self, text: str) -> None:
        """The master's energy in (``energy_j``: J at this instrument, cumulative): the budget
        of this port's controller. One that is no energy is counted and not used (the budget
        then stays where it was: the safe side)."""
        e = parse_energy(text)
        if e is None:
            self.bad_energy += 1
            return
        self.port.account.receive(e)
        self.port_active = True

    def stop_changed(self) -> None:
        """STOPPED entered or left: the release starts afresh."""
        self.releasing = self._release_done = False
        self.released_mm = 0.0

    def force_base(self) -> Vec3 | None:
        """The contact force on the instrument (N, the base frame: the frame of the targets)
        from the last estimate (the return channel's: at most one stream period old), or None
        without a healthy force source."""
        force, data = self.force, self.data
        if force is None or force.used is None or data is None:
            return None
        fx, fy, fz = force.force_n
        r = data.base
        return (
            float(r[0, 0] * fx + r[1, 0] * fy + r[2, 0] * fz),
            float(r[0, 1] * fx + r[1, 1] * fy + r[2, 1] * fz),
            float(r[0, 2] * fx + r[1, 2] * fy + r[2, 2] * fz),
        )

    def shaping(self, f: Vec3 | None) -> bool:
        """Has the command to move without a new master sample? (a gap to give back, or the
        force limit backing the tool out; ``f``: :meth:`force_base`)"""
        if self.cmd != self.raw:
            return True
        lim = self.max_tissue_force
        if lim is None or f is None:
            return False
        return f != (0.0, 0.0, 0.0)  # in contact: the approach to the limit is rate-limited

    def shape(self, now: float, f: Vec3 | None) -> Vec3:
        """The tip to command (base frame, m): the master's mapped target, the gap left so far
        given back at up to ``drift_return_mm_s``, the motion into the tissue no faster than
        5 mm/s per N below 90 % of ``max_tissue_force_n`` (backing out as fast above it), the
        rest within the energy the hand put in (the slave's port, occ/haptics/passivity.py)."""
        raw, cmd = self.raw, self.cmd
        ctx = self.ctx
        assert raw is not None and cmd is not None and ctx is not None
        last = self._t_shape
        self._t_shape = now
        dt = now - last if last == last else ctx.period_s
        dt = min(max(dt, 0.0), 0.05)
        ox, oy, oz = self._offset
        gap = math.sqrt(ox * ox + oy * oy + oz * oz)
        if gap > 0.0:
            keep = max(0.0, 1.0 - self._drift_speed * dt / gap)
            ox, oy, oz = keep * ox, keep * oy, keep * oz
        d = (raw[0] + ox - cmd[0], raw[1] + oy - cmd[1], raw[2] + oz - cmd[2])
        if f is not None:
            d = self._limit(f, d, dt)
            if self.port_on and self.port_active:
                d = self.port.step(f, d)
        dx, dy, dz = d
        new = (cmd[0] + dx, cmd[1] + dy, cmd[2] + dz)
        ox, oy, oz = new[0] - raw[0], new[1] - raw[1], new[2] - raw[2]
        self._offset = (ox, oy, oz)
        gap_mm = math.sqrt(ox * ox + oy * oy + oz * oz) / MM
        if gap_mm > self.offset_max_mm:
            self.offset_max_mm = gap_mm
        self.cmd = new
        return new

    def _limit(self, f: Vec3, d: Vec3, dt: float) -> Vec3:
        """The step ``d`` within the force limit, ``f`` the contact force (base frame)."""
        dx, dy, dz = d
        fx, fy, fz = f
        mag = math.sqrt(fx * fx + fy * fy + fz * fz)
        lim = self.max_tissue_force
        if lim is None or not mag > 0.0:
            return d
        # into the tissue at no more than 5 mm/s per N below 90 % of the limit, and out of it
        # as fast per N above: a first-order approach to the limit that the measurement's age
        # and the servo's lag cannot carry far past it, however fast the master moves
        # (10 N/mm: 20 ms)
        engage = 0.9 * lim
        nx, ny, nz = fx / mag, fy / mag, fz / mag  # out of the tissue
        inward = -(dx * nx + dy * ny + dz * nz)
        room = (engage - mag) * LIMIT_GAIN * dt
        if inward > room:
            push = inward - room
            dx, dy, dz = dx + push * nx, dy + push * ny, dz + push * nz
        if mag >= engage:
            self.limit_ticks += 1
            if not self._limiting:
                self._limiting = True
                self.limit_hits += 1
                self.tell(
                    "ForceLimit",
                    f"tissue force {mag:.2f} N at the limit (max_tissue_force_n {lim:g}): "
                    f"motion into the tissue stopped",
                    2,
                )
        elif self._limiting and mag < 0.8 * lim:
            self._limiting = False
        return (dx, dy, dz)

    def tell(self, name: str, text: str, code: int) -> None:
        log.warning("%s: %s", name, text)
        ctx = self.ctx
        alert = ctx.alert if ctx is not None else None
        if alert is not None:
            alert(name, text, code)

    def release(self, setpoint: list[float]) -> tuple[Vec3, float] | None:
        """While STOPPED, the held ``setpoint``'s tip backed out of the tissue this tick: (the
        tip's target, the step's length in m), or None to hold.

        While the measured contact force is over ``release_force_n`` the tool backs out along
        the force at ``release_speed_mm_s``, up to ``release_max_mm`` in all; under it, it
        holds (and backs out again if the tissue presses again: a compliant hold). The
        operators are told when it starts, when it is done and when the travel runs out."""
        data, ctx = self.data, self.ctx
        f = self.force_base()
        if f is None or data is None or ctx is None:
            return None
        fx, fy, fz = f
        mag = math.sqrt(fx * fx + fy * fy + fz * fz)
        if mag <= self._release_force:
            if self.releasing:
                self.releasing = False
                self.tell(
                    "Release",
                    f"let go of the tissue: {mag:.2f} N after {self.released_mm:.2f} mm",
                    STATUS_OK,
                )
            return None
        room = self._release_max - self.released_mm * MM
        if room <= 1e-12:
            if not self._release_done:
                self._release_done = True
                self.tell(
                    "Release",
                    f"still pressing {mag:.2f} N after backing out {self.released_mm:.2f} mm "
                    f"(release_max_mm): holding",
                    2,
                )
            return None
        if not self.releasing:
            self.releasing = True
            self.releases += 1
            self.tell(
                "Release",
                f"stopped pressing {mag:.2f} N on tissue: backing out along the force until "
                f"it is under {self._release_force:g} N",
                2,
            )
        step = min(self._release_speed * ctx.period_s, room)
        tx, ty, tz = ctx.frame.tip_position(setpoint)
        return (tx + step * fx / mag, ty + step * fy / mag, tz + step * fz / mag), step

    def stats(self) -> dict[str, Any]:
        """The instrument's limit, release and passivity port (GetStats ``instrument``)."""
        return {
            "max_tissue_force_n": self.max_tissue_force,
            "limit_hits": self.limit_hits,
            "limit_ticks": self.limit_ticks,
            "offset_max_mm": round(self.offset_max_mm, 4),
            "releasing": self.releasing,
            "releases": self.releases,
            "released_mm": round(self.released_mm, 4),
            "passivity": {
                "on": self.port_on,
                "active": self.port_active,
                "bad_energy": self.bad_energy,
                **self.port.stats(),
            },
        }
