"""The periodic control loop: absolute deadlines, timing statistics, watchdog, real-time setup.

Each tick ``k`` has the absolute deadline ``t0 + k * period`` (computed, never accumulated, so
there is no drift however long it runs). A tick:

    clock.sleep_until(deadline) -> tick(now, k) -> stats.record -> watchdog.feed -> spare-time GC

A loop that wakes more than ``max_burst`` periods late skips the deadlines it missed (counted
in ``missed_ticks``) instead of running them back to back; up to ``max_burst`` periods late, it
catches up by running the late ticks immediately.

The same code runs on :class:`~occ.clock.RealClock` (the daemon) and
:class:`~occ.clock.SimClock` (tests and soaks).

Real-time setup (``realtime`` mapping, all keys optional)::

    fifo_priority: int | None   SCHED_FIFO priority (1-99) for the loop thread
    cpu: int | None             pin the loop thread to this CPU
    gc: "freeze" | "off" | "default"
        freeze  gc.collect(); gc.freeze(); gc.disable() for the run; young-generation
                collections only in ticks with spare time (gen 0 every ``gc_every`` ticks,
                gen 1 every tenth time); restored at exit
        off     collector disabled for the run (cyclic garbage accumulates), restored at exit
        default untouched (the collector may run inside any tick)
    gc_every: int               ticks between spare-time collections (default 100)
    gc_min_spare_us: float      spare time needed before the next deadline (default 300)
    switch_interval_s: float    sys.setswitchinterval for the run (process-wide): how long
                                another Python thread may hold the GIL when the loop wakes

Scheduling policy and affinity are per thread on Linux: :meth:`ControlLoop.run` applies them
to the thread that calls it (``pid 0`` = the calling thread) and restores them when it
returns; :meth:`ControlLoop.run_in_thread` thus gives the loop thread, and only it, SCHED_FIFO.
When not permitted, the loop runs anyway and :attr:`ControlLoop.realtime_report` says what
applied, e.g. ``"realtime: SCHED_FIFO 80 on; cpu 1 pinned; gc freeze"`` or
``"realtime: SCHED_FIFO refused (EPERM), running SCHED_OTHER; cpu 1 pinned; gc freeze"``.
The GC mode and the switch interval are process-wide.
"""

from __future__ import annotations

import errno
import gc
import logging
import math
import os
import sys
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from igtl.transport.common import name_native_thread
from occ.clock import Clock, RealClock
from occ.core.safety import Watchdog
from occ.core.stats import LoopStats

__all__ = ["ControlLoop", "TickFn", "apply_realtime"]

logger = logging.getLogger(__name__)

TickFn = Callable[[float, int], None]
#: :meth:`ControlLoop.yield_to_loop`: the time before a deadline another thread's work stops,
#: and how long after it it looks again (a tick computes in about 0.1 ms)
YIELD_MARGIN_S = 0.0004
YIELD_AFTER_S = 0.0001

_REALTIME_KEYS = frozenset(
    {"fifo_priority", "cpu", "gc", "gc_every", "gc_min_spare_us", "switch_interval_s"}
)
_GC_MODES = ("freeze", "off", "default")


def _policy_name(policy: int) -> str:
    for name in ("SCHED_OTHER", "SCHED_FIFO", "SCHED_RR", "SCHED_BATCH", "SCHED_IDLE"):
        if getattr(os, name, None) == policy:
            return name
    return f"policy {policy}"


def _errname(err: OSError) -> str:
    if err.errno:
        return errno.errorcode.get(err.errno, str(err.errno))
    return "EPERM" if isinstance(err, PermissionError) else type(err).__name__


