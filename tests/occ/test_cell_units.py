"""The cell plan's pieces one by one (issue 40, item 5; occ/kinematics/cellpaths.py,
occ/controllers/keyframe/cellset.py): a path and its digest, the cell identity, a clash's
words, the time-aligned cross-check against a stand-in geometry (every sample, window and
skip known exactly), the common start on the loop's ticks, what a member says of its cell
set. The whole (members planning, exchanging and checking on loopback) is
test_cell_plan.py's."""

from __future__ import annotations

import hashlib
import json
import math
import threading
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from occ.controllers.keyframe.cellset import (
    MAX_SAMPLES,
    CellCheck,
    CellRole,
    _meta_path,
    first_tick,
    previewed,
    start_time,
)
from occ.errors import CommandError
from occ.events import ArrayInput
from occ.kinematics.cellpaths import (
    ArmPath,
    Clash,
    _links,
    cell_identity,
    cross_check,
    path_digest,
)
from occ.net.commands import ArrayReply, Deferred

BASE = np.eye(4)


def path(member: str = "arm0", qs: Any = None, base: Any = None, period: float = 0.001) -> ArmPath:
    qs = np.array([[0.0, 0.1], [0.01, 0.1], [0.02, 0.1]]) if qs is None else np.asarray(qs)
    return ArmPath(member, qs, BASE if base is None else np.asarray(base), period)


# ------------------------------------------------------------------ the path and its identity
@pytest.mark.req("SR-CELLPLAN-2")
@pytest.mark.parametrize(
    ("qs", "base", "period", "says"),
    [
        (np.zeros(3), BASE, 0.001, "samples x joints, got shape (3,)"),
        (np.zeros((0, 2)), BASE, 0.001, "samples x joints, got shape (0, 2)"),
        (np.zeros((3, 0)), BASE, 0.001, "samples x joints, got shape (3, 0)"),
        (np.zeros((3, 2)), np.eye(3), 0.001, "the base pose is 4 x 4, got shape (3, 3)"),
        (np.array([[0.0, math.nan]]), BASE, 0.001, "a joint value or the base pose is not finite"),
        (np.zeros((1, 2)), np.full((4, 4), math.inf), 0.001, "not finite"),
        (np.zeros((1, 2)), BASE, 0.0, "the period must be > 0, got 0.0"),
        (np.zeros((1, 2)), BASE, math.nan, "the period must be > 0, got nan"),
        (np.zeros((1, 2)), BASE, -0.001, "the period must be > 0, got -0.001"),
    ],
)
def test_a_path_that_is_not_one_is_refused_saying_what(
    qs: Any, base: Any, period: float, says: str
) -> None:
    with pytest.raises(ValueError, match="^arm1: ") as err:
        ArmPath("arm1", qs, base, period)
    assert says in str(err.value)


@pytest.mark.req("SR-CELLPLAN-2")
def test_a_path_of_one_sample_ends_at_its_start_and_of_three_two_periods_later() -> None:
    assert path(qs=[[0.0, 0.0]]).end == 0.0
    assert path(period=0.002).end == pytest.approx(0.004, abs=1e-15)


@pytest.mark.req("SR-CELLPLAN-2")
def test_the_digest_names_every_byte_of_a_path() -> None:
    """The same path the same digest; the member, the period, the shape, the base or one
    sample changed, another one."""
    one = path_digest(path())
    assert one == path_digest(path()) and len(one) == 64
    others = [
        path(member="arm1"),
        path(period=0.002),
        path(qs=[[0.0, 0.1, 0.0, 0.01, 0.1, 0.0]][0:1]),  # the same numbers, another shape
        path(base=np.diag([1.0, 1.0, 1.0, 1.0]) + np.eye(4, k=3) * 1e-3),
        path(qs=[[0.0, 0.1], [0.01, 0.1], [0.02, 0.1 + 1e-12]]),
    ]
    digests = {path_digest(p) for p in others}
    assert len(digests) == len(others) and one not in digests


@pytest.mark.req("SR-CELLPLAN-2")
def test_the_digest_is_of_little_endian_float64_whatever_the_arrays_dtype_or_layout() -> None:
    qs = np.array([[0.0, 0.1], [0.01, 0.1], [0.02, 0.1]])
    assert path_digest(path(qs=qs)) == path_digest(path(qs=np.asfortranarray(qs)))
    assert path_digest(path(qs=qs)) == path_digest(path(qs=qs.astype(">f8")))


@pytest.mark.req("SR-CELLPLAN-3")
def test_the_cell_identity_is_the_sets_and_each_members_path_in_name_order() -> None:
    a = cell_identity("s" * 64, {"arm0": "a" * 64, "arm1": "b" * 64})
    assert a == cell_identity("s" * 64, {"arm1": "b" * 64, "arm0": "a" * 64})
    assert len(a) == 64
    assert a != cell_identity("t" * 64, {"arm0": "a" * 64, "arm1": "b" * 64})
    assert a != cell_identity("s" * 64, {"arm0": "b" * 64, "arm1": "a" * 64})
    assert a != cell_identity("s" * 64, {"arm0": "a" * 64, "arm2": "b" * 64})
    assert a != cell_identity("s" * 64, {"arm0": "a" * 64})


# ------------------------------------------------------------------ a clash in words
@pytest.mark.req("SR-CELLPLAN-2")
def test_a_clash_says_when_which_links_how_near_and_the_skews_share() -> None:
    c = Clash(1.23456, "arm0", "wrist_3_link", "arm1", "forearm_link", 0.00412, 0.0, 0.005)
    assert c.describe() == (
        "at t=1.235 s link 'wrist_3_link' of arm0 comes 4.12 mm from link 'forearm_link' of "
        "arm1 (arm0:wrist_3_link vs arm1:forearm_link; margin 5 mm)"
    )
    skewed = Clash(0.5, "arm0", "a", "arm1", "b", 0.001, 0.00075, 0.0025)
    assert skewed.describe().endswith(
        "margin 2.5 mm, 0.75 mm of which arm1 may move within the skew)"
    )


@pytest.mark.req("SR-CELLPLAN-2")
@pytest.mark.parametrize(
    ("pair", "links"),
    [
        ("wrist_3_link vs ur5-b:forearm_link", ("wrist_3_link", "forearm_link")),
        ("tool vs ur5-b:shoulder:link", ("tool", "shoulder:link")),
        ("a vs b vs ur5-b:c", ("a", "c")),
        ("wrist_3_link vs forearm_link", ("wrist_3_link", "forearm_link")),
    ],
)
def test_a_contacts_pair_names_the_own_link_and_the_others_without_its_arm(
    pair: str, links: tuple[str, str]
) -> None:
    assert _links(pair) == links


# ------------------------------------------------------------------ the common start
@pytest.mark.req("SR-CELLPLAN-4")
def test_the_first_tick_is_the_loops_deadline_at_or_after_the_time() -> None:
    assert first_tick(10.0, 2.0, 0.001) == pytest.approx(10.0, abs=1e-12)
    assert first_tick(10.0004, 2.0, 0.001) == pytest.approx(10.001, abs=1e-12)
    assert first_tick(10.0000000000001, 2.0, 0.001) == pytest.approx(10.0, abs=1e-12)
    assert first_tick(5.0, 2.0005, 0.002) == pytest.approx(5.0005, abs=1e-12)
    assert first_tick(1.0, 2.0, 0.5) == pytest.approx(1.0, abs=1e-12)  # before the loop's t0
    assert first_tick(1.2, 2.0, 0.5) == pytest.approx(1.5, abs=1e-12)
    assert first_tick(7.25, -math.inf, 0.001) == 7.25  # no phase: simulated time
    assert first_tick(7.25, math.nan, 0.001) == 7.25


