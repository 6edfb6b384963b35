"""Timing statistics of the control loop, always on and cheap per tick.

:class:`Histogram` is a fixed-bucket histogram of microsecond values: a preallocated list of
counters, O(1) ``add`` with no allocation, percentiles from the bucket counts. Bucket layout
(relative error of a percentile is at most half a bucket):

=================  ===============================  =========
range (µs)         bucket width                     buckets
=================  ===============================  =========
[0, 100)           0.1 µs                           1000
[100, 1 000)       1 µs                             900
[1 000, 1 000 000) log-spaced, 100 per decade       300
                   (2.3 % wide)
>= 1 000 000       one overflow bucket              1
=================  ===============================  =========

``max``, ``min`` and ``mean`` are exact (tracked beside the buckets).

:class:`LoopStats` feeds three histograms per tick -- lateness (start - deadline), period
(start - previous start) and compute time (end - start) -- and counts overruns (compute over
budget), ticks more than 1 ms late and ticks skipped by the loop. It keeps the worst late
ticks with the wall-clock time they started (``late_ticks``), so a report can put a daemon's
maximum beside what else happened on the machine at that moment (benchmarks/bench_safety.py
beside its stall probe). :meth:`LoopStats.snapshot` returns the JSON-ready dict that the
daemon logs, records and reports.
"""

from __future__ import annotations

import heapq
import math
import time
from bisect import bisect_left
from collections.abc import Callable, Mapping
from itertools import accumulate
from typing import Any

__all__ = ["SUMMARY_PERCENTILES", "Histogram", "LoopStats", "bucket_bounds"]

_FINE_END = 100.0  # µs
_FINE_STEP = 0.1
_MID_END = 1_000.0
_LOG_END = 1_000_000.0
_LOG_PER_DECADE = 100
_N_FINE = 1000
_N_MID = 900
_N_LOG = 300
_MID0 = _N_FINE
_LOG0 = _N_FINE + _N_MID
_OVERFLOW = _LOG0 + _N_LOG
N_BUCKETS = _OVERFLOW + 1

#: Percentiles reported by :meth:`Histogram.summary`, as (key, p).
SUMMARY_PERCENTILES: tuple[tuple[str, float], ...] = (("p50", 50.0), ("p99", 99.0), ("p99_9", 99.9))


def _bucket_bounds(idx: int) -> tuple[float, float]:
    if idx < _MID0:
        return idx * _FINE_STEP, (idx + 1) * _FINE_STEP
    if idx < _LOG0:
        lo = _FINE_END + (idx - _MID0)
        return lo, lo + 1.0
    if idx < _OVERFLOW:
        j = idx - _LOG0
        return (
            _MID_END * 10.0 ** (j / _LOG_PER_DECADE),
            _MID_END * 10.0 ** ((j + 1) / _LOG_PER_DECADE),
        )
    return _LOG_END, math.inf


def bucket_bounds(idx: int) -> tuple[float, float]:
    """The [low, high) range in µs of bucket ``idx`` (the keys of :meth:`Histogram.buckets`);
    the overflow bucket's high is infinity. For clients that re-bin a daemon's raw buckets
    (the staff console's live histogram)."""
    if not 0 <= idx < N_BUCKETS:
        raise ValueError(f"bucket index must be 0..{N_BUCKETS - 1}, got {idx}")
    return _bucket_bounds(idx)


