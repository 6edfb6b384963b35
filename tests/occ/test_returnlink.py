"""The master's view of the slave's tip stream (occ/haptics/returnlink.py), the link alone: every
sample judged (a late or repeated one never moves the tool), the status a user sees (none,
fresh, stale, lost) and what it means for the fixture force, the metadata parsed (a malformed
map or force is refused and counted, never used), the counters and the snapshot in GetStats.

The master's controller built on it, in simulated time: tests/occ/test_return_channel.py."""

from __future__ import annotations

import math
from typing import Any

import pytest

from occ.haptics.returnlink import ReturnLink
from occ.samples import PoseSample

P = 0.002  # the shipped tip stream: 500 Hz
MAP = "0.1,0,0,0,0.1,0,0,0,0.1"


def tip(
    seq: int | None,
    pos: tuple[float, float, float] = (1.0, 2.0, 3.0),
    *,
    q: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0),
    kind: str = "POSITION",
    t_sample: float = 0.0,
    **meta: str,
) -> PoseSample:
    return PoseSample(
        "slave", None, "SlaveTip", pos, q, kind=kind, seq=seq, t_sample=t_sample, meta=meta
    )


def feed(link: ReturnLink, first: int, n: int, t0: float, force_n: str = "") -> float:
    """``n`` samples from sequence number ``first``, one a period from ``t0`` (with
    ``force_n`` when given), each followed by the master's check of the tick; the time of the
    last one."""
    t = t0
    for i in range(n):
        t = t0 + i * P
        pos = (float(first + i), 0.0, 0.0)
        s = tip(first + i, pos, force_n=force_n) if force_n else tip(first + i, pos)
        assert link.on_sample(s, t, t)
        link.check(t)
    return t


# ------------------------------------------------------------------ the defaults
def test_the_default_link_watches_a_500_hz_stream_loses_at_three_and_dies_at_100_ms() -> None:
    link = ReturnLink("slave")
    mon = link.monitor
    assert link.interface == "slave"
    assert mon.period_s == P and mon.max_consecutive == 2 and mon.grace_s == 0.1
    assert mon.deadline_s == pytest.approx(3 * P + P / 4)
    # before any tip: none, nothing shown, nothing to count
    assert link.status == "none" and link.tip is None and link.force is None
    assert link.quaternion == (0.0, 0.0, 0.0, 1.0) and link.linear is None
    assert not link.new and not link.following and link.seq is None and link.slave_state == ""
    assert math.isnan(link.t_tip)
    st = link.stats(1.0)
    assert st["status"] == "none" and st["age_ms"] is None and st["tip_mm"] is None
    assert st["force_n"] is None and st["map"] is None and st["seq"] is None


# ------------------------------------------------------------------ samples
def test_an_accepted_tip_is_the_tool_with_everything_it_carries() -> None:
    link = ReturnLink("slave")
    s = tip(
        7, (10.0, -20.0, 30.5), q=(0.0, 0.0, 0.6, 0.8), map=MAP, force_n="1.5,-2,0.25",
        following="1", state="RUNNING",
    )  # fmt: skip
    assert link.on_sample(s, 0.5, 0.5) is True
    assert link.tip == (10.0, -20.0, 30.5) and link.quaternion == (0.0, 0.0, 0.6, 0.8)
    assert link.t_tip == 0.5 and link.seq == 7 and link.new
    assert link.force == (1.5, -2.0, 0.25)
    assert link.linear == ((0.1, 0.0, 0.0), (0.0, 0.1, 0.0), (0.0, 0.0, 0.1))
    assert link.following and link.slave_state == "RUNNING"
    assert link.samples == 1 and link.refused == 0 and link.bad_metadata == 0
    assert link.status == "fresh" and link.last_error == ""
    assert link.monitor.received == 1 and link.monitor.accepted == 1


