"""Control loop and timing statistics, all on SimClock (no real sleeps, no wall-clock asserts)."""

from __future__ import annotations

import gc
import json
import math
import os
import random
import threading
import time

import numpy as np
import pytest

from occ.core import loop as loop_mod
from occ.clock import SimClock
from occ.core.loop import ControlLoop
from occ.core.safety import Watchdog
from occ.core.stats import Histogram, LoopStats

RATE = 1000.0
PERIOD = 1.0 / RATE


def _recorder(clock: SimClock, compute: float = 0.0):
    starts: list[float] = []
    ks: list[int] = []

    def tick(now: float, k: int) -> None:
        starts.append(now)
        ks.append(k)
        if compute:
            clock.advance(compute)

    return tick, starts, ks


# -- deadlines ---------------------------------------------------------------------------------


def test_absolute_deadlines_no_drift_over_100k_ticks() -> None:
    clock = SimClock(start=123.456)
    rng = random.Random(1)
    starts: list[float] = []

    def tick(now: float, k: int) -> None:
        starts.append(now)
        clock.advance(rng.uniform(0.0, 0.9) * PERIOD)  # variable compute time

    loop = ControlLoop(RATE, tick, clock=clock)
    stats = loop.run(ticks=100_000)
    t0 = 123.456
    assert len(starts) == 100_000
    assert stats.ticks == 100_000
    # every tick starts exactly on its absolute deadline: no accumulation of compute times
    for k in (0, 1, 999, 50_000, 99_999):
        assert starts[k] == t0 + k * PERIOD
    assert max(abs(s - (t0 + k * PERIOD)) for k, s in enumerate(starts)) == 0.0
    snap = stats.snapshot()
    assert snap["lateness_us"]["max"] == 0.0
    assert snap["period_us"]["mean"] == pytest.approx(1000.0, abs=1e-6)
    assert snap["overruns"] == 0 and snap["missed_ticks"] == 0
    assert snap["duration_s"] == pytest.approx(99_999 * PERIOD, abs=PERIOD)


def test_wake_jitter_does_not_accumulate() -> None:
    rng = random.Random(2)
    clock = SimClock(wake_latency=lambda _d: rng.uniform(0.0, 0.3 * PERIOD))
    tick, starts, ks = _recorder(clock, compute=0.1 * PERIOD)
    ControlLoop(RATE, tick, clock=clock).run(ticks=100_000)
    lateness = [s - k * PERIOD for k, s in zip(ks, starts, strict=True)]
    assert ks == list(range(100_000))
    assert max(lateness) <= 0.3 * PERIOD + 1e-9
    assert min(lateness) >= -1e-9


def test_duration_and_ticks_limits() -> None:
    clock = SimClock()
    tick, starts, _ = _recorder(clock)
    loop = ControlLoop(RATE, tick, clock=clock)
    assert loop.run(duration=1.0).ticks == 1000
    assert len(starts) == 1000
    loop2 = ControlLoop(500.0, _recorder(clock)[0], clock=clock)
    assert loop2.run(ticks=37).ticks == 37


def test_skip_ahead_when_more_than_max_burst_late() -> None:
    clock = SimClock()
    ks: list[int] = []
    starts: list[float] = []

    def tick(now: float, k: int) -> None:
        ks.append(k)
        starts.append(now)
        if k == 10:
            clock.inject_delay(5.5 * PERIOD)  # the wake-up for tick 11 stalls 5.5 periods

    loop = ControlLoop(RATE, tick, clock=clock, max_burst=2)
    stats = loop.run(ticks=20)
    assert ks[:12] == list(range(11)) + [16]
    assert ks[11:] == list(range(16, 25))
    assert loop.missed_ticks == 5
    assert stats.missed_ticks == 5
    assert stats.snapshot()["missed_ticks"] == 5
    # the stall is visible in the lateness statistics, the grid is unchanged afterwards
    assert stats.lateness.max == pytest.approx(5500.0)
    assert stats.late_over_1ms == 1
    assert starts[12] == 17 * PERIOD
    # no burst: after the skip, ticks are a period apart again
    assert starts[12] - starts[11] == pytest.approx(0.5 * PERIOD)


def test_small_lateness_is_caught_up_without_skipping() -> None:
    clock = SimClock()
    ks: list[int] = []
    starts: list[float] = []

    def tick(now: float, k: int) -> None:
        ks.append(k)
        starts.append(now)
        if k == 10:
            clock.inject_delay(1.5 * PERIOD)

    loop = ControlLoop(RATE, tick, clock=clock, max_burst=2)
    loop.run(ticks=20)
    assert ks == list(range(20))
    assert loop.missed_ticks == 0
    assert starts[11] == pytest.approx(12.5 * PERIOD)
    assert starts[12] == pytest.approx(12.5 * PERIOD)  # late tick run at once
    assert starts[13] == 13 * PERIOD  # back on the grid


