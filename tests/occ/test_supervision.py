"""occ.core.supervision: the supervisor's thread and the worker, each alone with real threads
(issue 29: mutation testing of the code beside the loop). Nothing here waits on a wall-clock
limit: each step waits for an event or a count (``wait_until``, bounded), never for a time."""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path

import pytest

from occ.clock import RealClock, SimClock
from occ.config import SupervisorConfig
from occ.core.safety import Supervisor
from occ.core.supervision import SupervisorThread, Worker
from occ_testkit.testing import wait_until


def _fifo_report(report: str, priority: int) -> bool:
    """What a thread says it got: the priority, or why not (unprivileged machines)."""
    return report == f"SCHED_FIFO {priority}" or (
        report.startswith("SCHED_FIFO refused (") and report.endswith(")")
    )


def _policy_of(thread: threading.Thread) -> tuple[int, int]:
    """The scheduling policy and priority the kernel holds for ``thread``."""
    tid = thread.native_id
    assert tid is not None
    return os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority


def _comm(thread: threading.Thread) -> str:
    """The thread's name as the operating system shows it (``top -H``, ``ps -L``)."""
    return Path(f"/proc/self/task/{thread.native_id}/comm").read_text().strip()


@pytest.mark.req("SR-SUP-1")
def test_the_supervisor_thread_catches_a_silent_loop_and_outlives_a_failing_action(
    caplog: pytest.LogCaptureFixture,
) -> None:
    trips: list[str] = []

    def act(reason: str) -> None:
        trips.append(reason)
        raise RuntimeError("the stop itself failed")

    clock = RealClock()
    sup = Supervisor(timeout_s=0.020, on_trip=act)
    th = SupervisorThread(sup, clock, name="test-supervisor")
    assert (th.min_sleep_s, th.max_sleep_s) == (0.020 / 8.0, 0.020 / 2.0)
    assert th.report == "" and th.wakeups == 0
    caplog.set_level(logging.ERROR, logger="occ.core.supervision")
    th.start()
    try:
        assert th._thread.name == "test-supervisor" and th._thread.daemon
        sup.arm(clock.now())  # and never a beat again: a hung loop
        assert wait_until(lambda: trips, timeout=10.0)
        assert sup.tripped and sup.trips == 1 and len(trips) == 1
        assert wait_until(
            lambda: any(r.getMessage() == "supervisor action failed" for r in caplog.records),
            timeout=10.0,
        )
        # the thread lives on after the failing action: it keeps waking
        woken = th.wakeups
        assert wait_until(lambda: th.wakeups > woken + 2, timeout=10.0)
        assert th._thread.is_alive() and len(trips) == 1  # latched: one trip
    finally:
        th.stop()
    assert not th._thread.is_alive()
    assert th.report == ""  # no priority asked


def test_the_supervisor_thread_reports_its_priority() -> None:
    sup = Supervisor(timeout_s=0.020)
    th = SupervisorThread(sup, SimClock(), fifo_priority=3).start()
    try:
        assert wait_until(lambda: th.report, timeout=10.0)
        assert _fifo_report(th.report, 3), th.report
        # what it says is what the kernel holds for this thread (and no other)
        granted = th.report == "SCHED_FIFO 3"
        assert _policy_of(th._thread) == ((os.SCHED_FIFO, 3) if granted else (os.SCHED_OTHER, 0))
        assert _comm(th._thread) == "supervisor"
        assert th._thread.name == "occ-supervisor"  # the default name, in Python
    finally:
        th.stop()
    assert not th._thread.is_alive()
    # a thread never started stops at once
    idle = SupervisorThread(sup, SimClock())
    idle.stop()
    assert not idle._thread.is_alive() and idle.wakeups == 0


def test_a_stopped_supervisor_thread_checks_no_more() -> None:
    sup = Supervisor(timeout_s=0.020)
    th = SupervisorThread(sup, SimClock()).start()
    assert wait_until(lambda: th.wakeups >= 2, timeout=10.0)
    th.stop()
    assert not th._thread.is_alive()
    n = th.wakeups
    th.stop()  # twice: harmless
    assert th.wakeups == n