def test_what_the_slave_does_not_send_has_its_default() -> None:
    """No ``following``: it follows (a slave before the field existed); no ``state``: empty;
    no ``force_n``: no force (a force sent before is not kept); no ``map``: the last one."""
    link = ReturnLink("slave")
    assert link.on_sample(tip(1, map=MAP, force_n="1,2,3", following="0", state="STOPPED"), 0, 0)
    assert link.force == (1.0, 2.0, 3.0) and not link.following
    assert link.slave_state == "STOPPED"
    assert link.on_sample(tip(2), P, P)
    assert link.force is None and link.following and link.slave_state == ""
    assert link.linear == ((0.1, 0.0, 0.0), (0.0, 0.1, 0.0), (0.0, 0.0, 0.1))
    assert link.on_sample(tip(3, following="yes"), 2 * P, 2 * P)
    assert not link.following  # only "1" means following


def test_a_transform_tip_keeps_the_orientation_a_position_gave() -> None:
    link = ReturnLink("slave")
    link.on_sample(tip(1, q=(0.0, 0.0, 0.6, 0.8)), 0.0, 0.0)
    assert link.on_sample(tip(2, (4.0, 5.0, 6.0), q=(1.0, 0.0, 0.0, 0.0), kind="TRANSFORM"), P, P)
    assert link.tip == (4.0, 5.0, 6.0) and link.quaternion == (0.0, 0.0, 0.6, 0.8)


@pytest.mark.parametrize("seq", [5, 3])  # a repeated number, an older one
def test_a_repeated_or_older_tip_is_refused_and_never_moves_the_tool(seq: int) -> None:
    link = ReturnLink("slave")
    link.on_sample(tip(4, (1.0, 1.0, 1.0)), 0.0, 0.0)
    link.on_sample(tip(5, (2.0, 2.0, 2.0)), P, P)
    link.new = False
    assert link.on_sample(tip(seq, (9.0, 9.0, 9.0), force_n="5,5,5"), 2 * P, 2 * P) is False
    assert link.tip == (2.0, 2.0, 2.0) and link.seq == 5 and link.force is None
    assert link.refused == 1 and link.samples == 2 and not link.new and link.t_tip == P
    assert link.stats(2 * P)["refused"] == 1


@pytest.mark.parametrize("pos", [(math.nan, 0.0, 0.0), (0.0, math.inf, 0.0), (0.0, 0.0, -math.inf)])
def test_a_tip_that_is_not_a_point_is_refused_and_counted(pos: tuple[float, ...]) -> None:
    link = ReturnLink("slave")
    link.on_sample(tip(1, (1.0, 2.0, 3.0), q=(0.0, 0.0, 0.6, 0.8)), 0.0, 0.0)
    link.new = False
    assert link.on_sample(tip(2, pos, map=MAP, force_n="1,2,3"), P, P) is False  # type: ignore[arg-type]
    assert link.tip == (1.0, 2.0, 3.0) and not link.new and link.samples == 1
    assert link.bad_metadata == 1 and link.refused == 0 and link.force is None
    assert link.last_error.startswith("seq 2: tip (") and "is not a point" in link.last_error
    assert link.linear is None  # nothing else of the sample was taken
    st = link.stats(P)
    assert st["bad"] == 1 and st["last_error"] == link.last_error