def test_skip_ahead_respects_duration_end() -> None:
    clock = SimClock()

    def tick(now: float, k: int) -> None:
        if k == 5:
            clock.inject_delay(100 * PERIOD)

    loop = ControlLoop(RATE, tick, clock=clock)
    stats = loop.run(duration=0.050)
    assert stats.ticks == 6  # the stall runs past the end: no tick after it


# -- stopping ----------------------------------------------------------------------------------


def test_stop_from_tick_ends_after_that_tick_and_loop_can_rerun() -> None:
    clock = SimClock()
    loop: ControlLoop

    def tick(now: float, k: int) -> None:
        if k == 41:
            loop.stop()

    loop = ControlLoop(RATE, tick, clock=clock)
    assert loop.run().ticks == 42
    assert not loop.running
    loop2_stats = loop.run(ticks=10)  # the stop request was consumed
    assert loop2_stats.ticks == 52


def test_stop_before_run_returns_without_ticking() -> None:
    loop = ControlLoop(RATE, lambda now, k: None, clock=SimClock())
    loop.stop()
    assert loop.run(ticks=100).ticks == 0


def test_stop_from_another_thread() -> None:
    clock = SimClock()
    reached = threading.Event()

    def tick(now: float, k: int) -> None:
        if k == 100:
            reached.set()

    loop = ControlLoop(RATE, tick, clock=clock)
    thread = loop.run_in_thread()
    assert reached.wait(10.0)
    loop.stop()
    thread.join(10.0)
    assert not thread.is_alive()
    assert loop.wait(0)
    assert loop.ticks_run >= 101
    assert loop.error is None


def test_run_in_thread_records_tick_exception() -> None:
    def tick(now: float, k: int) -> None:
        if k == 3:
            raise RuntimeError("boom")

    loop = ControlLoop(RATE, tick, clock=SimClock())
    loop.run_in_thread()
    assert loop.wait(10.0)
    loop.join(10.0)
    assert isinstance(loop.error, RuntimeError)


def test_tick_exception_propagates_and_restores_gc() -> None:
    assert gc.isenabled()

    def tick(now: float, k: int) -> None:
        assert not gc.isenabled()
        raise KeyError("x")

    loop = ControlLoop(RATE, tick, clock=SimClock(), realtime={"gc": "freeze"})
    with pytest.raises(KeyError):
        loop.run(ticks=5)
    assert gc.isenabled()
    assert gc.get_freeze_count() == 0
    assert not loop.running


# -- gc control --------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", ["freeze", "off"])
def test_gc_disabled_during_run_and_restored(mode: str) -> None:
    seen: list[bool] = []
    loop = ControlLoop(
        RATE, lambda now, k: seen.append(gc.isenabled()), clock=SimClock(), realtime={"gc": mode}
    )
    loop.run(ticks=10)
    assert seen == [False] * 10
    assert gc.isenabled()
    assert f"gc {mode}" in loop.realtime_report


def test_gc_default_is_untouched() -> None:
    seen: list[bool] = []
    loop = ControlLoop(RATE, lambda now, k: seen.append(gc.isenabled()), clock=SimClock())
    loop.run(ticks=3)
    assert seen == [True] * 3
    assert loop.realtime_report == "realtime: none requested"


def test_spare_time_gc_only_when_budget_allows() -> None:
    clock = SimClock()
    rt = {"gc": "freeze", "gc_every": 10, "gc_min_spare_us": 300}
    idle = ControlLoop(RATE, lambda now, k: None, clock=clock, realtime=rt)
    idle.run(ticks=1000)
    assert idle.gc_collections == 100
    busy = ControlLoop(RATE, lambda now, k: clock.advance(0.8 * PERIOD), clock=clock, realtime=rt)
    busy.run(ticks=1000)
    assert busy.gc_collections == 0  # 200 µs spare < 300 µs: never collects in a tick


def test_realtime_key_validation() -> None:
    with pytest.raises(ValueError, match="unknown realtime keys"):
        ControlLoop(RATE, lambda now, k: None, realtime={"priority": 3})
    with pytest.raises(ValueError):
        ControlLoop(RATE, lambda now, k: None, realtime={"gc": "sometimes"})
    with pytest.raises(ValueError):
        ControlLoop(0, lambda now, k: None)