@pytest.mark.req("SR-CELLPLAN-4")
def test_a_common_start_is_a_unix_time_ahead_but_not_too_far() -> None:
    wall, now = 1_700_000_000.0, 50.0
    assert start_time({"startat": " 1700000002.5 "}, wall, now, 30.0) == pytest.approx(52.5)
    assert start_time({"startat": "1700000000"}, wall, now, 30.0) == pytest.approx(50.0)
    assert start_time({"startat": "1700000030"}, wall, now, 30.0) == pytest.approx(80.0)
    with pytest.raises(CommandError) as err:
        start_time({"startat": "1699999999.5"}, wall, now, 30.0)
    assert str(err.value) == (
        "KeyframeAck: StartAt 1699999999.500 is 0.500 s in the past (now 1700000000.000): "
        "a common start must be ahead of every member; give a later one"
    )
    with pytest.raises(CommandError) as err:
        start_time({"startat": "1700000030.5"}, wall, now, 30.0)
    assert str(err.value) == (
        "KeyframeAck: StartAt 1700000030.500 is 30.5 s ahead, more than cell_start_max_s (30)"
    )
    for bad, shown in (({}, "''"), ({"startat": "soon"}, "'soon'"), ({"startat": "inf"}, "'inf'"),
                       ({"startat": "nan"}, "'nan'")):  # fmt: skip
        with pytest.raises(CommandError) as err:
            start_time(bad, wall, now, 30.0)
        assert str(err.value) == f"KeyframeAck: StartAt must be a unix time, got {shown}"


@pytest.mark.req("SR-CELLPLAN-2")
def test_the_previewed_plan_is_named_by_its_number_or_refused() -> None:
    plan = SimpleNamespace(id=7)
    assert previewed(plan, {"plan": " 7 "}, "KeyframeCellCheck") is plan  # type: ignore[arg-type]
    cases = [
        (plan, {}, "KeyframeCellCheck needs Plan (the number of the previewed plan)"),
        (plan, {"plan": " "}, "KeyframeCellCheck needs Plan (the number of the previewed plan)"),
        (plan, {"plan": "seven"}, "KeyframeCellCheck: Plan must be a number, got 'seven'"),
        (plan, {"plan": "8"},
         "KeyframeCellCheck: plan 8 is not the previewed plan (plan 7 is previewed)"),
        (None, {"plan": "7"},
         "KeyframeCellCheck: plan 7 is not the previewed plan (no plan is previewed)"),
    ]  # fmt: skip
    for pending, args, text in cases:
        with pytest.raises(CommandError) as err:
            previewed(pending, args, "KeyframeCellCheck")  # type: ignore[arg-type]
        assert str(err.value) == text


# ------------------------------------------------------------------ what a member says of it
@pytest.mark.req("SR-CELLPLAN-1")
def test_a_members_cell_statistics_say_its_set_paths_check_and_run() -> None:
    role = CellRole(threading.Lock())
    assert role.stats() == {
        "cell_set": None, "cell_paths": [], "cell_checked": None, "cell_running": None,
        "cell_paths_refused": 0, "cell_last_check": "",
    }  # fmt: skip
    role.cset = SimpleNamespace(digest="d" * 64)  # type: ignore[assignment]
    role.paths = {"arm2": object(), "arm1": object()}  # type: ignore[dict-item]
    role.checked = CellCheck(SimpleNamespace(id=3), "i" * 64, {})  # type: ignore[arg-type]
    role.running = "r" * 64
    role.refused_paths, role.last_check = 2, "i" * 64
    assert role.stats() == {
        "cell_set": "d" * 64, "cell_paths": ["arm1", "arm2"], "cell_checked": "i" * 64,
        "cell_running": "r" * 64, "cell_paths_refused": 2, "cell_last_check": "i" * 64,
    }  # fmt: skip
    role.install(None)  # another set: nothing of the cell's kept but what it has said
    assert role.stats() == {
        "cell_set": None, "cell_paths": [], "cell_checked": None, "cell_running": "r" * 64,
        "cell_paths_refused": 2, "cell_last_check": "i" * 64,
    }  # fmt: skip


@pytest.mark.req("SR-CELLPLAN-3")
def test_a_part_is_acknowledged_only_with_its_passed_checks_identity_and_a_common_start() -> None:
    role = CellRole(threading.Lock())
    cset = SimpleNamespace(name="turns")
    plan, other = SimpleNamespace(id=3), SimpleNamespace(id=4)
    ident = "i" * 64
    alone = (
        "KeyframeAck: plan 3 is a part of cell set turns: it runs only as one with the others "
        "(Cell=<the identity KeyframeCellCheck gave> and StartAt=<unix time>)"
    )
    unchecked = (
        "KeyframeAck: plan 3 has not passed KeyframeCellCheck against the other members' paths"
    )

    def refused(args: dict[str, str]) -> str:
        with pytest.raises(CommandError) as err:
            role._identity(cset, plan, args)  # type: ignore[arg-type]
        return str(err.value)

    for args in ({}, {"cell": ident}, {"startat": "1"}, {"cell": " ", "startat": "1"}):
        assert refused(args) == alone, args
    assert refused({"cell": ident, "startat": "1"}) == unchecked  # no check passed yet
    role.checked = CellCheck(other, ident, {})  # type: ignore[arg-type]
    assert refused({"cell": ident, "startat": "1"}) == unchecked  # passed for another plan
    role.checked = CellCheck(plan, ident, {})  # type: ignore[arg-type]
    assert refused({"cell": "j" * 64, "startat": "1"}) == (
        "KeyframeAck: Cell=jjjjjjjjjjjj.. is not this member's cell plan iiiiiiiiiiii..: the "
        "members planned or checked different plans"
    )
    assert role._identity(cset, plan, {"cell": f" {ident} ", "startat": "1"}) == ident  # type: ignore[arg-type]


@pytest.mark.req("SR-CELLPLAN-4")
def test_an_acknowledged_plan_starts_at_the_loops_first_tick_after_its_start_at() -> None:
    """A plan of no cell set starts now without ``StartAt``, and at the loop's first tick
    at or after it with one; a cell set's part at the first tick after its common start."""
    wall, now = 1_700_000_000.0, 50.0004
    ctx = SimpleNamespace(
        clock=SimpleNamespace(wall_time=lambda: wall), loop_t0=lambda: 2.0, period_s=0.002
    )
    role = CellRole(threading.Lock())
    plan = SimpleNamespace(id=3)
    kset = object()
    assert role.ack(kset, plan, {}, ctx, now, 30.0) == (None, now)  # type: ignore[arg-type]
    ident, t = role.ack(kset, plan, {"startat": f"{wall + 1.5}"}, ctx, now, 30.0)  # type: ignore[arg-type]
    assert ident is None and t == pytest.approx(51.502, abs=1e-9)  # 51.5004 on 2 ms ticks
    role.cset = SimpleNamespace(own=kset, name="turns")  # type: ignore[assignment]
    role.checked = CellCheck(plan, "i" * 64, {})  # type: ignore[arg-type]
    args = {"cell": "i" * 64, "startat": f"{wall + 0.25}"}
    ident, t = role.ack(kset, plan, args, ctx, now, 30.0)  # type: ignore[arg-type]
    assert ident == "i" * 64 and t == pytest.approx(50.252, abs=1e-9)
    with pytest.raises(CommandError, match="runs only as one"):
        role.ack(kset, plan, {"cell": "i" * 64}, ctx, now, 30.0)  # type: ignore[arg-type]


#: SHA-256 of b"occ-cell-plan/1", b"arm0\0", the period, the shape (u8) and the base pose and
#: the samples as little-endian float64 (computed by hand from that construction)
PATH_DIGEST = "7093ef852adb38e36060b9a3a5e3f08c9e68d060a50ca8ca89bdfd815ea079e2"
#: SHA-256 of b"occ-cell-plan/1/cell\0" + the set's digest, then b"\0" + member + b"=" + its
#: path's digest for each member by name
CELL_IDENTITY = "6c89b67beb3634f6d23e1c78b1f62da948a9153b45b972ca026f52028193b997"
CELL_IDENTITY_UTF8 = "5e9d293be7f288549d609748741c48a02173783bf70232ba88a563e278d4ef91"


