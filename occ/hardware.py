"""The HardwareSet: a robot's drives as one unit whose transitions succeed or fail whole.

A robot never moves on part of its hardware. Every operation here goes to every drive and
reports what failed instead of raising, so the robot decides (:mod:`occ.robot`):

=============  ===============================================================================
operation      on failure
=============  ===============================================================================
configure      the failed drives are latched FAULT in their base; the robot starts in FAULT
activate       all or nothing: the drives already powered are switched off again and the
               transition that asked for power (``enable``, ``run`` from STOPPED) is vetoed;
               the robot latches FAULT naming the drive
deactivate     never refused (a stop cannot be): a drive that fails to stop is latched FAULT
               by its base (which tries its ``_deactivate`` once more) and named in an alert
reset          the transition out of FAULT is vetoed: the robot stays FAULT
read           every drive is still read; the robot latches FAULT naming the drive
write          checked before anything is written: every drive must be ACTIVE (a drive that
               faulted by itself is never left out silently); a write that raises, whatever
               its type, is a failure; the robot latches FAULT and the FAULT transition powers
               every other drive off in the same tick
=============  ===============================================================================

:attr:`HardwareSet.last_fault_to_safe_s` is the measured time (``time.perf_counter``) from
the detection of a read or write failure to the moment the last drive was in its safe state
(INACTIVE or FAULT, power stages off), reported by ``GetStats`` under ``hardware``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from .drivers.base import Driver, DriverState
from .joint import Joint

log = logging.getLogger(__name__)

__all__ = ["HardwareFailure", "HardwareSet", "describe"]


@dataclass(frozen=True)
class HardwareFailure:
    """What failed: the drive's name, the operation, the cause (the driver's own words)."""

    driver: str
    action: str
    cause: str

    def __str__(self) -> str:
        return f"driver {self.driver}: {self.action} failed: {self.cause}"


def describe(failures: Sequence[HardwareFailure]) -> str:
    """One line naming every failed drive and its cause."""
    return "; ".join(str(f) for f in failures)


def _cause(err: BaseException) -> str:
    text = str(err)
    return text if text else type(err).__name__


#: driver states in which the hardware is safe: power stages off (or never on)
SAFE = (DriverState.INACTIVE, DriverState.FAULT, DriverState.UNCONFIGURED, DriverState.SHUTDOWN)


class HardwareSet:
    """The robot's drives, each with the joint indices it serves (see the module docstring)."""

    def __init__(self, pairs: Sequence[tuple[Driver, list[int]]]) -> None:
        #: (driver, the indices of its joints in the robot's joint order)
        self.pairs: list[tuple[Driver, list[int]]] = [(d, list(idx)) for d, idx in pairs]
        self.drivers: list[Driver] = [d for d, _ in self.pairs]
        # per driver: its slice of the robot's values, copied into a buffer it keeps
        self._slices = [(d, idx, [0.0] * len(idx)) for d, idx in self.pairs]
        n_joints = sum(len(idx) for _d, idx in self.pairs)
        #: one drive with every joint in order (the shipped robots): it takes the values as
        #: they come, no slice copied
        self._whole = (
            self.pairs[0][0]
            if len(self.pairs) == 1 and list(self.pairs[0][1]) == list(range(n_joints))
            else None
        )
        self._fault_t: float | None = None
        #: fault detected (read or write) -> last drive safe, seconds (None before any)
        self.last_fault_to_safe_s: float | None = None
        self.failures = 0
        #: the simulated world the drives touch (occ/contact.py), None on real hardware
        self.environment: Any = None

    # ------------------------------------------------------------------ inspection
    def faulted(self) -> list[HardwareFailure]:
        """Every drive latched FAULT, with its reason."""
        return [
            HardwareFailure(d.name, "drive", d.fault_reason or "fault")
            for d in self.drivers
            if d.state is DriverState.FAULT
        ]

    def unmeasured(self, joints: Sequence[Joint]) -> str:
        """The drives whose joints have never been measured, named with those joints ('' when
        every joint has been): the robot may not power them (it would hold a position nobody
        reported)."""
        missing = []
        for d, idx in self.pairs:
            names = [joints[i].name for i in idx if not joints[i].measured]
            if names:
                missing.append(f"driver {d.name} joints {names}")
        return "; ".join(missing)

    def all_safe(self) -> bool:
        return all(d.state in SAFE for d in self.drivers)

    def stats(self) -> dict[str, Any]:
        lat = self.last_fault_to_safe_s
        return {
            "drivers": {d.name: d.stats() for d in self.drivers},
            "states": {d.name: d.state.value for d in self.drivers},
            "failures": self.failures,
            "last_fault_to_safe_us": None if lat is None else round(lat * 1e6, 1),
            **({"environment": self.environment.stats()} if self.environment else {}),
        }

    # ------------------------------------------------------------------ lifecycle
    def await_measured(
        self, joints: Sequence[Joint], read: Any, now: Any, wait_s: float, real: bool
    ) -> None:
        """After :meth:`configure`: ``read(now())`` once, and on the real clock (``real``)
        again every 5 ms until every joint is measured or ``wait_s`` has passed (a joint still
        unmeasured keeps the robot from being enabled)."""
        read(now())
        give_up = now() + wait_s
        while real and now() < give_up:
            if all(j.measured for j in joints):
                break
            time.sleep(0.005)
            read(now())

    def configure(self) -> list[HardwareFailure]:
        """Configure every unconfigured drive; the failed ones are latched FAULT."""
        failures = []
        for d in self.drivers:
            if d.state is not DriverState.UNCONFIGURED:
                continue
            try:
                d.configure()
            except Exception as err:  # noqa: BLE001 - every drive is tried, each failure named
                failures.append(HardwareFailure(d.name, "configure", _cause(err)))
        return self._count(failures)

    def activate(self) -> list[HardwareFailure]:
        """Power every drive, or none: a drive that cannot be powered (its activation fails,
        or it is latched FAULT, or was never configured) switches the others off again."""
        failures = []
        for d in self.drivers:
            st = d.state
            if st is DriverState.ACTIVE:
                continue
            if st is not DriverState.INACTIVE:
                why = d.fault_reason or f"drive is {st.value}"
                failures.append(HardwareFailure(d.name, "activate", why))
                continue
            try:
                d.activate()
            except Exception as err:  # noqa: BLE001
                failures.append(HardwareFailure(d.name, "activate", _cause(err)))
        if failures:
            self._detected()
            self.deactivate()  # the ones that came up go off again: all or nothing
        return self._count(failures)

    def deactivate(self) -> list[HardwareFailure]:
        """Every ACTIVE drive to its safe state; never stops half way. A drive whose
        deactivation fails is latched FAULT by its base (which stops following commands)."""
        failures = []
        for d in self.drivers:
            if d.state is not DriverState.ACTIVE:
                continue
            try:
                d.deactivate()
            except Exception as err:  # noqa: BLE001
                failures.append(HardwareFailure(d.name, "deactivate", _cause(err)))
        t = self._fault_t
        if t is not None and self.all_safe():
            self.last_fault_to_safe_s = time.perf_counter() - t
            self._fault_t = None
        return self._count(failures)

    def reset(self) -> list[HardwareFailure]:
        """Clear every latched drive fault and configure the drives never configured."""
        failures = []
        for d in self.drivers:
            if d.state is not DriverState.FAULT:
                continue
            try:
                d.reset()
            except Exception as err:  # noqa: BLE001
                failures.append(HardwareFailure(d.name, "reset", _cause(err)))
        failures += self.configure()
        return self._count(failures)

    def safe_stop(self, reason: str) -> None:
        """From the supervisor's thread: every drive to its safe state at once (never raises)."""
        for d in self.drivers:
            d.safe_stop(reason)

    def shutdown(self) -> list[HardwareFailure]:
        failures = []
        for d in self.drivers:
            try:
                d.shutdown()
            except Exception as err:  # noqa: BLE001 - every driver must get its shutdown
                log.exception("driver %s: shutdown failed", d.name)
                failures.append(HardwareFailure(d.name, "shutdown", _cause(err)))
        return failures

    # ------------------------------------------------------------------ every tick
    def read(self, now: float) -> list[HardwareFailure] | None:
        """Read every configured drive (one that fails does not keep the others unread)."""
        failures: list[HardwareFailure] | None = None
        for d in self.drivers:
            st = d.state
            if st is DriverState.UNCONFIGURED or st is DriverState.SHUTDOWN:
                continue
            try:
                d.read(now)
            except Exception as err:  # noqa: BLE001
                if failures is None:
                    failures = []
                failures.append(HardwareFailure(d.name, "read", _cause(err)))
        if failures is not None:
            self._detected()
            self.failures += len(failures)
        return failures

    def write(
        self, values: Sequence[float], now: float, effort: bool = False
    ) -> HardwareFailure | None:
        """Each drive its slice of ``values`` (position setpoints, or efforts). Every drive
        must be ACTIVE, checked before anything is written; the first failure ends the write
        (the caller latches FAULT, which powers every drive off)."""
        whole = self._whole
        if whole is None or whole.state is not DriverState.ACTIVE:
            for d, _idx, _buf in self._slices:
                if d.state is not DriverState.ACTIVE:
                    self._detected()
                    why = d.fault_reason or f"drive is {d.state.value}"
                    return self._one(HardwareFailure(d.name, "write", f"not active ({why})"))
        for d, idx, buf in self._slices:
            out: Sequence[float] = values  # one drive, every joint: read (never kept) as given
            if whole is None:
                for n, i in enumerate(idx):
                    buf[n] = values[i]
                out = buf
            try:
                if effort:
                    d.write_effort(out, now)
                else:
                    d.write(out, now)
            except Exception as err:  # noqa: BLE001
                self._detected()
                return self._one(HardwareFailure(d.name, "write", _cause(err)))
        return None

    # ------------------------------------------------------------------ internals
    def _detected(self) -> None:
        if self._fault_t is None:
            self._fault_t = time.perf_counter()

    def _one(self, failure: HardwareFailure) -> HardwareFailure:
        self.failures += 1
        return failure

    def _count(self, failures: list[HardwareFailure]) -> list[HardwareFailure]:
        self.failures += len(failures)
        return failures