# ------------------------------------------------------------------ the map
@pytest.mark.parametrize(
    "bad",
    [
        "0.1,0,0,0,0.1,0,0,0",  # 8 numbers
        "0.1,0,0,0,0.1,0,0,0,x",  # not numbers
        "0.1,0,0,0,0.1,0,0,0,-0.1",  # a mirror: no rotation
        "0.1,0,0,0,0.2,0,0,0,0.1",  # not one scale
        "nan,0,0,0,0.1,0,0,0,0.1",
    ],
)
def test_a_malformed_map_is_refused_counted_and_the_last_good_one_kept(bad: str) -> None:
    link = ReturnLink("slave")
    assert link.on_sample(tip(1, (1.0, 1.0, 1.0), map=MAP), 0.0, 0.0)
    good = link.linear
    link.new = False
    assert link.on_sample(tip(2, (2.0, 2.0, 2.0), map=bad, force_n="1,0,0"), P, P) is False
    assert link.linear == good and link.tip == (1.0, 1.0, 1.0) and not link.new
    assert link.force is None and link.samples == 1
    assert link.bad_metadata == 1 and link.last_error.startswith("seq 2: map")
    # the same bad map again is refused again (never taken as known), a good one taken
    assert not link.on_sample(tip(3, map=bad), 2 * P, 2 * P)
    assert link.bad_metadata == 2
    assert link.on_sample(tip(4, map="0,-0.2,0,0.2,0,0,0,0,0.2"), 3 * P, 3 * P)
    assert link.linear == ((0.0, -0.2, 0.0), (0.2, 0.0, 0.0), (0.0, 0.0, 0.2))


def test_a_map_is_parsed_once_while_its_text_is_the_same(monkeypatch: pytest.MonkeyPatch) -> None:
    import occ.haptics.returnlink as rl

    calls: list[str] = []
    real = rl.parse_linear

    def counting(text: str) -> Any:
        calls.append(text)
        return real(text)

    monkeypatch.setattr(rl, "parse_linear", counting)
    link = ReturnLink("slave")
    other = "0.2,0,0,0,0.2,0,0,0,0.2"
    for i, m in enumerate((MAP, MAP, MAP, other, other, MAP)):
        assert link.on_sample(tip(i + 1, map=m), i * P, i * P)
    assert calls == [MAP, other, MAP]
    assert link.linear == ((0.1, 0.0, 0.0), (0.0, 0.1, 0.0), (0.0, 0.0, 0.1))
    assert link.on_sample(tip(7, map=""), 6 * P, 6 * P)  # an empty map: the last one kept
    assert calls == [MAP, other, MAP] and link.linear is not None


# ------------------------------------------------------------------ the force
@pytest.mark.parametrize(
    "bad",
    ["1,2", "1,2,3,4", "a,b,c", "1;2;3", "", "nan,0,0", "0,inf,0", "0,0,-inf", "1,2,3" + "0" * 60],
)
def test_a_malformed_force_is_refused_counted_and_never_displayed(bad: str) -> None:
    link = ReturnLink("slave")
    assert link.on_sample(tip(1, (1.0, 1.0, 1.0), force_n="0.5,0,0"), 0.0, 0.0)
    link.new = False
    ok = bad.startswith("1,2,3") and len(bad) > 40  # a long but valid number: taken
    assert link.on_sample(tip(2, (2.0, 2.0, 2.0), force_n=bad), P, P) is ok
    if ok:
        assert link.force == (1.0, 2.0, float("3" + "0" * 60))
        return
    assert link.force == (0.5, 0.0, 0.0) and link.tip == (1.0, 1.0, 1.0) and not link.new
    assert link.bad_metadata == 1 and link.samples == 1
    assert link.last_error == f"seq 2: force_n {bad[:40]!r} is not 3 numbers"


def test_a_malformed_force_text_is_quoted_at_most_40_characters() -> None:
    link = ReturnLink("slave")
    bad = "x" * 100
    assert not link.on_sample(tip(1, force_n=bad), 0.0, 0.0)
    assert link.last_error == f"seq 1: force_n {'x' * 40!r} is not 3 numbers"


