"""Time-domain passivity at the master's handle: bilateral teleoperation stays stable under delay.

A master that displays the slave's contact force closes a loop through the network: the hand
moves the handle, the slave follows a few milliseconds later, the tissue pushes back, the force
comes back a few milliseconds later again. Delay (and lost packets, held) turns that loop into
an energy source: released from the wall the hand gets back more energy than it put in, and
with a stiff enough contact the handle oscillates with growing amplitude (up to the force
clamp). The remedy used here is the time-domain passivity observer and controller of Hannaford
and Ryu ("Time-domain passivity control of haptic interfaces", IEEE Trans. Robotics and
Automation 18(1), 2002; extended to teleoperation by Ryu, Kwon and Hannaford, "Stable
teleoperation with time-domain passivity control", IEEE Trans. Robotics and Automation 20(2),
2004), applied at the master's port to the displayed feedback: everything behind it (the
stream, the delay, the slave, the tissue, the return channel) is one one-port network, and the
network must never give the operator more energy than it received. (The virtual fixtures are
left out: one defined with the tool outside its region pulls the hand in with energy it never
received, by design.)

The observer sums the energy flowing into the network at the handle, one term a tick::

    E(n) = E(n-1) - f(n) . v(n) dt

with ``f`` the force displayed on the hand (N, the master's axes) and ``v`` the handle's
velocity (m/s): pressing into a wall (force against the motion) puts energy in, being pushed
back takes it out. When the force about to be displayed would make ``E`` negative, the
controller adds a variable damper that dissipates exactly the excess::

    alpha = -E / (|v|^2 dt),   f <- f - alpha v

(at most ``max_damping``, N s/m, so a handle nearly at rest is not kicked). Without delay a
spring-like contact returns what it stored and the controller stays idle; with delay it acts
only on the excess. Off with ``passivity: false`` (teleop-master), e.g. to measure the unstable
loop it prevents (tests/occ/test_bilateral.py does).
"""

from __future__ import annotations

from typing import Any

__all__ = ["PassivityController"]

Vec3 = tuple[float, float, float]


class PassivityController:
    """The observer and controller of one handle (see the module docstring)."""

    def __init__(self, max_damping: float = 200.0) -> None:
        self.max_damping = max_damping
        #: energy the network has taken in from the operator (J); never negative while active
        self.energy = 0.0
        self.active_ticks = 0
        self.dissipated = 0.0  # J, by the controller's damper in all
        self.last_damping = 0.0

    def reset(self) -> None:
        """Start observing afresh (entering RUNNING: nothing stored in the network)."""
        self.energy = 0.0
        self.last_damping = 0.0

    def step(self, f: Vec3, v: Vec3, dt: float) -> Vec3:
        """The force to display (``f`` or ``f`` with the damper added) for handle velocity
        ``v`` over ``dt`` seconds."""
        fx, fy, fz = f
        vx, vy, vz = v
        e = self.energy - (fx * vx + fy * vy + fz * vz) * dt
        alpha = 0.0
        if e < 0.0:
            v2 = vx * vx + vy * vy + vz * vz
            if v2 > 0.0 and dt > 0.0:
                alpha = min(-e / (v2 * dt), self.max_damping)
                fx, fy, fz = fx - alpha * vx, fy - alpha * vy, fz - alpha * vz
                self.dissipated += alpha * v2 * dt
                e += alpha * v2 * dt
                self.active_ticks += 1
        self.last_damping = alpha
        self.energy = e
        return (fx, fy, fz)

    def observe(self, f: Vec3, v: Vec3, dt: float) -> None:
        """Observe only (the controller off): the energy the network has given back shows as
        a negative ``energy`` (a diagnostic: how active the loop is)."""
        self.energy -= (f[0] * v[0] + f[1] * v[1] + f[2] * v[2]) * dt

    def stats(self) -> dict[str, Any]:
        return {
            "energy_mj": round(self.energy * 1e3, 4),
            "dissipated_mj": round(self.dissipated * 1e3, 4),
            "active_ticks": self.active_ticks,
            "damping": round(self.last_damping, 3),
        }
