"""Threads that work beside the control loop, never inside it.

- :class:`SupervisorThread` runs a :class:`~occ.core.safety.Supervisor` in real time: a loop that
  stopped ticking (a hung tick, a blocking call) is noticed within the supervisor's timeout
  even though the loop thread cannot notice it itself.
- :class:`Worker` runs jobs the loop must not pay for (the statistics behind ``GetStats``):
  the loop hands a job over in O(1) and the worker sends the reply itself.

What still holds when the whole process is frozen (SIGSTOP, a VM pause, a C call that keeps
the interpreter lock): neither the loop nor these threads run, so nothing in this process can
act. The device-side heartbeat does (the ``Driver`` contract's ``heartbeat_ms``: the drive
stops itself when it is not refreshed in time), and the peer notices the silence (the
slave's loss monitor holds, then latches after the grace).
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from occ.clock import Clock, RealClock
from occ.core.safety import Supervisor

if TYPE_CHECKING:
    from occ.config import SupervisorConfig

__all__ = ["SupervisorThread", "Worker"]

from igtl.transport.common import name_native_thread

log = logging.getLogger(__name__)


class SupervisorThread:
    """Checks a :class:`Supervisor` on its own thread, waking when a trip could first be due.

    Not the loop's state: a checkpoint keeps no part of it (occ/core/checkpoint.py).

    After each check it sleeps until the moment the loop's silence would exceed the timeout
    (last beat + timeout), at most ``timeout / 2`` (see :meth:`sleep_after`): a healthy
    loop costs two wake-ups per timeout (100 a second at the default 20 ms, where a fixed
    ``timeout / 4`` cost 200), a hung loop is caught about one timeout after its last beat, and
    the supervisor never sleeps so long that :meth:`Supervisor.check` would take its own
    normal sleep for a paused process."""

    checkpoint_opaque = True

    def __init__(
        self,
        supervisor: Supervisor,
        clock: Clock,
        *,
        fifo_priority: int | None = None,
        name: str = "occ-supervisor",
    ) -> None:
        self.supervisor = supervisor
        self.clock = clock
        self.fifo_priority = fifo_priority
        self.min_sleep_s = supervisor.timeout_s / 8.0
        self.max_sleep_s = supervisor.timeout_s / 2.0
        self.wakeups = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._main, name=name, daemon=True)
        self.report = ""

    @classmethod
    def build(
        cls, sv: SupervisorConfig, supervisor: Supervisor, clock: Clock, loop_priority: int | None
    ) -> SupervisorThread | None:
        """The thread for ``safety.supervisor`` (started), one SCHED_FIFO priority above the
        loop's unless the config names its own; None when it is off or the clock is
        simulated."""
        if not sv.enabled or not isinstance(clock, RealClock):
            return None
        prio = sv.fifo_priority or (min(99, loop_priority + 1) if loop_priority else None)
        return cls(supervisor, clock, fifo_priority=prio).start()

    def start(self) -> SupervisorThread:
        self._thread.start()
        return self

    def stop(self) -> None:
        """Ends the thread at its next wake-up (within ``timeout / 2``)."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(1.0)

    def _main(self) -> None:
        name_native_thread("supervisor")
        if self.fifo_priority is not None:
            # Above the loop: when the loop spins (a hung tick that keeps the CPU), the
            # supervisor must still get a core the moment it wakes.
            try:
                # this thread by its own id, not pid 0: a slip in the id (mutation testing's
                # 0 -> 1) must not reach another process (pid 1, as root)
                os.sched_setscheduler(
                    threading.get_native_id(), os.SCHED_FIFO, os.sched_param(self.fifo_priority)
                )
                self.report = f"SCHED_FIFO {self.fifo_priority}"
            except (OSError, AttributeError) as err:
                self.report = f"SCHED_FIFO refused ({type(err).__name__})"
        now = self.clock.now
        sup = self.supervisor
        check = sup.check
        sleep_after = self.sleep_after
        sleep = self.max_sleep_s
        pause = time.sleep  # one system call; Event.wait(timeout) is several Python frames
        stopping = self._stop.is_set
        while True:
            pause(sleep)
            if stopping():
                break
            self.wakeups += 1
            t = now()
            try:
                check(t)
            except Exception:  # noqa: BLE001 - the supervisor must outlive a failing action
                log.exception("supervisor action failed")
            sleep = sleep_after(t)

    def sleep_after(self, now: float) -> float:
        """How long to sleep after a check at ``now``: until just past the instant the loop's
        silence would exceed the timeout (``check`` trips on "more than"), at most
        ``timeout / 2``; ``timeout / 8`` when that instant has passed without a trip (the
        check restarted its window after a pause of the whole process)."""
        sup = self.supervisor
        last = sup.last_beat
        if last is None or not sup.armed or sup.tripped:
            return self.max_sleep_s
        sleep = last + sup.timeout_s + 1e-4 - now
        if sleep <= 0.0:
            return self.min_sleep_s
        return sleep if sleep < self.max_sleep_s else self.max_sleep_s


class Worker:
    """A bounded queue of jobs run on one background thread (``submit`` never blocks).

    ``fifo_priority``: SCHED_FIFO for the thread where permitted (the daemon gives it two below
    the loop when the loop runs SCHED_FIFO). A job holds the interpreter lock while it runs (a
    GetStats snapshot: milliseconds); at normal priority any other process on the machine can
    preempt the worker while it holds it, and the loop waits for the lock meanwhile: measured
    on the two-pair benchmark with one CPU hog, a slave's lateness p99.9 of 463 us against 230
    us with the worker at SCHED_FIFO (docs/BENCHMARKS.md)."""

    def __init__(self, name: str, depth: int = 8, fifo_priority: int | None = None) -> None:
        self._jobs: queue.Queue[Callable[[], None] | None] = queue.Queue(depth)
        self._thread = threading.Thread(target=self._main, name=name, daemon=True)
        self._started = False
        self.fifo_priority = fifo_priority
        #: what the thread got: ``SCHED_FIFO N``, ``normal`` or why not
        self.policy = "normal"
        self.done = 0
        self.refused = 0
        self.failed = 0

    def start(self) -> Worker:
        if not self._started:
            self._started = True
            self._thread.start()
        return self

    def submit(self, job: Callable[[], None]) -> bool:
        """Queue ``job``; False (counted) when the queue is full or the worker not started."""
        if not self._started:
            self.refused += 1
            return False
        try:
            self._jobs.put_nowait(job)
        except queue.Full:
            self.refused += 1
            return False
        return True

    def stop(self) -> None:
        if self._started:
            try:
                self._jobs.put_nowait(None)
            except queue.Full:
                pass
            self._thread.join(1.0)

    def _main(self) -> None:
        name_native_thread("worker")
        if self.fifo_priority is not None:
            try:
                os.sched_setscheduler(
                    threading.get_native_id(), os.SCHED_FIFO, os.sched_param(self.fifo_priority)
                )
                self.policy = f"SCHED_FIFO {self.fifo_priority}"
            except (OSError, AttributeError) as err:  # not permitted here: normal priority
                self.policy = f"normal (SCHED_FIFO refused: {err.__class__.__name__})"
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:
                job()
                self.done += 1
            except Exception:  # noqa: BLE001 - one failing job must not end the worker
                self.failed += 1
                log.exception("%s: job failed", self._thread.name)