# -- real-time setup (mocked: tests never change the real scheduler) ----------------------------


def test_realtime_fallback_when_fifo_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*_args: object) -> None:
        raise PermissionError("Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    monkeypatch.setattr(os, "sched_getscheduler", lambda pid: os.SCHED_OTHER)
    monkeypatch.setattr(os, "sched_getparam", lambda pid: os.sched_param(0))
    affinity: list[set[int]] = []
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})
    monkeypatch.setattr(os, "sched_setaffinity", lambda pid, cpus: affinity.append(set(cpus)))
    clock = SimClock()
    loop = ControlLoop(
        RATE, lambda now, k: None, clock=clock, realtime={"fifo_priority": 80, "cpu": 1}
    )
    assert loop.run(ticks=50).ticks == 50  # runs anyway
    assert loop.realtime_report == (
        "realtime: SCHED_FIFO refused (EPERM), running SCHED_OTHER; cpu 1 pinned"
    )
    assert affinity == [{1}, {0, 1}]  # pinned, then restored


def test_realtime_affinity_refused_and_platform_without_sched(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import errno

    def einval(*_args: object) -> None:
        raise OSError(errno.EINVAL, "Invalid argument")

    monkeypatch.delattr(os, "sched_setscheduler", raising=False)
    monkeypatch.setattr(os, "sched_setaffinity", einval)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0})
    parts, restore = loop_mod.apply_realtime(50, 7)
    restore()
    assert parts == ["SCHED_FIFO unavailable on this platform", "cpu 7 pinning refused (EINVAL)"]


def test_realtime_applied_and_restored(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple[str, object]] = []
    monkeypatch.setattr(os, "sched_getscheduler", lambda pid: os.SCHED_OTHER)
    monkeypatch.setattr(os, "sched_getparam", lambda pid: os.sched_param(0))
    monkeypatch.setattr(
        os,
        "sched_setscheduler",
        lambda pid, policy, param: calls.append(("policy", (pid, policy, param.sched_priority))),
    )
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})
    monkeypatch.setattr(os, "sched_setaffinity", lambda pid, cpus: calls.append(("cpus", cpus)))
    in_tick: list[int] = []
    loop = ControlLoop(
        RATE,
        lambda now, k: in_tick.append(len(calls)),
        clock=SimClock(),
        realtime={"fifo_priority": 80, "cpu": 1, "gc": "freeze"},
    )
    loop.run(ticks=3)
    assert loop.realtime_report == "realtime: SCHED_FIFO 80 on; cpu 1 pinned; gc freeze"
    assert in_tick == [2, 2, 2]
    me = threading.get_native_id()  # this thread, never a pid (0 and 1 are others' to mutate)
    assert calls == [
        ("policy", (me, os.SCHED_FIFO, 80)),
        ("cpus", {1}),
        ("cpus", {0, 1}),  # restored in reverse order
        ("policy", (me, os.SCHED_OTHER, 0)),
    ]


# -- watchdog integration ----------------------------------------------------------------------


@pytest.mark.req("SR-WD-1")
def test_watchdog_stops_loop_after_consecutive_overruns() -> None:
    clock = SimClock()
    alerts: list[str] = []
    stops: list[tuple[str, str]] = []
    loop: ControlLoop

    def on_stop(reason: str, policy: str) -> None:
        stops.append((reason, policy))
        loop.stop()

    wd = Watchdog(
        PERIOD,
        stop_run=3,
        on_alert=lambda reason, n: alerts.append(reason),
        on_stop=on_stop,
        policy="fault",
    )
    seen: list[int] = []

    def tick(now: float, k: int) -> None:
        seen.append(k)
        if k >= 100:
            clock.advance(1.5 * PERIOD)  # compute over the 1 ms budget

    loop = ControlLoop(RATE, tick, clock=clock, watchdog=wd)
    stats = loop.run(ticks=1000)
    assert seen[-1] == 102  # third consecutive overrun stops the loop
    assert len(stops) == 1 and stops[0][1] == "fault"
    assert "3 consecutive overruns" in stops[0][0]
    assert len(alerts) == 1  # rate-limited
    assert "compute 1.500 ms > budget 1.000 ms" in alerts[0]
    assert stats.overruns == 3
    assert wd.overruns == 3


