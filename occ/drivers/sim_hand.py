"""A simulated haptic master held by a simulated hand: plugin ``sim-hand``.

The OCC paper tests its virtual fixture with a motion the operator makes on the master
(X = A sin 2πft, Y = A cos 2πft, Z constant). Played as a position command, that motion
cannot be pushed back by anything; here it is what the operator *intends*, and the hand is an
arm that yields: a spring-damper from the intended point to the handle. The device is the
``sim`` driver's rigid body per joint on a viscous bearing, driven by the effort the master
controller commands (the displayed force) plus the hand's force::

    m a = u + K_hand (q_intended - x) + B_hand (v_intended - v) - b v

So a fixture's force visibly changes the handle's measured path (the hand gives way by
``u / K_hand``), and the slave, which follows the measured handle, follows the corrected path.
Each interval between reads is one exact step of that linear system (the effort and the
intention held over it, the intention taken at the interval's middle), as the ``sim`` drive's
servo; a joint with no hand spring, or a step that reaches an end stop, integrates in substeps.

The intended motion is per joint, for a device whose joints are its Cartesian axes (the shipped
``master3``): ``q_i(t) = intent_offset_i + intent_amplitude_i sin(2π intent_frequency_hz t +
intent_phase_deg_i)`` (metres or radians), with ``t`` the time the drive has been ACTIVE (the
operator waits while the master is off). The defaults are the paper's motion around the
workspace centre: 50 mm sine on x, 50 mm cosine on y, z at 20 mm, 0.1 Hz, which starts at the
``master3`` joint home (0, 0.05, 0.02) without a jump.

Parameters: every ``sim`` parameter (``command_interface`` is ``effort``, the only one taken;
``inertia`` and ``damping`` are the device's plus the hand's), and:

=====================  ===================  ============================================
key                    default              meaning
=====================  ===================  ============================================
hand_stiffness         300.0                N/m (N m/rad): the arm's stiffness, a relaxed
                                            human arm's order of magnitude
hand_damping           20.0                 N s/m (N m s/rad)
intent_amplitude       [0.05, 0.05, 0.0]    per joint, m (rad)
intent_phase_deg       [0.0, 90.0, 0.0]     per joint, degrees (90: the cosine)
intent_offset          [0.0, 0.0, 0.02]     per joint, m (rad)
intent_frequency_hz    0.1                  Hz
=====================  ===================  ============================================

Brakes (default on) lock the joints while the drive is not ACTIVE, as ``sim`` does; the
heartbeat is ``sim``'s.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

from mypy_extensions import mypyc_attr

from occ.drivers.base import CommandInterface, LimitPolicy
from occ.drivers.sim import SimDriver
from occ.drivers.sim_model import SIM_DEFAULTS
from occ.drivers.sim_model import per_joint as _per_joint
from occ.joint import Joint

__all__ = ["SimHandDriver", "HAND_DEFAULTS"]

HAND_DEFAULTS: dict[str, Any] = {
    **SIM_DEFAULTS,
    "command_interface": "effort",
    "inertia": 0.5,
    "damping": 1.0,
    "hand_stiffness": 300.0,
    "hand_damping": 20.0,
    "intent_amplitude": [0.05, 0.05, 0.0],
    "intent_phase_deg": [0.0, 90.0, 0.0],
    "intent_offset": [0.0, 0.0, 0.02],
    "intent_frequency_hz": 0.1,
}


def _joint_values(key: str, value: Any, joints: Sequence[Joint]) -> list[float]:
    """A per-joint list; the 3-element defaults fit a 3-joint device, others get zeros."""
    if isinstance(value, (list, tuple)) and len(value) != len(joints):
        if value == HAND_DEFAULTS[key]:
            return [0.0] * len(joints)
        raise ValueError(f"sim-hand param {key!r}: expected {len(joints)} values, got {len(value)}")
    if isinstance(value, Mapping):
        return [float(value.get(j.name, 0.0)) for j in joints]
    return (
        _per_joint(key, value, joints)
        if not isinstance(value, (list, tuple))
        else [float(v) for v in value]
    )


@mypyc_attr(allow_interpreted_subclasses=True)  # mypyc: plugins extend built-ins
class SimHandDriver(SimDriver):
    """A ``sim`` device in effort mode moved by a simulated hand (see the module docstring)."""

    # SimDriver names two; this one takes efforts only
    supported_interfaces: ClassVar[tuple[str, ...]] = ("effort",)  # type: ignore[assignment]
    DEFAULT_PARAMS = HAND_DEFAULTS

    def __init__(
        self,
        name: str,
        joints: Sequence[Joint],
        params: Mapping[str, Any] | None = None,
        on_limit: LimitPolicy = "clamp",
        command_interface: CommandInterface | None = None,
    ) -> None:
        super().__init__(name, joints, params, on_limit, command_interface)
        p = self.params
        js = self.joints
        self._k_hand = _joint_values("hand_stiffness", p["hand_stiffness"], js)
        self._b_hand = _joint_values("hand_damping", p["hand_damping"], js)
        self._amp = _joint_values("intent_amplitude", p["intent_amplitude"], js)
        self._phase = [
            math.radians(v) for v in _joint_values("intent_phase_deg", p["intent_phase_deg"], js)
        ]
        self._offset = _joint_values("intent_offset", p["intent_offset"], js)
        self._w = 2.0 * math.pi * float(p["intent_frequency_hz"])
        for i, j in enumerate(js):
            if self._k_hand[i] < 0.0 or self._b_hand[i] < 0.0:
                raise ValueError(f"sim-hand joint {j.name!r}: hand stiffness and damping >= 0")
        # the hand's spring and damper are fast poles too: keep the substep inside them
        fastest = max(
            max(
                math.sqrt(k * inv) for k, (inv, *_r) in zip(self._k_hand, self._model, strict=True)
            ),
            max(b * inv for b, (inv, *_r) in zip(self._b_hand, self._model, strict=True)),
        )
        if fastest > 0.0:
            self._substep = min(self._substep, 0.1 / fastest)
        # The exact step: with the intention and the effort held over an interval, the handle
        # obeys m x'' = F - K_hand x - (B_hand + b) x' (F = u + K_hand q_i + B_hand v_i), so
        # e = x - F / K_hand obeys e'' + c e' + k e = 0 with k = K_hand / m, c = (B_hand + b) / m:
        # the sim drive's exact step (this drive has no servo; these are its poles). A joint
        # with no hand spring, or a step that reaches an end stop, integrates in substeps.
        self._set_poles(
            [
                (kh * inv, (bh + b) * inv)
                for kh, bh, (inv, b, *_r) in zip(
                    self._k_hand, self._b_hand, self._model, strict=True
                )
            ]
        )
        #: per joint, what the integrator reads every tick
        self._hand = [
            (kh, bh, a, ph, off, lo, hi)
            for kh, bh, a, ph, off, (_inv, _b, lo, hi, *_r) in zip(
                self._k_hand,
                self._b_hand,
                self._amp,
                self._phase,
                self._offset,
                self._model,
                strict=True,
            )
        ]
        #: time the drive has been ACTIVE: the operator's intended motion runs on it
        self.intent_t = 0.0

    def intended(self, t: float | None = None) -> list[float]:
        """The intended joint positions at intent time ``t`` (now when None)."""
        t = self.intent_t if t is None else t
        w = self._w
        return [
            o + a * math.sin(w * t + ph)
            for o, a, ph in zip(self._offset, self._amp, self._phase, strict=True)
        ]

    def _configure(self) -> None:
        super()._configure()
        self.intent_t = 0.0

    def _integrate(self, now: float) -> None:
        t = self._t
        if t != t:
            self._t = now
            return
        dt = now - t
        if dt <= 0.0:
            return
        self._t = now
        enabled = self._enabled
        if not enabled and self._brakes:
            u_all, v_all = self._u, self._v
            for i in range(len(u_all)):
                u_all[i] = 0.0
                v_all[i] = 0.0
            return
        w = self._w
        tau0 = self.intent_t
        # the intention at the middle of the interval, held over it: it moves at 0.1 Hz,
        # the interval is a tick (1 ms); one sin/cos per moving joint and tick
        mid = w * (tau0 + 0.5 * dt) if enabled else w * tau0
        x_all, v_all, u_all, cmd = self._x, self._v, self._u, self._cmd
        step = self._step if -1e-9 < dt - self._step_h < 1e-9 else self._exact_steps(dt)
        for i, (kh, bh, a, ph, off, lo, hi) in enumerate(self._hand):
            x = x_all[i]
            v = v_all[i]
            u = cmd[i] if enabled else 0.0
            if a != 0.0:
                target = off + a * math.sin(mid + ph)
                target_v = a * w * math.cos(mid + ph)
            else:
                target, target_v = off, 0.0
            if kh > 0.0:
                x_eq = (u + kh * target + bh * target_v) / kh
                a11, a12, a21, a22 = step[i]
                e = x - x_eq
                x1 = x_eq + a11 * e + a12 * v
                if lo <= x1 <= hi:
                    x_all[i] = x1
                    v_all[i] = a21 * e + a22 * v
                    u_all[i] = u
                    continue
            x_all[i], v_all[i] = self._substeps(i, dt, u, target, target_v)
            u_all[i] = u
        if enabled:
            self.intent_t = tau0 + dt

    def _substeps(
        self, i: int, dt: float, u: float, target: float, target_v: float
    ) -> tuple[float, float]:
        """Joint ``i`` over ``dt`` in explicit substeps: no hand spring, or an end stop."""
        inv_j, b, lo, hi, *_r = self._model[i]
        kh, bh = self._k_hand[i], self._b_hand[i]
        x, v = self._x[i], self._v[i]
        steps = math.ceil(dt / self._substep - 1e-9)
        h = dt / steps
        for _ in range(steps):
            hand = kh * (target - x) + bh * (target_v - v)
            v += (u + hand - b * v) * inv_j * h
            x += v * h
            if x < lo or x > hi:
                x = lo if x < lo else hi
                v = 0.0
        return x, v
