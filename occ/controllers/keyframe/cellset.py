"""Cell keyframe sets (issue 40, item 5): one timeline per arm of a cell, planned by each member,
checked against each other, acknowledged as one, run on one clock and stopped as one (the
package docstring, "A cell keyframe set").

:class:`CellKeyframeFile` is the file; :class:`CellSet` what a member keeps of it (its own part
is the controller's stored set, the others' parts are kept for the set's identity);
:class:`CellRole` the member's side of the exchange (the other arms' paths received, the
cross-check, the acknowledged identity), on the loop thread but for the cross-check's job,
which runs on the planner thread and hands its result back under the controller's lock.
"""

from __future__ import annotations

import hashlib
import json
import math
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, Protocol

import numpy as np
from pydantic import Field, StringConstraints

from occ.controllers.keyframe.plan import MAX_CELL_SAMPLES
from occ.controllers.keyframe.sets import (
    KeyframeFile,
    KeyframeSet,
    PlanSettings,
    Space,
    _Model,
    file_set,
    read_file_data,
    validated_file,
)
from occ.errors import CommandError
from occ.kinematics.cellpaths import ArmPath, cell_identity, cross_check, path_digest
from occ.net.commands import ArrayReply, Deferred

if TYPE_CHECKING:
    from occ.controllers import ControllerContext
    from occ.controllers.keyframe.pacer import Pacer
    from occ.controllers.keyframe.plan import CheckedPlan
    from occ.events import ArrayInput
    from occ.kinematics.collision import Checker, CollisionModel

#: the device name of a cell plan's path (the NDARRAY a member answers and is given)
PATH_DEVICE = "CellPath"
#: most samples of a path (an NDARRAY's dimension is at most 65535: 65 s at 1 kHz)
MAX_SAMPLES = MAX_CELL_SAMPLES

MemberName = Annotated[str, StringConstraints(pattern=r"^[^\s:]+$", max_length=64)]


class CellPlanItem(_Model):
    """How every member plans its part (KeyframePlan's settings; the command's arguments
    still override them)."""

    interpolation: Literal["linear", "spline"] = Field("linear", description="Interpolation.")
    mode: Literal["stop", "continuous"] = Field("stop", description="Rest at each keyframe.")
    steepness: Annotated[float, Field(gt=0)] = Field(6.0, description="Sigmoid steepness n.")
    ramp: Annotated[float, Field(gt=0, le=0.5)] = Field(0.25, description="Ramp share.")


class CellKeyframeFile(_Model):
    """A cell keyframe file: ``{cell: ..., space: ..., arms: {<member>: {space, keyframes}}}``,
    one timeline per member arm, all on one time base (s from the common start)."""

    cell: str | None = Field(None, description="The cell's name (said in replies).")
    space: Space | None = Field(None, description="The parts' space unless a part gives one.")
    plan: CellPlanItem | None = Field(
        None, description="How every member plans its part (default: its own params')."
    )
    arms: Annotated[dict[MemberName, KeyframeFile], Field(min_length=2)] = Field(
        description="One part per member arm, by its name in the cell."
    )


def read_any_keyframe_file(path: Path) -> KeyframeFile | CellKeyframeFile:
    """A keyframe file, or a cell keyframe file (it has ``arms``); ValueError with the
    reason."""
    data = read_file_data(path)
    model: type[KeyframeFile] | type[CellKeyframeFile] = (
        CellKeyframeFile if isinstance(data, dict) and "arms" in data else KeyframeFile
    )
    return validated_file(model, data, path)


@dataclass(frozen=True, eq=False)
class CellSet:
    """What a member keeps of a cell keyframe file: the whole file (the others' parts), its
    digest (SHA-256 of its canonical JSON: the same content gives the same digest on every
    member, however it is written), this member's name and its own part as a set."""

    name: str
    file: CellKeyframeFile
    digest: str
    me: str
    own: KeyframeSet

    @property
    def members(self) -> tuple[str, ...]:
        return tuple(sorted(self.file.arms))

    @property
    def others(self) -> tuple[str, ...]:
        return tuple(m for m in self.members if m != self.me)


