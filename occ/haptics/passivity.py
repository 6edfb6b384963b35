"""Two-port time-domain passivity: bilateral teleoperation that never gives energy it did not get.

The master streams the handle's position; the slave follows it and sends back the force on its
instrument, which the master displays (a position-force architecture). Delay and lost packets
make that loop an energy source: released from stiff tissue the hand gets back more than it
put in, and the handle buzzes or the loop grows. The remedy here is the two-port time-domain
passivity approach (TDPA) of Ryu, Artigas and Preusche ("A passive bilateral control scheme for
a teleoperator with time-varying communication delay", Mechatronics 20(7), 2010; Artigas et al.,
"Time domain passivity control for position-position teleoperation architectures", Presence
19(5), 2010), after the one-port observer and controller of Hannaford and Ryu ("Time-domain
passivity control of haptic interfaces", IEEE Trans. Robotics and Automation 18(1), 2002).

**The two ports.** The channel (everything between the handle and the slave's position servo:
the stream, the delay, the loss, the return link) has a port at each end:

- the *master port*: the handle's velocity ``v`` goes in, the displayed feedback ``f`` comes
  out; the power into the channel is ``-f . v`` (pressing against the force: the hand puts
  energy in; the force pushing the handle along: the channel gives energy out);
- the *slave port*: the commanded tip motion ``dx`` goes out, the measured contact force ``F``
  (the tissue on the tool) comes back; the power into the channel is ``F . dx / dt`` (the
  command retreating while the tissue pushes: the tissue gives energy back), into the tissue
  ``-F . dx``.

Each port's :class:`EnergyAccount` splits its flow into energy *in* (cumulative, monotone) and
energy *out*. Each side sends its energy in with every sample (the stream's and the return
channel's metadata ``energy_j``), and its controller keeps its own energy out below the other
side's energy in as received::

    E_out_master(n) <= E_in_slave(n - delay)        E_out_slave(n) <= E_in_master(n - delay)

Both sums only grow, so a lost or delayed sample leaves the receiver with an older, smaller
value: loss and delay of any length, either way, can only make the bound tighter, never
looser (Ryu et al. 2010, the property that makes it hold under time-varying delay). With a
passive tissue, ``E_in_slave <= E_out_slave``, so the hand never gets back more than it put in.

**Units.** The slave's energies are in its own units (N at the instrument times m at the tip);
with motion scaling ``kp`` (tip m per handle m) and force scaling ``kf`` (displayed N per N at
the instrument) one joule at the instrument is ``kf / kp`` joules at the handle (an ideal scaled
teleoperator's power ratio). The master converts both ways: it sends its energy in in the
slave's units and reads the slave's in its own.

**The controllers act on the variable that cannot saturate into activity.**

- At the master (:class:`MasterPort`), on the force: when the force about to be displayed would
  take out more than the budget over the next tick (``f . v dt`` against what the slave has put
  in and the master not yet given), its component along the handle's velocity is cut to what the
  budget allows: ``f <- f - alpha v``, ``alpha = (f . v dt - W) / (|v|^2 dt)``. Below
  ``max_damping`` that is the classic variable damper; above it (a handle nearly at rest) the
  same cut is counted as a force limitation, never as a larger damper: the change is at most the
  force's own component along the motion, so the controller can remove force but never push the
  hand (a capped damper left the excess in the hand: the activity of issue 37).
  Every tick the energy of the force displayed over the last tick is accounted exactly from the
  handle's displacement (``-f . dx``), so what the budget counts is what the hand got.
- At the slave (:class:`SlavePort`), on the position: a commanded step into the tissue that
  would take out more than the budget is shortened along the force (the tool stops short: a
  position drift, given back when the energy allows it, occ/controllers/teleop/).

**Sessions.** Each side's budget counts the peer's energy since its own last reset (the master
entering RUNNING, the slave re-indexing: nothing it stored before is taken over). A peer whose
sum went down has started afresh (a restarted daemon): the account starts a new session too.
"""

from __future__ import annotations

import math
from typing import Any

__all__ = ["EnergyAccount", "MasterPort", "OnePort", "SlavePort", "parse_energy"]

Vec3 = tuple[float, float, float]


def parse_energy(text: str) -> float | None:
    """An ``energy_j`` value as sent with the samples (J, cumulative: finite and >= 0), or
    None when it is no energy (the caller counts it and keeps its budget where it was)."""
    try:
        e = float(text)
    except ValueError:
        return None
    return e if math.isfinite(e) and e >= 0.0 else None