# ------------------------------------------------------------------ fresh, stale, lost
def test_a_silent_slave_is_fresh_then_stale_at_the_deadline_then_lost_at_the_grace() -> None:
    link = ReturnLink("slave")
    t = feed(link, 1, 5, 0.0, force_n="1,0,0")
    assert link.status == "fresh"
    # 6 ms after the last tip: still fresh; 7 ms: stale (held, the tip kept and shown)
    assert link.check(t + 0.006) is None and link.status == "fresh"
    ev = link.check(t + 0.007)
    assert ev is not None and ev.kind == "hold" and link.status == "stale"
    assert link.tip == (5.0, 0.0, 0.0) and link.force == (1.0, 0.0, 0.0) and not link.lost
    assert link.stats(t + 0.007)["late"] == 1 and link.losses == 0
    # past the grace: lost, the cause kept, counted once
    assert link.check(t + 0.1) is None and link.status == "stale"
    ev = link.check(t + 0.101)
    assert ev is not None and ev.kind == "latch" and link.status == "lost" and link.lost
    assert link.losses == 1 and link.lost_cause == ev.cause and "no packet for" in ev.cause
    assert link.check(t + 0.5) is None and link.losses == 1


def test_a_late_tip_that_comes_back_is_fresh_again_and_not_a_loss() -> None:
    link = ReturnLink("slave")
    t = feed(link, 1, 3, 0.0)
    link.check(t + 0.01)
    assert link.status == "stale"
    t2 = t + 0.012
    assert link.on_sample(tip(4), t2, t2)  # the next number: nothing missing
    ev = link.check(t2)
    assert ev is not None and ev.kind == "resume"
    assert link.status == "fresh" and link.losses == 0 and link.recoveries == 0


def test_three_missing_tips_are_a_loss_the_next_one_re_arms_it() -> None:
    link = ReturnLink("slave")
    t = feed(link, 1, 3, 0.0)
    # two missing: a gap, not a loss
    t += 3 * P
    assert link.on_sample(tip(6), t, t) and link.check(t) is None and link.status == "fresh"
    # three missing: the sample that proves it latches the link (lost at once, before the
    # tick's check marks it)
    t += 4 * P
    assert link.on_sample(tip(10, (10.0, 0.0, 0.0)), t, t)
    assert link.status == "lost" and not link.lost
    ev = link.check(t)
    assert ev is not None and ev.kind == "latch" and "3 consecutive packets lost" in ev.cause
    assert link.lost and link.losses == 1 and link.status == "lost"
    assert link.stats(t)["lost_total"] == 5
    # the next sample re-arms it from its own number on (the numbers may start over)
    t += P
    assert link.on_sample(tip(1, (11.0, 0.0, 0.0)), t, t)
    assert not link.lost and link.recoveries == 1 and link.status == "fresh"
    assert link.tip == (11.0, 0.0, 0.0) and link.monitor.trips == 1
    assert link.check(t) is None
    st = link.stats(t)
    assert st["losses"] == 1 and st["recoveries"] == 1 and st["lost_cause"] == link.lost_cause
    # and it is watched again: silence after it is late, then lost, as before
    assert link.check(t + 0.007) is not None and link.status == "stale"


def test_a_refused_sample_after_a_loss_leaves_it_lost() -> None:
    """A sample that comes back but is not a point re-arms the monitor and is refused: the
    link stays lost (no recovery) until an accepted one."""
    link = ReturnLink("slave")
    t = feed(link, 1, 3, 0.0)
    link.check(t + 0.2)
    assert link.lost
    assert not link.on_sample(tip(4, (math.nan, 0.0, 0.0)), t + 0.2, t + 0.2)
    assert link.lost and link.recoveries == 0 and link.status == "lost"
    assert link.on_sample(tip(5), t + 0.202, t + 0.202)
    assert not link.lost and link.recoveries == 1 and link.status == "fresh"


def test_arm_watches_a_slave_that_never_sent_and_clears_a_loss() -> None:
    link = ReturnLink("slave")
    link.arm(1.0)
    assert link.status == "none"
    assert link.check(1.0065) is None
    assert link.check(1.007).kind == "hold"  # type: ignore[union-attr]
    ev = link.check(1.101)
    assert ev is not None and ev.kind == "latch" and link.status == "lost" and link.losses == 1
    # the master enters RUNNING again: the link is no longer lost, watched from then on
    link.arm(2.0)
    assert not link.lost and not link.monitor.tripped and link.status == "none"
    assert link.check(2.006) is None
    assert link.check(2.101) is not None and link.lost