@pytest.mark.req("SR-CELLPLAN-3")
def test_the_identities_are_the_documented_hashes_so_builds_agree() -> None:
    """A path's digest and a cell plan's identity, pinned: members running different builds
    must compute them alike (a separator or an encoding changed would split the cell)."""
    p = ArmPath("arm0", np.array([[0.0, 0.5], [0.25, -1.0]]), np.eye(4), 0.001)
    assert path_digest(p) == PATH_DIGEST
    plans = {"arm1": "b" * 64, "arm0": "a" * 64}
    assert cell_identity("s" * 64, plans) == CELL_IDENTITY
    # the same, member names not ASCII
    assert cell_identity("s" * 64, {"bras-é": "a" * 64}) == CELL_IDENTITY_UTF8


# ------------------------------------------------------------------ the time-aligned check itself
# A stand-in geometry of one joint per arm: each arm's reach (m per unit of q) and a distance
# given as a function of the two arms' joint values (its slope within their reaches, as a real
# arm's distance is), so every sample checked, every window and every skip is known exactly.
# Periods and values are binary fractions: the sums below are exact.


class Pairs:
    """A checker: the distance ``dist(own q, other q)`` and a pair naming the other's q; it
    records every call (own q, own base, the other arm, its q, its base)."""

    def __init__(self, dist: Any, named: bool = True) -> None:
        self.dist, self.named = dist, named
        self.calls: list[tuple[float, Any, str, float, Any]] = []

    def arm_distance(self, q: Any, base: Any, arm: Any, st: Any) -> tuple[float, Any]:
        self.calls.append((q[0], base, arm.name, st.q[0], st.base))
        d = float(self.dist(q[0], st.q[0]))
        if math.isinf(d) or not self.named:
            return d, None
        return d, SimpleNamespace(pair=f"tool vs {arm.name}:q{st.q[0]:g}")

    def own(self) -> list[float]:
        return [c[0] for c in self.calls]

    def other(self) -> list[float]:
        return [c[3] for c in self.calls]


def unused() -> Any:
    raise AssertionError("cross_check built its own checker: the one given was not used")


def cell(margin: float, reach: float, peers: dict[str, float], checker: Any = unused) -> Any:
    """A collision model of one-joint arms: this arm's reach, each peer's by name."""
    arms = {
        name: SimpleNamespace(name=name, nq=1, arm=SimpleNamespace(reach=(r,)))
        for name, r in peers.items()
    }
    return SimpleNamespace(margin=margin, reach=(reach,), peer=arms.__getitem__, checker=checker)


OWN_BASE = np.diag([1.0, 1.0, 1.0, 1.0]) + np.eye(4, k=3) * 0.5
OTHER_BASE = np.diag([1.0, 1.0, 1.0, 1.0]) + np.eye(4, k=3) * 2.0


def arm(member: str, qs: list[float], period: float = 0.25) -> ArmPath:
    base = OWN_BASE if member == "arm0" else OTHER_BASE
    return ArmPath(member, np.array([[v] for v in qs]), base, period)


@pytest.mark.req("SR-CELLPLAN-2")
def test_at_the_margin_every_sample_is_checked_up_to_the_later_end_of_the_two() -> None:
    """Slack 0 skips nothing: one check per own period up to the longer path's end, own and
    other at their samples at that time (each at rest past its end), both bases given."""
    at_margin = Pairs(lambda a, b: 0.5)
    cm = cell(0.5, 1.0, {"arm1": 0.0})  # the other's reach 0: no skew motion
    res = cross_check(cm, arm("arm0", [0, 1, 2]), [arm("arm1", [10, 11, 12, 13, 14])], 0.0,
                      checker=at_margin)  # fmt: skip
    assert res.checked == 5 and res.clash is None
    assert at_margin.own() == [0, 1, 2, 2, 2]
    assert at_margin.other() == [10, 11, 12, 13, 14]  # its last sample (t = 1.0) too
    for _q, base, name, _qb, other_base in at_margin.calls:
        assert base is not None and (base == OWN_BASE).all() and name == "arm1"
        assert (other_base == OTHER_BASE).all()
    # the closest: the first of equals, its time and pair
    assert (res.closest, res.closest_at, res.closest_pair) == (0.5, 0.0, "tool vs arm1:q10")
    # the own path the longer: its every sample, the other resting at its last
    rest = Pairs(lambda a, b: 0.5)
    res = cross_check(cm, arm("arm0", [0, 1, 2, 3, 4]), [arm("arm1", [10, 11])], 0.0,
                      checker=rest)  # fmt: skip
    assert res.checked == 5 and rest.own() == [0, 1, 2, 3, 4]
    assert rest.other() == [10, 11, 11, 11, 11]


@pytest.mark.req("SR-CELLPLAN-2")
def test_the_other_arm_is_taken_at_its_sample_nearest_each_own_time() -> None:
    """Another period: the other's sample nearest ``j P`` (``t / P_other`` rounded), never
    before its first nor past its last; the own path's period sets the times."""
    seen = Pairs(lambda a, b: 0.5)
    cm = cell(0.5, 1.0, {"arm1": 0.0})
    own = arm("arm0", [0, 1, 2, 3, 4, 5, 6], period=0.25)
    res = cross_check(cm, own, [arm("arm1", [10, 11, 12], period=0.5)], 0.0, checker=seen)
    assert res.checked == 7
    # t = 0, .25, .5, .75, 1, 1.25, 1.5: t / 0.5 rounded half to even, clipped to 0..2
    assert seen.other() == [10, 10, 11, 12, 12, 12, 12]
    assert res.closest_at == 0.0


@pytest.mark.req("SR-CELLPLAN-2")
@pytest.mark.parametrize(
    ("own", "other", "checked", "others_seen"),
    [
        ([0], [10], 1, [10]),  # both one sample: one check at t = 0
        ([0], [10, 11], 2, [10, 11]),
        ([0, 1, 2], [10], 3, [10, 10, 10]),
    ],
)
def test_a_path_of_one_sample_is_checked_at_its_only_sample(
    own: list[float], other: list[float], checked: int, others_seen: list[float]
) -> None:
    seen = Pairs(lambda a, b: 0.5)
    res = cross_check(cell(0.5, 1.0, {"arm1": 0.0}), arm("arm0", own), [arm("arm1", other)],
                      0.0, checker=seen)  # fmt: skip
    assert res.checked == checked and seen.other() == others_seen
    assert res.clash is None and res.closest == 0.5


#: the other arm's joint (reach 1 m per unit): steps of 1, 2, 4, 8, 16 / 64 m, 0.25 s apart
RAMP = [0, 1 / 64, 3 / 64, 7 / 64, 15 / 64, 31 / 64]


@pytest.mark.req("SR-CELLPLAN-2")
def test_only_the_other_arms_motion_within_the_skew_makes_it_refuse() -> None:
    """Distance 0.5 + 26/64 m throughout, margin 0.5 m. Without skew the window is a sample
    either side: at most 24/64 m (t = 1.0), clear. With a skew of one period, two either
    side: 30/64 m at t = 0.75 leaves 0.5 - 4/64 m, a clash of which the skew took 30/64."""
    d = 0.5 + 26 / 64
    cm = cell(0.5, 1.0, {"arm1": 1.0})
    own, other = arm("arm0", [0]), arm("arm1", RAMP)
    seen = Pairs(lambda a, b: d)
    res = cross_check(cm, own, [other], 0.0, checker=seen)
    assert res.clash is None
    # checked at t = 0 and next at t = 1.0, where the other may have moved the slack
    assert res.checked == 2 and seen.other() == [0, RAMP[4]]
    assert (res.closest, res.closest_at) == (d - 24 / 64, 1.0)
    assert res.closest_pair == f"tool vs arm1:q{RAMP[4]:g}"

    seen = Pairs(lambda a, b: d)
    res = cross_check(cm, own, [other], 0.25, checker=seen)
    assert res.checked == 2 and seen.other() == [0, RAMP[3]]
    assert res.clash == Clash(0.75, "arm0", "tool", "arm1", f"q{RAMP[3]:g}", d, 30 / 64, 0.5)
    assert (res.closest, res.closest_at) == (d - 30 / 64, 0.75)
    assert res.closest_pair == f"tool vs arm1:q{RAMP[3]:g}"
    # a skew just over one period: three either side (7/64 at t = 0), the rest far within
    # the slack
    res = cross_check(cm, own, [other], 0.2500001, checker=Pairs(lambda a, b: 2.0))
    assert res.clash is None and (res.closest, res.checked) == (2.0 - 7 / 64, 1)


