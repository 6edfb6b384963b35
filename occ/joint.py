"""Joints: limits, measured state, commanded state and the per-joint servo law.

A :class:`Joint` is plain data that the drivers fill (``read``) and the controllers command
(``write``); it never touches hardware. Units are SI: radians for revolute joints, metres for
prismatic ones, newton-metres / newtons for efforts.

The servo law (:meth:`Joint.servo`) exists for drivers whose hardware takes torque/force
rather than position (``command_interface = 'effort'``): the driver base turns each position
setpoint into an effort with the joint's PID. It is a textbook parallel PID with two choices
that matter on a robot:

* derivative on *measurement*, not on error, so a step in the setpoint does not produce a
  derivative kick (the setpoint of a teleoperated joint changes every tick);
* anti-windup by clamping the integral term to ``i_limit`` and by conditional integration:
  the integrator is frozen while the output is saturated in the direction of the error, so a
  joint held against an obstacle does not wind up and overshoot when released.

The servo runs every tick of the 1 kHz loop, so it works on plain floats and keeps its memory
in slots.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

__all__ = ["JointLimits", "PIDGains", "Joint", "JointType"]

JointType = Literal["revolute", "prismatic"]
_JOINT_TYPES = ("revolute", "prismatic")


@dataclass(slots=True)
class JointLimits:
    """Hard limits of one joint, in SI units.

    ``velocity`` bounds the rate of change of the *setpoint* (checked by the driver base on
    every write), ``effort`` bounds the servo output. Use ``math.inf`` for "no limit".
    """

    min: float
    max: float
    velocity: float = math.inf
    effort: float = math.inf

    def __post_init__(self) -> None:
        for field_name in ("min", "max", "velocity", "effort"):
            value = getattr(self, field_name)
            if not isinstance(value, (int, float)) or math.isnan(value):
                raise ValueError(f"JointLimits.{field_name} must be a number, got {value!r}")
            setattr(self, field_name, float(value))
        if self.min > self.max:
            raise ValueError(f"JointLimits: min {self.min} > max {self.max}")
        if self.velocity <= 0.0:
            raise ValueError(f"JointLimits.velocity must be > 0, got {self.velocity}")
        if self.effort <= 0.0:
            raise ValueError(f"JointLimits.effort must be > 0, got {self.effort}")

    def contains(self, position: float) -> bool:
        """True when ``position`` lies inside ``[min, max]`` (NaN is never inside)."""
        return self.min <= position <= self.max

    def clamp(self, position: float) -> float:
        """Return ``position`` clamped to ``[min, max]``."""
        if position < self.min:
            return self.min
        if position > self.max:
            return self.max
        return position


@dataclass(slots=True)
class PIDGains:
    """Gains of the per-joint servo law (effort units per SI position unit).

    ``i_limit`` bounds the integral *term* (in effort units, not the raw integral) and
    ``out_limit`` bounds the total output; the joint's own ``limits.effort`` bounds it too.
    """

    kp: float
    ki: float = 0.0
    kd: float = 0.0
    i_limit: float = math.inf
    out_limit: float = math.inf

    def __post_init__(self) -> None:
        for field_name in ("kp", "ki", "kd", "i_limit", "out_limit"):
            value = getattr(self, field_name)
            if not isinstance(value, (int, float)) or math.isnan(value) or value < 0.0:
                raise ValueError(f"PIDGains.{field_name} must be a number >= 0, got {value!r}")
            setattr(self, field_name, float(value))


class Joint:
    """One joint: identity, limits, home, measured and commanded state, servo memory.

    State attributes (written by drivers on ``read`` and by the driver base on ``write``):

    ``position``, ``velocity``, ``effort``
        the last measured values (SI units);
    ``measured``
        ``False`` until a driver has filled the state once, so nobody mistakes the initial
        zeros (or ``home``) for a measurement;
    ``stamp``
        the ``now`` of the read that produced the measurement (seconds, loop clock);
    ``command_position``
        the last position setpoint accepted by the driver (after limit clamping), NaN before
        the first write;
    ``command_effort``
        the last effort sent to effort-interface hardware (NaN when not applicable).
    """

    __slots__ = (
        "name",
        "type",
        "limits",
        "home",
        "gains",
        "position",
        "velocity",
        "effort",
        "measured",
        "stamp",
        "command_position",
        "command_effort",
        "_integral",
        "_prev_measured",
    )

    def __init__(
        self,
        name: str,
        type: JointType = "revolute",  # noqa: A002 - URDF vocabulary
        limits: JointLimits | None = None,
        home: float = 0.0,
        gains: PIDGains | None = None,
    ) -> None:
        if not name:
            raise ValueError("a joint needs a non-empty name")
        if type not in _JOINT_TYPES:
            raise ValueError(f"joint {name!r}: type must be one of {_JOINT_TYPES}, got {type!r}")
        self.name: str = name
        self.type: JointType = type
        if limits is None:
            limits = JointLimits(-math.inf, math.inf)
        self.limits: JointLimits = limits
        home = float(home)
        if not self.limits.contains(home):
            raise ValueError(
                f"joint {name!r}: home {home} outside limits [{self.limits.min}, {self.limits.max}]"
            )
        self.home: float = home
        self.gains: PIDGains | None = gains
        self.position: float = home
        self.velocity: float = 0.0
        self.effort: float = 0.0
        self.measured: bool = False
        self.stamp: float = math.nan
        self.command_position: float = math.nan
        self.command_effort: float = math.nan
        self._integral: float = 0.0
        self._prev_measured: float = math.nan

    def __repr__(self) -> str:
        return (
            f"Joint({self.name!r}, {self.type!r}, position={self.position:.6g}, "
            f"limits=[{self.limits.min:.6g}, {self.limits.max:.6g}])"
        )

    def set_measured(self, position: float, velocity: float, effort: float, now: float) -> None:
        """Store one measurement (called by drivers; kept tiny because it runs every tick)."""
        self.position = position
        self.velocity = velocity
        self.effort = effort
        self.measured = True
        self.stamp = now

    def reset_servo(self) -> None:
        """Forget the integral and the previous measurement.

        Called by drivers on activation and on fault reset so that a stale integral from a
        previous session never becomes a torque step.
        """
        self._integral = 0.0
        self._prev_measured = math.nan
        self.command_effort = math.nan

    def servo(self, setpoint: float, dt: float) -> float:
        """One tick of the PID servo: return the effort that drives ``position`` to ``setpoint``.

        ``dt`` is the time since the previous call (seconds). With ``dt <= 0`` (first tick, or
        a clock that did not advance) only the proportional and the held integral terms act.
        Raises ``ValueError`` if the joint has no gains: asking an un-tuned joint for torque is
        a configuration mistake, not a runtime condition.
        """
        gains = self.gains
        if gains is None:
            raise ValueError(f"joint {self.name!r} has no PID gains but its driver wants effort")
        position = self.position
        error = setpoint - position
        p_term = gains.kp * error

        d_term = 0.0
        prev = self._prev_measured
        if dt > 0.0 and prev == prev:  # prev == prev is a NaN test without a call
            d_term = -gains.kd * (position - prev) / dt
        self._prev_measured = position

        limit = gains.out_limit
        if self.limits.effort < limit:
            limit = self.limits.effort

        integral = self._integral
        if dt > 0.0 and gains.ki > 0.0:
            candidate = integral + gains.ki * error * dt
            i_limit = gains.i_limit
            if candidate > i_limit:
                candidate = i_limit
            elif candidate < -i_limit:
                candidate = -i_limit
            unsat = p_term + candidate + d_term
            # Conditional integration: only accept the new integral if it does not push an
            # already saturated output further into saturation.
            if not ((unsat > limit and error > 0.0) or (unsat < -limit and error < 0.0)):
                integral = candidate
                self._integral = integral

        out = p_term + integral + d_term
        if out > limit:
            out = limit
        elif out < -limit:
            out = -limit
        self.command_effort = out
        return out


def step_together(values: list[float], target: Sequence[float], steps: Sequence[float]) -> bool:
    """Move ``values`` (in place) toward ``target`` along the straight line between them, by
    the largest common fraction of the way that keeps every joint within its ``steps``; True
    while still away. Every joint arrives on the same tick: the path in joint space is the
    straight line, not the corner of each joint stepping on its own (where the faster joints
    arrive first), so a constraint both ends meet (a tool's axis through a port) is left only
    to second order in the distance, never by the first-order detour of one joint moving
    alone."""
    frac = 1.0
    for i, step in enumerate(steps):
        d = target[i] - values[i]
        if d > step:
            f = step / d
        elif d < -step:
            f = -step / d
        else:
            continue
        if f < frac:
            frac = f
    if frac > 1.0 - 1e-12:  # there, or a rounding error away: exactly the target
        values[:] = target
        return False
    for i, v in enumerate(values):
        values[i] = v + frac * (target[i] - v)
    return True
