"""The slave's loop phase-locked to its master's stream (``phase_lock_us``)."""

from __future__ import annotations

from typing import Any


class PhaseLock:
    """Both loops tick at 1 kHz on the same clock but with an arbitrary phase between them, so
    without this a sample waits anywhere from 0 to 1 ms (constant for a whole run) before the
    tick that uses it. The phase used is the master's *sample time* (its POSITION timestamp,
    same machine clock; the reception time for peers without timestamps), which does not
    depend on which of our threads read the datagram. Every 250 samples the median phase
    within the period is compared with ``phase_lock_us`` before the next deadline, and the
    deadlines are shifted when it is off by more than 100 us (median: robust to the odd late
    packet). ``phase_lock_us`` must cover the transport time (p50 ~50-200 us here); the tick
    polls the socket itself, so a packet that arrived during the clock's spin is still used
    at once."""

    def __init__(self, lock_s: float) -> None:
        self.lock_s = lock_s
        self.phases: list[float] = []
        self.shifts = 0
        self.error_us: float | None = None
        self.history: list[float] = []

    def track(self, t_sample: float, ctx: Any) -> None:
        """One sample's time (on our loop's clock); ``ctx`` the controller's context."""
        t0 = ctx.loop_t0()
        if t0 != t0:  # NaN: the loop is not running (simulated-time tests stepping ticks)
            return
        period = ctx.period_s
        # deviation from the target phase, wrapped to [-period/2, period/2): taking the median
        # of raw phases would be wrong when they straddle the wrap-around point
        target = period - self.lock_s
        half = period / 2
        self.phases.append((t_sample - t0 - target + half) % period - half)
        if len(self.phases) < 250:
            return
        phases = sorted(self.phases)
        self.phases.clear()
        error = phases[len(phases) // 2]
        self.error_us = round(error * 1e6, 1)
        self.history.append(self.error_us)
        del self.history[:-20]
        if abs(error) > 100e-6:  # arrivals jitter by ~100 us here: don't chase the noise
            ctx.shift(error)
            self.shifts += 1
