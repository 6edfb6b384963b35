"""The simulated drive's joint model: its parameters and the arithmetic of its dynamics.

:class:`~occ.drivers.sim.SimDriver` is the drive (its hooks, heartbeat and injected faults);
this module holds what it computes with: :func:`sim_params` reads and checks the model's
parameters (the table in :mod:`occ.drivers.sim`'s docstring) and derives the servo's gains and
the integration substep; :func:`distinct_poles` and :func:`exact_steps` give the exact step of
a servoed joint over an interval; :func:`position_substeps` and :func:`effort_substeps`
integrate one joint in semi-implicit Euler substeps where the exact step does not apply;
:func:`average_effort` keeps the reported effort's running mean.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from occ.errors import caused
from occ.joint import Joint

__all__ = [
    "SIM_DEFAULTS",
    "SimParams",
    "sim_params",
    "distinct_poles",
    "exact_steps",
    "position_substeps",
    "effort_substeps",
    "average_effort",
]

_REVOLUTE_RESOLUTION = 2.0 * math.pi / 2**17  # a common 17-bit absolute rotary encoder
_PRISMATIC_RESOLUTION = 1e-6  # a 1 um linear scale

SIM_DEFAULTS: dict[str, Any] = {
    "command_interface": "position",
    "inertia": 0.01,
    "damping": 0.1,
    "bandwidth_hz": 10.0,
    "damping_ratio": 1.0,
    "encoder_resolution": None,  # by joint type, see the sim module's docstring
    "noise_std": 0.0,
    "seed": 0,
    "initial_positions": None,
    "max_substep": 0.0005,
    "brakes": True,
    "period": 0.001,
    "faults": (),
    "effort_average_ms": 0.0,
}

# A substep must stay well inside the stability region of semi-implicit Euler for the
# fastest pole of the model; 0.1 / rate keeps the discretisation error around 1 %.
_STEP_PER_RATE = 0.1


def per_joint(
    key: str, value: Any, joints: Sequence[Joint], defaults: Sequence[float] | None = None
) -> list[float]:
    """Expand a scalar / list / {name: value} parameter into one float per joint.

    Joints missing from a mapping take ``defaults`` (per joint) or the scalar default.
    """
    n = len(joints)
    if isinstance(value, Mapping):
        unknown = set(value) - {j.name for j in joints}
        if unknown:
            raise ValueError(f"sim param {key!r}: unknown joints {sorted(unknown)}")
        fallback = list(defaults) if defaults is not None else [SIM_DEFAULTS[key]] * n
        out = [value.get(j.name, fallback[i]) for i, j in enumerate(joints)]
    elif isinstance(value, (list, tuple)):
        if len(value) != n:
            raise ValueError(f"sim param {key!r}: expected {n} values, got {len(value)}")
        out = list(value)
    else:
        out = [value] * n
    try:
        return [float(v) for v in out]
    except (TypeError, ValueError) as err:
        raise caused(ValueError(f"sim param {key!r}: not a number: {value!r}"), err) from err


@dataclass(frozen=True)
class SimParams:
    """The model's parameters per joint, checked, and what follows from them."""

    inertia: list[float]
    damping: list[float]
    #: the encoders' noise (standard deviation) and quantum (0: exact)
    noise: list[float]
    resolution: list[float]
    #: where the joints start at configure
    initial: list[float]
    #: the internal servo's gains (position interface)
    kp: list[float]
    kd: list[float]
    #: the integration substep, s
    substep: float
    #: the reported effort's averaging window, s (0: none)
    avg_window: float


def _checked(
    p: Mapping[str, Any], js: Sequence[Joint]
) -> tuple[
    list[float], list[float], list[float], list[float], list[float], list[float], list[float]
]:
    """The per-joint values of ``p`` (inertia, damping, bandwidth, damping ratio, noise,
    resolution), checked joint by joint with the initial positions, and those positions."""
    inertia = per_joint("inertia", p["inertia"], js)
    damping = per_joint("damping", p["damping"], js)
    bandwidth = per_joint("bandwidth_hz", p["bandwidth_hz"], js)
    zeta = per_joint("damping_ratio", p["damping_ratio"], js)
    noise = per_joint("noise_std", p["noise_std"], js)
    by_type = [_REVOLUTE_RESOLUTION if j.type == "revolute" else _PRISMATIC_RESOLUTION for j in js]
    resolution = (
        by_type
        if p["encoder_resolution"] is None
        else per_joint("encoder_resolution", p["encoder_resolution"], js, by_type)
    )
    homes = [j.home for j in js]
    initial = (
        homes
        if p["initial_positions"] is None
        else per_joint("initial_positions", p["initial_positions"], js, homes)
    )
    for i, j in enumerate(js):
        if inertia[i] <= 0.0 or damping[i] < 0.0:
            raise ValueError(f"sim joint {j.name!r}: inertia must be > 0 and damping >= 0")
        if bandwidth[i] <= 0.0 or zeta[i] <= 0.0:
            raise ValueError(f"sim joint {j.name!r}: bandwidth and damping ratio must be > 0")
        if resolution[i] < 0.0 or noise[i] < 0.0:
            raise ValueError(f"sim joint {j.name!r}: resolution and noise must be >= 0")
        if not j.limits.contains(initial[i]):
            raise ValueError(f"sim joint {j.name!r}: initial position outside limits")
    return inertia, damping, bandwidth, zeta, noise, resolution, initial


