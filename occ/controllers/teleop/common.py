"""What the master and the slave share: units, status codes, config checks, small maths."""

from __future__ import annotations

from collections.abc import Sequence
from types import MappingProxyType
from typing import Any

from occ.config import DaemonConfig
from occ.controllers import Problem

MM = 1e-3
#: the force limit's approach and retreat rate (m/s per N from 90 % of max_tissue_force_n)
LIMIT_GAIN = 0.005
#: OpenIGTLink STATUS codes the controller's alerts carry (igtl.StatusCode: OK 1, TIME_OUT 7)
STATUS_OK = 1
STATUS_TIME_OUT = 7
#: the master stream's metadata, one read-only mapping per (run, clutch): shared by every
#: message sent (500 Hz), so none is built per packet
RUN_CLUTCH = {
    (run, clutch): MappingProxyType({"run": "1" if run else "0", "clutch": "1" if clutch else "0"})
    for run in (False, True)
    for clutch in (False, True)
}


def interfaces_exist(params: Any, config: DaemonConfig, keys: tuple[str, ...]) -> list[Problem]:
    from occ.config.base import _did_you_mean

    names = [i.name for i in config.interfaces]
    out: list[Problem] = []
    for key in keys:
        ref = getattr(params, key)
        if ref is not None and ref not in names:
            out.append(((key,), f"unknown interface '{ref}'" + _did_you_mean(ref, names)))
    return out


def as_mm(p: Sequence[float] | None) -> list[float] | None:
    return None if p is None else [round(float(v) / MM, 6) for v in p]


def apply_jt(jt: Sequence[Sequence[float]], w: Sequence[float]) -> tuple[float, float, float]:
    """``J w`` for a Cartesian master's constant Jacobian, kept as its transpose's rows
    (a joint's column): the handle's position from ``q``, its velocity from ``qdot``."""
    x = y = z = 0.0
    for i, (a, b, c) in enumerate(jt):
        v = w[i]
        x, y, z = x + a * v, y + b * v, z + c * v
    return (x, y, z)


def as_m(p_mm: Sequence[float]) -> tuple[float, float, float]:
    return (p_mm[0] * MM, p_mm[1] * MM, p_mm[2] * MM)