class EnergyAccount:
    """One port's energy (J, this side's units; see the module docstring)."""

    def __init__(self) -> None:
        #: energy into the channel at this port since the start (monotone; sent to the peer)
        self.e_in = 0.0
        #: since the last reset: energy in and out at this port
        self.session_in = 0.0
        self.e_out = 0.0
        #: the peer's energy in, as last received (this side's units), and at the last reset
        self.peer = 0.0
        self.base = 0.0
        self.received = 0
        self.restarts = 0

    def reset(self) -> None:
        """A new session: the peer's energy counts from what it has sent so far."""
        self.base = self.peer
        self.e_out = 0.0
        self.session_in = 0.0

    def receive(self, peer_in: float) -> None:
        """The peer's energy in (this side's units) with one of its samples."""
        self.received += 1
        if peer_in < self.peer:  # its sum went down: it started afresh
            self.peer = peer_in
            self.restarts += 1
            self.reset()
            return
        self.peer = peer_in

    def flow(self, work_in: float) -> None:
        """``work_in`` J flowed into the channel at this port (negative: out of it)."""
        if work_in >= 0.0:
            self.e_in += work_in
            self.session_in += work_in
        else:
            self.e_out -= work_in

    @property
    def budget(self) -> float:
        """What this port may still give out (J): the peer's energy in since the reset minus
        this port's energy out."""
        return self.peer - self.base - self.e_out

    @property
    def net(self) -> float:
        """This port's own balance since the reset (J): in minus out."""
        return self.session_in - self.e_out

    def stats(self) -> dict[str, Any]:
        return {
            "in_mj": round(self.session_in * 1e3, 4),
            "out_mj": round(self.e_out * 1e3, 4),
            "budget_mj": round(self.budget * 1e3, 4),
            "peer_in_mj": round((self.peer - self.base) * 1e3, 4),
            "energy_mj": round((self.session_in - self.e_out) * 1e3, 4),
            "restarts": self.restarts,
        }


class MasterPort:
    """The master's port: observer and force-acting controller (see the module docstring)."""

    def __init__(self, max_damping: float = 200.0) -> None:
        self.max_damping = max_damping
        self.account = EnergyAccount()
        self._f_prev: Vec3 = (0.0, 0.0, 0.0)
        self.active_ticks = 0
        #: ticks the cut was a damper within ``max_damping`` / a force cut beyond it
        self.damped_ticks = 0
        self.limited_ticks = 0
        #: energy the controller kept from the hand (J), in all
        self.dissipated = 0.0
        self.last_damping = 0.0

    def reset(self) -> None:
        """A new session (entering RUNNING): nothing displayed yet."""
        self.account.reset()
        self._f_prev = (0.0, 0.0, 0.0)
        self.last_damping = 0.0

    def observe(self, dx: Vec3) -> None:
        """The force displayed over the last tick did ``-f . dx`` J of work into the channel
        (``dx``: the handle's displacement since, m)."""
        f = self._f_prev
        self.account.flow(-(f[0] * dx[0] + f[1] * dx[1] + f[2] * dx[2]))

    def step(self, f: Vec3, v: Vec3, dt: float) -> Vec3:
        """The force to display (``f``, or ``f`` cut along ``v``) for the handle moving at
        ``v`` (m/s) over the next ``dt`` s; call :meth:`observe` first, :meth:`displayed`
        after."""
        fx, fy, fz = f
        vx, vy, vz = v
        out = (fx * vx + fy * vy + fz * vz) * dt
        acc = self.account
        # the two-port bound, and the hand's own balance: see the module docstring
        allowed = min(acc.budget, acc.net)
        if allowed < 0.0:
            allowed = 0.0
        alpha = 0.0
        if out > allowed:
            v2 = vx * vx + vy * vy + vz * vz
            if v2 > 0.0 and dt > 0.0:
                alpha = (out - allowed) / (v2 * dt)
                fx, fy, fz = fx - alpha * vx, fy - alpha * vy, fz - alpha * vz
                self.dissipated += out - allowed
                self.active_ticks += 1
                if alpha <= self.max_damping:
                    self.damped_ticks += 1
                else:
                    self.limited_ticks += 1
        self.last_damping = alpha
        return (fx, fy, fz)

    def displayed(self, f: Vec3) -> None:
        """What the port really displays this tick (after the clamp): observed next tick."""
        self._f_prev = f

    @property
    def shown(self) -> Vec3:
        """The force the port displayed last tick."""
        return self._f_prev

    def stats(self) -> dict[str, Any]:
        return {
            **self.account.stats(),
            "dissipated_mj": round(self.dissipated * 1e3, 4),
            "active_ticks": self.active_ticks,
            "damped_ticks": self.damped_ticks,
            "force_limited_ticks": self.limited_ticks,
            "damping": round(self.last_damping, 3),
        }