@pytest.mark.req("SR-SUP-1")
def test_the_supervisor_thread_sleeps_exactly_until_a_trip_could_be_due() -> None:
    sup = Supervisor(timeout_s=0.020)
    th = SupervisorThread(sup, SimClock())
    assert th.sleep_after(5.0) == 0.010  # never armed
    sup.arm(1.0)
    assert th.sleep_after(1.0) == 0.010  # capped at timeout / 2
    assert th.sleep_after(1.015) == pytest.approx(0.0051, rel=1e-9, abs=0.0)
    assert th.sleep_after(1.0201) == 0.020 / 8.0  # exactly due: the short sleep
    assert th.sleep_after(1.03) == 0.020 / 8.0
    sup.disarm()
    assert th.sleep_after(1.015) == 0.010
    sup.arm(2.0)
    sup.check(2.015)
    sup.check(2.03)
    assert sup.tripped and th.sleep_after(2.03) == 0.010


def test_the_worker_runs_jobs_in_order_counts_and_survives_a_failing_one(
    caplog: pytest.LogCaptureFixture,
) -> None:
    w = Worker("test-worker", depth=4)
    assert (w.policy, w.done, w.refused, w.failed) == ("normal", 0, 0, 0)
    assert w.submit(lambda: None) is False and w.refused == 1  # not started
    assert w.start() is w and w.start() is w  # once
    ran: list[int] = []

    def fail() -> None:
        raise ValueError("boom")

    caplog.set_level(logging.ERROR, logger="occ.core.supervision")
    try:
        assert w.submit(lambda: ran.append(1))
        assert w.submit(fail)
        assert w.submit(lambda: ran.append(2))
        assert w.submit(fail)
        assert wait_until(lambda: w.done == 2 and w.failed == 2, timeout=10.0)
        assert ran == [1, 2]
        assert [r.getMessage() for r in caplog.records] == ["test-worker: job failed"] * 2
        assert w._thread.name == "test-worker" and w._thread.daemon
    finally:
        w.stop()
    assert not w._thread.is_alive()
    assert (w.done, w.failed, w.refused) == (2, 2, 1)


def test_a_full_worker_refuses_and_counts_and_a_stop_never_hangs() -> None:
    w = Worker("test-worker", depth=2).start()
    hold, started = threading.Event(), threading.Event()

    def block() -> None:
        started.set()
        hold.wait(10.0)

    try:
        assert w.submit(block)
        assert started.wait(10.0)
        assert w.submit(lambda: None) and w.submit(lambda: None)  # the queue holds 2
        assert w.submit(lambda: None) is False and w.refused == 1
        assert w.submit(lambda: None) is False and w.refused == 2
        assert w.submit(lambda: None) is False and w.refused == 3
    finally:
        hold.set()
    assert wait_until(lambda: w.done == 3, timeout=10.0)
    assert w._thread.is_alive()  # a worker started lazily once stays started
    w.stop()
    assert not w._thread.is_alive()
    # stopping with a full queue: the sentinel does not fit, the join is bounded
    full = Worker("test-full", depth=1).start()
    gate, began = threading.Event(), threading.Event()
    full.submit(lambda: (began.set(), gate.wait(10.0)))
    assert began.wait(10.0)
    assert full.submit(lambda: None)  # the queue is full now
    stopper = threading.Thread(target=full.stop)
    stopper.start()
    stopper.join(10.0)
    assert not stopper.is_alive()  # returned, without the sentinel
    gate.set()
    assert wait_until(lambda: full.done == 2, timeout=10.0)
    assert full._thread.is_alive()  # no sentinel reached it: it waits for work
    full.submit(None)  # type: ignore[arg-type]  # the sentinel by hand ends it
    full._thread.join(10.0)
    assert not full._thread.is_alive()
    # a worker never started: stop is a no-op
    Worker("never").stop()


def test_the_worker_reports_its_priority() -> None:
    w = Worker("test-prio", fifo_priority=2).start()
    try:
        done = threading.Event()
        assert w.submit(done.set) and done.wait(10.0)
        assert w.policy == "SCHED_FIFO 2" or (
            w.policy.startswith("normal (SCHED_FIFO refused: ") and w.policy.endswith(")")
        ), w.policy
        granted = w.policy == "SCHED_FIFO 2"
        assert _policy_of(w._thread) == ((os.SCHED_FIFO, 2) if granted else (os.SCHED_OTHER, 0))
        assert _comm(w._thread) == "worker"
    finally:
        w.stop()