def sim_params(p: Mapping[str, Any], js: Sequence[Joint], interface: str) -> SimParams:
    """The model of joints ``js`` from the merged parameters ``p`` (``interface``: the
    driver's command interface); ValueError naming the first bad one."""
    n = len(js)
    inertia, damping, bandwidth, zeta, noise, resolution, initial = _checked(p, js)
    max_substep = float(p["max_substep"])
    if not max_substep > 0.0:
        raise ValueError("sim param 'max_substep' must be > 0")
    # Servo gains placing the closed-loop poles (position interface).
    wn = [2.0 * math.pi * f for f in bandwidth]
    kp = [inertia[i] * wn[i] ** 2 for i in range(n)]
    kd = [max(0.0, 2.0 * zeta[i] * wn[i] * inertia[i] - damping[i]) for i in range(n)]
    fastest = 0.0
    for i in range(n):
        rate = damping[i] / inertia[i]
        if interface == "position":
            rate = max(rate, wn[i], (damping[i] + kd[i]) / inertia[i])
        fastest = max(fastest, rate)
    substep = min(max_substep, _STEP_PER_RATE / fastest) if fastest > 0 else max_substep
    avg = float(p["effort_average_ms"])
    if not (avg >= 0.0 and math.isfinite(avg)):
        raise ValueError("sim param 'effort_average_ms' must be >= 0")
    return SimParams(inertia, damping, noise, resolution, initial, kp, kd, substep, avg * 1e-3)


def distinct_poles(
    poles: Sequence[tuple[float, float]],
) -> tuple[list[int], list[tuple[float, float, float, float]]]:
    """The poles ``(k, c)`` of each joint's exact step (``e'' + c e' + k e = 0``): which
    distinct pair each joint has, and per distinct pair what of the step does not depend on
    its length, ``(k, c/2, d^2, sqrt(|d^2|))`` (see :func:`exact_steps`)."""
    distinct: list[tuple[float, float]] = []
    for pole in poles:
        if pole not in distinct:
            distinct.append(pole)
    which = [distinct.index(pole) for pole in poles]
    out = []
    for k, c in distinct:
        half = 0.5 * c
        d2 = half * half - k
        out.append((k, half, d2, math.sqrt(d2 if d2 > 0.0 else -d2)))
    return which, out


def exact_steps(
    distinct: Sequence[tuple[float, float, float, float]], h: float
) -> list[tuple[float, float, float, float]]:
    """Per distinct pair of poles (:func:`distinct_poles`), the transition matrix over ``h``
    of ``(e, v)`` (``e = x - r``) for ``e'' + c e' + k e = 0``: ``exp(A h)`` with
    ``A = [[0, 1], [-k, -c]]``, written as ``exp(s h) (C I + S (A - s I))``, ``s = -c/2``,
    ``d^2 = c^2/4 - k``, ``C = cosh(d h)`` and ``S = sinh(d h)/d`` (cos and sin/omega when
    ``d^2 < 0``; series near 0)."""
    out = []
    for k, half, d2, root in distinct:  # root: d, or w when d^2 < 0
        z = d2 * h * h
        if abs(z) < 1e-8:  # near critical damping: the series of cosh and sinh/d
            big_c = 1.0 + 0.5 * z
            big_s = h * (1.0 + z / 6.0)
        elif d2 > 0.0:
            big_c = math.cosh(root * h)
            big_s = math.sinh(root * h) / root
        else:
            big_c = math.cos(root * h)
            big_s = math.sin(root * h) / root
        g = math.exp(-half * h)
        out.append(
            (g * (big_c + half * big_s), g * big_s, -g * big_s * k, g * (big_c - half * big_s))
        )
    return out


def position_substeps(
    model: tuple[float, float, float, float, float, float, float],
    x: float,
    v: float,
    r: float,
    te: float,
    steps: int,
    h: float,
) -> tuple[float, float, float]:
    """One servoed joint (``model``: 1/J, b, lo, hi, kp, kd, effort limit) from ``(x, v)``
    towards ``r`` under the load ``te`` in ``steps`` substeps of ``h``, its effort clamped and
    its end stops hard: the new ``(x, v, u)``."""
    inv_j, b, lo, hi, kp, kd, ulim = model
    u = 0.0
    for _ in range(steps):
        u = kp * (r - x) - kd * v
        if u > ulim:
            u = ulim
        elif u < -ulim:
            u = -ulim
        v += (u + te - b * v) * inv_j * h
        x += v * h
        if x < lo or x > hi:  # end stop
            x = lo if x < lo else hi
            v = 0.0
    return x, v, u


def effort_substeps(
    model: tuple[float, float, float, float, float, float, float],
    x: float,
    v: float,
    u: float,
    te: float,
    steps: int,
    h: float,
) -> tuple[float, float]:
    """One joint under the effort ``u`` and the load ``te`` in ``steps`` substeps of ``h``
    (``model`` as :func:`position_substeps`'s): the new ``(x, v)``."""
    inv_j, b, lo, hi = model[0], model[1], model[2], model[3]
    for _ in range(steps):
        v += (u + te - b * v) * inv_j * h
        x += v * h
        if x < lo or x > hi:
            x = lo if x < lo else hi
            v = 0.0
    return x, v


def average_effort(
    hist: list[tuple[float, list[float]]],
    window: float,
    dt: float,
    integral: list[float],
    avg: list[float],
) -> None:
    """The reported effort ``avg``: the mean over the last intervals spanning ``window``,
    ``hist`` holding them (length, per joint the effort's integral), this one's added."""
    hist.append((dt, integral))
    span = 0.0
    for h, _ in hist:
        span += h
    while len(hist) > 1 and span - hist[0][0] >= window - 1e-9:
        span -= hist.pop(0)[0]
    for i in range(len(avg)):
        total = 0.0
        for _, part in hist:
            total += part[i]
        avg[i] = total / span