@pytest.mark.req("SR-CELLPLAN-2")
def test_the_skew_window_before_the_others_start_begins_at_its_first_sample() -> None:
    """At t = 0 a skew of one period reaches its samples 0..2 (3/64 m), none before its
    start: 0.5 + 2/64 m is a clash at the first sample, 0.5 + 3/64 m clear there."""
    cm = cell(0.5, 1.0, {"arm1": 1.0})
    own, other = arm("arm0", [0]), arm("arm1", RAMP)
    res = cross_check(cm, own, [other], 0.25, checker=Pairs(lambda a, b: 0.5 + 2 / 64))
    assert res.clash == Clash(0.0, "arm0", "tool", "arm1", "q0", 0.5 + 2 / 64, 3 / 64, 0.5)
    assert (res.checked, res.closest, res.closest_at) == (1, 0.5 - 1 / 64, 0.0)
    seen = Pairs(lambda a, b: 0.5 + 3 / 64 if b == 0 else 2.0)
    res = cross_check(cm, own, [other], 0.25, checker=seen)
    assert res.clash is None and (res.closest, res.closest_at) == (0.5, 0.0)
    # the window at t = 0.25 (its samples 0..3: 7/64) is the next check's
    assert seen.other() == [0, RAMP[1]] and res.checked == 2


@pytest.mark.req("SR-CELLPLAN-2")
def test_a_clash_at_the_very_last_sample_is_found() -> None:
    """The own arm moves 0.95 m onto the other at its last sample (t = 1.0): checked there
    (its motion from t = 0 reaches the slack) and refused."""
    cm = cell(0.125, 1.0, {"arm1": 1.0})
    seen = Pairs(lambda a, b: 1.0 - a)
    res = cross_check(cm, arm("arm0", [0, 0, 0, 0, 0.95]), [arm("arm1", [0])], 0.0,
                      checker=seen)  # fmt: skip
    assert res.checked == 2 and seen.own() == [0, 0.95]
    assert res.clash is not None and res.clash.t == 1.0
    assert res.clash.distance == pytest.approx(0.05, abs=1e-15) and res.clash.skew_motion == 0.0
    assert res.closest == res.clash.distance and res.closest_at == 1.0


@pytest.mark.req("SR-CELLPLAN-2")
def test_samples_are_skipped_only_while_the_own_motion_is_under_the_slack() -> None:
    """Slack 0.25 m, the own arm 1/8 m a sample: every second sample is checked (its motion
    reaching the slack exactly counts); 1/1024 m a sample over 300 samples with slack 1/8:
    samples 0, 128 and 256, past the blocks the search reads at a time."""
    cm = cell(0.5, 1.0, {"arm1": 1.0})
    seen = Pairs(lambda a, b: 0.75)
    res = cross_check(cm, arm("arm0", [k / 8 for k in range(17)]), [arm("arm1", [0])], 0.0,
                      checker=seen)  # fmt: skip
    assert seen.own() == [k / 4 for k in range(9)] and res.checked == 9
    seen = Pairs(lambda a, b: 0.625)
    res = cross_check(cm, arm("arm0", [k / 1024 for k in range(300)]), [arm("arm1", [0])],
                      0.0, checker=seen)  # fmt: skip
    assert seen.own() == [0.0, 0.125, 0.25] and res.checked == 3
    # the own reach counts: half of it, every fourth sample of the first path
    seen = Pairs(lambda a, b: 0.75)
    res = cross_check(cell(0.5, 0.5, {"arm1": 1.0}), arm("arm0", [k / 8 for k in range(17)]),
                      [arm("arm1", [0])], 0.0, checker=seen)  # fmt: skip
    assert seen.own() == [k / 2 for k in range(5)] and res.checked == 5


@pytest.mark.req("SR-CELLPLAN-2")
def test_the_other_arms_motion_from_its_checked_sample_brings_the_next_check() -> None:
    """The own arm still: after t = 0 (the other at its sample 0) the next check is the first
    time whose window reaches as far from sample 0 as the slack (t = 0.5, its window's end at
    sample 3: 7/64 m), and from there the next (t = 0.75, 12/64 m more), a clash."""
    cm = cell(0.5, 1.0, {"arm1": 1.0})
    seen = Pairs(lambda a, b: 0.5 + 7 / 64)  # slack 7/64: the window's end at sample 3
    res = cross_check(cm, arm("arm0", [0]), [arm("arm1", RAMP)], 0.0, checker=seen)
    assert seen.other() == [0, RAMP[2], RAMP[3]] and res.checked == 3
    assert res.clash == Clash(0.75, "arm0", "tool", "arm1", f"q{RAMP[3]:g}", 0.5 + 7 / 64,
                              12 / 64, 0.5)  # fmt: skip


@pytest.mark.req("SR-CELLPLAN-2")
def test_each_other_arm_is_checked_and_counted_the_closest_kept_and_a_clash_ends_it() -> None:
    cm = cell(0.5, 1.0, {"arm1": 0.0, "arm2": 0.0})
    one, two = arm("arm1", [10, 11, 12]), arm("arm2", [20, 21])
    seen = Pairs(lambda a, b: 0.5)
    res = cross_check(cm, arm("arm0", [0]), [one, two], 0.0, checker=seen)
    assert [c[2] for c in seen.calls] == ["arm1"] * 3 + ["arm2"] * 2
    assert res == type(res)(None, 0.5, 0.0, "tool vs arm1:q10", 5)  # the first of equals
    seen = Pairs(lambda a, b: 0.5 if b < 20 else 0.75 - (b - 20) / 8)
    res = cross_check(cm, arm("arm0", [0]), [one, two], 0.0, checker=seen)
    assert (res.closest, res.closest_at, res.closest_pair) == (0.5, 0.0, "tool vs arm1:q10")
    # nearer the second: its closest (the own arm moving 1 m a sample: each checked)
    seen = Pairs(lambda a, b: 0.75 if b < 20 else 0.625 - a / 16)
    res = cross_check(cm, arm("arm0", [0, 1]), [one, two], 0.0, checker=seen)
    assert [(c[2], c[3]) for c in seen.calls] == [
        ("arm1", 10), ("arm1", 11), ("arm2", 20), ("arm2", 21)
    ]  # fmt: skip
    assert res.clash is None and res.checked == 2 + 2
    assert (res.closest, res.closest_at, res.closest_pair) == (0.5625, 0.25, "tool vs arm2:q21")
    # a clash with the second: its result, the samples of both counted
    seen = Pairs(lambda a, b: 0.75 if b < 20 else 0.25)
    res = cross_check(cm, arm("arm0", [0]), [one, two], 0.0, checker=seen)
    assert res.clash == Clash(0.0, "arm0", "tool", "arm2", "q20", 0.25, 0.0, 0.5)
    assert (res.closest, res.closest_at, res.closest_pair, res.checked) == (
        0.25, 0.0, "tool vs arm2:q20", 1 + 1,
    )  # fmt: skip


