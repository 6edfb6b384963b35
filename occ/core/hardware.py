"""The HardwareSet: a robot's drives as one unit whose transitions succeed or fail whole.

A robot never moves on part of its hardware. Every operation here goes to every drive and
reports what failed instead of raising, so the robot decides (:mod:`occ.core.robot`):

=============  ===============================================================================
operation      on failure
=============  ===============================================================================
configure      the failed drives are latched FAULT in their base; the robot starts in FAULT
activate       all or nothing: the drives already powered are switched off again and the
               transition that asked for power (``enable``, ``run`` from STOPPED) is vetoed;
               the robot latches FAULT naming the drive (and any that failed to switch off
               again). Once every drive is up, :meth:`HardwareSet.verify` proves it: a read
               that passes every feedback check and a write of where the joints are, every
               drive still ACTIVE after both; a failure vetoes the same way. The drives whose
               activation waits (:meth:`HardwareSet.waiting`) are powered on threads of their
               own first (occ/core/powerup.py), :attr:`HardwareSet.busy` meanwhile: no
               operation here touches them (not read, never written, not switched off: their
               power-up does that) until the loop releases them and completes the rule
deactivate     never refused (a stop cannot be): a drive that fails to stop is latched FAULT
               by its base (which tries its ``_deactivate`` once more), marked unsafe
               (:attr:`~occ.drivers.base.Driver.stop_failed`) and named; the robot FAULTs
reset          every faulted drive resets (its backend refuses while the cause persists) and
               then every drive is read afresh through every feedback check; any failure
               vetoes the transition out of FAULT: the robot stays FAULT, the reply names it
read           every drive is still read; the robot latches FAULT naming the drive
write          checked before anything is written: every drive must be ACTIVE (a drive that
               faulted by itself is never left out silently); a write that raises, whatever
               its type, is a failure; the robot latches FAULT and the FAULT transition powers
               every other drive off in the same tick
=============  ===============================================================================

:attr:`HardwareSet.last_fault_to_safe_s` is the measured time (``time.perf_counter``) from
the detection of a read or write failure to the moment the last drive was in its safe state
(INACTIVE or FAULT, power stages off), reported by ``GetStats`` under ``hardware``. A drive
whose switch-off failed is never safe (:meth:`HardwareSet.unsafe`): while one is, the time is
not taken, and ``GetStats`` lists it under ``unsafe``. The time from the fault itself (not its
detection) is the fault matrix's to measure: it knows when it injected the fault
(occ_testkit/faultmatrix.py).

The supervisor's safe stop (:meth:`HardwareSet.safe_stop`) stops every drive at once, each on
a thread of its own, and waits at most a bound for them: a plugin whose stop hangs delays
neither the other drives nor the operators' alert (the supervisor alerts first).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from occ.drivers.base import Driver, DriverState
from occ.joint import Joint

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


def _stop_one(driver: Driver, reason: str) -> None:
    driver.safe_stop(reason)  # never raises (the base catches and keeps what failed)


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
        #: drives another thread is powering up (occ/core/powerup.py): no operation here
        #: touches them until the loop releases them (only the loop thread changes this set)
        self.busy: frozenset[Driver] = frozenset()
        #: the simulated world the drives touch (occ/haptics/contact.py), None on real hardware
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
        """Every drive's power stage off: a state in SAFE, no switch-off that failed, and none
        being powered up on another thread."""
        return not self.busy and all(
            d.state in SAFE and d.stop_failed is None for d in self.drivers
        )

    def waiting(self, state: DriverState = DriverState.INACTIVE) -> list[Driver]:
        """The drives an Enable would power up (``state`` INACTIVE), or a Reset reset (FAULT),
        that wait while they do (:attr:`~occ.drivers.base.Driver.activation_waits`): in
        ``state`` and not busy."""
        return [
            d
            for d in self.drivers
            if d.activation_waits and d.state is state and d not in self.busy
        ]

    def hold(self, drivers: Sequence[Driver]) -> None:
        """On the loop thread: ``drivers`` are being powered up on another thread; nothing here
        touches them until :meth:`release`."""
        self.busy = self.busy | frozenset(drivers)

    def release(self, drivers: Sequence[Driver]) -> None:
        """On the loop thread, once their activation has ended: the loop's again."""
        self.busy = self.busy - frozenset(drivers)

    def unsafe(self) -> list[HardwareFailure]:
        """The drives whose switch-off failed (their power stage may still be on)."""
        return [
            HardwareFailure(d.name, "switch-off", d.stop_failed)
            for d in self.drivers
            if d.stop_failed is not None
        ]

    def stats(self) -> dict[str, Any]:
        lat = self.last_fault_to_safe_s
        return {
            "drivers": {d.name: d.stats() for d in self.drivers},
            "states": {d.name: d.state.value for d in self.drivers},
            "unsafe": {f.driver: f.cause for f in self.unsafe()},
            "all_safe": self.all_safe(),
            "failures": self.failures,
            "last_fault_to_safe_us": None if lat is None else round(lat * 1e6, 1),
            **({"environment": self.environment.stats()} if self.environment else {}),
        }

    # ------------------------------------------------------------------ lifecycle
    def await_measured(
        self,
        joints: Sequence[Joint],
        read: Callable[[float], None],
        now: Callable[[], float],
        wait_s: float,
        real: bool,
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

    def configure(self, count: bool = True) -> list[HardwareFailure]:
        """Configure every unconfigured drive; the failed ones are latched FAULT."""
        failures = []
        for d in self.drivers:
            if d.state is not DriverState.UNCONFIGURED:
                continue
            try:
                d.configure()
            except Exception as err:  # noqa: BLE001 - every drive is tried, each failure named
                failures.append(HardwareFailure(d.name, "configure", _cause(err)))
        return self._count(failures) if count else failures

    def activate(self, prior: Sequence[HardwareFailure] = ()) -> list[HardwareFailure]:
        """Power every drive, or none: a drive that cannot be powered (its activation fails,
        or it is latched FAULT, or was never configured) switches the others off again.

        ``prior``: what failed of the activations run on other threads (occ/core/powerup.py;
        the drives that came up there are ACTIVE already). When any did, no other drive is
        powered: every one that came up is switched off again, the failures returned."""
        failures = list(prior)
        for d in self.drivers if not failures else ():
            st = d.state
            if st is DriverState.ACTIVE:
                continue
            if d in self.busy:
                failures.append(HardwareFailure(d.name, "activate", "being powered up already"))
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
            # the ones that came up go off again: all or nothing; one that fails to is a
            # failure of its own (it may still be powered), never forgotten
            failures += self.deactivate(count=False)
        return self._count(failures)

    def verify(
        self, joints: Sequence[Joint], now: float, effort: bool = False
    ) -> list[HardwareFailure]:
        """After :meth:`activate`, before the robot says it is powered: every drive read
        through every feedback check, then told to hold where its joints are (zero effort on
        an effort drive), and every drive still ACTIVE after both. The failures (none when
        proven); the caller switches everything off again when there are any."""
        failures = list(self.read(now) or ())
        if not failures:
            values = [0.0] * len(joints) if effort else [j.position for j in joints]
            failed = self.write(values, now, effort)
            if failed is not None:
                failures.append(failed)
        failures += [
            HardwareFailure(d.name, "verify", f"left ACTIVE: {d.fault_reason or d.state.value}")
            for d in self.drivers
            if d.state is not DriverState.ACTIVE and not any(f.driver == d.name for f in failures)
        ]
        if failures:
            self._detected()
        return failures

    def deactivate(self, count: bool = True) -> list[HardwareFailure]:
        """Every ACTIVE drive to its safe state; never stops half way. A drive whose
        deactivation fails is latched FAULT by its base (which tries once more and, when
        that fails too, marks it :attr:`~occ.drivers.base.Driver.stop_failed`): named in the
        failures, with whether it is still unsafe."""
        failures = []
        for d in self.drivers:
            if d.state is not DriverState.ACTIVE or d in self.busy:
                continue  # a busy drive: its power-up switches it off (occ/core/powerup.py)
            try:
                d.deactivate()
            except Exception as err:  # noqa: BLE001
                still = " (still powered: its switch-off failed twice)" if d.stop_failed else ""
                failures.append(HardwareFailure(d.name, "deactivate", _cause(err) + still))
        t = self._fault_t
        if t is not None and self.all_safe():
            self.last_fault_to_safe_s = time.perf_counter() - t
            self._fault_t = None
        return self._count(failures) if count else failures

    def reset(
        self, now: float | None = None, prior: Sequence[HardwareFailure] = ()
    ) -> list[HardwareFailure]:
        """Clear every latched drive fault, configure the drives never configured, and prove
        the repair: every drive read afresh at ``now`` through every feedback check (a drive
        that reset but still reads wrong is a failure; it is latched FAULT again by its base).
        The failures, each naming its drive: the robot stays FAULT when there are any.
        ``prior``: what failed of the resets run on other threads (occ/core/powerup.py)."""
        failures = list(prior)
        tried = {f.driver for f in prior}  # their reset failed already: not twice
        for d in self.drivers:
            if d.state is not DriverState.FAULT or d.name in tried:
                continue
            if d in self.busy:
                failures.append(HardwareFailure(d.name, "reset", "still being powered up"))
                continue
            try:
                d.reset()
            except Exception as err:  # noqa: BLE001
                failures.append(HardwareFailure(d.name, "reset", _cause(err)))
        failures += self.configure(count=False)
        if not failures and now is not None:
            failures += [
                HardwareFailure(f.driver, "reset", f"a fresh read failed: {f.cause}")
                for f in self.read(now, count=False) or ()
            ]
        return self._count(failures)

    def safe_stop(self, reason: str, bound_s: float = 0.010) -> list[HardwareFailure]:
        """From the supervisor's thread: every drive to its safe state at once, each on a
        thread of its own (a drive whose stop hangs on a lock its hung read holds does not
        delay the others); waits at most ``bound_s`` for them. Never raises. The drives that
        did not confirm their stop within the bound, or whose stop failed."""
        stoppers = []
        for d in self.drivers:
            t = threading.Thread(
                target=_stop_one, args=(d, reason), name=f"occ-safe-stop-{d.name}", daemon=True
            )
            t.start()
            stoppers.append((d, t))
        give_up = time.perf_counter() + bound_s
        failures = []
        for d, t in stoppers:
            t.join(max(0.0, give_up - time.perf_counter()))
            if t.is_alive():
                failures.append(
                    HardwareFailure(
                        d.name, "safe stop", f"not confirmed within {bound_s * 1e3:g} ms"
                    )
                )
            elif d.stop_failed is not None:
                failures.append(HardwareFailure(d.name, "safe stop", d.stop_failed))
        return failures

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
    def read(self, now: float, count: bool = True) -> list[HardwareFailure] | None:
        """Read every configured drive (one that fails does not keep the others unread)."""
        failures: list[HardwareFailure] | None = None
        busy = self.busy
        for d in self.drivers:
            st = d.state
            if st is DriverState.UNCONFIGURED or st is DriverState.SHUTDOWN:
                continue
            if busy and d in busy:
                continue  # another thread is powering it up: its joints keep their reading
            try:
                d.read(now)
            except Exception as err:  # noqa: BLE001
                if failures is None:
                    failures = []
                failures.append(HardwareFailure(d.name, "read", _cause(err)))
        if failures is not None:
            self._detected()
            if count:
                self.failures += len(failures)
        return failures

    def write(
        self, values: Sequence[float], now: float, effort: bool = False
    ) -> HardwareFailure | None:
        """Each drive its slice of ``values`` (position setpoints, or efforts). Every drive
        must be ACTIVE, checked before anything is written; the first failure ends the write
        (the caller latches FAULT, which powers every drive off)."""
        whole = self._whole
        if whole is None or whole.state is not DriverState.ACTIVE or self.busy:
            for d, _idx, _buf in self._slices:
                if d.state is not DriverState.ACTIVE or d in self.busy:
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