def test_an_unnumbered_tip_is_judged_by_its_timestamp() -> None:
    """A v1 slave (no sequence numbers): the sender's timestamps tell a loss; a repeated
    timestamp is refused; a timestamp of 0 (not set) is no timestamp."""
    link = ReturnLink("slave")
    for i in range(3):
        assert link.on_sample(tip(None, t_sample=100.0 + i * P), i * P, i * P)
    assert not link.on_sample(tip(None, t_sample=100.0 + 2 * P), 3 * P, 3 * P)
    assert link.refused == 1
    assert link.on_sample(tip(None, t_sample=100.0 + 6 * P), 4 * P, 4 * P)
    assert link.monitor.tripped and link.status == "lost"  # 3 missing, told by the timestamps
    link2 = ReturnLink("slave")
    for i in range(4):  # no timestamp: every one taken, none told missing
        assert link2.on_sample(tip(None, t_sample=0.0), i * P, i * P)
    assert link2.samples == 4 and link2.monitor.lost_total == 0


# ------------------------------------------------------------------ the slave's energy (issue 37)
@pytest.mark.req("SR-FORCE-1")
@pytest.mark.parametrize("bad", ["x", "nan", "-1e-3", "inf", ""])
def test_the_slaves_energy_is_read_and_one_that_is_no_energy_refuses_its_sample(bad: str) -> None:
    """``energy_j``: the slave port's energy in (J, cumulative) for the master's passivity
    budget; one that is not a finite, non-negative number refuses the whole sample (counted),
    as a malformed force does: a budget is never taken from a sample that is not sound."""
    link = ReturnLink("slave")
    assert link.on_sample(tip(1, force_n="1,2,3", energy_j="0.00125"), 0.0, 0.0)
    assert link.energy == 0.00125 and link.stats(0.0)["energy_mj"] == 1.25
    assert not link.on_sample(tip(2, force_n="1,2,3", energy_j=bad), P, P)
    assert link.bad_metadata == 1 and "energy_j" in link.last_error
    assert link.energy == 0.00125  # the last sound one
    assert link.on_sample(tip(3, force_n="1,2,3"), 2 * P, 2 * P)
    assert link.energy is None  # a slave that sends none: none


@pytest.mark.parametrize(
    ("key", "why"), [("torque_nm", "is not 3 numbers"), ("energy_j", "is not an energy")]
)
def test_samples_refused_for_their_torque_or_energy_are_lost_at_the_grace_counted(
    key: str, why: str
) -> None:
    """A slave whose samples keep coming with a torque or an energy that is not one: each
    refused and counted, and past the grace (100 ms after the last usable tip) the link is
    lost, the cause naming how many were refused and the last one's fault."""
    link = ReturnLink("slave")
    assert link.on_sample(tip(1), 0.0, 0.0)
    link.check(0.0)
    event = None
    seq = 1
    while event is None and seq < 200:
        seq += 1
        t = (seq - 1) * P
        assert not link.on_sample(tip(seq, force_n="1,2,3", **{key: "x"}), t, t)
        event = link.check(t)
    assert event is not None and event.kind == "latch" and link.status == "lost"
    assert seq == 52 and link.bad_metadata == 51  # 102 ms after the last usable tip
    assert event.cause.endswith(f": 51 samples refused, the last: seq 52: {key} 'x' {why}")


def test_the_slaves_energy_is_shown_in_millijoules_to_four_places() -> None:
    link = ReturnLink("slave")
    assert link.on_sample(tip(1, force_n="1,2,3", energy_j="0.0012345678"), 0.0, 0.0)
    assert link.stats(0.0)["energy_mj"] == 1.2346