@pytest.mark.req("SR-WD-1")
def test_watchdog_hard_gap_from_injected_stall() -> None:
    clock = SimClock()
    stops: list[str] = []

    def tick(now: float, k: int) -> None:
        if k == 50:
            clock.inject_delay(0.012)

    wd = Watchdog(PERIOD, on_stop=lambda reason, policy: stops.append(reason))
    loop = ControlLoop(RATE, tick, clock=clock, watchdog=wd)
    loop.run(ticks=100)
    assert len(stops) == 1
    assert stops[0].startswith("gap of 13.000 ms between ticks")  # 1 ms period + 12 ms stall
    assert loop.missed_ticks == 12


@pytest.mark.req("SR-WD-1")
def test_watchdog_quiet_on_a_healthy_loop() -> None:
    clock = SimClock()
    events: list[object] = []
    wd = Watchdog(PERIOD, on_alert=lambda *a: events.append(a), on_stop=lambda *a: events.append(a))
    ControlLoop(RATE, lambda now, k: clock.advance(0.9 * PERIOD), clock=clock, watchdog=wd).run(
        ticks=10_000
    )
    assert events == []
    assert wd.overruns == 0


# -- statistics --------------------------------------------------------------------------------

SUMMARY_KEYS = {"p50", "p99", "p99_9", "max", "mean"}
SNAPSHOT_KEYS = {
    "ticks",
    "rate_hz",
    "duration_s",
    "lateness_us",
    "period_us",
    "compute_us",
    "late_over_1ms",
    "late_over_1ms_percent",
    "overruns",
    "missed_ticks",
    "late_ticks",
    "cpu_percent",
    "interfaces",
}


def test_snapshot_shape_and_json() -> None:
    clock = SimClock()
    stats = LoopStats(RATE)
    stats.interfaces["slave_udp"] = {"rx": 5}
    stats.interfaces["loss"] = lambda: {"lost_total": 2}
    ControlLoop(RATE, lambda now, k: clock.advance(1e-4), clock=clock, stats=stats).run(ticks=500)
    snap = stats.snapshot()
    assert set(snap) == SNAPSHOT_KEYS
    for key in ("lateness_us", "period_us", "compute_us"):
        assert set(snap[key]) == SUMMARY_KEYS
    assert snap["ticks"] == 500
    assert snap["rate_hz"] == RATE
    assert snap["compute_us"]["p50"] == pytest.approx(100.0, abs=0.5)
    assert snap["period_us"]["p99"] == pytest.approx(1000.0, abs=0.5)
    assert snap["interfaces"] == {"slave_udp": {"rx": 5}, "loss": {"lost_total": 2}}
    assert isinstance(snap["cpu_percent"], float)  # its arithmetic: the test below
    assert json.loads(json.dumps(snap)) == snap
    line = stats.format_line()
    assert "500 ticks" in line and "late>1ms 0" in line and "overruns 0" in line


def test_cpu_percent_is_process_time_over_wall_time(monkeypatch: pytest.MonkeyPatch) -> None:
    import occ.core.stats as stats_mod

    class FakeTime:
        wall, cpu = 10.0, 1.0

        def perf_counter(self) -> float:
            return self.wall

        def process_time(self) -> float:
            return self.cpu

    fake = FakeTime()
    monkeypatch.setattr(stats_mod, "time", fake)
    stats = LoopStats(RATE)
    stats.begin(0.0)
    fake.wall, fake.cpu = 12.0, 1.5  # 0.5 s of CPU in 2 s
    assert stats.cpu_percent == 25.0  # still running: measured up to now
    stats.end()
    fake.wall, fake.cpu = 20.0, 9.0  # after the end: frozen
    assert stats.cpu_percent == 25.0 and stats.snapshot()["cpu_percent"] == 25.0
    stats.begin(0.0)  # a new run measures afresh
    assert stats.cpu_percent == 0.0  # no wall time yet


def test_stats_counts_overruns_and_late_ticks() -> None:
    stats = LoopStats(RATE, budget_s=0.0005)
    stats.begin(0.0)
    stats.record(0.000, 0.000, 0.0004)
    stats.record(0.001, 0.0010, 0.0016)  # compute 600 µs > 500 µs budget
    stats.record(0.002, 0.0032, 0.0033)  # 1.2 ms late
    stats.record(0.003, 0.0040, 0.0041)  # 1.0 ms late: not over
    snap = stats.snapshot()
    assert snap["ticks"] == 4
    assert snap["overruns"] == 1
    assert snap["late_over_1ms"] == 1
    assert snap["late_over_1ms_percent"] == pytest.approx(25.0)
    assert snap["lateness_us"]["max"] == pytest.approx(1200.0)
    assert snap["period_us"]["max"] == pytest.approx(2200.0)
    assert snap["duration_s"] == pytest.approx(0.0041)
    # the one tick over 1 ms late, with the wall-clock time it started
    (late,) = snap["late_ticks"]
    assert late["late_us"] == pytest.approx(1200.0)
    assert abs(late["at"] - time.time()) < 60.0
    stats.reset()
    assert stats.snapshot()["ticks"] == 0


