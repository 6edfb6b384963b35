"""The hardware faults a simulated drive can be made to play (:meth:`SimDriver.inject`).

:class:`SimFaults` holds which faults are injected (kind -> joint index), their amounts, and
turns the model's true reading into the faulty one the drive reports; the drive's hooks ask it
which of their own faults apply. The kinds and what each does are in the table of
:mod:`occ.drivers.sim`'s docstring.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from occ.joint import Joint

__all__ = ["SIM_FAULTS", "FAULT_AMOUNTS", "SimFaults", "fault_specs"]

#: the hardware faults :meth:`SimDriver.inject` can play (see the sim module's docstring)
SIM_FAULTS = (
    "configure",
    "activate",
    "hook",
    "write",
    "heartbeat",
    "nan",
    "frozen",
    "jump",
    "drift",
    "slip",
)
#: the default ``amount`` of the faults that take one: a runaway encoder at one period's worth
#: of the shipped insertion's velocity limit a tick (0.1 m/s; rad/s on a revolute joint), a
#: slip of five times that in one go (issue 36's cases)
FAULT_AMOUNTS = {"drift": 0.1, "slip": 0.0005}


def fault_specs(faults: Any) -> list[str]:
    """The ``faults`` parameter: a list of specs (``kind``, ``kind:joint`` or
    ``kind:joint:amount``), as strings; ValueError when it is no list."""
    if isinstance(faults, str) or not isinstance(faults, (list, tuple)):
        raise ValueError(f"sim param 'faults' must be a list of fault kinds, got {faults!r}")
    return [str(spec) for spec in faults]


class SimFaults:
    """The faults injected into one simulated drive of ``joints`` (empty when healthy)."""

    def __init__(self, joints: Sequence[Joint]) -> None:
        self.joints = list(joints)
        #: injected faults: kind -> joint index (see :meth:`inject`); empty when healthy
        self.kinds: dict[str, int] = {}
        self._amounts: dict[str, float] = {}
        self._drift_from = math.nan
        self._frozen_at: list[float] = []
        self._out = [0.0] * len(joints)

    def inject(
        self,
        kind: str,
        joint: int,
        amount: float | None,
        driver: str,
        measured: Sequence[float],
        t: float,
    ) -> None:
        """Fault ``kind`` on ``joint`` from now on (``driver``: its name, for the errors;
        ``measured``: the drive's last reading, where ``frozen`` stays; ``t``: the model's
        time, where ``drift`` starts). ValueError for a fault that cannot be played."""
        if kind not in SIM_FAULTS:
            raise ValueError(f"unknown fault {kind!r}; faults are: {', '.join(SIM_FAULTS)}")
        if not 0 <= joint < len(self.joints):
            raise ValueError(f"joint index {joint} out of range for driver {driver!r}")
        if amount is not None and kind not in FAULT_AMOUNTS:
            raise ValueError(f"fault {kind!r} takes no amount")
        if amount is not None and not math.isfinite(amount):
            raise ValueError(f"fault {kind!r}: amount must be finite, got {amount}")
        if kind == "frozen":
            self._frozen_at = list(measured)
        if kind in FAULT_AMOUNTS:
            self._amounts[kind] = FAULT_AMOUNTS[kind] if amount is None else float(amount)
            self._drift_from = t  # NaN before the first step: from the first read
        self.kinds[kind] = joint

    def reading(self, out: Sequence[float], t: float) -> Sequence[float]:
        """What the faulty drive reports at model time ``t`` for the true reading ``out``
        (a buffer reused by every call)."""
        faults = self.kinds
        if "hook" in faults:
            raise RuntimeError("simulated fault: exception in the drive's read hook")
        res = self._out
        res[:] = self._frozen_at if "frozen" in faults else out
        if "jump" in faults:
            j = self.joints[faults["jump"]]
            res[faults["jump"]] += 0.2 * (j.limits.max - j.limits.min)
        if "drift" in faults:
            if self._drift_from != self._drift_from:
                self._drift_from = t
            res[faults["drift"]] += self._amounts["drift"] * (t - self._drift_from)
        if "slip" in faults:
            res[faults["slip"]] += self._amounts["slip"]
        if "nan" in faults:
            res[faults["nan"]] = math.nan
        return res