@pytest.mark.parametrize("bad", ["1,2", "1,2,3,4", "1,x,3", "1,nan,3", "inf,0,0", ""])
def test_the_slaves_torque_is_read_and_a_malformed_one_refuses_its_sample(bad: str) -> None:
    """``torque_nm`` (a slave with a 6-axis sensor, issue 37): three finite numbers in N m,
    kept with the tip and shown in the snapshot to five places; anything else refuses the
    whole sample (counted, quoted at most 40 characters), the last sound torque kept."""
    link = ReturnLink("slave")
    assert link.torque is None and link.stats(0.0)["torque_nm"] is None
    assert link.on_sample(tip(1, force_n="1,2,3", torque_nm="0.0123456,-0.5,2"), 0.0, 0.0)
    assert link.torque == (0.0123456, -0.5, 2.0)
    assert link.stats(0.0)["torque_nm"] == [0.01235, -0.5, 2.0]
    assert not link.on_sample(tip(2, force_n="1,2,3", torque_nm=bad), P, P)
    assert link.bad_metadata == 1
    assert link.last_error == f"seq 2: torque_nm {bad[:40]!r} is not 3 numbers"
    assert link.torque == (0.0123456, -0.5, 2.0)
    assert link.on_sample(tip(3, force_n="1,2,3"), 2 * P, 2 * P)
    assert link.torque is None and link.stats(2 * P)["torque_nm"] is None


# ------------------------------------------------------------------ the snapshot
def test_the_snapshot_shows_the_tip_its_age_and_the_counters() -> None:
    link = ReturnLink("slave2")
    link.on_sample(
        tip(3, (1.23456, -2.0, 3.0001), map=MAP, force_n="0.123456,-1,2", state="RUNNING"),
        1.0,
        1.0,
    )
    st = link.stats(1.00125)
    assert st == {
        "interface": "slave2",
        "status": "fresh",
        "age_ms": 1.2,
        "tip_mm": [1.235, -2.0, 3.0],
        "force_n": [0.1235, -1.0, 2.0],
        "torque_nm": None,  # a 3-axis force (tests/occ/test_six_axis.py has one)
        "energy_mj": None,
        "following": True,
        "slave_state": "RUNNING",
        "seq": 3,
        "map": [[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]],
        "samples": 1,
        "refused": 0,
        "bad": 0,
        "last_error": "",
        "late": 0,
        "lost_total": 0,
        "losses": 0,
        "recoveries": 0,
        "lost_cause": "",
    }
    # not checked (the master not RUNNING): a tip older than the deadline shows stale
    assert link.stats(1.0065)["status"] == "fresh"
    assert link.stats(1.0066)["status"] == "stale"
    assert link.stats(1.0066)["age_ms"] == 6.6
    link.check(1.2)
    assert link.stats(1.2)["status"] == "lost"