@pytest.mark.req("SR-CELLPLAN-2")
def test_arms_never_near_leave_no_closest_and_no_other_arm_checks_nothing() -> None:
    """A distance of infinity (no pair near): one check, no closest, no pair, no time."""
    cm = cell(0.5, 1.0, {"arm1": 1.0})
    far = Pairs(lambda a, b: math.inf)
    res = cross_check(cm, arm("arm0", [0, 1]), [arm("arm1", [0, 1, 2])], 0.0, checker=far)
    assert res == type(res)(None, math.inf, 0.0, "", 1) and len(far.calls) == 1
    assert cross_check(cm, arm("arm0", [0]), [], 0.0, checker=far) == type(res)(
        None, math.inf, 0.0, "", 0
    )


@pytest.mark.req("SR-CELLPLAN-2")
def test_the_checker_and_the_pace_given_are_used_and_without_one_the_models() -> None:
    beats: list[int] = []
    seen = Pairs(lambda a, b: 0.5)
    cm = cell(0.5, 1.0, {"arm1": 0.0})
    res = cross_check(cm, arm("arm0", [0, 1, 2]), [arm("arm1", [0])], 0.0, checker=seen,
                      pace=lambda: beats.append(1))  # fmt: skip
    assert res.checked == 3 and len(beats) == 3 and len(seen.calls) == 3
    own = Pairs(lambda a, b: 0.5)
    res = cross_check(cell(0.5, 1.0, {"arm1": 0.0}, lambda: own), arm("arm0", [0, 1]),
                      [arm("arm1", [0])], 0.0)  # fmt: skip
    assert res.checked == 2 and len(own.calls) == 2


@pytest.mark.req("SR-CELLPLAN-2")
def test_another_arms_path_of_other_joints_than_its_arm_is_refused() -> None:
    other = ArmPath("arm1", np.zeros((2, 2)), OTHER_BASE, 0.25)
    with pytest.raises(ValueError) as err:
        cross_check(cell(0.5, 1.0, {"arm1": 1.0}), arm("arm0", [0]), [other], 0.0,
                    checker=Pairs(lambda a, b: 1.0))  # fmt: skip
    assert str(err.value) == "arm1: its path has 2 joints, its arm 1"


@pytest.mark.req("SR-CELLPLAN-2")
def test_a_distance_with_no_pair_named_is_checked_and_its_clash_names_no_link() -> None:
    """Far pairs give a lower bound and no contact: the closest names no pair, and a clash
    (the skew window taking it under the margin) says '?' for both links."""
    cm = cell(0.5, 1.0, {"arm1": 1.0})
    res = cross_check(cm, arm("arm0", [0]), [arm("arm1", [0])], 0.0,
                      checker=Pairs(lambda a, b: 0.75, named=False))  # fmt: skip
    assert res == type(res)(None, 0.75, 0.0, "", 1)
    res = cross_check(cm, arm("arm0", [0]), [arm("arm1", RAMP)], 0.25,
                      checker=Pairs(lambda a, b: 0.5 + 2 / 64, named=False))  # fmt: skip
    assert res.clash == Clash(0.0, "arm0", "?", "arm1", "?", 0.5 + 2 / 64, 3 / 64, 0.5)
    assert res.closest_pair == ""


# ------------------------------------------------------------------ another member's path, as given
SET = "s" * 64


def given(p: ArmPath, **meta: str) -> ArrayInput:
    """``p`` as an NDARRAY ``CellPath`` names it: its member, set, period, base and digest,
    ``meta`` replacing any of them (``""``: left out)."""
    names = {
        "member": p.member,
        "set": SET,
        "period": repr(p.period),
        "base": ",".join(repr(float(v)) for v in p.base.ravel()),
        "digest": path_digest(p),
    }
    names.update(meta)
    kept = {k: v for k, v in names.items() if v != ""}
    return ArrayInput("op", None, 0.0, "NDARRAY", "CellPath", kept, p.qs)


@pytest.mark.req("SR-CELLPLAN-2")
def test_a_given_path_is_read_from_its_metadata_and_its_samples_as_float() -> None:
    """Integer samples are taken as float64 (the digest's values), the base as 4 x 4."""
    p = ArmPath("arm1", np.array([[0, 1], [2, 3]]), OTHER_BASE, 0.25)
    read, claimed = _meta_path(given(p))
    assert read.member == "arm1" and read.period == 0.25 and claimed == path_digest(p)
    assert read.qs.dtype == np.float64 and read.qs.tolist() == [[0.0, 1.0], [2.0, 3.0]]
    assert read.base.dtype == np.float64 and (read.base == OTHER_BASE).all()
    assert path_digest(read) == claimed


@pytest.mark.req("SR-CELLPLAN-2")
@pytest.mark.parametrize(
    ("meta", "says"),
    [
        ({"member": ""}, "'member'"),
        ({"period": ""}, "'period'"),
        ({"base": ""}, "'base'"),
        ({"digest": ""}, "'digest'"),
        ({"period": "soon"}, "could not convert string to float: 'soon'"),
        ({"base": "1,0,0"}, "cannot reshape array of size 3 into shape (4,4)"),
    ],
)
def test_a_given_path_without_what_names_it_is_refused_saying_what(
    meta: dict[str, str], says: str
) -> None:
    with pytest.raises(ValueError) as err:
        _meta_path(given(arm("arm1", [0, 1]), **meta))
    assert str(err.value) == f"NDARRAY 'CellPath': metadata member, period, base, digest: {says}"


def member_set(others: tuple[str, ...] = ("arm1",)) -> Any:
    return SimpleNamespace(me="arm0", others=others, digest=SET, name="turns")


@pytest.mark.req("SR-CELLPLAN-2")
def test_a_path_of_at_most_max_samples_matching_its_digest_is_taken() -> None:
    longest = ArmPath("arm1", np.zeros((MAX_SAMPLES, 1)), OTHER_BASE, 0.001)
    paths, digests = CellRole._validated(member_set(), {"arm1": given(longest)})
    assert [len(p.qs) for p in paths] == [MAX_SAMPLES] and digests == {"arm1": path_digest(longest)}
    over = ArmPath("arm1", np.zeros((MAX_SAMPLES + 1, 1)), OTHER_BASE, 0.001)
    with pytest.raises(ValueError) as err:
        CellRole._validated(member_set(), {"arm1": given(over)})
    assert str(err.value) == f"arm1's path has more than {MAX_SAMPLES} samples"


@pytest.mark.req("SR-CELLPLAN-2")
def test_a_path_given_as_anothers_or_not_matching_its_digest_is_refused() -> None:
    p, q = arm("arm1", [0, 1]), arm("arm2", [5])
    paths, digests = CellRole._validated(
        member_set(("arm1", "arm2")), {"arm2": given(q), "arm1": given(p)}
    )
    assert [x.member for x in paths] == ["arm1", "arm2"]
    assert digests == {"arm1": path_digest(p), "arm2": path_digest(q)}
    with pytest.raises(ValueError) as err:
        CellRole._validated(member_set(), {"arm1": given(q)})
    assert str(err.value) == "the path given as arm1's names arm2"
    with pytest.raises(ValueError) as err:
        CellRole._validated(member_set(), {"arm1": given(p, digest="d" * 64)})
    assert str(err.value) == "arm1's path does not match its digest dddddddddddd"
    with pytest.raises(ValueError) as err:
        CellRole._validated(member_set(), {"arm1": given(p, period="0.5")})
    assert "arm1's path does not match its digest" in str(err.value)