def cell_set(
    cf: CellKeyframeFile, name: str, me: str | None, default: Space, joints: int, cap: int
) -> CellSet:
    """``me``'s part of ``cf`` (read from the file ``name``); ValueError when this robot is in
    no cell, has no part, or its part is not a valid set for it."""
    if me is None:
        raise ValueError(f"{name} is a cell keyframe set, and this robot is in no cell")
    part = cf.arms.get(me)
    if part is None:
        raise ValueError(f"{name} has no part for {me} (parts: {', '.join(sorted(cf.arms))})")
    text = json.dumps(cf.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))
    digest = hashlib.sha256(text.encode("utf-8")).hexdigest()
    own_file = KeyframeFile(space=part.space or cf.space, keyframes=part.keyframes)
    source = f"cell set {name} ({digest[:12]}), part {me}"
    try:
        own = file_set(own_file, default, source, joints, cap)
    except ValueError as err:
        raise ValueError(f"{name}: arms.{me}: {err}") from err
    if cf.plan is not None:
        p = cf.plan
        own = replace(own, settings=PlanSettings(p.interpolation, p.mode, p.steepness, p.ramp))
    return CellSet(name, cf, digest, me, own)


@dataclass(frozen=True, eq=False)
class CellCheck:
    """A cross-check passed: the plan it was for, the identity every member acknowledges."""

    plan: CheckedPlan
    identity: str
    plans: Mapping[str, str]  # member -> path digest


def _meta_path(event: ArrayInput) -> tuple[ArmPath, str]:
    """The path an NDARRAY ``CellPath`` carries and the digest it claims; ValueError."""
    meta = event.meta
    try:
        member = meta["member"]
        period = float(meta["period"])
        base = np.array([float(v) for v in meta["base"].split(",")], dtype=float).reshape(4, 4)
        claimed = meta["digest"]
    except (KeyError, ValueError) as err:
        raise ValueError(
            f"{event.describe()}: metadata member, period, base, digest: {err}"
        ) from err
    qs = np.asarray(event.array, dtype=float)
    return ArmPath(member, qs, base, period), claimed