# ------------------------------------------------------------------ samples that come refused
def test_samples_that_keep_coming_refused_are_a_late_then_a_lost_tip() -> None:
    """The monitor hears every one (its numbers accounted, never a loss), but no usable tip
    comes: stale past the deadline from the last usable tip, lost past the grace, once."""
    link = ReturnLink("slave")
    t = feed(link, 1, 3, 0.0, force_n="2,0,0")
    seq = 4
    events = []
    for k in range(1, 60):  # a malformed force every 2 ms
        now = t + k * P
        assert not link.on_sample(tip(seq, force_n="x"), now, now)
        seq += 1
        ev = link.check(now)
        if ev is not None:
            events.append(ev)
        if k * P <= 0.0065:
            assert link.status == "fresh" and not link.unusable
        elif k * P <= 0.1:
            assert link.status == "stale" and link.unusable and not link.lost
    assert link.monitor.accepted == 62 and link.monitor.lost_total == 0
    assert not link.monitor.holding and not link.monitor.tripped
    # 59 x 2 ms: lost at the first check past 100 ms (k = 51: 102 ms)
    (ev,) = events
    assert ev.kind == "latch" and ev.source == "content" and ev.time == t + 51 * P
    assert ev.since_last_good_s == pytest.approx(0.102)
    assert ev.run == int((0.102 - 0.0005) / P) == 50
    assert ev.cause == (
        "no usable tip for 102.00 ms (limit 100.0 ms): 51 samples refused, the last: "
        "seq 54: force_n 'x' is not 3 numbers"
    )
    assert link.lost and link.losses == 1 and link.lost_cause == ev.cause
    assert link.status == "lost" and not link.unusable
    assert link.force == (2.0, 0.0, 0.0) and link.tip == (3.0, 0.0, 0.0)  # nothing taken
    # a usable tip: back (re-armed), the count of refused ones starts again
    now = t + 60 * P
    assert link.on_sample(tip(seq, force_n="1,0,0"), now, now)
    assert not link.lost and link.recoveries == 1 and link.status == "fresh"
    assert link.check(now) is None and link.status == "fresh"
    for k in range(1, 52):
        seq += 1
        assert not link.on_sample(tip(seq, map="1"), now + k * P, now + k * P)
        link.check(now + k * P)
    assert link.lost and link.losses == 2 and link.recoveries == 1
    assert "102.00 ms" in link.lost_cause and "ms): 51 samples refused" in link.lost_cause
    assert f"the last: seq {seq}: map" in link.lost_cause


def test_a_refused_sample_now_and_then_leaves_the_tip_fresh() -> None:
    link = ReturnLink("slave")
    t = 0.0
    for seq in range(1, 200):
        t = seq * P
        good = seq % 3 != 0
        assert link.on_sample(tip(seq, force_n="1,0,0" if good else "?"), t, t) is good
        assert link.check(t) is None and link.status == "fresh"
    assert link.bad_metadata == 66 and link.losses == 0


def test_before_any_usable_tip_or_arm_refused_samples_start_no_deadline() -> None:
    """A master not yet RUNNING has not armed the link: nothing to be late for."""
    link = ReturnLink("slave")
    for seq in range(1, 100):
        assert not link.on_sample(tip(seq, map="bad"), seq * P, seq * P)
        assert link.check(seq * P) is None
    assert link.status == "none" and not link.lost and not link.unusable


def test_after_arm_a_slave_sending_only_refused_samples_is_lost_at_the_grace() -> None:
    link = ReturnLink("slave")
    link.unusable = True
    link.arm(1.0)
    assert not link.unusable
    events = []
    for k in range(1, 52):
        now = 1.0005 + k * P  # half a period off the grace
        link.on_sample(tip(k, (math.nan, 0.0, 0.0)), now, now)
        ev = link.check(now)
        if ev is not None:
            events.append(ev.kind)
        assert link.lost == (k >= 50)  # 100.5 ms after arm()
    assert events == ["latch"]
    assert link.lost and link.status == "lost" and "tip (nan, 0.0, 0.0)" in link.lost_cause
    assert "(limit 100.0 ms): 50 samples refused, the last: seq 50: tip" in link.lost_cause
    # then silence too: the monitor latches, but the link is lost already (told once)
    assert link.check(2.0) is None and link.losses == 1 and link.monitor.tripped
    assert "tip (nan, 0.0, 0.0)" in link.lost_cause
    link.arm(3.0)
    assert not link.lost and link.status == "none"


def test_a_silent_link_is_the_monitors_to_tell_not_told_twice() -> None:
    link = ReturnLink("slave")
    t = feed(link, 1, 3, 0.0)
    kinds = [e.kind for k in range(1, 80) if (e := link.check(t + k * 0.002)) is not None]
    assert kinds == ["hold", "latch"] and link.losses == 1
    assert "no packet for" in link.lost_cause