def test_the_worker_queue_holds_eight_by_default() -> None:
    w = Worker("test-default").start()
    hold, started = threading.Event(), threading.Event()
    try:
        assert w.submit(lambda: (started.set(), hold.wait(10.0)))
        assert started.wait(10.0)
        assert all(w.submit(lambda: None) for _ in range(8))
        assert w.submit(lambda: None) is False and w.refused == 1
    finally:
        hold.set()
        w.stop()


def test_every_wake_up_of_the_supervisor_thread_is_one_check() -> None:
    checks = [0]

    class Counting(Supervisor):
        def check(self, now: float) -> str | None:
            checks[0] += 1
            return super().check(now)

    th = SupervisorThread(Counting(timeout_s=0.020), SimClock()).start()
    assert wait_until(lambda: th.wakeups >= 3, timeout=10.0)
    th.stop()
    assert th.wakeups == checks[0]


def test_a_priority_the_kernel_refuses_is_reported_with_the_error() -> None:
    """An impossible SCHED_FIFO priority (1000) is refused on every machine: the thread says
    so, with the error's class, and runs at normal priority."""
    th = SupervisorThread(Supervisor(timeout_s=0.020), SimClock(), fifo_priority=1000).start()
    w = Worker("test-refused", fifo_priority=1000).start()
    try:
        assert wait_until(lambda: th.report, timeout=10.0)
        assert th.report == "SCHED_FIFO refused (OSError)"
        done = threading.Event()
        assert w.submit(done.set) and done.wait(10.0)
        assert w.policy == "normal (SCHED_FIFO refused: OSError)"
        assert _policy_of(w._thread) == (os.SCHED_OTHER, 0)
    finally:
        th.stop()
        w.stop()


def test_a_worker_not_started_refuses_every_job_and_counts_each() -> None:
    w = Worker("test-idle")
    assert [w.submit(lambda: None) for _ in range(3)] == [False] * 3 and w.refused == 3


def test_stopping_a_supervisor_thread_stuck_in_its_action_returns() -> None:
    """stop() waits a bounded time: a supervisor thread stuck in its trip action (a stop that
    blocks) cannot hang the daemon's shutdown."""
    release, stuck = threading.Event(), threading.Event()

    def act(reason: str) -> None:
        stuck.set()
        release.wait(30.0)

    sup = Supervisor(timeout_s=0.020, on_trip=act)
    th = SupervisorThread(sup, RealClock()).start()
    try:
        sup.arm(RealClock().now())
        assert stuck.wait(10.0)
        stopper = threading.Thread(target=th.stop)
        stopper.start()
        stopper.join(10.0)
        assert not stopper.is_alive() and th._thread.is_alive()  # returned; still stuck
    finally:
        release.set()
    th._thread.join(10.0)
    assert not th._thread.is_alive()


def _built(
    enabled: bool, clock: RealClock | SimClock, loop: int | None, fifo_priority: int | None = None
) -> SupervisorThread | None:
    """SupervisorThread.build from the supervisor's settings, the supervisor and the clock."""
    sv = SupervisorConfig(enabled=enabled, fifo_priority=fifo_priority)
    return SupervisorThread.build(sv, Supervisor(timeout_s=0.020), clock, loop)


@pytest.mark.parametrize(
    ("configured", "loop", "expected"),
    [(None, 60, 61), (None, 99, 99), (None, None, None), (70, 60, 70), (70, None, 70)],
)
def test_the_robots_supervisor_thread_runs_one_priority_above_the_loop(
    configured: int | None, loop: int | None, expected: int | None
) -> None:
    """On a real clock the robot's supervisor gets its thread, started, one SCHED_FIFO
    priority above the loop's (at most 99) unless the config names its own; no priority when
    the loop has none."""
    clock = RealClock()
    th = _built(True, clock, loop, configured)
    assert th is not None
    try:
        assert th.clock is clock and th.supervisor.timeout_s == 0.020
        assert th.fifo_priority == expected
        assert wait_until(lambda: th.wakeups > 0, 5.0)  # started: it checks
    finally:
        th.stop()


def test_no_supervisor_thread_when_it_is_off_or_the_clock_is_simulated() -> None:
    assert _built(False, RealClock(), 60) is None
    assert _built(True, SimClock(), 60) is None
    assert _built(False, SimClock(), 60) is None