class Histogram:
    """Fixed-bucket histogram of non-negative values in microseconds (see module docstring).

    ``add`` is meant for the loop thread; the read methods may run on any thread and see an
    approximately consistent view (the bucket list is copied in one C-level step).
    """

    __slots__ = ("_counts", "count", "max", "min", "total")
    #: statistics steer nothing: a checkpoint does not take them (occ/core/checkpoint.py)
    checkpoint_opaque = True

    def __init__(self) -> None:
        self._counts: list[int] = [0] * N_BUCKETS
        self.count = 0
        self.total = 0.0
        self.max = 0.0
        self.min = math.inf

    def add(self, us: float) -> None:
        """Record one value (µs). Negative values land in the first bucket."""
        if us < _FINE_END:
            idx = int(us * 10.0) if us > 0.0 else 0
        elif us < _MID_END:
            idx = 900 + int(us)  # _MID0 + int(us) - 100
        elif us < _LOG_END:
            idx = _LOG0 + int(math.log10(us * 1e-3) * 100.0)
        else:
            idx = _OVERFLOW
        self._counts[idx] += 1
        self.count += 1
        self.total += us
        # plain comparisons, not max()/min(): a builtin call costs more on this per-tick path
        if us > self.max:  # noqa: PLR1730
            self.max = us
        if us < self.min:  # noqa: PLR1730
            self.min = us

    def clear(self) -> None:
        counts = self._counts
        for i in range(N_BUCKETS):
            counts[i] = 0
        self.count = 0
        self.total = 0.0
        self.max = 0.0
        self.min = math.inf

    @property
    def mean(self) -> float:
        return self.total / self.count if self.count else 0.0

    def percentiles(self, ps: tuple[float, ...] | list[float]) -> list[float]:
        """Several percentiles (0-100) in one pass; 0.0 for an empty histogram.

        Uses the order statistic at rank ``round(p/100 * (count-1))`` (numpy's position) and
        returns the middle of its bucket, clamped to the exact [min, max]; p=0 and p=100 are the
        exact min and max.
        """
        counts = list(self._counts)  # one atomic copy under the GIL
        n = sum(counts)
        if n == 0:
            return [0.0 for _ in ps]
        cumulative = list(accumulate(counts))
        lo_clamp = self.min
        hi_clamp = self.max
        out: list[float] = []
        for p in ps:
            if not 0.0 <= p <= 100.0:
                raise ValueError(f"percentile must be in [0, 100], got {p}")
            if p >= 100.0:
                out.append(hi_clamp)
                continue
            if p <= 0.0:
                out.append(lo_clamp)
                continue
            rank = round(p / 100.0 * (n - 1))  # 0-based order statistic
            idx = bisect_left(cumulative, rank + 1)
            lo, hi = _bucket_bounds(idx)
            mid = (lo + hi) / 2.0 if hi != math.inf else lo
            out.append(min(max(mid, lo_clamp), hi_clamp))
        return out

    def buckets(self) -> dict[int, int]:
        """The non-empty buckets as ``{index: count}`` (one atomic copy). Two of them taken at
        different times subtract into the histogram of the ticks in between: a measurement
        window (tools/attack.py: baseline against attack in one run of the daemon)."""
        return {i: c for i, c in enumerate(list(self._counts)) if c}

    @classmethod
    def from_buckets(cls, counts: Mapping[int, int]) -> Histogram:
        """A histogram holding ``counts`` (e.g. the difference of two :meth:`buckets`). The
        exact min, max and mean are not known: min and max become the edges of the outermost
        non-empty buckets (percentiles stay accurate to a bucket), the mean their middles'."""
        h = cls()
        for idx, n in counts.items():
            if n <= 0:
                continue
            h._counts[idx] = n
            lo, hi = _bucket_bounds(idx)
            h.count += n
            h.total += n * ((lo + hi) / 2.0 if hi != math.inf else lo)
            h.min = min(h.min, lo)
            h.max = max(h.max, hi if hi != math.inf else lo)
        return h

    def percentile(self, p: float) -> float:
        """The p-th percentile (0-100), accurate to half a bucket."""
        return self.percentiles((p,))[0]

    def summary(self) -> dict[str, float]:
        """``{p50, p99, p99_9, max, mean}`` in µs, rounded to 0.001 µs."""
        values = self.percentiles([p for _, p in SUMMARY_PERCENTILES])
        out = {key: round(v, 3) for (key, _), v in zip(SUMMARY_PERCENTILES, values, strict=True)}
        out["max"] = round(self.max, 3)
        out["mean"] = round(self.mean, 3)
        return out


