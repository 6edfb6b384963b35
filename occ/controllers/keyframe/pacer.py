"""The Pacer: how the keyframe planner thread shares the interpreter with the loop."""

from __future__ import annotations

import math
import time
from collections.abc import Callable

#: how the planner thread shares the interpreter with the loop (see :class:`Pacer`)
PACE_WORK_S = 100e-6
PACE_BEFORE_S = 200e-6
PACE_AFTER_S = 350e-6
PACE_HANDBACK_S = 10e-6
PACE_MODE = "phase"


class Pacer:
    """Keeps the planner thread off the interpreter lock when the loop needs it.

    One interpreter lock serves every thread: a thread that wants it waits until the holder
    lets go, up to the switch interval. A planner that computed flat out made the loop wait for
    it at most ticks (measured: lateness p50 0.5 ms, p99 6 ms; docs/BENCHMARKS.md). So the
    planner works in slices of ``PACE_WORK_S`` and, while the loop runs, only in the quiet part
    of its period: from ``PACE_AFTER_S`` after a deadline (the tick is done by then) to
    ``PACE_BEFORE_S`` before the next, sleeping through the rest; inside that window it still
    sleeps ``PACE_HANDBACK_S`` between slices. With no loop running (a stepped simulation) it
    only does the latter.
    """

    def __init__(
        self, now: Callable[[], float], loop_t0: Callable[[], float], period: float
    ) -> None:
        self.now = now
        self.loop_t0 = loop_t0
        self.period = period
        self._since = now()
        self.sleeps = 0

    def begin(self) -> None:
        """Wait for the quiet part of the loop's period before the first slice (the thread
        that starts the planner is the loop, mid-tick)."""
        self._since = -math.inf
        self()

    def __call__(self) -> None:
        t = self.now()
        if t - self._since < PACE_WORK_S:
            return
        t0 = self.loop_t0()
        if PACE_MODE == "phase" and t0 == t0:  # not NaN: the loop is running
            period = self.period
            phase = (t - t0) % period
            if phase < PACE_AFTER_S:
                wait = PACE_AFTER_S - phase
            elif phase > period - PACE_BEFORE_S - PACE_WORK_S:
                wait = period - phase + PACE_AFTER_S
            else:
                # a real sleep, however short: a zero one often takes the lock straight back
                # before a waiting loop thread (mid-tick) has woken to take it
                wait = PACE_HANDBACK_S
            self.sleeps += 1
            time.sleep(wait)
        elif PACE_MODE == "rest":
            time.sleep(PACE_WORK_S)
        elif PACE_MODE == "yield":
            time.sleep(0)
        else:
            time.sleep(PACE_HANDBACK_S)
        self._since = self.now()