@pytest.mark.req("SR-CELLPLAN-2")
def test_a_path_is_kept_only_from_another_member_of_the_loaded_cell_set() -> None:
    kset = object()
    role = CellRole(threading.Lock())
    p = arm("arm1", [0, 1])

    def refused(event: ArrayInput, loaded: Any = kset) -> str:
        with pytest.raises(CommandError) as err:
            role.take_path(event, loaded)  # type: ignore[arg-type]
        return str(err.value)

    assert refused(given(p)) == "NDARRAY 'CellPath': no cell keyframe set is loaded"
    role.cset = SimpleNamespace(  # type: ignore[assignment]
        own=kset, digest=SET, others=("arm1", "arm2"), name="turns"
    )
    assert refused(given(p), object()) == "NDARRAY 'CellPath': no cell keyframe set is loaded"
    assert refused(given(p, set="t" * 64)) == (
        "NDARRAY 'CellPath' of arm1: for another cell set (its digest tttttttttttt, this "
        "member's ssssssssssss)"
    )
    assert refused(given(p, set="", member="")) == (
        "NDARRAY 'CellPath' of ?: for another cell set (its digest ?, this member's ssssssssssss)"
    )
    assert refused(given(p, member="")) == (
        "NDARRAY 'CellPath': '' is not another member of cell set turns (arm1, arm2)"
    )
    assert refused(given(p, member="arm0")) == (
        "NDARRAY 'CellPath': 'arm0' is not another member of cell set turns (arm1, arm2)"
    )
    assert role.paths == {}
    role.checked = CellCheck(SimpleNamespace(id=3), "i" * 64, {})  # type: ignore[arg-type]
    event = given(p)
    role.take_path(event, kset)  # type: ignore[arg-type]
    assert role.paths == {"arm1": event} and role.checked is None


def job_for(role: CellRole, cm: Any, paths: dict[str, ArrayInput]) -> Deferred:
    """``KeyframeCellCheck``'s job for plan 3 (arm0's one sample) run here, its answer."""
    kset = object()
    cset = SimpleNamespace(own=kset, me="arm0", others=tuple(sorted(paths)), digest=SET,
                           name="turns")  # fmt: skip
    role.cset = cset  # type: ignore[assignment]
    role.paths = dict(paths)
    plan = SimpleNamespace(id=3, qs=np.array([[0.0]]), digest="p" * 64, base=OWN_BASE,
                           period=0.25, kset=kset)  # fmt: skip
    answer = Deferred()
    role.check_job(cset, plan, cm, 0.0, None, lambda c: c is plan)(answer)  # type: ignore[arg-type]
    return answer


@pytest.mark.req("SR-CELLPLAN-2")
def test_a_refused_cross_check_is_said_and_kept_as_the_last_check() -> None:
    role = CellRole(threading.Lock())
    near = Pairs(lambda a, b: 0.25)
    cm = cell(0.5, 1.0, {"arm1": 0.0}, lambda: near)
    answer = job_for(role, cm, {"arm1": given(arm("arm1", [0]))})
    text = (
        "cell plan refused: at t=0.000 s link 'tool' of arm0 comes 250.00 mm from link 'q0' of "
        "arm1 (arm0:tool vs arm1:q0; margin 500 mm)"
    )
    assert answer.result == (False, text) and role.last_check == text
    assert role.checked is None
    bad = given(arm("arm1", [0]), digest="d" * 64)
    answer = job_for(role, cm, {"arm1": bad})
    text = "cell plan refused: arm1's path does not match its digest dddddddddddd"
    assert answer.result == (False, text) and role.last_check == text
    # clear: the identity kept and said (another member: a role keeps its first checker)
    role = CellRole(threading.Lock())
    far = Pairs(lambda a, b: 0.75)
    p = arm("arm1", [0])
    answer = job_for(role, cell(0.5, 1.0, {"arm1": 0.0}, lambda: far), {"arm1": given(p)})
    ident = cell_identity(SET, {"arm0": "p" * 64, "arm1": path_digest(p)})
    assert role.checked is not None and role.checked.identity == ident == role.last_check
    assert answer.result is not None and answer.result[0]
    assert answer.result[1].startswith(f"cell plan {ident}: set ssssssssssss, plans arm0 ")
    assert (
        "(1 samples checked, closest 750.0 mm (tool vs arm1:q0 at t=0.000 s))" in (answer.result[1])
    )


# ------------------------------------------------------------------ a member's part of a cell set
@pytest.mark.req("SR-CELLPLAN-1")
def test_a_members_part_keeps_the_sets_canonical_digest_its_space_and_its_plan() -> None:
    """Each member keeps its own part as a set (named in its source with the set's digest),
    the part's space or else the file's, the file's plan settings, and one digest of the
    whole file's content however it is written: SHA-256 of its canonical JSON (keys sorted, no
    spaces)."""
    from occ.controllers.keyframe.cellset import CellKeyframeFile, cell_set
    from occ.controllers.keyframe.sets import PlanSettings

    arms = {
        "arm0": {"keyframes": [{"t": 0.0, "pose": [0.0, 0.1]}, {"t": 1.0, "pose": [0.2, 0.1]}]},
        "arm1": {"space": "cartesian", "keyframes": [{"t": 0.0, "pose": [1.0, 2.0, 3.0]}]},
    }
    raw = {"cell": "or1", "space": "joint", "arms": arms,
           "plan": {"interpolation": "spline", "mode": "continuous", "steepness": 4.0,
                    "ramp": 0.125}}  # fmt: skip
    cf = CellKeyframeFile.model_validate(raw)
    shuffled = CellKeyframeFile.model_validate(dict(reversed(list(raw.items()))))
    canonical = json.dumps(cf.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))
    digest = hashlib.sha256(canonical.encode("utf-8")).hexdigest()
    assert '"arms":{"arm0":' in canonical and ", " not in canonical
    a0 = cell_set(cf, "two.yaml", "arm0", "cartesian", 2, 100)
    a1 = cell_set(shuffled, "two.yaml", "arm1", "joint", 2, 100)
    assert (a0.name, a0.me, a0.digest, a0.file) == ("two.yaml", "arm0", digest, cf)
    assert a1.digest == digest and a1.members == ("arm0", "arm1") and a1.others == ("arm0",)
    assert a0.own.space == "joint"  # the file's space, not the robot's default
    assert a1.own.space == "cartesian"  # the part's own
    assert [k.t for k in a0.own.keyframes] == [0.0, 1.0]
    assert a0.own.source == f"cell set two.yaml ({digest[:12]}), part arm0"
    assert a0.own.settings == PlanSettings("spline", "continuous", 4.0, 0.125)
    # without a plan in the file: the robot's defaults (none kept with the set), its own digest
    del raw["plan"]
    plain = cell_set(CellKeyframeFile.model_validate(raw), "two.yaml", "arm0", "joint", 2, 100)
    assert plain.own.settings is None and plain.digest != digest


# ------------------------------------------------------------------ the role's commands and job
class Pace:
    """A stand-in pacer: how often the job began and how often it was paced."""

    def __init__(self) -> None:
        self.begun = 0
        self.beats = 0

    def begin(self) -> None:
        self.begun += 1

    def __call__(self) -> None:
        self.beats += 1


class Planner:
    """The controller's side of ``KeyframeCellCheck``: its previewed plan, and a planner
    thread that runs each job at once (here, on the test's thread)."""

    def __init__(self, plan: Any) -> None:
        self.plan = plan

    def start(self, job: Any) -> Deferred:
        answer = Deferred()
        job(answer)
        return answer


def loaded(role: CellRole, others: tuple[str, ...] = ("arm1",), qs: Any = None) -> Any:
    """A cell set of arm0 and ``others`` loaded in ``role``, and its part's previewed plan 3
    (arm0's one sample unless ``qs``)."""
    kset = object()
    role.cset = SimpleNamespace(  # type: ignore[assignment]
        own=kset, me="arm0", others=others, members=("arm0", *others), digest=SET, name="turns"
    )
    return SimpleNamespace(id=3, qs=np.array([[0.0]]) if qs is None else qs, digest="p" * 64,
                           base=OWN_BASE, period=0.25, kset=kset)  # fmt: skip


