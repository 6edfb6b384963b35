"""Arms that plan together (issue 40, item 5): one arm's planned joint path checked against the
other arms' *planned* paths at the same times, and the identity of a plan the cell runs as one.

A path (:class:`ArmPath`) is what a keyframe plan will command: one joint sample per loop period
from its start, the base pose it was planned with (world <- base, metres) and that period. It
rests at its first sample before its start and at its last after its end. Each member of a cell
plans its own part and the paths are exchanged as they are (never planned again elsewhere); the
:func:`path_digest` of a path names it byte for byte, and :func:`cell_identity` of a set's digest
and each member's path digest is the one identity every member acknowledges.

The time-aligned check (:func:`cross_check`)
    For each own sample ``j`` (time ``t = j P``, up to the later of the two paths' ends) the
    other arm is taken at its sample nearest ``t``; since two members' parts start on their own
    loops' ticks and clocks, the other arm may be anywhere within ``skew`` of ``t``, so the
    distance counts, against it, how far the other arm can move in that window (``w``: its
    motion bound summed over its samples in the window, occ/kinematics/collision.py
    ``CollisionModel.bound`` with the other arm's reach). A sample passes when
    ``distance - w >= margin`` (the regions' margin, the same as the plan check's and the
    guard's). Samples are skipped by conservative advancement, as the plan check does, with
    both arms' motion counted: after a check at ``j`` with slack ``s = distance - margin``,
    sample ``k`` is checked only once ``bound_own(q_k, q_j) + span_other(j, k) >= s``, where
    ``span_other`` bounds how far the other arm's samples in ``k``'s window are from the one
    ``j`` was checked with. So no sample with the two arms inside the margin is skipped; between
    two samples each arm moves at most its step bound (the margin exceeds half of it).

No robot, loop or wire here: numpy, pinocchio and coal through a :class:`Checker`.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from occ.kinematics.collision import Checker, CollisionModel, PeerArm, PeerState

__all__ = ["ArmPath", "Clash", "CrossResult", "cell_identity", "cross_check", "path_digest"]

MM = 1e-3
_TAG = b"occ-cell-plan/1"


@dataclass(frozen=True, eq=False)
class ArmPath:
    """One arm's planned path: ``qs`` (samples x joints, float64) one per ``period`` from t = 0,
    ``base`` (4 x 4, world <- base, metres)."""

    member: str
    qs: np.ndarray
    base: np.ndarray
    period: float

    def __post_init__(self) -> None:
        qs, base = self.qs, self.base
        if qs.ndim != 2 or len(qs) < 1 or qs.shape[1] < 1:
            raise ValueError(f"{self.member}: a path is samples x joints, got shape {qs.shape}")
        if base.shape != (4, 4):
            raise ValueError(f"{self.member}: the base pose is 4 x 4, got shape {base.shape}")
        if not (np.isfinite(qs).all() and np.isfinite(base).all()):
            raise ValueError(f"{self.member}: a joint value or the base pose is not finite")
        if not (math.isfinite(self.period) and self.period > 0.0):
            raise ValueError(f"{self.member}: the period must be > 0, got {self.period}")

    @property
    def end(self) -> float:
        """When the path rests at its last sample (s from its start)."""
        return (len(self.qs) - 1) * self.period


def path_digest(path: ArmPath) -> str:
    """SHA-256 (hex) of the member's name, the period, the base pose and every sample, as
    little-endian float64: two paths with the same digest command the same joints."""
    h = hashlib.sha256(_TAG)
    h.update(path.member.encode("utf-8") + b"\0")
    h.update(np.asarray([path.period], dtype="<f8").tobytes())
    h.update(np.asarray(path.qs.shape, dtype="<u8").tobytes())
    h.update(np.ascontiguousarray(path.base, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(path.qs, dtype="<f8").tobytes())
    return h.hexdigest()


def cell_identity(set_digest: str, plans: Mapping[str, str]) -> str:
    """The identity of a plan the cell runs as one: the set's digest and each member's path
    digest (``plans``: member -> digest), in the members' order by name."""
    h = hashlib.sha256(_TAG + b"/cell\0" + set_digest.encode("ascii"))
    for member in sorted(plans):
        h.update(b"\0" + member.encode("utf-8") + b"=" + plans[member].encode("ascii"))
    return h.hexdigest()


@dataclass(frozen=True)
class Clash:
    """Where two arms' plans come within the margin: the time, both arms and links, the
    distance and how much of it the other arm's time skew took."""

    t: float
    own: str
    own_link: str
    other: str
    other_link: str
    distance: float
    skew_motion: float
    margin: float

    def describe(self) -> str:
        skew = (
            f", {self.skew_motion / MM:.2f} mm of which {self.other} may move within the skew"
            if self.skew_motion > 0.0
            else ""
        )
        return (
            f"at t={self.t:.3f} s link {self.own_link!r} of {self.own} comes "
            f"{self.distance / MM:.2f} mm from link {self.other_link!r} of {self.other} "
            f"({self.own}:{self.own_link} vs {self.other}:{self.other_link}; margin "
            f"{self.margin / MM:g} mm{skew})"
        )


