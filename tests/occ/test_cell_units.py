"""The cell plan's pieces one by one (issue 40, item 5; occ/kinematics/cellpaths.py,
occ/controllers/keyframe/cellset.py): a path and its digest, the cell identity, a clash's
words, the common start on the loop's ticks, what a member says of its cell set. The whole
(members planning, exchanging and checking on loopback) is test_cell_plan.py's."""

from __future__ import annotations

import math
import threading
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from occ.controllers.keyframe.cellset import (
    CellCheck,
    CellRole,
    first_tick,
    previewed,
    start_time,
)
from occ.errors import CommandError
from occ.kinematics.cellpaths import ArmPath, Clash, _links, cell_identity, path_digest

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
    }  # fmt: skip
    role.cset = SimpleNamespace(digest="d" * 64)  # type: ignore[assignment]
    role.paths = {"arm2": object(), "arm1": object()}  # type: ignore[dict-item]
    role.checked = CellCheck(SimpleNamespace(id=3), "i" * 64, {})  # type: ignore[arg-type]
    role.running = "r" * 64
    assert role.stats() == {
        "cell_set": "d" * 64, "cell_paths": ["arm1", "arm2"], "cell_checked": "i" * 64,
        "cell_running": "r" * 64,
    }  # fmt: skip
    role.install(None)  # another set: nothing of the cell's kept
    assert role.stats() == {
        "cell_set": None, "cell_paths": [], "cell_checked": None, "cell_running": "r" * 64,
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
