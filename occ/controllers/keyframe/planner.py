"""The keyframe controller's planner service: the one thread that plans, checks, reads keyframe
files and does the library's file work off the loop, one job at a time
(:class:`PlannerThread`), and the plan and file jobs it runs, which hand their results to the
controller through :class:`PlannerPort` (package docstring, "Plan, check and preview")."""

from __future__ import annotations

import logging
import os
import queue
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from occ.controllers.keyframe.cellset import (
    CellKeyframeFile,
    CellSet,
    cell_set,
    read_any_keyframe_file,
)
from occ.controllers.keyframe.plan import CheckedPlan, PlanRefused, PlanRequest, build_plan
from occ.controllers.keyframe.sets import KeyframeSet, Space, file_set
from occ.errors import CommandError
from occ.net.commands import Deferred

if TYPE_CHECKING:
    from occ.kinematics.frame import Frame

# the package's one logger (the name operators and tests filter on)
log = logging.getLogger("occ.controllers.keyframe")


def _loop_priority() -> int | None:
    """The calling (loop) thread's SCHED_FIFO priority, None when it is not SCHED_FIFO."""
    try:
        if os.sched_getscheduler(threading.get_native_id()) == os.SCHED_FIFO:
            return int(os.sched_getparam(threading.get_native_id()).sched_priority)
    except (OSError, AttributeError):
        pass
    return None


class PlannerThread:
    """One daemon thread that runs the planner's jobs, one at a time. The loop only puts a
    job in its queue (microseconds); a job submitted while one is pending is refused."""

    def __init__(self) -> None:
        self._jobs: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self.idle = threading.Event()
        self.idle.set()
        self.fifo: int | None = None  # the thread's SCHED_FIFO priority (None: SCHED_OTHER)
        self.fifo_refused = ""
        self._thread = threading.Thread(target=self._main, name="occ-keyframe-planner", daemon=True)
        self._thread.start()

    def submit(self, job: Callable[[], None], answer: Deferred, fifo: int | None) -> bool:
        """Queue ``job``; False when one is pending. ``fifo``: the loop's SCHED_FIFO priority
        (None: it runs SCHED_OTHER); the job runs one below it, as the interface threads do."""
        with self._lock:
            if not self.idle.is_set():
                return False
            self.idle.clear()

        def run() -> None:
            self._schedule(fifo)
            try:
                job()
            except Exception as err:  # noqa: BLE001 - the operator gets an answer whatever
                log.exception("keyframe planner failed")
                answer.fail(f"planner failed: {err}")

        self._jobs.put(run)
        return True

    def _schedule(self, fifo: int | None) -> None:
        # Below the loop but above ordinary processes, like the interface threads: a planner
        # thread preempted while it holds the interpreter lock (a busy machine) would keep a
        # SCHED_FIFO loop waiting for the lock for as long as the kernel keeps it off the CPU.
        want = None if fifo is None else max(1, fifo - 1)
        if want == self.fifo:
            return
        try:
            if want is None:
                os.sched_setscheduler(threading.get_native_id(), os.SCHED_OTHER, os.sched_param(0))
            else:
                os.sched_setscheduler(
                    threading.get_native_id(), os.SCHED_FIFO, os.sched_param(want)
                )
            self.fifo = want
        except (OSError, AttributeError) as err:
            self.fifo_refused = f"{type(err).__name__}: {err}"

    def start(self, job: Callable[[Deferred], None]) -> Deferred:
        """Hand ``job`` to the thread with the answer it gives (called on the loop thread: the
        job runs one below its SCHED_FIFO priority); CommandError "busy" when one is pending."""
        answer = Deferred()
        if not self.submit(lambda: job(answer), answer, _loop_priority()):
            raise CommandError("busy: the planner is still working on the last request; retry")
        return answer

    def stop(self) -> None:
        """Let the thread end once the queued job (if any) is done."""
        self._jobs.put(None)

    def _main(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:
                job()
            finally:
                self.idle.set()


class PlannerPort(Protocol):
    """What the planner's jobs hand their results to (the keyframe controller; under its
    lock, which the loop shares)."""

    def install_unless_changed(
        self, kset: KeyframeSet, generation: int, cell: CellSet | None = None
    ) -> bool:
        """Make ``kset`` the stored set (``cell``: the cell set it is this member's part of)
        unless the set changed since ``generation``."""
        ...

    def plan_done(
        self, req: PlanRequest, generation: int, checked: CheckedPlan | None, refusal: str
    ) -> bool:
        """Preview ``checked`` (False: the keyframes changed since ``generation``), or keep
        ``refusal``."""
        ...


def plan_job(
    port: PlannerPort, req: PlanRequest, frame: Frame, generation: int
) -> Callable[[Deferred], None]:
    """KeyframePlan's job: plan and check ``req`` with the planner's own ``frame``; the answer
    is the plan's summary, or the refusal."""

    def job(answer: Deferred) -> None:
        try:
            checked = build_plan(req, frame)
        except PlanRefused as err:
            text = f"plan {req.id} refused: {err}"
            port.plan_done(req, generation, None, text)
            answer.fail(text)
            return
        if port.plan_done(req, generation, checked, ""):
            answer.resolve(checked.summary)
        else:
            answer.fail(f"plan {req.id} dropped: the keyframes changed meanwhile; plan again")

    return job


def load_file_job(
    port: PlannerPort,
    path: Path,
    name: str,
    space: Space,
    joints: int,
    cap: int,
    generation: int,
    member: str | None = None,
) -> Callable[[Deferred], None]:
    """KeyframeLoad File=NAME's job: read and validate the file, install its set; a cell
    keyframe set's part for ``member`` (this robot's name in its cell)."""

    def job(answer: Deferred) -> None:
        cset: CellSet | None = None
        try:
            kf = read_any_keyframe_file(path)
            if isinstance(kf, CellKeyframeFile):
                cset = cell_set(kf, name, member, space, joints, cap)
                kset = cset.own
            else:
                kset = file_set(kf, space, f"file {name}", joints, cap)
        except ValueError as err:
            answer.fail(f"KeyframeLoad refused: {err}")
            return
        if not port.install_unless_changed(kset, generation, cset):
            answer.fail("KeyframeLoad: the keyframes changed meanwhile; load again")
            return
        text = f"{len(kset.keyframes)} keyframes ({kset.space}) from {name}"
        if cset is not None:
            text += (
                f": part {cset.me} of cell set {cset.digest} (parts "
                f"{', '.join(cset.members)}); KeyframePlan, then KeyframeCellPath"
            )
        answer.resolve(text)

    return job