@dataclass(frozen=True)
class CrossResult:
    """A cross-check's outcome: the first clash (None: clear), the closest approach seen (m;
    its time and pair), the samples checked."""

    clash: Clash | None
    closest: float
    closest_at: float
    closest_pair: str
    checked: int


def cross_check(
    cm: CollisionModel,
    own: ArmPath,
    others: Sequence[ArmPath],
    skew: float,
    *,
    checker: Checker | None = None,
    pace: Callable[[], None] | None = None,
) -> CrossResult:
    """``own`` against each of ``others`` at the same times (module docstring); each other arm
    must be one of ``cm``'s peers (its geometry, ValueError otherwise)."""
    checker = checker if checker is not None else cm.checker()
    closest, closest_at, closest_pair, checked = math.inf, 0.0, "", 0
    for other in others:
        arm = cm.peer(other.member)
        if arm.nq != other.qs.shape[1]:
            raise ValueError(
                f"{other.member}: its path has {other.qs.shape[1]} joints, its arm {arm.nq}"
            )
        res = _pair(cm, checker, own, other, arm, skew, pace)
        checked += res.checked
        if res.clash is not None:
            return CrossResult(res.clash, res.closest, res.closest_at, res.closest_pair, checked)
        if res.closest < closest:
            closest, closest_at, closest_pair = res.closest, res.closest_at, res.closest_pair
    return CrossResult(None, closest, closest_at, closest_pair, checked)


def _pair(
    cm: CollisionModel,
    checker: Checker,
    own: ArmPath,
    other: ArmPath,
    arm: PeerArm,
    skew: float,
    pace: Callable[[], None] | None,
) -> CrossResult:
    """``own`` against ``other`` alone (module docstring, "The time-aligned check")."""
    period = own.period
    n = math.ceil(max(own.end, other.end) / period - 1e-9) + 1
    qa, qb = own.qs, other.qs
    reach_b = np.asarray(arm.arm.reach, dtype=float)
    # C[k]: the other arm's motion bound summed along its samples up to k
    steps = np.abs(np.diff(qb, axis=0)) @ reach_b if len(qb) > 1 else np.zeros(0)
    cum = np.concatenate(([0.0], np.cumsum(steps)))
    last_b = len(qb) - 1
    half = math.ceil(skew / other.period) + 1  # its samples within the skew, and a half period

    # for every own sample: the other arm's sample at its time, and its window's first and last
    times = np.arange(n) * period
    kb_all = np.clip(np.rint(times / other.period).astype(np.int64), 0, last_b)
    lo_all = np.maximum(kb_all - half, 0)
    hi_all = np.minimum(kb_all + half, last_b)
    reach_a = np.asarray(cm.reach, dtype=float)
    qa_all = qa[np.minimum(np.arange(n), len(qa) - 1)]

    closest, closest_at, closest_pair, checked = math.inf, 0.0, "", 0
    base_b = np.asarray(other.base, dtype=float)
    j = 0
    while j < n:
        if pace is not None:
            pace()
        q = qa_all[j]
        kb, lo, hi = int(kb_all[j]), int(lo_all[j]), int(hi_all[j])
        st = PeerState(tuple(float(v) for v in qb[kb]), base_b, 0.0)
        d, contact = checker.arm_distance(q.tolist(), own.base, arm, st)
        checked += 1
        w = float(cum[hi] - cum[lo])
        t = j * period
        if d - w < closest:
            closest, closest_at = d - w, t
            closest_pair = contact.pair if contact is not None else ""
        slack = d - cm.margin
        if slack - w < 0.0:
            own_link, other_link = ("?", "?") if contact is None else _links(contact.pair)
            clash = Clash(t, own.member, own_link, other.member, other_link, d, w, cm.margin)
            return CrossResult(clash, closest, closest_at, closest_pair, checked)
        if not math.isfinite(slack):
            break
        j = _advance(j, n, slack, q, kb, qa_all, reach_a, cum, lo_all, hi_all)
    return CrossResult(None, closest, closest_at, closest_pair, checked)


def _advance(
    j: int,
    n: int,
    slack: float,
    q: np.ndarray,
    kb: int,
    qa: np.ndarray,
    reach_a: np.ndarray,
    cum: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
) -> int:
    """The next sample to check after ``j`` (slack ``slack``, the other arm at ``kb``): the
    first whose own motion bound from ``q`` plus the other arm's span from ``kb`` to its window
    reaches the slack (in blocks, as arrays)."""
    start, block = j + 1, 64
    while start < n:
        stop = min(start + block, n)
        own = np.abs(qa[start:stop] - q) @ reach_a
        span = cum[np.maximum(hi[start:stop], kb)] - cum[np.minimum(lo[start:stop], kb)]
        over = np.flatnonzero(own + span >= slack)
        if len(over):
            return start + int(over[0])
        start, block = stop, block * 2
    return n


def _links(pair: str) -> tuple[str, str]:
    """``wrist_3_link vs ur5-b:forearm_link`` -> (``wrist_3_link``, ``forearm_link``)."""
    own, _, other = pair.partition(" vs ")
    return own, other.partition(":")[2] or other