@pytest.mark.req("SR-CELLPLAN-2")
def test_each_command_names_itself_when_its_plan_is_not_the_previewed_one() -> None:
    role = CellRole(threading.Lock())
    plan = loaded(role)
    ctx = SimpleNamespace(collision=cell(0.5, 1.0, {"arm1": 0.0}))
    for key, name in (("keyframecellpath", "KeyframeCellPath"),
                      ("keyframecellcheck", "KeyframeCellCheck")):  # fmt: skip
        with pytest.raises(CommandError) as err:
            role.command(key, {}, plan.kset, plan, ctx, 0.0, Pace(), Planner(plan))  # type: ignore[arg-type]
        assert str(err.value) == f"{name} needs Plan (the number of the previewed plan)"
        with pytest.raises(CommandError) as err:
            role.command(key, {"plan": "4"}, plan.kset, plan, ctx, 0.0, Pace(), Planner(plan))  # type: ignore[arg-type]
        assert str(err.value) == f"{name}: plan 4 is not the previewed plan (plan 3 is previewed)"
    with pytest.raises(CommandError) as err:
        role.command("keyframecellpath", {"plan": "3"}, object(), plan, ctx, 0.0, Pace(),  # type: ignore[arg-type]
                     Planner(plan))  # fmt: skip
    assert str(err.value) == "no cell keyframe set is loaded (KeyframeLoad File=<a cell set>)"


@pytest.mark.req("SR-CELLPLAN-2")
def test_the_path_answered_is_the_previewed_plans_with_what_names_it() -> None:
    role = CellRole(threading.Lock())
    qs = np.array([[0.0], [0.5], [1.0]])
    plan = loaded(role, qs=qs)
    reply = role.command("keyframecellpath", {"plan": "3"}, plan.kset, plan, SimpleNamespace(),  # type: ignore[arg-type]
                         0.0, Pace(), Planner(plan))  # fmt: skip
    assert isinstance(reply, ArrayReply)
    assert reply.array is qs and reply.device == "CellPath"
    assert reply.meta == {
        "member": "arm0", "set": SET, "plan": "3", "digest": "p" * 64, "period": "0.25",
        "base": "1.0,0.0,0.0,0.5,0.0,1.0,0.0,0.0,0.0,0.0,1.0,0.0,0.0,0.0,0.0,1.0",
    }  # fmt: skip
    assert reply.text == (
        f"CellPath of arm0: plan 3, 3 samples, digest {'p' * 64}; give it to the other "
        "members of cell set turns"
    )


@pytest.mark.req("SR-CELLPLAN-2")
def test_a_plan_that_kept_no_path_or_no_digest_is_neither_answered_nor_checked() -> None:
    """Either one missing refuses: a path without its digest cannot be named to the others,
    a digest without its path cannot be checked."""
    role = CellRole(threading.Lock())
    plan = loaded(role)
    cm = cell(0.5, 1.0, {"arm1": 0.0}, unused)
    role.paths = {"arm1": given(arm("arm1", [0]))}
    for broken in (replace_ns(plan, qs=None), replace_ns(plan, digest="")):
        with pytest.raises(CommandError) as err:
            role.path_reply(role.cset, broken, "arm0")  # type: ignore[arg-type]
        assert str(err.value) == "plan 3 kept no path: plan again"
        with pytest.raises(CommandError) as err:
            role.check_job(role.cset, broken, cm, 0.0, None, lambda c: True)  # type: ignore[arg-type]
        assert str(err.value) == "plan 3 kept no path: plan again"


def replace_ns(ns: Any, **changes: Any) -> Any:
    return SimpleNamespace(**{**vars(ns), **changes})


@pytest.mark.req("SR-CELLPLAN-2")
def test_a_check_without_the_arms_geometry_or_every_others_path_is_refused_saying_what() -> None:
    role = CellRole(threading.Lock())
    plan = loaded(role, others=("arm1", "arm2", "arm3"))
    role.paths = {"arm2": given(arm("arm2", [0]))}
    with pytest.raises(CommandError) as err:
        role.check_job(role.cset, plan, None, 0.0, None, lambda c: True)  # type: ignore[arg-type]
    assert str(err.value) == "the cross-check needs safety.collision (the arms' geometry)"
    cm = cell(0.5, 1.0, {"arm1": 0.0, "arm2": 0.0, "arm3": 0.0}, unused)
    with pytest.raises(CommandError) as err:
        role.check_job(role.cset, plan, cm, 0.0, None, lambda c: True)  # type: ignore[arg-type]
    assert str(err.value) == (
        "no path yet from arm1, arm3: give this member every other member's CellPath "
        "(KeyframeCellPath on each) first"
    )


@pytest.mark.req("SR-CELLPLAN-2")
def test_the_check_runs_paced_on_the_planner_with_one_checker_kept_for_the_next() -> None:
    """``KeyframeCellCheck`` hands the job to the planner; the job begins the pacer once and
    paces each sample checked; the geometry's checker is built once per member (the planner
    thread's) and used again by the next check."""
    built: list[Pairs] = []

    def checker() -> Pairs:
        built.append(Pairs(lambda a, b: 0.75))
        return built[-1]

    role = CellRole(threading.Lock())
    plan = loaded(role, qs=np.array([[0.0], [1.0], [2.0]]))
    role.paths = {"arm1": given(arm("arm1", [0]))}
    ctx = SimpleNamespace(collision=cell(0.5, 1.0, {"arm1": 0.0}, checker))
    pace = Pace()
    answer = role.command("keyframecellcheck", {"plan": "3"}, plan.kset, plan, ctx, 0.0, pace,  # type: ignore[arg-type]
                          Planner(plan))  # fmt: skip
    assert isinstance(answer, Deferred) and answer.result is not None and answer.result[0]
    assert len(built) == 1 and len(built[0].calls) == 3
    assert (pace.begun, pace.beats) == (1, 3)
    answer = job_for(role, ctx.collision, {"arm1": given(arm("arm1", [0]))})
    assert answer.result is not None and answer.result[0]
    assert len(built) == 1 and len(built[0].calls) == 4  # the same checker, once more


@pytest.mark.req("SR-CELLPLAN-2")
def test_a_check_whose_plan_or_set_changed_meanwhile_keeps_nothing() -> None:
    """The job's result is kept only while its plan is still the previewed one of the same
    cell set: either changed, it is refused and no identity is kept."""
    far = cell(0.5, 1.0, {"arm1": 0.0}, lambda: Pairs(lambda a, b: 0.75))
    for superseded, reloaded in ((True, False), (False, True)):
        role = CellRole(threading.Lock())
        plan = loaded(role)
        role.paths = {"arm1": given(arm("arm1", [0]))}
        job = role.check_job(role.cset, plan, far, 0.0, None, lambda c, s=superseded: not s)  # type: ignore[arg-type,misc]
        if reloaded:
            role.cset = replace_ns(role.cset)  # another set of the same content
        answer = Deferred()
        job(answer)
        assert answer.result == (False, "plan 3 is no longer previewed: plan again")
        assert role.checked is None and role.last_check == ""


@pytest.mark.req("SR-CELLPLAN-3")
def test_a_passed_check_keeps_every_members_digest_and_says_the_whole_answer() -> None:
    role = CellRole(threading.Lock())
    p, q = arm("arm1", [0]), arm("arm2", [5])
    cm = cell(0.5, 1.0, {"arm1": 0.0, "arm2": 0.0}, lambda: Pairs(lambda a, b: 0.75))
    answer = job_for(role, cm, {"arm1": given(p), "arm2": given(q)})
    digests = {"arm0": "p" * 64, "arm1": path_digest(p), "arm2": path_digest(q)}
    ident = cell_identity(SET, digests)
    assert role.checked is not None and dict(role.checked.plans) == digests
    assert answer.result == (True, (
        f"cell plan {ident}: set ssssssssssss, plans arm0 pppppppppppp, "
        f"arm1 {digests['arm1'][:12]}, arm2 {digests['arm2'][:12]}; clear of arm1, arm2 at the "
        "same times (2 samples checked, closest 750.0 mm (tool vs arm1:q0 at t=0.000 s)); "
        f"KeyframeAck Plan=3 StartAt=<unix time> Cell={ident} on every member"
    ))  # fmt: skip
    never = cell(0.5, 1.0, {"arm1": 0.0}, lambda: Pairs(lambda a, b: math.inf))
    answer = job_for(CellRole(threading.Lock()), never, {"arm1": given(p)})
    ident = cell_identity(SET, {"arm0": "p" * 64, "arm1": digests["arm1"]})
    assert answer.result == (True, (
        f"cell plan {ident}: set ssssssssssss, plans arm0 pppppppppppp, "
        f"arm1 {digests['arm1'][:12]}; clear of arm1 at the same times (1 samples checked, "
        f"the arms never near); KeyframeAck Plan=3 StartAt=<unix time> Cell={ident} on every "
        "member"
    ))  # fmt: skip