def apply_realtime(
    fifo_priority: int | None = None, cpu: int | None = None
) -> tuple[list[str], Callable[[], None]]:
    """Give the calling thread SCHED_FIFO ``fifo_priority`` and pin it to ``cpu``, if permitted.

    Returns (report parts, restore function). Never raises for lack of permission or support:
    each refusal becomes a report part saying what runs instead.
    """
    parts: list[str] = []
    undo: list[Callable[[], None]] = []
    if fifo_priority is not None:
        try:
            old_policy = os.sched_getscheduler(threading.get_native_id())
            old_param = os.sched_getparam(threading.get_native_id())
            os.sched_setscheduler(
                threading.get_native_id(), os.SCHED_FIFO, os.sched_param(fifo_priority)
            )
        except AttributeError:
            parts.append("SCHED_FIFO unavailable on this platform")
        except OSError as err:  # PermissionError (EPERM) included
            try:
                current = _policy_name(os.sched_getscheduler(threading.get_native_id()))
            except (AttributeError, OSError):
                current = "the default policy"
            parts.append(f"SCHED_FIFO refused ({_errname(err)}), running {current}")
        else:
            parts.append(f"SCHED_FIFO {fifo_priority} on")

            def _restore_policy() -> None:
                os.sched_setscheduler(threading.get_native_id(), old_policy, old_param)

            undo.append(_restore_policy)
    if cpu is not None:
        try:
            old_cpus = os.sched_getaffinity(threading.get_native_id())
            os.sched_setaffinity(threading.get_native_id(), {cpu})
        except AttributeError:
            parts.append("cpu pinning unavailable on this platform")
        except OSError as err:
            parts.append(f"cpu {cpu} pinning refused ({_errname(err)})")
        else:
            parts.append(f"cpu {cpu} pinned")

            def _restore_affinity() -> None:
                os.sched_setaffinity(threading.get_native_id(), old_cpus)

            undo.append(_restore_affinity)

    def restore() -> None:
        for fn in reversed(undo):
            try:
                fn()
            except (AttributeError, OSError) as err:
                logger.warning("realtime: could not restore scheduling: %s", err)

    return parts, restore