class CellRole:
    """This member's side of a cell keyframe set (module docstring)."""

    def __init__(self, lock: threading.Lock) -> None:
        self._lock = lock  # the controller's: the cross-check's result comes from its job
        self.cset: CellSet | None = None
        #: the other members' paths, as received (validated by the cross-check's job)
        self.paths: dict[str, ArrayInput] = {}
        self.checked: CellCheck | None = None
        #: the identity of the acknowledged cell plan running (or waiting for its start)
        self.running: str | None = None
        self._checker: Checker | None = None  # the planner thread's
        #: the other members' paths refused on arrival (GetStats: a sender's mistake is counted)
        self.refused_paths = 0
        #: the last cross-check's outcome: the identity it passed with, or why it refused
        self.last_check = ""

    def install(self, cset: CellSet | None) -> None:
        """A new stored set: a cell set's part, or any other set (``None``)."""
        self.cset = cset
        self.paths = {}
        self.checked = None

    def current(self, kset: KeyframeSet | None) -> CellSet | None:
        """The cell set whose part is the stored set ``kset``, or None."""
        cset = self.cset
        return cset if cset is not None and kset is not None and cset.own is kset else None

    # ------------------------------------------------------------------ the exchange
    def command(
        self,
        key: str,
        args: Mapping[str, str],
        kset: KeyframeSet | None,
        pending: CheckedPlan | None,
        ctx: ControllerContext,
        skew: float,
        pace: Pacer,
        planner: PlannerStart,
    ) -> ArrayReply | Deferred:
        """``KeyframeCellPath Plan=N`` (the previewed plan's path, an NDARRAY) and
        ``KeyframeCellCheck Plan=N`` (its cross-check against the other members' paths, a
        job for the ``planner`` thread) of the stored cell set's part ``kset``."""
        cset = self.current(kset)
        if cset is None:
            raise CommandError("no cell keyframe set is loaded (KeyframeLoad File=<a cell set>)")
        path = key == "keyframecellpath"
        plan = previewed(pending, args, "KeyframeCellPath" if path else "KeyframeCellCheck")
        if path:
            return self.path_reply(cset, plan, cset.me)
        job = self.check_job(cset, plan, ctx.collision, skew, pace, lambda c: c is planner.plan)
        return planner.start(job)

    def path_reply(self, cset: CellSet, plan: CheckedPlan, member: str) -> ArrayReply:
        """``KeyframeCellPath``: the previewed plan's path as an NDARRAY with what names it."""
        if plan.qs is None or not plan.digest:
            raise CommandError(f"plan {plan.id} kept no path: plan again")
        base = np.asarray(plan.base, dtype=float)
        meta = {
            "member": member,
            "set": cset.digest,
            "plan": str(plan.id),
            "digest": plan.digest,
            "period": repr(plan.period),
            "base": ",".join(repr(float(v)) for v in base.ravel()),
        }
        text = (
            f"{PATH_DEVICE} of {member}: plan {plan.id}, {len(plan.qs)} samples, digest "
            f"{plan.digest}; give it to the other members of cell set {cset.name}"
        )
        return ArrayReply(text, plan.qs, PATH_DEVICE, meta)

    def take_path(self, event: ArrayInput, kset: KeyframeSet | None) -> None:
        """An NDARRAY ``CellPath`` given to this member: kept for the cross-check (O(1) here;
        its digest and values are checked by the cross-check's job); CommandError when it is
        not one of the stored cell set's other members (counted in ``refused_paths``)."""
        cset = self.current(kset)
        who = event.meta.get("member", "")
        why = self._path_refusal(event, cset, who)
        if why is not None:
            self.refused_paths += 1
            raise CommandError(why)
        self.paths[who] = event
        self.checked = None

    @staticmethod
    def _path_refusal(event: ArrayInput, cset: CellSet | None, who: str) -> str | None:
        """Why a path given by ``who`` is not kept for the cell set ``cset``, or None."""
        if cset is None:
            return f"{event.describe()}: no cell keyframe set is loaded"
        if event.meta.get("set") != cset.digest:
            return (
                f"{event.describe()} of {who or '?'}: for another cell set (its digest "
                f"{event.meta.get('set', '?')[:12]}, this member's {cset.digest[:12]})"
            )
        if who not in cset.others:
            return (
                f"{event.describe()}: {who!r} is not another member of cell set {cset.name} "
                f"({', '.join(cset.others)})"
            )
        return None

    # one function: the checks before the cross-check, each refusal with its reason
    def check_job(
        self,
        cset: CellSet,
        plan: CheckedPlan,
        cm: CollisionModel | None,
        skew: float,
        pace: Pacer | None,
        is_pending: Callable[[CheckedPlan], bool],
    ) -> Callable[[Deferred], None]:
        """``KeyframeCellCheck``: the job (planner thread) that checks ``plan`` against every
        other member's path and, clear, keeps the identity to acknowledge."""
        if plan.qs is None or not plan.digest:
            raise CommandError(f"plan {plan.id} kept no path: plan again")
        if cm is None:
            raise CommandError("the cross-check needs safety.collision (the arms' geometry)")
        missing = [m for m in cset.others if m not in self.paths]
        if missing:
            raise CommandError(
                f"no path yet from {', '.join(missing)}: give this member every other "
                f"member's {PATH_DEVICE} (KeyframeCellPath on each) first"
            )
        given = dict(self.paths)
        own = ArmPath(cset.me, plan.qs, np.asarray(plan.base, dtype=float), plan.period)

        def job(answer: Deferred) -> None:
            if pace is not None:
                pace.begin()
            try:
                others, digests = self._validated(cset, given)
                if self._checker is None:
                    self._checker = cm.checker()
                res = cross_check(cm, own, others, skew, checker=self._checker, pace=pace)
            except ValueError as err:
                self._refuse(answer, f"cell plan refused: {err}")
                return
            if res.clash is not None:
                self._refuse(answer, f"cell plan refused: {res.clash.describe()}")
                return
            digests[cset.me] = plan.digest
            identity = cell_identity(cset.digest, digests)
            with self._lock:
                if not is_pending(plan) or self.current(plan.kset) is not cset:
                    answer.fail(f"plan {plan.id} is no longer previewed: plan again")
                    return
                self.checked = CellCheck(plan, identity, digests)
                self.last_check = identity
            parts = ", ".join(f"{m} {d[:12]}" for m, d in sorted(digests.items()))
            near = (
                f"closest {res.closest / 1e-3:.1f} mm ({res.closest_pair} at "
                f"t={res.closest_at:.3f} s)"
                if math.isfinite(res.closest)
                else "the arms never near"
            )
            answer.resolve(
                f"cell plan {identity}: set {cset.digest[:12]}, plans {parts}; clear of "
                f"{', '.join(cset.others)} at the same times ({res.checked} samples checked, "
                f"{near}); KeyframeAck Plan={plan.id} StartAt=<unix time> Cell={identity} on "
                "every member"
            )

        return job

    def _refuse(self, answer: Deferred, text: str) -> None:
        with self._lock:
            self.last_check = text
        answer.fail(text)

    @staticmethod
    def _validated(
        cset: CellSet, given: Mapping[str, ArrayInput]
    ) -> tuple[list[ArmPath], dict[str, str]]:
        """The paths given, each checked against the digest it claims (planner thread)."""
        others: list[ArmPath] = []
        digests: dict[str, str] = {}
        for member in cset.others:
            path, claimed = _meta_path(given[member])
            if path.member != member:
                raise ValueError(f"the path given as {member}'s names {path.member}")
            if len(path.qs) > MAX_SAMPLES:
                raise ValueError(f"{member}'s path has more than {MAX_SAMPLES} samples")
            if path_digest(path) != claimed:
                raise ValueError(f"{member}'s path does not match its digest {claimed[:12]}")
            others.append(path)
            digests[member] = claimed
        return others, digests

    # ------------------------------------------------------------------ the acknowledgement
    def ack(
        self,
        kset: KeyframeSet | None,
        plan: CheckedPlan,
        args: Mapping[str, str],
        ctx: ControllerContext,
        now: float,
        ahead_max: float,
    ) -> tuple[str | None, float]:
        """``KeyframeAck``'s ``Cell`` and ``StartAt`` for ``plan``: (the identity of its passed
        cross-check, None for a plan of no cell set; when it starts on the loop's clock: the
        first tick at or after ``StartAt``, or ``now`` without one). CommandError for a part
        of a cell set acknowledged alone, with another identity or without a common start."""
        cset = self.current(kset)
        identity = None if cset is None else self._identity(cset, plan, args)
        if "startat" not in args and identity is None:
            return None, now
        at = start_time(args, ctx.clock.wall_time(), now, ahead_max)
        return identity, first_tick(at, ctx.loop_t0(), ctx.period_s)

    def _identity(self, cset: CellSet, plan: CheckedPlan, args: Mapping[str, str]) -> str:
        given = args.get("cell", "").strip()
        chk = self.checked
        if not given or "startat" not in args:
            raise CommandError(
                f"KeyframeAck: plan {plan.id} is a part of cell set {cset.name}: it runs only "
                "as one with the others (Cell=<the identity KeyframeCellCheck gave> and "
                "StartAt=<unix time>)"
            )
        if chk is None or chk.plan is not plan:
            raise CommandError(
                f"KeyframeAck: plan {plan.id} has not passed KeyframeCellCheck against the "
                "other members' paths"
            )
        if given != chk.identity:
            raise CommandError(
                f"KeyframeAck: Cell={given[:12]}.. is not this member's cell plan "
                f"{chk.identity[:12]}..: the members planned or checked different plans"
            )
        return chk.identity

    def describe(self, kset: KeyframeSet | None) -> list[str]:
        cset = self.current(kset)
        if cset is None:
            return []
        have = ", ".join(sorted(self.paths)) or "none"
        lines = [
            f"cell set: {cset.name} {cset.digest[:12]}, parts {', '.join(cset.members)}; "
            f"paths from {have}"
        ]
        if self.checked is not None:
            lines.append(f"cell plan: {self.checked.identity} (plan {self.checked.plan.id})")
        return lines

    def stats(self) -> dict[str, Any]:
        cset = self.cset
        return {
            "cell_set": None if cset is None else cset.digest,
            "cell_paths": sorted(self.paths),
            "cell_checked": None if self.checked is None else self.checked.identity,
            "cell_running": self.running,
            "cell_paths_refused": self.refused_paths,
            "cell_last_check": self.last_check,
        }