class OnePort:
    """A one-port observer and controller on a channel that carries no energy from the peer:
    the torque of a 6-axis sensor displayed on a master's rotational axes (issue 37). The
    hand's own balance bounds what it is given back: the energy it put in through this
    channel minus what came out; beyond that the torque is cut along the motion (a damper up
    to ``max_damping``, N m s/rad, never more than the component along the motion). What a
    damper at its cap leaves is observed (``energy_mj`` below 0), not cut further: without
    the peer's energy an uncapped cut would take every steady torque off a yielding hand.
    ``passivity_max_rot_damping`` (occ/controllers/teleop_params.py) is the cap."""

    def __init__(self, max_damping: float = 2.0) -> None:
        self.max_damping = max_damping
        self.account = EnergyAccount()
        self.active_ticks = 0
        self.dissipated = 0.0
        self.last_damping = 0.0

    def reset(self) -> None:
        self.account.reset()
        self.last_damping = 0.0

    def observe(self, f: Vec3, v: Vec3, dt: float) -> None:
        """``f`` displayed while the handle turned at ``v`` for ``dt``: its work observed."""
        self.account.flow(-(f[0] * v[0] + f[1] * v[1] + f[2] * v[2]) * dt)

    def step(self, f: Vec3, v: Vec3, dt: float) -> Vec3:
        """The torque to display, cut so the channel gives back no more than it took; the
        work of what is returned is observed."""
        fx, fy, fz = f
        vx, vy, vz = v
        out = (fx * vx + fy * vy + fz * vz) * dt  # energy the channel would give the hand
        allowed = max(0.0, self.account.net)
        alpha = 0.0
        if out > allowed:
            v2 = vx * vx + vy * vy + vz * vz
            if v2 > 0.0 and dt > 0.0:
                alpha = (out - allowed) / (v2 * dt)
                # the cut never reverses the torque's component along the motion: beyond the
                # damper's cap it removes that component and no more
                along = (fx * vx + fy * vy + fz * vz) / v2
                alpha = min(alpha, along, self.max_damping)
                fx, fy, fz = fx - alpha * vx, fy - alpha * vy, fz - alpha * vz
                self.dissipated += alpha * v2 * dt
                self.active_ticks += 1
        self.last_damping = alpha
        result = (fx, fy, fz)
        self.observe(result, v, dt)
        return result

    def stats(self) -> dict[str, Any]:
        return {
            **self.account.stats(),
            "dissipated_mj": round(self.dissipated * 1e3, 4),
            "active_ticks": self.active_ticks,
            "damping": round(self.last_damping, 4),
        }


class SlavePort:
    """The slave's port: observer and position-acting controller (see the module docstring)."""

    def __init__(self) -> None:
        self.account = EnergyAccount()
        self.limited = 0
        #: energy the controller kept from the tissue (J), in all
        self.withheld = 0.0

    def reset(self) -> None:
        self.account.reset()

    def step(self, force: Vec3, dx: Vec3) -> Vec3:
        """The commanded step ``dx`` (m) with the force ``force`` (N) on the tool, both in one
        frame: shortened along the force when it would put more energy into the tissue than
        the budget, and accounted."""
        fx, fy, fz = force
        x, y, z = dx
        out = -(fx * x + fy * y + fz * z)
        allowed = self.account.budget
        if allowed < 0.0:
            allowed = 0.0
        if out > allowed:
            f2 = fx * fx + fy * fy + fz * fz
            c = (out - allowed) / f2  # out > 0 needs a force: f2 > 0
            x, y, z = x + c * fx, y + c * fy, z + c * fz
            self.withheld += out - allowed
            self.limited += 1
        self.account.flow(fx * x + fy * y + fz * z)
        return (x, y, z)

    def stats(self) -> dict[str, Any]:
        return {
            **self.account.stats(),
            "withheld_mj": round(self.withheld * 1e3, 4),
            "limited_ticks": self.limited,
        }