# ------------------------------------------------------------------ parameters and counters
def test_the_loss_rule_and_the_grace_are_the_links_own() -> None:
    link = ReturnLink("slave", period_s=0.001, max_consecutive=0, grace_s=0.05)
    mon = link.monitor
    assert (mon.period_s, mon.max_consecutive, mon.grace_s) == (0.001, 0, 0.05)
    assert link.on_sample(tip(1), 0.0, 0.0)
    assert link.on_sample(tip(3), 0.002, 0.002)  # one number missing: a loss here
    assert link.status == "lost"
    link.arm(1.0)
    assert link.check(1.0495) is not None and not link.lost  # held at the deadline
    ev = link.check(1.0505)
    assert ev is not None and ev.kind == "latch" and link.lost  # lost past its 50 ms grace


def test_every_refusal_loss_and_recovery_is_counted() -> None:
    link = ReturnLink("slave")
    assert link.on_sample(tip(1), 0.0, 0.0)
    for _ in range(2):
        assert not link.on_sample(tip(1), P, P)
    assert link.refused == 2
    for seq in (2, 3):
        assert not link.on_sample(tip(seq, (math.inf, 0.0, 0.0)), P, P)
    for seq in (4, 5):
        assert not link.on_sample(tip(seq, force_n="1,2"), P, P)
    for seq in (6, 7):
        assert not link.on_sample(tip(seq, map="1,2"), P, P)
    assert link.bad_metadata == 6 and link.samples == 1
    t = P
    seq = 8
    for n in (1, 2):
        t += 0.2
        link.check(t)  # silent past the grace: lost
        assert link.losses == n and link.lost
        assert link.on_sample(tip(seq), t, t)  # back
        seq += 1
        assert link.recoveries == n and not link.lost
    st = link.stats(t)
    assert (st["refused"], st["bad"], st["losses"], st["recoveries"]) == (2, 6, 2, 2)


def test_the_snapshot_before_any_tip_says_not_following() -> None:
    st = ReturnLink("slave").stats(0.0)
    assert st["following"] is False and st["slave_state"] == "" and st["samples"] == 0
    assert st["lost_cause"] == "" and st["last_error"] == "" and st["late"] == 0


def test_a_tip_exactly_at_the_deadline_is_still_fresh_in_the_snapshot() -> None:
    link = ReturnLink("slave")
    link.on_sample(tip(1), 0.0, 0.0)
    d = link.monitor.deadline_s
    assert link.stats(d)["status"] == "fresh"
    assert link.stats(math.nextafter(d, 1.0))["status"] == "stale"


def test_small_timestamps_of_an_unnumbered_tip_are_timestamps_too() -> None:
    """A v1 sender whose clock started at 0 (a simulator): any timestamp above 0 counts."""
    link = ReturnLink("slave")
    for i in range(3):
        assert link.on_sample(tip(None, t_sample=0.1 + i * P), i * P, i * P)
    assert link.on_sample(tip(None, t_sample=0.1 + 6 * P), 3 * P, 3 * P)
    assert link.monitor.tripped and link.monitor.lost_total == 3


def test_a_link_refusing_samples_is_stale_only_past_the_deadline() -> None:
    link = ReturnLink("slave")
    link.on_sample(tip(1), 0.0, 0.0)
    d = link.monitor.deadline_s
    assert not link.on_sample(tip(2, force_n="?"), P, P)
    link.check(d)  # exactly the deadline after the last usable tip: still fresh
    assert link.status == "fresh" and not link.unusable
    link.check(math.nextafter(d, 1.0))
    assert link.status == "stale" and link.unusable


def test_any_first_map_is_parsed_whatever_its_text() -> None:
    link = ReturnLink("slave")
    assert not link.on_sample(tip(1, map="XXXX"), 0.0, 0.0)
    assert link.bad_metadata == 1 and link.linear is None