@pytest.mark.req("SR-CELLPLAN-2")
def test_a_refused_path_is_counted_and_the_last_check_reported() -> None:
    """A path refused on arrival is the sender's mistake: counted (GetStats
    ``cell_paths_refused``) as well as refused; ``cell_last_check`` says the last cross-check's
    outcome, its identity or why it refused."""
    role = CellRole(threading.Lock())
    assert (role.stats()["cell_paths_refused"], role.stats()["cell_last_check"]) == (0, "")
    kset = object()
    p = arm("arm1", [0])
    for event, loaded_set in ((given(p), kset), (given(p), object())):
        with pytest.raises(CommandError):
            role.take_path(event, loaded_set)  # type: ignore[arg-type]
    assert role.stats()["cell_paths_refused"] == 2
    role.cset = SimpleNamespace(own=kset, digest=SET, others=("arm1",), name="turns")  # type: ignore[assignment]
    for event in (given(p, set="t" * 64), given(p, member="arm2")):
        with pytest.raises(CommandError):
            role.take_path(event, kset)  # type: ignore[arg-type]
    role.take_path(given(p), kset)  # type: ignore[arg-type]
    assert role.stats()["cell_paths_refused"] == 4 and role.paths == {"arm1": given(p)}
    near = cell(0.5, 1.0, {"arm1": 0.0}, lambda: Pairs(lambda a, b: 0.25))
    job_for(role, near, {"arm1": given(p)})
    assert role.stats()["cell_last_check"].startswith("cell plan refused: at t=0.000 s")


@pytest.mark.req("SR-CELLPLAN-1")
def test_the_desk_is_told_the_loaded_cell_set_the_paths_given_and_the_plan_checked() -> None:
    role = CellRole(threading.Lock())
    plan = loaded(role, others=("arm1", "arm2"))
    assert role.describe(object()) == []  # type: ignore[arg-type]
    assert role.describe(plan.kset) == [
        "cell set: turns ssssssssssss, parts arm0, arm1, arm2; paths from none"
    ]
    role.paths = {"arm2": object(), "arm1": object()}  # type: ignore[dict-item]
    role.checked = CellCheck(plan, "i" * 64, {})
    assert role.describe(plan.kset) == [
        "cell set: turns ssssssssssss, parts arm0, arm1, arm2; paths from arm1, arm2",
        f"cell plan: {'i' * 64} (plan 3)",
    ]


# ------------------------------------------------------------------ a keyframe file of either kind
@pytest.mark.req("SR-CELLPLAN-1")
def test_a_file_with_arms_is_read_as_a_cell_set_and_one_without_as_a_keyframe_file(
    tmp_path: Any,
) -> None:
    from occ.controllers.keyframe.cellset import CellKeyframeFile, read_any_keyframe_file
    from occ.controllers.keyframe.sets import KeyframeFile

    plain = tmp_path / "plain.yaml"
    plain.write_text("space: joint\nkeyframes:\n  - {t: 0.0, pose: [0.0, 0.1]}\n")
    bare = tmp_path / "bare.yaml"
    bare.write_text("- {t: 0.0, pose: [0.0, 0.1]}\n")
    two = tmp_path / "two.yaml"
    two.write_text(
        "arms:\n  arm0: {keyframes: [{t: 0.0, pose: [0.0]}]}\n"
        "  arm1: {keyframes: [{t: 0.0, pose: [1.0]}]}\n"
    )
    assert type(read_any_keyframe_file(plain)) is KeyframeFile
    assert type(read_any_keyframe_file(bare)) is KeyframeFile
    assert type(read_any_keyframe_file(two)) is CellKeyframeFile


# ------------------------------------------------------------------ another arm of the cell
@pytest.mark.req("SR-ARMS-1")
def test_a_peer_of_a_builtin_model_has_its_kinematics_and_a_frame_refused_is_named() -> None:
    from occ.config import FrameConfig
    from occ.errors import ConfigError
    from occ.kinematics.peers import peer_frame

    frame = peer_frame(FrameConfig(model="occ_slave"), "peer arm 'x'")
    assert frame.tip_link == "tool_tip" and frame.model.nq == 3
    with pytest.raises(ConfigError) as err:  # a model the schema would refuse: named by key
        peer_frame(SimpleNamespace(model="nosuch"), "peer arm 'x'")  # type: ignore[arg-type]
    assert str(err.value) == (
        "peer arm 'x': unknown built-in model 'nosuch'; known: master3, occ_slave"
    )


def stand_in_arm(limits: list[float], reach: tuple[float, ...] = (0.5, 0.25)) -> Any:
    """An arm's geometry as the peer needs it: its joints, their URDF limits, their reach."""
    return SimpleNamespace(
        model=SimpleNamespace(nq=len(reach), velocityLimit=limits), reach=reach, links=()
    )


@pytest.mark.req("SR-ARMS-1")
def test_a_peers_urdf_limits_are_used_only_when_each_is_a_number_over_0(monkeypatch: Any) -> None:
    """Without velocities the URDF's: 1.0 and 0.5 rad/s give its speed bound; a limit of 0,
    infinity or NaN is none, refused naming the arm. Its kinematics and geometry are asked
    for with the arm's name for their own refusals."""
    import occ.kinematics.peers as peers
    from occ.errors import ConfigError

    asked: list[tuple[str, str]] = []
    geometry = stand_in_arm([1.0, 0.5])

    def frame(cfg: Any, key: str) -> str:
        asked.append(("frame", key))
        return "kinematics"

    def load_arm(cfg: Any, fr: Any, *, convex: bool, link_radius: float, tool: Any = None,
                 key: str = "safety.collision") -> Any:  # fmt: skip
        assert fr == "kinematics"
        asked.append(("geometry", key))
        return geometry

    monkeypatch.setattr(peers, "peer_frame", frame)
    monkeypatch.setattr(peers, "load_arm", load_arm)
    peer = peers.build_peer("ur5-b", object(), convex=True, link_radius=0.05)  # type: ignore[arg-type]
    assert asked == [("frame", "peer arm 'ur5-b'"), ("geometry", "peer arm 'ur5-b'")]
    assert peer.speed == 1.0 * 0.5 + 0.5 * 0.25
    for limits in ([0.0, 1.0], [1.0, math.inf], [math.nan, 1.0], [1.0, -0.5]):
        geometry = stand_in_arm(limits)
        with pytest.raises(ConfigError) as err:
            peers.build_peer("ur5-b", object(), convex=True, link_radius=0.05)  # type: ignore[arg-type]
        assert str(err.value) == "peer arm 'ur5-b': its URDF gives no velocity limits; give them"


@pytest.mark.req("SR-ARMS-2")
def test_a_peers_speed_bound_needs_a_limit_for_every_joint() -> None:
    """Fewer limits than joints would leave a joint's motion out of the bound: refused."""
    from occ.kinematics.peers import PeerArm

    assert PeerArm("b", stand_in_arm([]), [2.0, 4.0]).speed == 2.0 * 0.5 + 4.0 * 0.25
    with pytest.raises(ValueError):
        PeerArm("b", stand_in_arm([]), [2.0])