class PlannerStart(Protocol):
    """What the cross-check is handed to (the keyframe controller): its previewed plan and
    its planner thread."""

    @property
    def plan(self) -> CheckedPlan | None: ...

    def start(self, job: Callable[[Deferred], None]) -> Deferred: ...


def previewed(pending: CheckedPlan | None, args: Mapping[str, str], name: str) -> CheckedPlan:
    """The previewed plan ``pending`` when ``args`` names it (``Plan=N``; keys in lower
    case); CommandError otherwise."""
    text = args.get("plan", "").strip()
    if not text:
        raise CommandError(f"{name} needs Plan (the number of the previewed plan)")
    try:
        plan_id = int(text)
    except ValueError:
        raise CommandError(f"{name}: Plan must be a number, got {text!r}") from None
    if pending is None or pending.id != plan_id:
        have = f"plan {pending.id} is previewed" if pending else "no plan is previewed"
        raise CommandError(f"{name}: plan {plan_id} is not the previewed plan ({have})")
    return pending


def first_tick(t: float, loop_t0: float, period: float) -> float:
    """The first tick of a loop whose deadlines are ``loop_t0 + k period`` at or after ``t``
    (``t`` itself while the loop has no phase: simulated time): a run started there samples
    its plan at the times it was checked at."""
    if not math.isfinite(loop_t0):
        return t
    return loop_t0 + math.ceil((t - loop_t0) / period - 1e-9) * period


def start_time(args: Mapping[str, str], wall: float, now: float, ahead_max: float) -> float:
    """``KeyframeAck StartAt=<unix time>``: the start on the loop's clock (``now`` is the loop
    time at wall time ``wall``); CommandError for a start in the past or too far ahead."""
    text = args.get("startat", "").strip()
    try:
        at = float(text)
    except ValueError:
        raise CommandError(f"KeyframeAck: StartAt must be a unix time, got {text!r}") from None
    if not math.isfinite(at):
        raise CommandError(f"KeyframeAck: StartAt must be a unix time, got {text!r}")
    if at < wall:
        raise CommandError(
            f"KeyframeAck: StartAt {at:.3f} is {wall - at:.3f} s in the past (now {wall:.3f}): "
            "a common start must be ahead of every member; give a later one"
        )
    if at - wall > ahead_max:
        raise CommandError(
            f"KeyframeAck: StartAt {at:.3f} is {at - wall:.1f} s ahead, more than "
            f"cell_start_max_s ({ahead_max:g})"
        )
    return now + (at - wall)
