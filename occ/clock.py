"""Time sources for the control loop: the real clock and a deterministic simulated one.

The loop never calls :mod:`time` directly; it asks a :class:`Clock`. The same loop, watchdog
and loss-monitor code then runs

- on :class:`RealClock`: ``time.perf_counter`` with a sleep-then-spin wait, for the daemon;
- on :class:`SimClock`: simulated seconds that jump to each deadline, for exact, repeatable
  tests and soaks of many simulated hours in minutes.

Units are seconds (floats) everywhere. ``now()`` is monotonic and has an arbitrary origin;
``wall_time()`` is Unix time, for timestamps that leave the process (IGTL headers, logs).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol, runtime_checkable

__all__ = ["Clock", "RealClock", "SimClock"]


@runtime_checkable
class Clock(Protocol):
    """What the control loop needs from a time source."""

    def now(self) -> float:
        """Monotonic time in seconds (arbitrary origin)."""
        ...

    def sleep_until(self, deadline: float) -> None:
        """Return at ``deadline`` (in :meth:`now` seconds) or as soon after as possible.

        Returns immediately when the deadline has already passed.
        """
        ...

    def wall_time(self) -> float:
        """Unix time in seconds, for timestamps sent to peers."""
        ...


class RealClock:
    """``time.perf_counter`` clock that sleeps to ``spin_us`` before a deadline, then spins.

    ``time.sleep`` alone wakes 0.2-0.5 ms late at p99 on a stock kernel (timer slack plus
    scheduler wake-up); spinning the last ~200 µs brings p99 lateness to ~10-20 µs for the
    price of ``spin_us / period`` of one core (20 % at 1 kHz). ``spin_us=0`` gives a plain
    sleep.

    A plain busy-wait holds the GIL for the whole spin, so an interface thread that receives
    a packet then cannot even enqueue it until the tick is over: the sample misses the tick it
    arrived before and waits a whole period. With ``yield_gil`` the spin releases the GIL on
    every turn (``time.sleep(0)``), so interface threads run during the spin; measured in the
    full daemon here that made the loop itself much later (p99 lateness 610 us vs 110-215 us:
    any thread that takes the GIL keeps it up to the switch interval), so it is off by default;
    the slave instead phase-locks its ticks so the master's packets arrive before the spin.
    """

    __slots__ = ("_spin_s", "_yield", "now", "wall_time")

    def __init__(self, spin_us: float = 200.0, *, yield_gil: bool = False) -> None:
        if spin_us < 0:
            raise ValueError(f"spin_us must be >= 0, got {spin_us}")
        self._spin_s = spin_us * 1e-6
        self._yield = yield_gil
        # the time functions themselves, not methods calling them: the loop, the interfaces
        # and the controllers ask several times a tick, and a Python call costs more than
        # the clock read
        #: monotonic seconds (``time.perf_counter``)
        self.now: Callable[[], float] = time.perf_counter
        #: Unix time in seconds (``time.time``)
        self.wall_time: Callable[[], float] = time.time

    @property
    def spin_us(self) -> float:
        return self._spin_s * 1e6

    def sleep_until(self, deadline: float) -> None:
        perf_counter = time.perf_counter
        remaining = deadline - perf_counter()
        if remaining <= 0.0:
            return
        coarse = remaining - self._spin_s
        if coarse > 0.0:
            time.sleep(coarse)
        if self._yield:
            sleep = time.sleep
            while perf_counter() < deadline:
                sleep(0)  # releases the GIL for a moment: interface threads may run
        else:
            while perf_counter() < deadline:
                pass

    def __repr__(self) -> str:
        return f"RealClock(spin_us={self.spin_us:g})"


class SimClock:
    """Deterministic simulated time.

    - :meth:`sleep_until` jumps straight to the deadline (never backwards), plus any wake-up
      latency injected with :meth:`inject_delay` or produced by ``wake_latency``;
    - :meth:`advance` lets simulated work take time: a tick that calls ``clock.advance(0.0015)``
      has a compute time of 1.5 ms, which is how tests produce overruns;
    - ``wake_latency(deadline) -> seconds`` (optional) adds latency to every wake-up, e.g. a
      seeded random jitter for soaks.

    ``wall_time()`` is ``wall_epoch + now()``, so simulated runs produce reproducible
    timestamps. Not thread-safe: drive it from one thread (the loop's).
    """

    __slots__ = ("_pending_delay", "_t", "sleeps", "wake_latency", "wall_epoch")

    def __init__(
        self,
        start: float = 0.0,
        *,
        wall_epoch: float = 1_700_000_000.0,
        wake_latency: Callable[[float], float] | None = None,
    ) -> None:
        self._t = float(start)
        self._pending_delay = 0.0
        self.wake_latency = wake_latency
        self.wall_epoch = float(wall_epoch)
        self.sleeps = 0  # number of sleep_until calls, for tests

    def now(self) -> float:
        return self._t

    def sleep_until(self, deadline: float) -> None:
        self.sleeps += 1
        self._t = max(self._t, deadline)
        extra = self._pending_delay
        self._pending_delay = 0.0
        if self.wake_latency is not None:
            extra += self.wake_latency(deadline)
        if extra > 0.0:
            self._t += extra

    def wall_time(self) -> float:
        return self.wall_epoch + self._t

    def advance(self, dt: float) -> None:
        """Let ``dt`` seconds of simulated time pass (simulated computation)."""
        if dt < 0:
            raise ValueError(f"time cannot go backwards (dt={dt})")
        self._t += dt

    def set(self, t: float) -> None:
        """Move time forward to ``t`` (never backwards)."""
        if t < self._t:
            raise ValueError(f"time cannot go backwards ({t} < {self._t})")
        self._t = float(t)

    def inject_delay(self, dt: float) -> None:
        """Make the next :meth:`sleep_until` wake ``dt`` seconds late (a stall: GC, scheduler).

        Calls accumulate until the next wake-up consumes them.
        """
        if dt < 0:
            raise ValueError(f"delay must be >= 0, got {dt}")
        self._pending_delay += dt

    def __repr__(self) -> str:
        return f"SimClock(t={self._t!r})"
