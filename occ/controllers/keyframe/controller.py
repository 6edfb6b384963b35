"""The keyframe controller on the loop thread (:class:`KeyframeController`): the stored set,
the commands, the acknowledgement and the run, sampled every tick (package docstring)."""

from __future__ import annotations

import logging
import threading
import time
import weakref
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel

from occ.controllers import Controller, ControllerContext, Problem, SourceFn
from occ.controllers.keyframe.cellset import PATH_DEVICE, CellRole, CellSet, previewed
from occ.controllers.keyframe.library import LibraryCommands
from occ.controllers.keyframe.pacer import Pacer
from occ.controllers.keyframe.params import KeyframeParams, check_params, regions_check
from occ.controllers.keyframe.plan import (
    CheckedPlan,
    ForbiddenCheck,
    PathCheck,
    PlanRequest,
    ack_ready,
    plan_request,
    plan_settings,
    run_tick,
)
from occ.controllers.keyframe.planner import PlannerThread, load_file_job, plan_job
from occ.controllers.keyframe.preview import Preview
from occ.controllers.keyframe.sets import (
    KeyframeFile,
    KeyframeSet,
    PlanSettings,
    added_set,
    file_set,
    keyframe_path,
    make_set,
    read_keyframe_file,
)
from occ.core.safety import RobotState
from occ.errors import CommandError, ConfigError, LibraryError
from occ.events import ArrayInput, PointsOut, PolylineOut
from occ.joint import JointLimits
from occ.kinematics.keyframe_inputs import items_from_event
from occ.kinematics.trajlib import Library, config_hash
from occ.net.commands import ArrayReply, Deferred
from occ.ratelimit import RateLimit

if TYPE_CHECKING:
    from occ.config import DaemonConfig
    from occ.core.data import RobotData
    from occ.events import InputEvent
    from occ.kinematics.frame import Frame
    from occ.net.commands import Request
    from occ.net.outputs import Output

#: the controller's statistics counters ("planner_waits": how often the planner waited for the
#: quiet part of the loop's period, the Pacer)
COUNTERS = (
    "sets",
    "inputs_refused",
    "plans_checked",
    "plans_refused",
    "runs",
    "runs_completed",
    "runs_stopped",
    "ik_failures",
    "port_stops",
    "library_saved",
    "library_loaded",
    "library_deleted",
    "library_refused",
    "planner_waits",
)

# the package's one logger (the name operators and tests filter on)
log = logging.getLogger("occ.controllers.keyframe")

#: the STATUS names of a run's start and end (package docstring, "Acknowledge and run")
STATUS_RUNNING = "KEYFRAME_RUNNING"
STATUS_ENDED = "KEYFRAME_ENDED"
#: their STATUS codes (igtl StatusCode values; controllers do not import igtl): OK, DISABLED
_CODE_OK = 1
_CODE_DROPPED = 15