def test_empty_stats() -> None:
    snap = LoopStats(50.0).snapshot()
    assert snap["ticks"] == 0
    assert snap["lateness_us"] == dict.fromkeys(SUMMARY_KEYS, 0.0)
    assert snap["late_over_1ms_percent"] == 0.0
    assert Histogram().percentile(50) == 0.0


def _bucket_width(v: float) -> float:
    if v < 100:
        return 0.1
    if v < 1000:
        return 1.0
    return v * (10 ** (1 / 100) - 1)


@pytest.mark.parametrize(
    "name",
    ["uniform_fine", "lognormal", "uniform_mid", "exponential_wide", "bimodal"],
)
def test_histogram_percentiles_match_numpy(name: str) -> None:
    rng = np.random.default_rng(7)
    n = 50_000
    data = {
        "uniform_fine": rng.uniform(0, 100, n),
        "lognormal": rng.lognormal(mean=2.0, sigma=1.0, size=n),
        "uniform_mid": rng.uniform(100, 1000, n),
        "exponential_wide": rng.exponential(2000.0, n),
        "bimodal": np.concatenate(
            [rng.normal(3, 0.5, n - 100).clip(0), rng.uniform(5e3, 5e5, 100)]
        ),
    }[name]
    h = Histogram()
    for v in data.tolist():
        h.add(v)
    assert h.count == len(data)
    assert h.max == data.max()
    assert h.min == data.min()
    assert h.mean == pytest.approx(data.mean(), rel=1e-9)
    srt = np.sort(data)
    for p in (0, 1, 10, 50, 90, 99, 99.9, 99.99, 100):
        ref = float(np.percentile(data, p))
        pos = p / 100 * (len(data) - 1)
        lo, hi = srt[math.floor(pos)], srt[math.ceil(pos)]
        neighbour_gap = float(srt[min(math.ceil(pos) + 1, len(srt) - 1)] - lo)
        tol = _bucket_width(ref) + neighbour_gap + 1e-9
        got = h.percentile(p)
        assert abs(got - ref) <= tol, (p, got, ref, lo, hi)
    assert h.percentile(100) == data.max()


def test_histogram_overflow_and_negative() -> None:
    h = Histogram()
    h.add(-5.0)
    h.add(2_000_000.0)
    assert h.count == 2
    assert h.max == 2_000_000.0
    assert h.percentile(100) == 2_000_000.0
    assert h.percentile(0) == -5.0  # clamped to the exact minimum
    with pytest.raises(ValueError):
        h.percentile(101)


def test_histogram_buckets_subtract_into_a_window() -> None:
    h = Histogram()
    for v in range(1, 1001):
        h.add(v * 0.05)  # 0.05-50 µs: the baseline
    before = h.buckets()
    for v in range(1, 101):
        h.add(1000.0 + v * 10.0)  # 1.01-2 ms: the window
    after = h.buckets()
    window = Histogram.from_buckets({i: n - before.get(i, 0) for i, n in after.items()})
    assert window.count == 100
    assert 1000.0 <= window.percentile(0) <= 1010.0
    assert window.percentile(50) == pytest.approx(1500.0, rel=0.03)
    assert window.percentile(100) == pytest.approx(2000.0, rel=0.03)
    assert Histogram.from_buckets({}).percentile(99.9) == 0.0


def test_stats_keep_the_worst_late_ticks_with_their_wall_time() -> None:
    stats = LoopStats(RATE)
    stats.begin(0.0)
    for i in range(60):  # late by 1.1, 1.2, ... 7.0 ms, in a scrambled order
        late = 1.1e-3 + 0.1e-3 * ((i * 37) % 60)
        stats.record(i * 0.01, i * 0.01 + late, i * 0.01 + late + 1e-4)
    stats.record(1.0, 1.0005, 1.0006)  # 0.5 ms late: not kept
    kept = stats.snapshot()["late_ticks"]
    assert len(kept) == LoopStats.LATE_KEPT
    assert [k["late_us"] for k in kept] == [
        pytest.approx(7000.0 - 100.0 * j) for j in range(LoopStats.LATE_KEPT)
    ]
    stats.reset()
    assert stats.snapshot()["late_ticks"] == []
