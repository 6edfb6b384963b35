"""Safety logic: state machine (exhaustive), watchdog, loss monitor (exact tick timing)."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from occ.clock import SimClock
from occ.errors import StateError
from occ.safety import (
    EVENTS,
    TRANSITIONS,
    LossEvent,
    LossMonitor,
    RobotState,
    StateMachine,
    Watchdog,
)

S = RobotState

# -- state machine -----------------------------------------------------------------------------

# The table of the specification, typed independently of the implementation.
# "." = refused, "=" = accepted without change.
SPEC = """
          configure enable  run      hold     stop     disable fault  estop  reset  shutdown
INIT      READY     .       .        .        .        .       FAULT  ESTOP  .      SHUTDOWN
READY     .         ENABLED .        .        .        .       FAULT  ESTOP  .      SHUTDOWN
ENABLED   .         .       RUNNING  .        STOPPED  READY   FAULT  ESTOP  .      SHUTDOWN
RUNNING   .         .       .        ENABLED  STOPPED  READY   FAULT  ESTOP  .      SHUTDOWN
STOPPED   .         ENABLED RUNNING  .        =        READY   FAULT  ESTOP  .      SHUTDOWN
FAULT     .         .       .        .        .        .       =      ESTOP  READY  SHUTDOWN
ESTOP     .         .       .        .        .        .       =      =      READY  SHUTDOWN
SHUTDOWN  .         .       .        .        .        .       .      .      .      =
"""


def _parse(table: str) -> dict[tuple[RobotState, str], RobotState | None]:
    lines = [line.split() for line in table.strip().splitlines()]
    events = lines[0]
    out: dict[tuple[RobotState, str], RobotState | None] = {}
    for row in lines[1:]:
        state = RobotState[row[0]]
        for event, cell in zip(events, [c.rstrip("(1)") for c in row[1:]], strict=True):
            out[(state, event)] = None if cell == "." else state if cell == "=" else S[cell]
    return out


EXPECTED = _parse(SPEC)


def test_spec_covers_every_pair_and_matches_docstring() -> None:
    assert set(EXPECTED) == {(s, e) for s in S for e in EVENTS}
    doc = StateMachine.__doc__ or ""
    start = doc.index("configure enable")
    block = "\n".join(line.strip() for line in doc[start:].split("\n\n")[0].splitlines())
    assert _parse(block) == EXPECTED


@pytest.mark.parametrize(("state", "event"), sorted(EXPECTED, key=lambda p: (p[0].value, p[1])))
def test_every_state_event_pair(state: RobotState, event: str) -> None:
    clock = SimClock(start=5.0, wall_epoch=1000.0)
    sm = StateMachine(state, clock=clock)
    calls: list[tuple[RobotState, RobotState, str, str, float]] = []
    sm.add_listener(lambda *args: calls.append(args))
    expected = EXPECTED[(state, event)]
    if expected is None:
        assert not sm.can(event)
        with pytest.raises(StateError) as info:
            sm.request(event, "test")
        assert sm.state is state
        assert calls == []
        message = str(info.value)
        assert state.value in message and "allowed from" in message
        for allowed in sm.allowed_events():
            assert allowed in message
    else:
        assert sm.can(event)
        t = sm.request(event, "because")
        assert sm.state is expected
        assert (t.old, t.new, t.event, t.reason, t.time) == (
            state,
            expected,
            event,
            "because",
            1005.0,
        )
        if expected is state:
            assert not t.changed and calls == []
        else:
            assert t.changed
            assert calls == [(state, expected, event, "because", 1005.0)]
    assert TRANSITIONS.get((state, event)) is expected


def test_typical_lifecycle_and_latching() -> None:
    sm = StateMachine()
    for event, state in [
        ("configure", S.READY),
        ("Enable", S.ENABLED),
        ("RUN", S.RUNNING),
        ("stop", S.STOPPED),
        ("run", S.RUNNING),
        ("hold", S.ENABLED),
        ("run", S.RUNNING),
        ("fault", S.FAULT),
    ]:
        sm.request(event, "")
        assert sm.state is state
    with pytest.raises(StateError, match="allowed from FAULT: fault, estop, reset, shutdown"):
        sm.request("run")
    assert sm.try_request("enable") is None
    sm.request("e-stop", "button")
    assert sm.state is S.ESTOP
    sm.request("fault", "late fault")  # ESTOP outranks FAULT
    assert sm.state is S.ESTOP
    sm.request("reset", "operator")
    assert sm.state is S.READY
    sm.request("shutdown")
    sm.request("shutdown")  # idempotent
    assert sm.state is S.SHUTDOWN
    with pytest.raises(StateError, match="allowed from SHUTDOWN: shutdown"):
        sm.request("reset")


def test_unknown_event_is_a_value_error() -> None:
    sm = StateMachine()
    with pytest.raises(ValueError, match="unknown event"):
        sm.request("jump")
    assert sm.state is S.INIT


def test_failing_listener_does_not_block_transition() -> None:
    sm = StateMachine(S.RUNNING)
    seen: list[RobotState] = []

    def bad(*_args: object) -> None:
        raise RuntimeError("listener bug")

    sm.add_listener(bad)
    sm.add_listener(lambda old, new, *_: seen.append(new))
    sm.request("estop", "button")
    assert sm.state is S.ESTOP
    assert seen == [S.ESTOP]
    sm.remove_listener(bad)


# -- watchdog ----------------------------------------------------------------------------------

B = 0.001


def _wd(**kw: object) -> tuple[Watchdog, list[tuple[str, int]], list[tuple[str, str]]]:
    alerts: list[tuple[str, int]] = []
    stops: list[tuple[str, str]] = []
    wd = Watchdog(
        B,
        on_alert=lambda r, n: alerts.append((r, n)),
        on_stop=lambda r, p: stops.append((r, p)),
        **kw,  # type: ignore[arg-type]
    )
    return wd, alerts, stops


def test_watchdog_alerts_are_rate_limited_with_counts() -> None:
    wd, alerts, stops = _wd(stop_run=1000, alert_interval_s=0.1)
    for _ in range(50):  # 50 ms of overruns
        assert wd.feed(B, 1.2 * B)
    assert len(alerts) == 1
    for _ in range(60):  # another 60 ms: crosses the 100 ms interval once
        wd.feed(B, 1.2 * B)
    assert len(alerts) == 2
    assert alerts[1][1] == 101  # total overruns when the second alert fired
    assert "101 total, 99 alerts suppressed" in alerts[1][0]
    assert stops == []


def test_watchdog_alert_run() -> None:
    wd, alerts, _ = _wd(alert_run=3, stop_run=10)
    wd.feed(B, 2 * B)
    wd.feed(B, 2 * B)
    assert alerts == []
    wd.feed(B, 2 * B)
    assert len(alerts) == 1 and "3 consecutive" in alerts[0][0]


def test_watchdog_stop_run_latches_until_reset() -> None:
    wd, _, stops = _wd(stop_run=5, policy="hold")
    for _ in range(4):
        wd.feed(B, 2 * B)
    wd.feed(B, 0.5 * B)  # run broken
    for _ in range(4):
        wd.feed(B, 2 * B)
    assert stops == []
    wd.feed(B, 2 * B)
    assert len(stops) == 1 and stops[0][1] == "hold"
    assert "5 consecutive overruns" in stops[0][0]
    for _ in range(20):
        wd.feed(B, 2 * B)
    assert len(stops) == 1 and wd.stopped
    wd.reset()
    assert not wd.stopped and wd.consecutive == 0
    for _ in range(5):
        wd.feed(B, 2 * B)
    assert len(stops) == 2
    assert wd.counters()["stops"] == 2


def test_watchdog_period_overrun_and_hard_gap() -> None:
    wd, alerts, stops = _wd(stop_run=100)
    assert not wd.feed(None, 0.1 * B)  # first tick has no period
    assert not wd.feed(1.9 * B, 0.1 * B)
    assert wd.feed(2.5 * B, 0.1 * B)  # a missed deadline
    assert "period 2.500 ms > limit 2.000 ms" in alerts[0][0]
    assert stops == []
    wd.feed(0.011, 0.1 * B)  # one gap past the 10 ms hard limit
    assert len(stops) == 1 and "gap of 11.000 ms" in stops[0][0]


def test_watchdog_supervisor_check() -> None:
    wd, _, stops = _wd()
    assert not wd.check(100.0)  # never fed: nothing to judge
    wd.feed(B, 0.1 * B, now=1.000)
    assert not wd.check(1.009)
    assert wd.check(1.0101)
    assert len(stops) == 1 and stops[0][0].startswith("no tick for 10.100 ms")


def test_watchdog_validation() -> None:
    with pytest.raises(ValueError):
        Watchdog(0.0)
    with pytest.raises(ValueError):
        Watchdog(B, policy="panic")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        Watchdog(B, stop_run=0)


# -- loss monitor ------------------------------------------------------------------------------

MS = 1e-3


def run_stream(
    mon: LossMonitor,
    sent: list[bool],
    *,
    first_seq: int = 0,
    delays: list[int] | None = None,
    extra_ticks: int = 20,
    seq: bool = True,
    timestamps: bool = False,
) -> list[tuple[int, LossEvent]]:
    """500 Hz stream (packet i due at tick 2*i ms) checked by a 1 kHz loop.

    ``sent[i]`` False = packet i lost; ``delays[i]`` ticks of delivery delay (0 or 1).
    Each tick drains the packets due, then calls ``check`` -- the loop's order.
    Returns the (tick, event) pairs.
    """
    arrivals: dict[int, list[int]] = {}
    for i, ok in enumerate(sent):
        if ok:
            t = 2 * i + (delays[i] if delays else 0)
            arrivals.setdefault(t, []).append(i)
    events: list[tuple[int, LossEvent]] = []
    for t in range(2 * len(sent) + extra_ticks):
        now = t * MS
        for i in arrivals.get(t, ()):
            mon.on_packet(
                (first_seq + i) & 0xFFFFFFFF if seq else None,
                1000.0 + i * 2 * MS if timestamps else None,
                now,
            )
        event = mon.check(now)
        if event is not None:
            events.append((t, event))
    return events


def test_defaults_match_occ_spec() -> None:
    mon = LossMonitor()
    assert mon.period_s == 0.002 and mon.max_consecutive == 2
    assert mon.deadline_s == pytest.approx(0.0065)


@pytest.mark.parametrize("where", [1, 5, 17, 40])
def test_two_consecutive_lost_never_trips(where: int) -> None:
    sent = [True] * 60
    sent[where] = sent[where + 1] = False
    mon = LossMonitor()
    assert run_stream(mon, sent, extra_ticks=1) == []
    assert mon.lost_total == 2
    assert mon.max_run == 2
    assert mon.trips == 0


@pytest.mark.parametrize("last_good", [0, 3, 10, 25])
def test_three_consecutive_lost_trips_at_exactly_7ms(last_good: int) -> None:
    sent = [True] * 50
    for i in range(last_good + 1, last_good + 4):
        sent[i] = False
    mon = LossMonitor()
    events = run_stream(mon, sent)
    assert len(events) == 1  # reported once, then latched
    tick, event = events[0]
    last_good_tick = 2 * last_good
    # the third lost packet is due at +6 ms; the first 1 kHz tick past it with tolerance is +7
    assert tick == last_good_tick + 7
    assert event.since_last_good_s == pytest.approx(7 * MS)
    assert event.since_last_good_s <= 7 * MS + 1e-12
    assert event.kind == "deadline"
    assert event.run == 3
    assert event.cause == "no packet for 7.0 ms (3 periods)"
    assert mon.tripped and mon.trips == 1
    assert mon.lost_total == 3  # corrected by the sequence number of the next packet


def test_trip_is_latched_until_reset() -> None:
    mon = LossMonitor()
    mon.on_packet(1, None, 0.0)
    assert mon.check(0.006) is None
    assert mon.check(0.007) is not None
    for t in range(8, 30):
        assert mon.check(t * MS) is None
    mon.on_packet(2, None, 0.030)
    assert mon.check(0.030) is None and mon.tripped
    mon.reset()
    assert not mon.tripped
    assert mon.check(1.0) is None  # unarmed until a packet
    mon.on_packet(500, None, 1.0)  # any sequence number after reset
    assert mon.check(1.006) is None
    assert mon.check(1.007) is not None
    assert mon.trips == 2


def test_sequence_gap_trips_on_arrival_with_range() -> None:
    mon = LossMonitor()
    mon.on_packet(1040, None, 0.000)
    mon.on_packet(1044, None, 0.001)  # 1041-1043 lost, noticed before the deadline
    event = mon.check(0.001)
    assert event is not None
    assert event.kind == "sequence"
    assert event.cause == "3 consecutive packets lost (seq 1041-1043)"
    assert mon.check(0.002) is None


@pytest.mark.parametrize(
    ("seqs", "lost", "trip_cause"),
    [
        ([2**32 - 2, 2**32 - 1, 0, 1, 2], 0, None),
        ([2**32 - 2, 1], 2, None),
        ([2**32 - 1, 3], 3, "3 consecutive packets lost (seq 0-2)"),
        ([2**32 - 3, 2**32 - 2, 2**32 - 1], 0, None),
    ],
)
def test_sequence_wraparound(seqs: list[int], lost: int, trip_cause: str | None) -> None:
    mon = LossMonitor()
    event = None
    for i, s in enumerate(seqs):
        mon.on_packet(s, None, i * MS)
        event = event or mon.check(i * MS)
    assert mon.lost_total == lost
    assert (event.cause if event else None) == trip_cause


def test_duplicates_and_reordering_are_not_losses() -> None:
    mon = LossMonitor()
    for s in (1, 2, 2, 4, 3, 3, 5, 1):
        mon.on_packet(s, None, 0.0)
    assert mon.duplicates == 3  # 2, 3 and the old 1
    assert mon.reordered == 1  # 3, late
    assert mon.lost_total == 0
    assert mon.max_run == 1
    assert mon.received == 8
    mon.on_packet(1000, None, 0.0)
    mon.on_packet(900, None, 0.0)  # far behind the window: late, not a duplicate we can tell
    assert mon.reordered == 2
    assert mon.counters() == {
        "received": 10,
        "lost_total": 994,
        "max_run": 994,
        "duplicates": 3,
        "reordered": 2,
        "trips": 1,
        "tripped": True,
    }


def test_duplicates_do_not_refresh_the_deadline() -> None:
    mon = LossMonitor()
    mon.on_packet(7, None, 0.0)
    events = []
    for t in range(1, 10):
        mon.on_packet(7, None, t * MS)  # a replaying network: same packet over and over
        ev = mon.check(t * MS)
        if ev:
            events.append((t, ev))
    assert [t for t, _ in events] == [7]
    assert mon.duplicates == 9


def test_silent_peer_counts_each_overdue_period() -> None:
    mon = LossMonitor()
    assert mon.check(5.0) is None  # nothing received yet: not armed
    mon.arm(10.0)
    lost = []
    event = None
    for t in range(1, 8):
        event = mon.check(10.0 + t * MS)
        lost.append(mon.lost_total)
    # packet i (due at 2i ms) counts once now > 2i + 0.5 ms
    assert lost == [0, 0, 1, 1, 2, 2, 3]
    assert event is not None and event.cause.startswith("no packet for 7.0 ms (3 periods)")


def test_late_sequence_number_corrects_deadline_count() -> None:
    mon = LossMonitor(max_consecutive=5)
    mon.on_packet(1, None, 0.0)
    mon.check(0.0055)  # 2 overdue
    assert mon.lost_total == 2
    mon.on_packet(2, None, 0.0056)  # the peer only paused: nothing was lost
    assert mon.lost_total == 0
    assert mon.max_run == 2  # the silence was real


def test_v1_timestamps() -> None:
    mon = LossMonitor()
    for ts in (0.000, 0.002, 0.004, 0.0101, 0.0101, 0.008):
        mon.on_packet(None, 100.0 + ts, 0.0)
    assert mon.lost_total == 2  # 6.1 ms gap = 2 missing, tolerated
    assert mon.duplicates == 1 and mon.reordered == 1
    assert mon.check(0.0) is None
    mon.on_packet(None, 100.0 + 0.0181, 0.0)  # 8 ms gap = 3 missing
    event = mon.check(0.0)
    assert event is not None and event.kind == "timestamp"
    assert event.cause == "3 consecutive packets lost (timestamp gap 8.0 ms)"


def test_v1_stream_deadline_timing_matches_v2() -> None:
    sent = [True] * 20
    sent[5] = sent[6] = sent[7] = False
    events = run_stream(LossMonitor(), sent, seq=False, timestamps=True)
    assert [t for t, _ in events] == [2 * 4 + 7]


def test_stream_without_seq_or_timestamp_uses_deadline_only() -> None:
    mon = LossMonitor()
    sent = [True] * 20
    sent[3] = sent[4] = False
    assert run_stream(mon, sent, seq=False, extra_ticks=1) == []
    assert mon.lost_total == 2
    sent[10] = sent[11] = sent[12] = False
    mon2 = LossMonitor()
    assert [t for t, _ in run_stream(mon2, sent, seq=False)] == [2 * 9 + 7]


def test_custom_deadline_and_validation() -> None:
    mon = LossMonitor(period_s=0.001, max_consecutive=0, deadline_s=0.0015)
    mon.on_packet(1, None, 0.0)
    assert mon.check(0.0015) is None
    assert mon.check(0.0016) is not None
    with pytest.raises(ValueError):
        LossMonitor(period_s=0)
    with pytest.raises(ValueError):
        LossMonitor(max_consecutive=-1)


# Streams built from gaps of 0-2 lost packets between received ones: no run of >= 3 losses.
gaps_0_2 = st.lists(st.integers(0, 2), min_size=1, max_size=300)


def _stream(gaps: list[int]) -> list[bool]:
    sent: list[bool] = [True]
    for g in gaps:
        sent += [False] * g + [True]
    return sent


@settings(max_examples=200, deadline=None)
@given(gaps=gaps_0_2, first_seq=st.integers(0, 2**32 - 1), data=st.data())
def test_property_no_run_of_three_never_trips(gaps: list[int], first_seq: int, data) -> None:
    sent = _stream(gaps)
    delays = data.draw(st.lists(st.integers(0, 1), min_size=len(sent), max_size=len(sent)))
    mon = LossMonitor()
    events = run_stream(mon, sent, first_seq=first_seq, delays=delays, extra_ticks=1)
    assert events == []
    assert mon.lost_total == sum(gaps)
    assert mon.max_run == max(gaps)
    assert mon.trips == 0


@settings(max_examples=200, deadline=None)
@given(gaps=gaps_0_2, run=st.integers(3, 10), first_seq=st.integers(0, 2**32 - 1))
def test_property_first_run_of_three_trips_at_7ms(
    gaps: list[int], run: int, first_seq: int
) -> None:
    sent = _stream(gaps)
    last_good = len(sent) - 1
    sent += [False] * run + [True] * 5
    mon = LossMonitor()
    events = run_stream(mon, sent, first_seq=first_seq)
    assert [t for t, _ in events] == [2 * last_good + 7]
    assert events[0][1].since_last_good_s <= 7 * MS + 1e-12