class ControlLoop:
    """A periodic loop calling ``tick(now, k)`` at ``rate_hz`` on absolute deadlines.

    ``tick`` gets the tick's start time (clock seconds) and its deadline index ``k``
    (``deadline = t0 + k / rate_hz``; skipped deadlines leave gaps in ``k``). An exception
    from ``tick`` ends the run and propagates (after the real-time settings are restored).

    ``stats`` defaults to a new :class:`LoopStats`; pass ``watchdog`` to have it fed each
    tick. :meth:`stop` may be called from the tick, another thread or a signal handler.
    """

    def __init__(
        self,
        rate_hz: float,
        tick: TickFn,
        clock: Clock | None = None,
        stats: LoopStats | None = None,
        watchdog: Watchdog | None = None,
        realtime: Mapping[str, Any] | None = None,
        *,
        max_burst: int = 2,
    ) -> None:
        if rate_hz <= 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        if max_burst < 0:
            raise ValueError(f"max_burst must be >= 0, got {max_burst}")
        rt = dict(realtime or {})
        unknown = set(rt) - _REALTIME_KEYS
        if unknown:
            raise ValueError(f"unknown realtime keys: {sorted(unknown)}")
        gc_mode = rt.get("gc", "default")
        if gc_mode not in _GC_MODES:
            raise ValueError(f"realtime gc must be one of {_GC_MODES}, got {gc_mode!r}")
        self.rate_hz = float(rate_hz)
        self.period_s = 1.0 / self.rate_hz
        self._tick = tick
        self.clock: Clock = clock if clock is not None else RealClock()
        self.stats = stats if stats is not None else LoopStats(self.rate_hz)
        self.watchdog = watchdog
        self.max_burst = max_burst
        self.fifo_priority: int | None = rt.get("fifo_priority")
        self.cpu: int | None = rt.get("cpu")
        self.gc_mode: str = gc_mode
        self.gc_every = int(rt.get("gc_every", 100))
        self.gc_min_spare_s = float(rt.get("gc_min_spare_us", 300.0)) * 1e-6
        self.switch_interval_s: float | None = rt.get("switch_interval_s")
        #: work for the time a tick leaves before the next deadline (the black box's
        #: checkpoints): ``spare(roomy)`` after every tick, ``roomy`` when the tick left more
        #: than ``spare_min_s``; returns True when it did some (then no collection in that
        #: tick)
        self.spare: Callable[[bool], bool] | None = None
        self.spare_min_s = 0.6 * self.period_s
        #: called when a run ends, first, while the loop still has its real-time settings
        #: (the robot's supervisor stops watching there)
        self.on_end: Callable[[], None] | None = None
        self.realtime_report = ""
        self.missed_ticks = 0
        self.t0 = math.nan  # deadline k is t0 + k / rate_hz (updated by shift())
        self._shift = 0.0
        self.shifts = 0
        self.gc_collections = 0
        self.ticks_run = 0
        #: the deadline of the tick the loop waits for or runs (NaN: not running): what a
        #: thread of long work reads to keep out of the loop's way (:meth:`yield_to_loop`)
        self.next_deadline = math.nan
        self.error: BaseException | None = None
        self._stop_requested = False
        self._running = False
        self._done = threading.Event()
        self._done.set()
        self._thread: threading.Thread | None = None

    # -- control ------------------------------------------------------------------------------
    def yield_to_loop(self, margin_s: float = YIELD_MARGIN_S) -> None:
        """For a thread of this process with long work to do (the black box's writer):
        return when the loop has at least ``margin_s`` before its next deadline (at once when
        it is not running), sleeping meanwhile. Called between pieces of work well under
        ``margin_s`` each, the thread never holds the interpreter lock when the loop wakes for
        a tick, nor asks for it while a tick runs (which, past the switch interval, takes it
        from the tick): it works only in the time the ticks leave. Bounded: after about 0.2 s
        of a loop that does not tick, it returns."""
        now = self.clock.now
        for _ in range(2000):
            d = self.next_deadline
            if d != d:
                return
            t = now()
            if t < d - margin_s:
                return
            # the tick is due or under way: let it run, look again when it should be done
            time.sleep(max(0.0, d - t) + YIELD_AFTER_S)

    def stop(self) -> None:
        """Ask the loop to end after the current tick. Safe from a signal handler (a flag)."""
        self._stop_requested = True

    def shift(self, dt: float) -> None:
        """Move every later deadline by ``dt`` seconds (|dt| < one period), from the next tick.

        Used to phase-lock the loop to a periodic input (the slave to the master's stream), so
        a sample waits a fixed short time for the tick that uses it. Call from the tick.
        """
        if not -self.period_s < dt < self.period_s:
            raise ValueError(f"shift must be within one period, got {dt}")
        self._shift += dt
        self.shifts += 1

    @property
    def running(self) -> bool:
        return self._running

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until a run ends; True if it did within ``timeout``."""
        return self._done.wait(timeout)

    def run_in_thread(
        self,
        duration: float | None = None,
        ticks: int | None = None,
        *,
        name: str = "occ-loop",
        daemon: bool = True,
    ) -> threading.Thread:
        """Start :meth:`run` on a new thread (which gets the real-time settings) and return it.

        An exception from the run is logged and kept in :attr:`error`.
        """
        if self._thread is not None and self._thread.is_alive():
            raise RuntimeError("the loop is already running in a thread")
        self._done.clear()

        def main() -> None:
            try:
                self.run(duration=duration, ticks=ticks)
            except BaseException as err:
                self.error = err
                logger.exception("control loop ended with an error")
            finally:
                self._done.set()

        self._thread = threading.Thread(target=main, name=name, daemon=daemon)
        self._thread.start()
        return self._thread

    def join(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    # -- the loop -----------------------------------------------------------------------------

    def _setup(self) -> Callable[[], None]:
        name_native_thread("occd-loop")  # the main thread of occd: `pgrep occd` still finds it
        parts, restore_sched = apply_realtime(self.fifo_priority, self.cpu)
        gc_was_enabled = gc.isenabled()
        if self.gc_mode == "freeze":
            gc.collect()
            gc.freeze()
            gc.disable()
            parts.append("gc freeze")
        elif self.gc_mode == "off":
            gc.disable()
            parts.append("gc off")
        old_switch = sys.getswitchinterval()
        if self.switch_interval_s is not None:
            sys.setswitchinterval(self.switch_interval_s)
            parts.append(f"switch interval {self.switch_interval_s * 1e3:g} ms")
        self.realtime_report = "realtime: " + ("; ".join(parts) if parts else "none requested")
        logger.info("%s", self.realtime_report)

        def restore() -> None:
            if self.switch_interval_s is not None:
                sys.setswitchinterval(old_switch)
            if self.gc_mode == "freeze":
                gc.unfreeze()
            if self.gc_mode in ("freeze", "off") and gc_was_enabled:
                gc.enable()
            restore_sched()

        return restore

    def run(self, duration: float | None = None, ticks: int | None = None) -> LoopStats:
        """Run on the calling thread until :meth:`stop`, ``duration`` seconds of deadlines
        (``duration * rate_hz`` ticks) or ``ticks`` ticks, whichever comes first."""
        if self._running:
            raise RuntimeError("the loop is already running")
        self._running = True
        self._done.clear()
        restore = self._setup()
        stats = self.stats
        try:
            self._run(duration, ticks)
        finally:
            if self.on_end is not None:
                self.on_end()
            stats.end()
            restore()
            self._running = False
            self.next_deadline = math.nan
            self._stop_requested = False
            self._done.set()
        logger.info("%s", stats.format_line())
        return stats

    def _run(self, duration: float | None, ticks: int | None) -> None:
        # Everything used per tick is bound to a local: attribute look-ups cost on this path.
        clock = self.clock
        now = clock.now
        sleep_until = clock.sleep_until
        tick = self._tick
        period = self.period_s
        stats = self.stats
        record = stats.record
        feed = self.watchdog.feed if self.watchdog is not None else None
        max_late = self.max_burst * period
        tick_limit = -1 if ticks is None else int(ticks)
        spare_gc = self.gc_mode == "freeze" and self.gc_every > 0
        gc_every = self.gc_every
        gc_min_spare = self.gc_min_spare_s
        next_gc = gc_every
        gc_count = 0
        spare = self.spare
        spare_min = self.spare_min_s
        if spare is not None:
            spare(True)  # before the first tick: the black box's first checkpoint

        t0 = now()
        self.t0 = t0
        end_deadline = math.inf if duration is None else t0 + duration
        stats.begin(t0)
        k = 0
        n = 0
        prev_start: float | None = None
        while not self._stop_requested and n != tick_limit:
            if self._shift:
                t0 += self._shift
                end_deadline += self._shift
                self._shift = 0.0
                self.t0 = t0
            deadline = t0 + k * period
            self.next_deadline = deadline
            if deadline >= end_deadline:
                break
            sleep_until(deadline)
            start = now()
            late = start - deadline
            if late > max_late:
                # the small epsilon absorbs float error so that a stall of exactly n periods
                # skips n deadlines (not n-1 plus a catch-up tick)
                skipped = int(late / period + 1e-6)
                if skipped:
                    k += skipped
                    if t0 + k * period >= end_deadline:
                        break
                    self.missed_ticks += skipped
                    stats.record_missed(skipped)
            tick(start, k)
            end = now()
            record(deadline, start, end)
            if feed is not None:
                feed(None if prev_start is None else start - prev_start, end - start)
            prev_start = start
            k += 1
            n += 1
            self.ticks_run = n
            if spare is not None and spare((t0 + k * period) - end > spare_min):
                continue  # spare time used: no collection after it
            if spare_gc and n >= next_gc and (t0 + k * period) - end > gc_min_spare:
                gc_count += 1
                gc.collect(1 if gc_count % 10 == 0 else 0)
                next_gc = n + gc_every
        self.gc_collections += gc_count
