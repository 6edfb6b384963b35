"""The cell's judgement at close range (occ/core/cell.py): member ``arm0`` of the cell ``or1``,
a robot in simulated time, whose cell link the test plays. Each heartbeat of ``arm1`` and
``arm2`` is made here (its boot, sequence number, state, stop and the tick it arrives in) and
each one ``arm0`` sends is kept, so what the cell decides is seen exactly: who stops it, what
is latched and when it clears, what it tells the operators and what it counts. The link
itself (what it refuses before the cell sees it) is tests/occ/test_cell_link.py's.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from occ.core.cell import Cell
from occ.core.safety import RobotState
from occ.net.celllink import Beat, CellLink
from occ_testkit.testing import SimRobot
from tests.occ.test_cell import _udp_ports, error_of, member_config, ok

S = RobotState
WALL0 = 1_700_000_000.0  # SimClock's wall time at t = 0


class PlayedLink:
    """The cell link of ``arm0`` as the test plays it: ``take`` hands over the heartbeats
    queued with :meth:`Judge.beat`, ``send`` keeps what arm0 sends."""

    def __init__(self, real: CellLink) -> None:
        self.real = real
        self.inbox: list[Beat] = []
        self.sent: list[Beat] = []

    def take(self) -> list[Beat]:
        out, self.inbox = self.inbox, []
        return out

    def send(self, beat: Beat) -> int:
        self.sent.append(beat)
        return 2

    def start(self) -> None:
        pass

    def stop(self) -> None:
        self.real.stop()

    def stats(self) -> dict[str, int]:
        return {"sent": len(self.sent)}


class Judge:
    """``arm0`` (a robot in simulated time, 1 ms ticks) with its played link; ``arm1`` and
    ``arm2`` exist only as the heartbeats a test queues."""

    def __init__(self, n: int = 3, *, frames: bool = False, box: bool = True, **cell: Any) -> None:
        ports = _udp_ports(n)
        frame = {"frame": {"model": "occ_slave"}} if frames else {}
        members = [
            {"name": f"arm{i}", "address": f"127.0.0.1:{p}"} | frame for i, p in enumerate(ports)
        ]
        raw = member_config("arm0", members, **cell).model_dump(mode="json")
        raw["black_box"] = raw["black_box"] | {"enabled": box}
        self.sim = SimRobot(raw)
        cell_ = self.sim.robot.cell
        assert cell_ is not None
        self.cell: Cell = cell_
        self.link = PlayedLink(cell_.link)
        cell_.link = self.link  # type: ignore[assignment]
        self.op = self.sim.peer("operator")
        self.seq = {f"arm{i}": 0 for i in range(1, n)}

    @property
    def next_t(self) -> float:
        """The time of the next tick (a heartbeat queued now arrives in it)."""
        return self.sim.k * self.sim.period

    def beat(self, member: str, state: str = "RUNNING", *, boot: int = 1, seq: int | None = None,
             cause: str = "", origin: str = "", stop_wall: float = 0.0, chain: str = "",
             leaving: bool = False) -> None:  # fmt: skip
        """A heartbeat of ``member`` taken in the next tick (``seq`` None: one more than its
        last)."""
        if seq is None:
            self.seq[member] += 1
            seq = self.seq[member]
        self.link.inbox.append(
            Beat(cell="or1", member=member, boot=boot, seq=seq, state=state, cause=cause,
                 origin=origin, stop_wall=stop_wall, chain=chain, q=(0.0, 0.35, 0.05),
                 base=(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0),
                 leaving=leaving, sent_wall=WALL0 + self.next_t, t_rx=self.next_t)
        )  # fmt: skip

    def both_running(self) -> None:
        self.beat("arm1")
        self.beat("arm2")
        self.sim.tick()

    def command(self, name: str, text: str = "") -> Any:
        return self.sim.command(self.op, name, text)

    def run(self) -> None:
        """Enable and Run (every member heard and running)."""
        self.both_running()
        for cmd in ("Enable", "Run"):
            assert ok(self.command(cmd)), cmd
        assert self.state is S.RUNNING

    @property
    def state(self) -> RobotState:
        return self.sim.robot.state

    def alerts(self) -> list[str]:
        return [m.status_message for m in self.op.messages("STATUS") if m.error_name == "CELL"]

    def close(self) -> None:
        self.sim.close()


@pytest.fixture
def judge() -> Iterator[Judge]:
    j = Judge()
    yield j
    j.close()


@pytest.mark.req("SR-CELL-3")
def test_a_members_row_says_what_was_heard_of_it(judge: Judge) -> None:
    m = judge.cell.members["arm1"]
    quiet = {"state": None, "heard_ms_ago": None, "cause": "", "origin": "", "left": False,
             "chain_ok": None, "lost": 0, "stale": 0, "restarts": 0}  # fmt: skip
    assert m.row(0.5) == quiet
    judge.beat("arm1", "FAULT", seq=7, cause="FAULT: drive", origin="arm1", chain="abc")
    t = judge.next_t
    judge.sim.tick()
    # no URDF configured for arm1: its announced chain is neither trusted nor distrusted
    assert m.row(t + 0.01234) == quiet | {
        "state": "FAULT", "heard_ms_ago": 12.3, "cause": "FAULT: drive", "origin": "arm1",
    }  # fmt: skip
    judge.beat("arm1", "FAULT", seq=10, cause="FAULT: drive", origin="arm1")  # 8, 9 lost
    judge.beat("arm1", "FAULT", seq=10, cause="FAULT: drive", origin="arm1")  # again: stale
    judge.beat("arm1", "READY", boot=2, seq=1)  # restarted
    judge.beat("arm1", "READY", boot=3, seq=1)  # and again
    judge.beat("arm1", "FAULT", boot=2, seq=2)  # of the boot before: stale
    t = judge.next_t
    judge.sim.tick()
    assert m.row(t) == quiet | {
        "state": "READY", "heard_ms_ago": 0.0, "lost": 2, "stale": 2, "restarts": 2,
    }  # fmt: skip
    assert ok(judge.command("CellForget", '<Command Name="CellForget" member="arm1"/>'))
    assert m.row(t)["left"] is True


@pytest.mark.req("SR-CELL-1")
def test_stats_count_each_hold_and_its_propagation(judge: Judge) -> None:
    """Four stops of arm1 (two alike, then two others alike), each begun 4, 1, 3 and 2 ms
    before arm0 reads it: four holds and alerts, the propagation of each (median the third
    of the four sorted, as the others' statistics), the last stop's origin, cause and wall
    time."""
    judge.run()
    for i, ms in enumerate((4, 1, 3, 2)):
        wall = WALL0 + judge.next_t
        judge.beat("arm1", "FAULT", cause=f"FAULT: {i // 2}", origin="arm1",
                   stop_wall=wall - ms * 1e-3)  # fmt: skip
        judge.sim.tick()
        assert judge.state is S.STOPPED
        judge.beat("arm1")  # running again: the latch clears, an operator may Run
        judge.sim.tick()
        assert ok(judge.command("Run"))
    st = judge.cell.stats()
    props = st.pop("propagation_ms")
    near = pytest.approx  # wall times near 1.7e9 s: a ms difference good to about 1e-4 ms
    assert props == {"n": 4, "p50": near(3.0, abs=1e-3), "max": near(4.0, abs=1e-3)}
    last = st.pop("last_stop")
    assert last == {"origin": "arm1", "cause": "arm1 FAULT: 1", "wall": wall,
                    "propagation_ms": near(2.0, abs=1e-3),
                    "origin_sent_wall": wall}  # the stop's heartbeat sent in that tick  # fmt: skip
    members = st.pop("members")
    assert set(members) == {"arm1", "arm2"} and members["arm1"]["state"] == "RUNNING"
    assert st == {"name": "or1", "me": "arm0", "policy": "stop-all", "left": False,
                  "cause": "", "origin": "", "latched": {}, "holds": 4, "alerts": 4,
                  "link": {"sent": len(judge.link.sent)}}  # fmt: skip
    # a stop over and the same again is told again
    assert judge.alerts() == [f"cell or1: arm1 FAULT: {i // 2}; holding" for i in range(4)]


@pytest.mark.req("SR-CELL-4")
def test_a_silence_has_no_propagation_and_an_alert_without_a_hold_says_so(judge: Judge) -> None:
    judge.both_running()  # arm0 READY: nothing of it is powered, nothing to hold
    sent = WALL0 + judge.sim.k * judge.sim.period - judge.sim.period  # the tick that took them
    judge.sim.step(101)
    last = judge.cell.stats()["last_stop"]
    assert last["propagation_ms"] is None and last["origin"] == "arm2"
    # the silence is dated by the origin's last heartbeat: the hold at least the grace after it
    assert last["origin_sent_wall"] == pytest.approx(sent, abs=1e-6)
    assert last["wall"] - last["origin_sent_wall"] > 0.1
    assert judge.alerts() == [
        "cell or1: arm1 silent (nothing for over 100 ms)",
        "cell or1: arm2 silent (nothing for over 100 ms)",
    ]
    assert judge.cell.holds == 0 and judge.sim.robot.alarms.last_alert == judge.alerts()[-1]


@pytest.mark.req("SR-CELL-2")
def test_a_relay_stands_until_its_origin_is_heard_running() -> None:
    """arm2 relays a stop of arm1's. It holds arm0, naming arm1, unless arm1 is heard here
    within the grace, RUNNING with no stop of its own: a stopped arm1 without a cause is not
    over, nor one heard RUNNING longer ago than the grace."""
    j = Judge(grace_ms=125.0)
    try:
        j.run()
        j.beat("arm1", "STOPPED")  # an operator's stop there: no cause, not running
        j.beat("arm2", "STOPPED", cause="ESTOP: pedal", origin="arm1", stop_wall=WALL0)
        j.sim.tick()
        assert j.state is S.STOPPED
        assert j.cell.latched == {"arm1": "ESTOP: pedal (via arm2)"}
        j.beat("arm1")  # running, no stop: the relay is over and so is the latch
        j.sim.tick()
        assert j.cell.latched == {} and ok(j.command("Run"))
        heard = j.cell.members["arm1"].heard
        assert heard is not None
        # arm1 heard exactly the grace ago, running: still recovered (silent only past it)
        while j.next_t - heard < j.cell.grace_s:
            j.beat("arm2")
            j.sim.tick()
        assert j.next_t - heard == j.cell.grace_s
        j.beat("arm2", "STOPPED", cause="ESTOP: pedal", origin="arm1", stop_wall=WALL0)
        j.sim.tick()
        assert j.state is S.RUNNING and j.cell.latched == {}
    finally:
        j.close()


@pytest.mark.req("SR-CELL-2")
def test_a_relay_of_a_member_never_heard_holds(judge: Judge) -> None:
    judge.beat("arm2", "STOPPED", cause="FAULT: drive", origin="arm1", stop_wall=WALL0)
    judge.sim.tick()
    assert judge.cell.latched == {"arm1": "FAULT: drive (via arm2)"}
    assert ok(judge.command("Enable"))
    assert "FAULT: drive (via arm2); Run once arm1 runs" in error_of(judge.command("Run"))


@pytest.mark.req("SR-CELL-2")
def test_a_relay_of_an_origin_missing_from_this_members_list_holds_until_no_one_relays_it(
    judge: Judge,
) -> None:
    """The members' files disagree: arm2's lists an arm9 that arm0's does not. arm2 relays a
    stop of arm9's; arm0 cannot see arm9 recover, so it holds while any member relays the stop,
    says why, refuses Run with a way out that works (CellForget cannot name arm9 here), and lets
    go once no member relays it."""
    judge.run()
    judge.beat("arm1")
    judge.beat("arm2", "STOPPED", cause="FAULT: drive", origin="arm9", stop_wall=WALL0)
    judge.sim.tick()
    why = "FAULT: drive (via arm2; arm9 is not in this member's cell list)"
    assert judge.state is S.STOPPED and judge.cell.latched == {"arm9": why}
    assert judge.alerts() == [f"cell or1: {why}; holding"]
    refusal = error_of(judge.command("Run"))
    assert refusal.endswith(
        f"cell or1: {why}; Run once no member relays arm9's stop (the members' cell lists "
        "should agree)"
    ), refusal
    assert "CellForget" not in refusal
    # arm1 takes the relay up (arm2 runs again): still held, the latch keeps its first words
    judge.beat("arm1", "STOPPED", cause="FAULT: drive", origin="arm9", stop_wall=WALL0)
    judge.beat("arm2")
    judge.sim.tick()
    assert set(judge.cell.latched) == {"arm9"} and judge.state is S.STOPPED
    assert not ok(judge.command("Run"))
    judge.beat("arm1")  # no member relays arm9 any more
    judge.sim.tick()
    assert judge.cell.latched == {} and ok(judge.command("Run"))


@pytest.mark.req("SR-CELL-2")
def test_a_latch_stands_through_a_restart_until_running_and_ends_when_the_origin_leaves(
    judge: Judge,
) -> None:
    judge.run()
    judge.beat("arm1", "FAULT", cause="FAULT: drive", origin="arm1")
    judge.sim.tick()
    assert judge.state is S.STOPPED
    last = judge.cell.last_stop
    judge.beat("arm1", "FAULT", cause="FAULT: drive", origin="arm1")  # the same stop again
    judge.sim.tick()
    assert judge.cell.last_stop == last and judge.cell.alerts == 1
    judge.beat("arm1", "READY", boot=2, seq=1)  # restarted: no stop, not running either
    judge.sim.tick()
    assert judge.cell.latched == {"arm1": "arm1 FAULT: drive"}
    assert "arm1 FAULT: drive; Run once arm1 runs again" in error_of(judge.command("Run"))
    judge.beat("arm1", boot=2)
    judge.sim.tick()
    assert judge.cell.latched == {} and ok(judge.command("Run"))
    # stopped again, then it leaves the cell (CellLeave there): its stop is no longer ours
    judge.beat("arm1", "FAULT", boot=2, cause="FAULT: again", origin="arm1")
    judge.sim.tick()
    assert judge.state is S.STOPPED
    judge.beat("arm1", "FAULT", boot=2, cause="FAULT: again", origin="arm1", leaving=True)
    judge.sim.tick()
    assert judge.cell.latched == {} and ok(judge.command("Run"))


@pytest.mark.req("SR-CELL-2")
def test_leave_and_join_are_announced_at_once_and_judged_again(judge: Judge) -> None:
    """CellLeave and CellJoin go out in the tick of the command, not a period later, with or
    without a stop standing; after CellJoin a stop that stood is latched again though no
    heartbeat came, held, and not told the operators a second time."""
    replies = {
        "CellLeave": "arm0 left cell or1: its stops stop no one, the cell's stop it no more",
        "CellJoin": "arm0 joined cell or1",
    }
    judge.run()
    for stop in (False, True):
        if stop:
            judge.beat("arm1", "FAULT", cause="FAULT: drive", origin="arm1")
            judge.sim.tick()
            assert judge.state is S.STOPPED and judge.cell.alerts == 1
        for name, leaving in (("CellLeave", True), ("CellJoin", False)):
            sent = len(judge.link.sent)
            while len(judge.link.sent) == sent:  # a periodic heartbeat: the next is 5 ms off
                judge.sim.tick()
            sent = len(judge.link.sent)
            reply = judge.command(name)
            assert ok(reply) and reply.metadata["Message"] == replies[name]
            assert len(judge.link.sent) == sent + 1 and judge.link.sent[-1].leaving is leaving
            if leaving and stop:
                assert judge.cell.latched == {} and ok(judge.command("Run"))
                assert judge.state is S.RUNNING
    # joined again: arm1's stop stands (nothing new came from it) and holds
    assert judge.cell.latched == {"arm1": "arm1 FAULT: drive"}
    assert judge.state is S.STOPPED and judge.cell.holds == 2 and judge.cell.alerts == 1


@pytest.mark.req("SR-CELL-2")
def test_forget_takes_member_in_either_case_and_its_stop_is_told_again_if_heard(
    judge: Judge,
) -> None:
    """CellForget ends the latch at once (a Run in the same tick goes), tells the arm check
    the member is gone, and takes ``member=`` as well as ``Member=``; heard in the cell
    again, the member's stop latches and is told again."""
    gone: list[str] = []
    judge.cell.on_peer_gone = gone.append
    judge.both_running()
    assert ok(judge.command("Enable"))
    judge.beat("arm1", "FAULT", cause="FAULT: drive", origin="arm1")
    judge.sim.tick()
    assert judge.cell.latched == {"arm1": "arm1 FAULT: drive"} and judge.cell.alerts == 1
    assert judge.state is S.STOPPED
    forget = judge.op.send_command("CellForget", '<Command Name="CellForget" member="arm1"/>')
    run = judge.op.send_command("Run")
    judge.sim.tick()  # both in one tick, the Run after the CellForget
    assert ok(judge.op.reply_to(forget)) and ok(judge.op.reply_to(run))
    assert gone == ["arm1"] and judge.cell.latched == {} and judge.state is S.RUNNING
    why = error_of(judge.command("CellForget", '<Command Name="CellForget"/>'))
    assert why == "no member '' in cell or1 (members: arm1, arm2)"
    judge.beat("arm1", "FAULT", cause="FAULT: drive", origin="arm1")  # heard in the cell again
    judge.sim.tick()
    assert judge.cell.latched == {"arm1": "arm1 FAULT: drive"} and judge.cell.alerts == 2
    assert judge.alerts() == ["cell or1: arm1 FAULT: drive; holding"] * 2


def _tick_powered(judge: Judge, n: int) -> None:
    """``n`` ticks, each power-up off the loop thread waited for (as SimRobot.command does)."""
    for _ in range(n):
        judge.sim.tick()
        while judge.sim.robot.effects.powering_up:
            assert judge.sim.robot.effects.await_power_up(10.0)
            judge.sim.tick()


@pytest.mark.req("SR-CELL-2")
def test_start_runs_once_every_member_is_heard_saying_so_once(
    judge: Judge, caplog: pytest.LogCaptureFixture
) -> None:
    """``occd --start``: its Run waits, ENABLED, for a member not heard yet (told once in the
    log), and goes in the tick that hears it; an Enable never waits for the cell."""
    judge.beat("arm1")
    judge.sim.robot.start_in("enable", "run")
    _tick_powered(judge, 5)
    assert judge.state is S.ENABLED
    why = "--start: Run waits for cell or1: not heard yet from arm2"
    assert judge.cell.start_wait("run") == why and judge.cell.start_wait("enable") == ""
    assert [r.getMessage() for r in caplog.records].count(why) == 1
    judge.beat("arm2")
    judge.sim.step(2)  # heard in the cell's part of one tick, --start's Run in the next
    assert judge.state is S.RUNNING


@pytest.mark.req("SR-CELL-2")
def test_start_does_not_wait_for_a_latched_stop_a_cell_left_or_alert_only() -> None:
    """A latched stop refuses ``--start``'s Run at once (as an operator's), a member that left
    the cell or a cell that only alerts does not wait for anyone."""
    j = Judge()
    try:
        j.beat("arm1", "FAULT", cause="FAULT: drive", origin="arm1")
        j.sim.robot.start_in("enable", "run")
        _tick_powered(j, 5)
        # held in the first tick (it was ENABLED by then); the Run then refused, not waiting
        assert j.cell.start_wait("run") == ""
        assert j.state is S.STOPPED and j.sim.robot.effects.pending_start == []
        assert ok(j.command("CellLeave")) and j.cell.start_wait("run") == ""
    finally:
        j.close()
    j = Judge()
    try:
        assert j.cell.may_run(S.ENABLED, "run") == "cell or1: not heard yet from arm1, arm2"
        assert j.cell.may_run(S.READY, "enable") == ""
    finally:
        j.close()
    j = Judge(policy="alert-only")
    try:
        assert j.cell.start_wait("run") == "" and j.cell.may_run(S.ENABLED, "run") == ""
    finally:
        j.close()


def test_the_black_box_is_given_each_heartbeat_the_loop_takes(judge: Judge) -> None:
    taken: list[tuple[Beat, str]] = []
    judge.cell.tap = lambda beat, source: taken.append((beat, source))
    judge.beat("arm1")
    judge.beat("arm2", "FAULT", cause="FAULT: drive", origin="arm2")
    beats = list(judge.link.inbox)
    judge.sim.tick()
    judge.beat("arm1", seq=1)  # a duplicate is given too: the box records what came
    beats += judge.link.inbox
    judge.sim.tick()
    assert taken == [(b, "cell") for b in beats] and len(taken) == 3


@pytest.mark.req("SR-CELL-3")
def test_sequence_numbers_count_losses_across_the_wrap_and_refuse_half_a_turn_back(
    judge: Judge,
) -> None:
    """The sequence is uint32: 0xFFFFFFFF then 1 lost one (0), a step of less than half the
    range is ahead, half the range or more is behind (a replay); a heartbeat of a member not
    in this cell (a cell renamed under its link) is ignored."""
    m = judge.cell.members["arm1"]
    for seq in (0xFFFFFFFF, 1, 1 + (1 << 31), (1 << 31)):
        judge.beat("arm1", seq=seq)
    judge.beat("arm9", seq=1)  # no such member here
    judge.sim.tick()
    assert (m.seq, m.lost, m.stale) == ((1 << 31), 1 + (1 << 31) - 2, 1)
    # exactly half the range ahead of 1 << 31 is 0: behind, refused
    judge.beat("arm1", "FAULT", seq=0)
    judge.sim.tick()
    assert (m.seq, m.stale, m.state) == ((1 << 31), 2, "RUNNING")


@pytest.mark.req("SR-CELL-2")
def test_a_member_forgotten_stays_so_while_it_says_it_left_and_the_peer_arm_is_fed() -> None:
    """A forgotten member heard leaving stays out; heard in the cell it is in again. Its arm
    is given to the arm check (``on_peer``) from each heartbeat while its chain is its URDF's
    (or not announced), never when it is another."""
    j = Judge(frames=True)
    try:
        fed: list[tuple[Any, ...]] = []
        j.cell.on_peer = lambda *a: fed.append(a)
        chain = j.cell.members["arm1"].chain
        assert chain is not None
        assert ok(j.command("CellForget", '<Command Name="CellForget" Member="arm1"/>'))
        j.beat("arm1", chain=chain, leaving=True)
        t = j.next_t
        j.sim.tick()
        assert j.cell.members["arm1"].out
        j.beat("arm1", chain="another")
        j.beat("arm1")
        j.sim.tick()
        assert not j.cell.members["arm1"].out
        q, base = (0.0, 0.35, 0.05), (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
        assert fed == [("arm1", q, base, t), ("arm1", q, base, t + j.sim.period)]
    finally:
        j.close()


@pytest.mark.req("SR-CELL-4")
def test_silence_is_judged_from_the_member_heard_longest_ago_though_nothing_comes(
    judge: Judge,
) -> None:
    """Nothing arrives at all: arm1 (heard at 0) holds arm0 in the first tick past its grace,
    though arm2 was heard 50 ms later; not one tick before."""
    judge.run()
    start = judge.next_t
    judge.beat("arm1")
    judge.beat("arm2")
    judge.sim.tick()
    while judge.next_t < start + 0.05:
        judge.beat("arm2")
        judge.sim.tick()
    while judge.next_t <= start + judge.cell.grace_s:
        judge.sim.tick()
        assert judge.state is S.RUNNING, judge.next_t
    held_at = WALL0 + judge.next_t
    judge.sim.tick()
    assert judge.state is S.STOPPED and list(judge.cell.latched) == ["arm1"]
    # a silence has no stop time of its own: arm0's relay of it says when arm0 held
    b = judge.link.sent[-1]
    assert (b.origin, b.cause, b.stop_wall) == (
        "arm1", "arm1 silent (nothing for over 100 ms)", held_at,
    )  # fmt: skip


@pytest.mark.req("SR-CELL-1")
def test_each_heartbeat_says_this_members_state_its_stop_joints_and_base(judge: Judge) -> None:
    """What arm0 sends: its boot and chain, its state, its stop (cause, itself as origin, the
    transition's wall time), its joints and its base (the rotation by rows, then the
    translation); every 5 ms while nothing changes, at once when it does."""
    robot = judge.sim.robot
    robot.data.base[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    robot.data.base[:3, 3] = [0.6, -0.02, 0.005]
    judge.run()
    sent = len(judge.link.sent)
    while len(judge.link.sent) == sent:
        judge.sim.tick()
    ticks = []  # the ticks that send, for 100 ms from one that sent
    for k in range(100):
        sent = len(judge.link.sent)
        judge.beat("arm1")
        judge.beat("arm2")
        judge.sim.tick()
        ticks += [k] * (len(judge.link.sent) - sent)
    assert ticks == list(range(4, 100, 5))  # one every 5 ms, never 6 (a float's rounding)
    assert ok(judge.command("EStop"))
    b = judge.link.sent[-1]
    assert b.cause.startswith("ESTOP: ") and b.stop_wall == WALL0 + judge.next_t - judge.sim.period
    assert b == Beat(
        cell="or1", member="arm0", boot=judge.cell.boot, seq=0, state="ESTOP", cause=b.cause,
        origin="arm0", stop_wall=b.stop_wall, chain=judge.cell.chain,
        q=tuple(float(v) for v in robot.data.q),
        base=(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.6, -0.02, 0.005),
    )  # fmt: skip
    assert judge.cell.boot > 1_700_000_000 * 10**9  # a start in Unix ns: a restart is newer
    for cmd in ("Reset", "Enable"):
        assert ok(judge.command(cmd))
    assert judge.link.sent[-1].cause == b.cause  # a stop stands until it runs again
    assert ok(judge.command("Run"))
    assert (judge.link.sent[-1].cause, judge.link.sent[-1].stop_wall) == ("", 0.0)
    assert ok(judge.command("Stop"))  # an operator's Stop is no stop of the cell's
    assert judge.link.sent[-1].state == "STOPPED" and judge.link.sent[-1].cause == ""


@pytest.mark.req("SR-CELL-1")
def test_a_member_held_for_another_relays_its_origin_and_keeps_it(judge: Judge) -> None:
    """Held for arm1's stop, arm0's heartbeats name arm1 and arm1's stop time; a controller's
    stop of the cell then keeps that origin (else two members would wait for each other). A
    hung loop is announced only while something of the arm is powered."""
    judge.run()
    judge.beat("arm1", "FAULT", cause="FAULT: drive", origin="arm1", stop_wall=WALL0 + 0.001)
    judge.sim.tick()
    relay = judge.link.sent[-1]
    assert (relay.state, relay.cause, relay.origin, relay.stop_wall) == (
        "STOPPED", "arm1 FAULT: drive", "arm1", WALL0 + 0.001,
    )  # fmt: skip
    assert judge.sim.robot.state_machine.last_reason == "cell: arm1 FAULT: drive"
    judge.cell.announce_stop("cell plan 3 dropped")
    assert judge.link.sent[-1] == relay
    judge.beat("arm1")
    judge.sim.tick()
    # running again, an operator's Stop: no stop of the cell's, nobody held for
    assert ok(judge.command("Run")) and ok(judge.command("Stop"))
    assert (judge.link.sent[-1].state, judge.link.sent[-1].cause) == ("STOPPED", "")
    assert ok(judge.command("Disable"))  # READY: nothing powered
    sent = len(judge.link.sent)
    judge.cell.announce_hung("no tick for 25 ms")
    assert len(judge.link.sent) == sent and judge.cell.own.cause == ""


@pytest.mark.req("SR-CELL-1")
def test_a_relay_that_is_over_hides_no_other_members_stop() -> None:
    """Four members: arm1 still relays arm2's stop, over (arm2 runs); arm3's own stop after
    them in the cell's order holds arm0 all the same."""
    j = Judge(4)
    try:
        j.beat("arm3")
        j.run()
        j.beat("arm1", "STOPPED", cause="FAULT: drive", origin="arm2", stop_wall=WALL0)
        j.beat("arm2")
        j.beat("arm3", "ESTOP", cause="ESTOP: pedal", origin="arm3", stop_wall=WALL0)
        j.sim.tick()
        assert j.cell.latched == {"arm3": "arm3 ESTOP: pedal"} and j.state is S.STOPPED
    finally:
        j.close()


@pytest.mark.req("SR-CELL-2")
def test_a_cell_without_a_black_box_takes_heartbeats() -> None:
    j = Judge(box=False)
    try:
        assert j.cell.tap is None
        j.both_running()
        assert j.cell.members["arm1"].state == "RUNNING"
    finally:
        j.close()


@pytest.mark.req("SR-CELL-2")
def test_the_shipped_cells_arm_check_is_fed_by_the_heartbeats_until_forgotten() -> None:
    """configs/cell/: each UR5 checks the other's links where its heartbeats put them (from
    the first heartbeat), until an operator forgets it."""
    from tests.occ.test_cell import shipped_cell

    sims: list[SimRobot] = []
    try:
        for raw in shipped_cell():
            sims.append(SimRobot(raw))
        guard = sims[0].robot.collision
        assert guard is not None
        other = guard.cm.peer("ur5-b")
        assert other.describe()["t"] is None
        for _ in range(10):
            for sim in sims:
                sim.tick()
        assert other.describe()["t"] is not None and other.describe()["present"] is True
        op = sims[0].peer("operator")
        assert ok(sims[0].command(op, "CellForget", '<Command Name="CellForget" Member="ur5-b"/>'))
        assert other.describe()["present"] is False
    finally:
        for sim in sims:
            sim.close()


@pytest.mark.req("SR-CELL-4")
def test_a_stops_origin_is_dated_by_its_own_last_heartbeat_never_the_relays() -> None:
    """``last_stop.origin_sent_wall`` is when the origin itself last sent a heartbeat taken
    here: none for an origin relayed but never heard, the origin's own for one heard, whoever
    relays it."""
    j = Judge(4)
    try:
        # arm3 never heard: arm1 relays its stop
        j.beat("arm1", "STOPPED", cause="FAULT: drive", origin="arm3", stop_wall=WALL0)
        j.sim.tick()
        last = j.cell.stats()["last_stop"]
        assert (last["origin"], last["origin_sent_wall"]) == ("arm3", None)
        # arm3 heard (stopped), arm1 running again; arm3's stop relayed by arm2 ten ticks
        # later: dated by arm3's heartbeat, not arm2's
        sent3 = WALL0 + j.next_t
        j.beat("arm3", "STOPPED")
        j.beat("arm1")
        j.sim.tick()
        j.sim.step(9)
        j.beat("arm2", "STOPPED", cause="FAULT: joint", origin="arm3", stop_wall=sent3)
        j.sim.tick()
        last = j.cell.stats()["last_stop"]
        assert last["origin"] == "arm3" and last["cause"] == "FAULT: joint (via arm2)"
        assert last["origin_sent_wall"] == pytest.approx(sent3, abs=1e-9)
    finally:
        j.close()