class KeyframeController(Controller):
    """Keyframes planned, checked, previewed in Slicer, run once acknowledged (issue 11)."""

    name = "keyframe"
    Params = KeyframeParams

    COMMANDS = (
        "KeyframeAdd",
        "KeyframeList",
        "KeyframeClear",
        "KeyframeLoad",
        "KeyframePlan",
        "KeyframeAck",
        "KeyframeSave",
        "KeyframeLibrary",
        "KeyframeDelete",
        "KeyframeCellPath",
        "KeyframeCellCheck",
    )

    def __init__(self, params: BaseModel | dict[str, Any] | None = None) -> None:
        super().__init__(params)
        p = self.params
        assert isinstance(p, KeyframeParams)
        self.p = p
        self.forbidden_checks: list[ForbiddenCheck] = []
        self.path_checks: list[PathCheck] = []
        # shared with the planner thread: every change under the lock; the loop reads the
        # references (atomic) without it
        self._lock = threading.Lock()
        self._generation = 0  # +1 whenever the set changes or a plan is invalidated
        self.kset: KeyframeSet | None = None
        self.plan: CheckedPlan | None = None  # checked, previewed, not yet acknowledged
        self.status = "no keyframes"
        self._next_id = 1
        self._planner: PlannerThread | None = None
        # the run (loop thread only)
        self.active: CheckedPlan | None = None
        self._t0 = 0.0
        self._q_last: list[float] = []
        self._preview = Preview(p.preview_repeat_s)
        self._frame_planner: Frame | None = None
        self._log_limit = RateLimit(5)
        # the trajectory library's commands (library.py; the file work on the planner thread)
        self.library_cmds = LibraryCommands(self)
        #: the last plan acknowledged (loop thread): KeyframeSave stores its set while the
        #: stored keyframes are still that set
        self._acked: CheckedPlan | None = None
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.last_error = ""
        #: a cell keyframe set's part: the exchange, the cross-check, the common start
        self.cell = CellRole(self._lock)

    # ------------------------------------------------------------------ configuration
    @classmethod
    def check(cls, params: Any, config: DaemonConfig) -> list[Problem]:
        return check_params(params, config)

    def configure(self, data: RobotData, ctx: ControllerContext) -> None:
        super().configure(data, ctx)
        self._frame_planner = ctx.frame.copy()  # the planner thread's own (pinocchio data)
        # started now, not by a command: starting a thread from the loop cost the tick ~1 ms;
        # it ends when this controller is collected (controllers have no shutdown hook)
        self._planner = PlannerThread()
        weakref.finalize(self, self._planner.stop)
        self.limits = ctx.joint_limits or tuple(
            JointLimits(lo, hi) for lo, hi in zip(ctx.frame.lower, ctx.frame.upper, strict=True)
        )
        p = self.p
        n = len(data.joint_names)
        lib = self.library_cmds
        lib.robot = data.name
        lib.digest = config_hash(ctx.frame, data.joint_names)
        lib.joint_names, lib.max_keyframes = tuple(data.joint_names), p.max_keyframes
        if p.library is not None:
            try:
                lib.library = Library(p.library)
            except LibraryError as err:
                raise ConfigError(f"controller keyframe: library: {err}") from err
        try:
            if p.keyframes:
                kf = KeyframeFile(keyframes=p.keyframes)
                self._install(file_set(kf, p.space, "config", n, p.max_keyframes))
            elif p.file is not None:
                path = Path(p.file)
                kf = read_keyframe_file(path)
                self._install(file_set(kf, p.space, f"file {path.name}", n, p.max_keyframes))
        except ValueError as err:  # occd --check reports these with their line already
            raise ConfigError(f"controller keyframe: {err}") from err
        if p.forbidden:
            try:
                self.add_forbidden_check(regions_check(p.forbidden))
            except ValueError as err:
                raise ConfigError(f"controller keyframe: forbidden: {err}") from err
        if ctx.collision is not None:  # safety.collision: the whole arm along the path
            self.add_forbidden_check(ctx.collision.path_check())

    def outputs(self) -> dict[str, SourceFn]:
        return {"keyframe-path": self._source_path, "keyframe-points": self._source_points}

    def commands(self) -> tuple[str, ...]:
        return self.COMMANDS

    def add_forbidden_check(self, check: ForbiddenCheck | PathCheck) -> None:
        """Add a collision check every new plan must pass: a :class:`ForbiddenCheck` of the
        tip, or a :class:`PathCheck` of the whole arm (it has ``check_path``)."""
        if hasattr(check, "check_path"):
            self.path_checks.append(check)  # type: ignore[arg-type]
        else:
            self.forbidden_checks.append(check)  # type: ignore[arg-type]

    def invalidate_plan(self, reason: str) -> None:
        """The world changed (e.g. the forbidden regions): a checked plan not yet acknowledged
        must be planned again. Thread-safe; a running plan is not affected."""
        with self._lock:
            self._generation += 1
            if self.plan is not None:
                self.status = f"plan {self.plan.id} invalidated: {reason}; plan again"
                self._set_plan(None)

    # ------------------------------------------------------------------ inputs
    def on_input(self, event: InputEvent, now: float) -> None:
        """Keyframes from 3D Slicer: a Markups POINT list or a TRAJ (a discrete input); an
        NDARRAY ``CellPath``: another member's plan of the stored cell set."""
        if isinstance(event, ArrayInput) and event.device == PATH_DEVICE:
            self.cell.take_path(event, self.kset)  # CommandError: the sender is told
            return
        if event.kind not in ("POINT", "TRAJ"):
            return
        if self.p.input_interface is not None and event.interface != self.p.input_interface:
            return
        assert self.data is not None
        source = f"{event.describe()} from {event.interface}"
        try:
            items = items_from_event(event, self.p.point_interval_s)
            kset = make_set(
                "cartesian",
                items,
                source,
                joints=len(self.data.joint_names),
                max_keyframes=self.p.max_keyframes,
            )
        except ValueError as err:
            self.counters["inputs_refused"] += 1
            self.last_error = f"{source} refused: {err}"
            if self._log_limit.allow():
                log.warning("keyframes: %s", self.last_error)
            return
        self._install(kset)
        log.info("keyframes: %d from %s", len(kset.keyframes), source)

    def _install(self, kset: KeyframeSet | None, cset: CellSet | None = None) -> None:
        """A new keyframe set (or none; ``cset``: the cell set it is this member's part of):
        any checked plan is dropped (a running one runs on)."""
        with self._lock:
            self._generation += 1
            self.kset = kset
            self.cell.install(cset)
            if kset is not None:
                self.counters["sets"] += 1
            self._set_plan(None)
            self.status = (
                f"{len(kset.keyframes)} keyframes from {kset.source}; send KeyframePlan"
                if kset is not None
                else "no keyframes"
            )

    def _set_plan(self, plan_: CheckedPlan | None) -> None:
        """The previewed plan (caller holds the lock)."""
        if plan_ is self.plan and plan_ is not None:
            return
        self.plan = plan_
        self._preview.show(plan_)

    # ------------------------------------------------------------------ the planner's port
    def install_unless_changed(
        self, kset: KeyframeSet, generation: int, cell: CellSet | None = None
    ) -> bool:
        """Install ``kset`` (from the planner thread; ``cell``: its cell set) unless the set
        changed or a plan was invalidated since ``generation``; False then."""
        with self._lock:
            superseded = self._generation != generation
        if superseded:
            return False
        self._install(kset, cell)
        return True

    def record(self, counter: str, error: str | None = None) -> None:
        with self._lock:
            self.counters[counter] += 1
            if error is not None:
                self.last_error = error

    def start(self, job: Callable[[Deferred], None]) -> Deferred:
        """Hand ``job`` to the planner thread (one at a time; a second is refused)."""
        planner = self._planner
        if planner is None:
            planner = self._planner = PlannerThread()
        return planner.start(job)

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Wait for the planner thread (tests, tools); True when it is idle."""
        return self._planner is None or self._planner.idle.wait(timeout)

    # ------------------------------------------------------------------ commands
    def on_command(self, request: Request, now: float) -> str | Deferred | ArrayReply | None:
        key = request.name.strip().lower()
        args = {k.lower(): v for k, v in request.args.items()}
        if key == "keyframelist":
            return self.describe()
        if key == "keyframeclear":
            if self.active is not None:
                raise CommandError(f"plan {self.active.id} is running; Stop first")
            self._install(None)
            return "keyframes and plan cleared"
        if key == "keyframeadd":
            assert self.data is not None
            n = len(self.data.joint_names)
            kset = added_set(self.kset, args, self.p.space, n, self.p.max_keyframes)
            self._install(kset)
            return f"{len(kset.keyframes)} keyframes ({kset.space}); send KeyframePlan"
        if key == "keyframeload":
            return self._cmd_load(args)
        if key == "keyframeplan":
            return self._cmd_plan(args)
        if key == "keyframeack":
            return self._cmd_ack(args, now)
        if key == "keyframesave":
            return self.library_cmds.save(args, self._acked, self.kset)
        if key == "keyframelibrary":
            return self.library_cmds.listing()
        if key == "keyframedelete":
            return self.library_cmds.delete(args)
        if key in ("keyframecellpath", "keyframecellcheck"):
            return self._cmd_cell(key, args)
        raise CommandError(f"unknown command {request.name!r}")

    def _cmd_load(self, args: dict[str, str]) -> Deferred:
        if "set" in args:
            if "file" in args:
                raise CommandError(
                    "KeyframeLoad takes File (a file) or Set (the library), not both"
                )
            return self.library_cmds.load(args, self._generation)
        name, path = keyframe_path(self.p.keyframe_dir, args)
        assert self.data is not None
        n, p = len(self.data.joint_names), self.p
        member = self.ctx.cell_member if self.ctx is not None else None
        return self.start(
            load_file_job(self, path, name, p.space, n, p.max_keyframes, self._generation, member)
        )

    def _cmd_plan(self, args: dict[str, str]) -> Deferred:
        p = self.p
        kset = self.kset
        if kset is None:
            raise CommandError("no keyframes to plan: load or send some first")
        if self.active is not None:
            raise CommandError(f"plan {self.active.id} is running; wait or Stop")
        # a set from the library is planned as it was saved, unless told otherwise
        given = kset.settings or PlanSettings(p.interpolation, p.mode, p.steepness, p.ramp)
        settings = plan_settings(args, given)
        with self._lock:
            generation = self._generation
            plan_id = self._next_id
            self._next_id += 1
        assert self.data is not None and self.ctx is not None
        req = plan_request(
            plan_id,
            kset,
            settings,
            self.p,
            self.data,
            self.ctx,
            self.limits,
            (tuple(self.forbidden_checks), tuple(self.path_checks)),
        )
        cset = self.cell.current(kset)
        if cset is not None:  # a part of a cell set: its path is kept to be exchanged
            req = replace(req, cell_member=cset.me)
        frame = self._frame_planner
        assert frame is not None
        return self.start(plan_job(self, req, frame, generation))

    def plan_done(
        self, req: PlanRequest, generation: int, checked: CheckedPlan | None, refusal: str
    ) -> bool:
        """A plan's end (planner thread): ``checked`` is previewed unless the keyframes
        changed since ``generation`` (False then); None: ``refusal`` is kept (False)."""
        with self._lock:
            if req.pace is not None:
                self.counters["planner_waits"] += req.pace.sleeps
            if checked is None:
                self.counters["plans_refused"] += 1
                self.last_error = refusal
                if self._generation == generation:
                    self.status = refusal
                return False
            self.counters["plans_checked"] += 1
            if self._generation != generation:
                return False
            self._set_plan(checked)
            self.status = f"plan {req.id} previewed; KeyframeAck Plan={req.id} runs it"
            return True

    def _cmd_cell(self, key: str, args: dict[str, str]) -> ArrayReply | Deferred:
        """``KeyframeCellPath Plan=N`` and ``KeyframeCellCheck Plan=N`` (cellset.py)."""
        assert self.ctx is not None
        pace = Pacer(time.perf_counter, self.ctx.loop_t0, self.ctx.period_s)
        return self.cell.command(
            key, args, self.kset, self.plan, self.ctx, self.p.cell_skew_ms * 1e-3, pace, self
        )

    def _cmd_ack(self, args: dict[str, str], now: float) -> str:
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        if self.active is not None:
            raise CommandError(f"plan {self.active.id} is running already")
        pending = previewed(self.plan, args, "KeyframeAck")
        plan_id = pending.id
        ack_ready(pending, data, self.p.preview_required and not self._preview.sent)
        identity, t0 = self.cell.ack(self.kset, pending, args, ctx, now, self.p.cell_start_max_s)
        self.active = self._acked = pending
        if ctx.note is not None:  # the planner's result the loop runs now (the black box)
            ctx.note("plan", {"id": plan_id, "t0": t0, "duration": pending.traj.duration})
        self._t0 = t0
        self._q_last = list(pending.q_start)
        self.cell.running = identity
        self.counters["runs"] += 1
        what = f"plan {plan_id}" + (f" (cell plan {identity[:12]})" if identity else "")
        when = f"starts in {t0 - now:.3f} s, " if t0 > now else ""
        with self._lock:
            self.status = f"{what} running ({when}{pending.traj.duration:.3f} s)"
        self._announce(STATUS_RUNNING, self.status, _CODE_OK)
        log.info("keyframes: %s acknowledged, running %s%.3f s", what, when, pending.traj.duration)
        return f"{what} running: {when}{pending.traj.duration:.3f} s"

    # ------------------------------------------------------------------ the loop
    def on_state(self, old: RobotState, new: RobotState, now: float) -> None:
        run = self.active
        if run is not None and old is RobotState.RUNNING and new is not RobotState.RUNNING:
            t = now - self._t0
            self._end_run(
                "runs_stopped",
                f"plan {run.id} stopped at t={t:.3f} s of {run.traj.duration:.3f} s "
                f"({old.value} -> {new.value}); the robot holds there; plan again to run "
                "the keyframes",
                _CODE_DROPPED,
            )

    def _end_run(self, counter: str, status: str, code: int) -> None:
        """The run ends (completed, or dropped: the robot holds); announced and logged. A cell
        plan dropped stops the cell: every other member holds (and drops its part)."""
        self.active = None
        identity, self.cell.running = self.cell.running, None
        ctx = self.ctx
        if identity is not None and code != _CODE_OK and ctx is not None and ctx.cell_stop:
            ctx.cell_stop(f"cell plan {identity[:12]} dropped in {ctx.cell_member}: {status}")
        self.counters[counter] += 1
        with self._lock:
            self._generation += 1
            self._set_plan(None)
            self.status = status
        self._announce(STATUS_ENDED, status, code)
        if code == _CODE_OK:
            log.info("keyframes: %s", status)
        else:
            log.warning("keyframes: %s", status)

    def update(self, now: float) -> Sequence[float] | None:
        run = self.active
        if run is None:
            return None
        t = now - self._t0
        if t < 0.0:
            return list(run.q_start)  # acknowledged with a common start: it holds until then
        assert self.ctx is not None
        q, failure = run_tick(self.ctx.frame, run, t, self._q_last)
        if failure is not None:
            # checked offline, so only a different sampling time can get here: hold
            counter, why, error = failure
            if error is not None:
                self.last_error = error
            text = f"plan {run.id} stopped at t={t:.3f} s: {why}"
            self._end_run(counter, text, _CODE_DROPPED)
            return None
        self._q_last = q
        if t >= run.traj.end:
            text = f"plan {run.id} completed ({run.traj.duration:.3f} s)"
            self._end_run("runs_completed", text, _CODE_OK)
        return q

    def _announce(self, name: str, text: str, code: int) -> None:
        """A run's start or end as a STATUS to every viewer and operator (package docstring);
        on the loop thread, once per run and end."""
        ctx = self.ctx
        if ctx is not None and ctx.alert is not None:
            ctx.alert(name, text, code)

    # ------------------------------------------------------------------ preview
    def _source_path(self, out: Output, now: float) -> PolylineOut | None:
        assert self.ctx is not None
        return self._preview.path(out, now, self.ctx.clock.wall_time)

    def _source_points(self, out: Output, now: float) -> PointsOut | None:
        assert self.ctx is not None
        return self._preview.points(out, now, self.ctx.clock.wall_time)

    # ------------------------------------------------------------------ reporting
    def describe(self) -> str:
        kset = self.kset
        lines = [f"status: {self.status}"]
        lines += kset.describe() if kset is not None else ["keyframes: none"]
        acked = self._acked
        if acked is not None and kset is not None and acked.kset is kset:
            lines.append(f"acknowledged: plan {acked.id} (KeyframeSave Set=... keeps the set)")
        lines += self.cell.describe(kset)
        pending = self.plan
        if pending is not None:
            lines.append(f"previewed: {pending.summary}")
        if self.active is not None:
            lines.append(f"running: plan {self.active.id}")
        library = self.library_cmds.library
        if library is not None:
            lines.append(f"library: {library.path} (KeyframeLibrary lists it)")
        return "\n".join(lines)

    def shutdown(self) -> None:
        """The planner thread ends once a job it is running (if any) is done; a plan being
        checked then is dropped (the robot is shutting down)."""
        if self._planner is not None:
            self._planner.stop()
            self._planner = None

    def stats(self) -> dict[str, Any]:
        kset = self.kset
        return {
            **self.counters,
            "keyframes": len(kset.keyframes) if kset else 0,
            "space": kset.space if kset else None,
            "source": kset.source if kset else None,
            "plan": self.plan.id if self.plan else None,
            "running": self.active.id if self.active else None,
            "status": self.status,
            "last_error": self.last_error,
            "forbidden_checks": len(self.forbidden_checks),
            "planner_fifo": self._planner.fifo if self._planner else None,
            **self.cell.stats(),
        }