InterfaceStats = Mapping[str, Any] | Callable[[], Mapping[str, Any]]


class LoopStats:
    """Per-tick timing of a periodic loop.

    The loop calls :meth:`begin` once, :meth:`record` after every tick, :meth:`record_missed`
    when it skips deadlines, and :meth:`end` when it stops. Times are the loop clock's seconds.
    ``budget_s`` (default: one period) is the compute time above which a tick is an overrun.

    CPU usage is measured with ``time.process_time`` against ``time.perf_counter`` between
    :meth:`begin` and :meth:`end` (or now): the whole process, all threads, real time even when
    the loop runs on a simulated clock.

    ``interfaces`` is filled by others (one entry per interface: a dict, or a callable
    returning one, evaluated at snapshot time) and copied into the snapshot as is.
    """

    LATE_LIMIT_S = 1e-3
    #: how many of the latest ticks over ``LATE_LIMIT_S`` are kept, the worst ones
    LATE_KEPT = 20

    def __init__(self, rate_hz: float, budget_s: float | None = None) -> None:
        if rate_hz <= 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        self.rate_hz = float(rate_hz)
        self.period_s = 1.0 / self.rate_hz
        self.budget_s = self.period_s if budget_s is None else float(budget_s)
        self.lateness = Histogram()
        self.period = Histogram()
        self.compute = Histogram()
        # bound once: three look-ups a tick fewer
        self._add_late = self.lateness.add
        self._add_compute = self.compute.add
        self._add_period = self.period.add
        self.interfaces: dict[str, InterfaceStats] = {}
        self._reset_counters()

    def _reset_counters(self) -> None:
        self.ticks = 0
        self.overruns = 0
        self.late_over_1ms = 0
        self.missed_ticks = 0
        self._t0: float | None = None
        self._t_last: float | None = None
        self._prev_start: float | None = None
        self._wall0 = time.perf_counter()
        self._cpu0 = time.process_time()
        self._wall1: float | None = None
        self._cpu1: float | None = None
        #: the worst ticks over LATE_LIMIT_S: a min-heap of (lateness s, wall time of the
        #: tick's start); the loop thread writes it on a late tick only
        self._late: list[tuple[float, float]] = []

    def reset(self) -> None:
        """Start a new measurement window (loop thread only)."""
        self.lateness.clear()
        self.period.clear()
        self.compute.clear()
        self._reset_counters()

    def begin(self, t0: float) -> None:
        """Mark the start of a run at loop time ``t0`` (the first deadline).

        Histograms and counters keep accumulating across runs; :meth:`reset` starts afresh.
        """
        self._t0 = t0
        self._t_last = t0
        self._prev_start = None
        self._wall0 = time.perf_counter()
        self._cpu0 = time.process_time()
        self._wall1 = None
        self._cpu1 = None

    def end(self) -> None:
        """Freeze the CPU measurement at the end of a run."""
        self._wall1 = time.perf_counter()
        self._cpu1 = time.process_time()

    def record(self, deadline: float, start: float, end: float) -> None:
        """Record one tick: scheduled ``deadline``, actual ``start``, ``end`` of its work."""
        lateness = start - deadline
        compute = end - start
        self._add_late(lateness * 1e6)
        self._add_compute(compute * 1e6)
        prev = self._prev_start
        if prev is not None:
            self._add_period((start - prev) * 1e6)
        elif self._t0 is None:
            self._t0 = deadline
        self._prev_start = start
        self._t_last = end
        self.ticks += 1
        if compute > self.budget_s:
            self.overruns += 1
        if lateness > self.LATE_LIMIT_S:
            self.late_over_1ms += 1
            self._note_late(lateness, compute)

    def _note_late(self, lateness: float, compute: float) -> None:
        """Keep a late tick among the worst (the rare path: a tick over LATE_LIMIT_S), with
        the wall-clock time it started (now, less its compute time)."""
        item = (lateness, time.time() - compute)
        late = self._late
        if len(late) < self.LATE_KEPT:
            heapq.heappush(late, item)
        elif item > late[0]:
            heapq.heapreplace(late, item)

    def late_ticks(self) -> list[dict[str, float]]:
        """The worst late ticks kept, worst first: ``at`` the wall-clock (Unix) time the tick
        started, ``late_us`` how late; the tick waited from ``at - late_us`` to ``at``."""
        return [
            {"at": round(at, 6), "late_us": round(late * 1e6, 1)}
            for late, at in sorted(list(self._late), reverse=True)
        ]

    def record_missed(self, n: int) -> None:
        """Count ``n`` deadlines skipped by the loop (never run)."""
        self.missed_ticks += n

    @property
    def duration_s(self) -> float:
        if self._t0 is None or self._t_last is None:
            return 0.0
        return self._t_last - self._t0

    @property
    def cpu_percent(self) -> float:
        wall1 = time.perf_counter() if self._wall1 is None else self._wall1
        cpu1 = time.process_time() if self._cpu1 is None else self._cpu1
        wall = wall1 - self._wall0
        return (cpu1 - self._cpu0) / wall * 100.0 if wall > 0 else 0.0

    def snapshot(self) -> dict[str, Any]:
        """JSON-ready summary; times in µs. Safe to call from another thread."""
        ticks = self.ticks
        interfaces: dict[str, Any] = {}
        for name, source in list(self.interfaces.items()):
            interfaces[name] = dict(source() if callable(source) else source)
        return {
            "ticks": ticks,
            "rate_hz": self.rate_hz,
            "duration_s": round(self.duration_s, 6),
            "lateness_us": self.lateness.summary(),
            "period_us": self.period.summary(),
            "compute_us": self.compute.summary(),
            "late_over_1ms": self.late_over_1ms,
            "late_over_1ms_percent": (
                round(self.late_over_1ms / ticks * 100.0, 6) if ticks else 0.0
            ),
            "overruns": self.overruns,
            "missed_ticks": self.missed_ticks,
            "late_ticks": self.late_ticks(),
            "cpu_percent": round(self.cpu_percent, 2),
            "interfaces": interfaces,
        }

    def format_line(self) -> str:
        """One-line human summary for the log."""
        late = self.lateness.summary()
        comp = self.compute.summary()
        ticks = self.ticks
        pct = self.late_over_1ms / ticks * 100.0 if ticks else 0.0
        return (
            f"loop {self.rate_hz:g} Hz: {ticks} ticks in {self.duration_s:.3f} s; "
            f"late us p50 {late['p50']:.1f} p99 {late['p99']:.1f} p99.9 {late['p99_9']:.1f} "
            f"max {late['max']:.1f}; compute us p99 {comp['p99']:.1f} max {comp['max']:.1f}; "
            f"late>1ms {self.late_over_1ms} ({pct:.3f}%); overruns {self.overruns}; "
            f"missed {self.missed_ticks}; cpu {self.cpu_percent:.1f}%"
        )


class StatsRegistry:
    """Every part's statistics, for ``GetStats`` (``occd --stats``): each part registers a
    name and a callable giving its statistics; :meth:`report` starts from the loop's snapshot
    and adds every entry under its name, in the order registered. Called off the loop thread
    (the worker's), so every callable must be safe there."""

    #: registered as the robot is built, never changed after: not a checkpoint's
    checkpoint_fixed = ("_entries",)

    def __init__(self, base: Callable[[], dict[str, Any]]) -> None:
        self._base = base
        self._entries: list[tuple[str, Callable[[], Any]]] = []

    def add(self, name: str, stats: Callable[[], Any]) -> None:
        """``stats()`` reported under ``name`` (ValueError for a name taken twice)."""
        if any(name == taken for taken, _ in self._entries):
            raise ValueError(f"statistics {name!r} registered twice")
        self._entries.append((name, stats))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(name for name, _ in self._entries)

    def report(self) -> dict[str, Any]:
        snap = self._base()
        for name, stats in self._entries:
            snap[name] = stats()
        return snap
