"""The robot's stream inputs (occ/net/streams.py) and the typed sample (occ/samples.py), on the
shipped slaves (configs/slave.yaml; configs/collab/slave.yaml for two masters) in simulated
time: every sample judged by its loss monitor in arrival order, only the accepted samples of
the stream in control followed (a late, repeated or stale one never moves the robot), samples
the loop could not take in time still seen by the sequence accounting (never called lost), a
master not in control judged and counted but moving nothing, a refused input answered to its
sender, and the polled path bounded per tick. The polled path against real sockets:
test_streams_direct.py; the hand-over: test_collab.py."""

from __future__ import annotations

import math
import socket
import time
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest

import igtl
from occ.core.loader import load_config, parse_config
from occ.core.robot import Robot
from occ.core.safety import RobotState
from occ.errors import CommandError
from occ.events import SphereList
from occ.net.decoders import pose_sample
from occ.net.interfaces import Inbound
from occ.net.streams import POLL_LIMIT, StreamInputs, judge
from occ.samples import PoseSample, quaternion_to_rotation, rotation_to_quaternion
from occ_testkit.testing import SimRobot, loopback_robot

ROOT = Path(__file__).resolve().parents[2]
SLAVE = ROOT / "configs" / "slave.yaml"
COLLAB = ROOT / "configs" / "collab" / "slave.yaml"
MASTER = ("127.0.0.1", 41000)

# the shipped slave with one more link: a tracker's TRANSFORM stream and fixture definitions
# on a stream queue, which no loss monitor watches (no master sends them)
TRACKER = """  - name: tracker
    transport: udp
    host: 127.0.0.1
    port: 18990
    inputs:
      - {type: TRANSFORM, queue: stream, depth: 10}
      - {type: VFIXTURE, queue: stream, depth: 10}
"""


def _with_tracker() -> Any:
    text = SLAVE.read_text().replace("safety:\n", TRACKER + "safety:\n", 1)
    return parse_config(text, str(SLAVE))


class Seen:
    """Where the stream items go (StreamInputs.bind) and the recorder: what each got."""

    def __init__(self, streams: StreamInputs) -> None:
        self.samples: list[tuple[PoseSample, float]] = []
        self.inputs: list[tuple[Any, float]] = []
        self.refused: list[tuple[Inbound, CommandError]] = []
        self.recorded: list[tuple[Any, str, str, float]] = []
        self.sample_error: Exception | None = None
        self.input_error: Exception | None = None
        streams.bind(self.on_sample, self.on_input, self.refuse)

    def on_sample(self, sample: PoseSample, now: float) -> None:
        self.samples.append((sample, now))
        if self.sample_error is not None:
            raise self.sample_error

    def on_input(self, item: Any, now: float) -> None:
        self.inputs.append((item, now))
        if self.input_error is not None:
            raise self.input_error

    def refuse(self, item: Inbound, err: CommandError) -> None:
        self.refused.append((item, err))

    def record_message(self, msg: Any, direction: str, interface: str, now: float) -> None:
        self.recorded.append((msg, direction, interface, now))

    def seqs(self) -> list[int | None]:
        return [s.seq for s, _ in self.samples]


class Slave:
    """A shipped slave whose stream inputs are driven tick by tick with ``drain``."""

    def __init__(self, config: Any = SLAVE) -> None:
        self.sim = SimRobot(config)
        self.robot = self.sim.robot
        self.streams = self.robot.streams
        self.seen = Seen(self.streams)
        self.clock = self.sim.clock

    def position(self, seq: int, *, age_s: float = 0.0, iface: str = "master", **kw: Any) -> Any:
        """A master's sample stamped ``age_s`` before now (negative: from the future)."""
        return igtl.PositionMessage(
            (float(seq), 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 24, device_name="Master",
            header_version=2, message_id=seq, timestamp=self.clock.wall_time() - age_s,
            metadata={"run": "1", "clutch": "0"}, **kw,
        )  # fmt: skip

    def drain(self, now: float) -> None:
        self.clock.set(now)
        self.streams.drain(now, self.seen)

    def close(self) -> None:
        self.sim.close()


@pytest.fixture
def slave() -> Any:
    s = Slave()
    yield s
    s.close()


# ------------------------------------------------------------------ judged, then followed
def test_every_sample_is_judged_and_followed_in_arrival_order_and_recorded(slave: Slave) -> None:
    master = slave.sim.peer("master", address=MASTER)
    slave.clock.set(0.009)
    msgs = [slave.position(s) for s in (1, 2, 3)]
    for m in msgs:
        master.send(m)
    slave.drain(0.01)
    assert slave.seen.seqs() == [1, 2, 3]
    assert all(now == 0.01 for _, now in slave.seen.samples)
    s = slave.seen.samples[0][0]
    assert isinstance(s, PoseSample) and s.interface == "master" and s.t_rx == 0.009
    mon = slave.streams.monitor
    assert mon is slave.streams.monitors["master"] and mon.received == 3 and mon.accepted == 3
    assert mon.last_good == 0.01
    # the recording gets every message as received, before it is judged
    assert [(r[1], r[2], r[3]) for r in slave.seen.recorded] == [("in", "master", 0.01)] * 3
    assert [r[0].message_id for r in slave.seen.recorded] == [1, 2, 3]
    # a repeated number is recorded and judged (a duplicate) but never followed
    master.send(slave.position(3))
    master.send(slave.position(4))
    slave.drain(0.011)
    assert slave.seen.seqs() == [1, 2, 3, 4] and mon.duplicates == 1 and mon.received == 5
    assert len(slave.seen.recorded) == 5
    assert slave.seen.samples[-1][1] == 0.011


def test_the_tap_sees_each_item_and_a_replay_takes_them_as_the_drain_did(slave: Slave) -> None:
    """The black box's tap gets every item the loop takes, with its interface; a replay of
    those items (occ/core/replay.py) on another robot judges, records and follows them as the
    drain did."""
    master = slave.sim.peer("master", address=MASTER)
    tapped: list[tuple[Any, str]] = []
    slave.streams.tap = lambda item, name: tapped.append((item, name))
    slave.clock.set(0.009)
    for seq in (1, 2):
        master.send(slave.position(seq))
    slave.drain(0.01)
    assert [(item.event.seq, name) for item, name in tapped] == [(1, "master"), (2, "master")]
    again = Slave()
    try:
        again.clock.set(0.01)
        again.streams.replay(0.01, again.seen, [(name, item) for item, name in tapped])
        assert again.seen.seqs() == [1, 2] and [now for _, now in again.seen.samples] == [0.01] * 2
        assert [(r[1], r[2], r[3]) for r in again.seen.recorded] == [("in", "master", 0.01)] * 2
        mon = again.streams.monitor
        assert mon is not None and mon.received == 2 and mon.accepted == 2
        assert mon.last_good == 0.01
    finally:
        again.close()


def test_a_drain_without_a_recorder_still_follows(slave: Slave) -> None:
    master = slave.sim.peer("master", address=MASTER)
    master.send(slave.position(1))
    slave.clock.set(0.01)
    slave.streams.drain(0.01, None)
    assert slave.seen.seqs() == [1] and slave.seen.recorded == []


def test_a_stale_or_future_sample_is_judged_by_its_timestamp_and_not_followed(
    slave: Slave,
) -> None:
    master = slave.sim.peer("master", address=MASTER)
    mon = slave.streams.monitor
    assert mon is not None and mon.timestamp_tolerance_s == 0.05
    slave.clock.set(0.5)
    master.send(slave.position(1))
    slave.drain(0.5)  # the peer's clock offset learned: age 0
    assert mon.offset_s == pytest.approx(0.0, abs=1e-9)
    # ticks later (other loop times: the wall clock's offset from the loop's stays put)
    slave.drain(0.59)
    slave.clock.set(0.6)
    master.send(slave.position(2, age_s=0.08))  # stamped 80 ms before it arrived: stale
    master.send(slave.position(3, age_s=-0.08))  # 80 ms ahead of its arrival: the future
    master.send(slave.position(4, age_s=0.01))  # 10 ms: within the tolerance
    slave.drain(0.601)
    assert slave.seen.seqs() == [1, 4]
    assert mon.stale == 1 and mon.future == 1 and mon.lost_total == 0
    assert not mon.tripped


def test_a_stall_of_the_loop_never_makes_the_samples_it_kept_waiting_stale(
    slave: Slave,
) -> None:
    """A sample's earliest arrival is the previous tick's start: one stamped 20 ms after that
    tick and read 90 ms after it (the loop stalled, its receiver stamped it when read) is
    accepted; one stamped before the previous tick and read late is stale."""
    master = slave.sim.peer("master", address=MASTER)
    slave.clock.set(0.5)
    master.send(slave.position(1))
    slave.drain(0.5)
    slave.drain(0.51)  # the previous tick: nothing came
    slave.clock.set(0.6)
    # stamped at 0.53, received (t_rx) at 0.6: 70 ms after its stamp
    master.send(slave.position(2, age_s=0.07))
    slave.drain(0.6)
    assert slave.seen.seqs() == [1, 2]
    slave.clock.set(0.7)
    master.send(slave.position(3, age_s=0.17))  # stamped at 0.53 again: 70 ms before 0.6
    slave.drain(0.7)
    assert slave.seen.seqs() == [1, 2] and slave.streams.monitor.stale == 1  # type: ignore[union-attr]


def test_samples_queued_before_the_first_tick_are_never_stale(slave: Slave) -> None:
    """The socket is bound before the loop starts: what waited for the first tick may be old
    by its stamp, and is not refused for it."""
    master = slave.sim.peer("master", address=MASTER)
    slave.clock.set(0.5)
    master.send(slave.position(1))
    master.send(slave.position(2, age_s=0.2))
    slave.drain(0.5)
    assert slave.seen.seqs() == [1, 2] and slave.streams.monitor.stale == 0  # type: ignore[union-attr]


def test_a_sample_queued_late_by_its_reader_is_judged_by_its_own_arrival(slave: Slave) -> None:
    """The interface thread stamped it (t_rx) before the previous tick began and queued it
    after that tick drained: its earliest arrival is its own stamp, not the previous tick."""
    master = slave.sim.peer("master", address=MASTER)
    slave.clock.set(0.5)
    master.send(slave.position(1))
    slave.drain(0.5)
    slave.clock.set(0.55)
    msg = slave.position(2, age_s=0.04)
    late = pose_sample("master", None, msg, slave.clock.now())
    assert late is not None and late.t_rx == 0.55
    slave.drain(0.6)
    item = Inbound("master", cast(Any, None), msg, late.t_rx, event=late)
    slave.robot.interfaces["master"].streams["POSITION"].put(item)
    slave.drain(0.61)  # 40 ms old at its arrival (followed), 90 ms at the previous tick
    assert slave.seen.seqs() == [1, 2] and slave.streams.monitor.stale == 0  # type: ignore[union-attr]


def test_samples_pushed_out_of_the_queue_are_judged_by_the_same_rule(slave: Slave) -> None:
    """Overflowed samples are judged as the queued ones are (earliest arrival: the previous
    tick): stale ones are counted stale; none moves the robot, none is lost."""
    master = slave.sim.peer("master", address=MASTER)
    slave.clock.set(0.5)
    master.send(slave.position(1))
    slave.drain(0.5)
    slave.drain(0.59)
    slave.clock.set(0.6)
    for s in range(2, 14):  # the 2 oldest pushed out, all stamped 70 ms before 0.6
        master.send(slave.position(s, age_s=0.07))
    slave.drain(0.6)
    mon = slave.streams.monitor
    assert mon is not None
    assert mon.stale == 12 and mon.received == 13 and mon.lost_total == 0
    assert slave.seen.seqs() == [1]


def test_the_wall_clock_is_asked_once_a_tick_and_only_when_a_sample_needs_it(
    slave: Slave,
) -> None:
    calls: list[float] = []
    wall = slave.streams._wall_time

    def counting() -> float:
        calls.append(1.0)
        return wall()

    slave.streams._wall_time = counting
    master = slave.sim.peer("master", address=MASTER)
    slave.drain(0.01)
    assert calls == []
    for s in (1, 2, 3):
        master.send(slave.position(s))
    slave.drain(0.02)
    assert len(calls) == 1 and slave.seen.seqs() == [1, 2, 3]
    master.send(slave.position(4))
    slave.drain(0.03)
    assert len(calls) == 2
    # samples pushed out of a queue and queued ones: still once
    for s in range(5, 20):
        master.send(slave.position(s))
    slave.drain(0.04)
    assert len(calls) == 3 and slave.seen.seqs()[-1] == 19


def test_two_overflowing_queues_ask_the_wall_clock_once() -> None:
    t = Trio()
    try:
        calls: list[float] = []
        wall = t.s.streams._wall_time

        def counting() -> float:
            calls.append(1.0)
            return wall()

        t.s.streams._wall_time = counting
        for seq in range(1, 15):
            t.send(t.mentor, seq)
            t.send(t.trainee, seq)
        t.s.drain(0.01)
        assert len(calls) == 1 and t.s.seen.seqs() == list(range(5, 15))
        assert t.s.streams.monitors["trainee"].received == 14
    finally:
        t.s.close()


def test_samples_the_loop_could_not_take_in_time_are_seen_never_lost_never_followed(
    slave: Slave,
) -> None:
    master = slave.sim.peer("master", address=MASTER)
    q = slave.robot.interfaces["master"].streams["POSITION"]
    assert q.depth == 10
    master.send(slave.position(1))
    slave.drain(0.01)
    slave.clock.set(0.02)
    for s in range(2, 17):  # 15 samples in one tick: the 5 oldest pushed out of the queue
        master.send(slave.position(s))
    assert len(q.evicted) == 5 and q.dropped == 5
    slave.drain(0.04)
    mon = slave.streams.monitor
    assert mon is not None
    assert slave.seen.seqs() == [1, *range(7, 17)]  # the queued ones followed
    assert mon.received == 16 and mon.lost_total == 0 and not mon.tripped
    assert mon.reordered == 0 and mon.duplicates == 0 and mon.stale == 0 and mon.future == 0
    assert not q.evicted and not q.pending
    # each is recorded once: the pushed-out ones are not
    assert len(slave.seen.recorded) == 11


def test_a_stream_no_monitor_watches_is_followed_and_its_overflow_dropped() -> None:
    s = Slave(_with_tracker())
    try:
        streams = s.streams
        assert "tracker" not in streams.monitors and streams.input == "master"
        tracker = s.sim.peer("tracker", address=("127.0.0.1", 44000))
        q = s.robot.interfaces["tracker"].streams["TRANSFORM"]
        m = np.eye(4)
        for i in range(12):  # no sequence numbers, no timestamps: nothing to judge
            m[0, 3] = float(i)
            tracker.send(
                igtl.TransformMessage.from_matrix(m, device_name="Tracker", header_version=1)
            )
        assert len(q.evicted) == 2
        s.drain(0.01)
        assert [p.position_mm[0] for p, _ in s.seen.samples] == [float(i) for i in range(2, 12)]
        assert all(p.kind == "TRANSFORM" and p.seq is None for p, _ in s.seen.samples)
        assert not q.evicted and not q.pending
        assert streams.monitor is not None and streams.monitor.received == 0
    finally:
        s.close()


# ------------------------------------------------------------------ refusals and inputs
def test_a_pose_the_controller_refuses_is_answered_to_its_sender(slave: Slave) -> None:
    master = slave.sim.peer("master", address=MASTER)
    slave.seen.sample_error = CommandError("no such fixture")
    slave.clock.set(0.009)
    master.send(slave.position(1))
    slave.drain(0.01)
    ((item, err),) = slave.seen.refused
    ((sample, _),) = slave.seen.samples
    # the refused item is the one the interface made: the message beside its event
    assert isinstance(item, Inbound) and item.event is sample
    assert item.interface == "master" and item.peer is sample.peer and item.msg is not None
    assert item.t_rx == 0.009 and str(err) == "no such fixture"
    # any other error is the tick's (a FAULT naming the controller, occ/core/robot.py)
    slave.seen.sample_error = RuntimeError("bug")
    master.send(slave.position(2))
    with pytest.raises(RuntimeError, match="bug"):
        slave.drain(0.011)


def test_a_discrete_input_on_a_stream_goes_to_the_controllers_and_a_refusal_to_its_sender() -> None:
    s = Slave(_with_tracker())
    try:
        tracker = s.sim.peer("tracker", address=("127.0.0.1", 44000))
        vf = igtl.VirtualFixtureMessage(
            hardness=0.5, spheres=((0.0, 0.0, 0.0, 1.0),), device_name="VF", header_version=2
        )
        tracker.send(vf)
        s.drain(0.01)
        ((item, now),) = s.seen.inputs
        assert isinstance(item, SphereList) and item.kind == "VFIXTURE" and now == 0.01
        assert item.spheres == ((0.0, 0.0, 0.0, 1.0),) and item.hardness == 0.5
        assert s.seen.samples == [] and s.seen.refused == []
        s.seen.input_error = CommandError("refused VF")
        tracker.send(vf)
        s.drain(0.02)
        ((ref, err),) = s.seen.refused
        assert ref.event is s.seen.inputs[-1][0] and str(err) == "refused VF"
        s.seen.input_error = RuntimeError("bug")
        tracker.send(vf)
        with pytest.raises(RuntimeError, match="bug"):
            s.drain(0.03)
    finally:
        s.close()


# ------------------------------------------------------------------ two masters
class Trio:
    def __init__(self) -> None:
        self.s = Slave(COLLAB)
        self.mentor = self.s.sim.peer("mentor", address=MASTER)
        self.trainee = self.s.sim.peer("trainee", address=("127.0.0.1", 42000))

    def send(self, peer: Any, seq: int) -> None:
        peer.send(self.s.position(seq))


def test_only_the_owners_stream_moves_the_robot_the_other_is_judged_and_counted() -> None:
    t = Trio()
    try:
        streams = t.s.streams
        assert streams.input == "mentor" and set(streams.monitors) == {"mentor", "trainee"}
        assert streams.monitor is streams.monitors["mentor"]
        for seq in (1, 2):
            t.send(t.mentor, seq)
            t.send(t.trainee, 10 + seq)
        t.s.drain(0.01)
        assert t.s.seen.seqs() == [1, 2]
        assert streams.monitors["trainee"].received == 2
        assert streams.monitors["trainee"].accepted == 2
        assert streams.monitors["mentor"].accepted == 2
        assert [r[2] for r in t.s.seen.recorded] == ["mentor", "mentor", "trainee", "trainee"]
        # silence of both: each monitor tells its own event, in the configured order
        assert streams.events(0.012) == ()
        events = streams.events(0.02)
        assert [(n, m, e.kind) for n, m, e in events] == [
            ("mentor", streams.monitors["mentor"], "hold"),
            ("trainee", streams.monitors["trainee"], "hold"),
        ]
        assert streams.holding
        # Reset: every monitor cleared, armed by its next packet
        streams.events(0.5)
        assert streams.monitors["mentor"].tripped and streams.monitors["trainee"].tripped
        streams.reset()
        for mon in streams.monitors.values():
            assert not mon.tripped and not mon.holding and mon.last_good is None
        assert not streams.holding and streams.events(5.0) == ()
    finally:
        t.s.close()


def test_a_replay_follows_only_the_stream_in_control() -> None:
    t = Trio()
    tapped: list[tuple[Any, str]] = []
    t.s.streams.tap = lambda item, name: tapped.append((item, name))
    again = Slave(COLLAB)
    try:
        t.send(t.mentor, 1)
        t.send(t.trainee, 11)
        t.s.drain(0.01)
        again.clock.set(0.01)
        again.streams.replay(0.01, again.seen, [(name, item) for item, name in tapped])
        assert again.seen.seqs() == [1]  # the trainee's is judged, not followed
        assert again.streams.monitors["trainee"].accepted == 1
    finally:
        t.s.close()
        again.close()


def test_holding_is_the_monitor_of_the_stream_in_control() -> None:
    t = Trio()
    try:
        streams = t.s.streams
        t.send(t.mentor, 1)
        t.send(t.trainee, 1)
        t.s.drain(0.01)
        t.send(t.trainee, 2)
        t.s.drain(0.016)
        streams.events(0.018)
        assert streams.monitors["mentor"].holding and not streams.monitors["trainee"].holding
        assert streams.holding
        t.send(t.mentor, 2)
        t.s.drain(0.019)
        streams.events(0.019)
        assert not streams.holding
    finally:
        t.s.close()


def test_a_slave_without_a_watched_stream_never_holds() -> None:
    cfg = load_config(SLAVE)
    cfg = cfg.model_copy(
        update={"safety": cfg.safety.model_copy(
            update={"loss": cfg.safety.loss.model_copy(update={"input": None})})}
    )  # fmt: skip
    s = Slave(cfg)
    try:
        assert s.streams.input is None and s.streams.monitor is None
        assert s.streams.monitors == {} and not s.streams.holding
        master = s.sim.peer("master", address=MASTER)
        master.send(s.position(1))
        master.send(s.position(1))  # nothing judges it: both followed
        s.drain(0.01)
        assert s.seen.seqs() == [1, 1] and s.streams.events(1.0) == ()
    finally:
        s.close()


def test_stream_items_before_bind_have_nowhere_to_go(slave: Slave) -> None:
    fresh = StreamInputs(
        slave.robot.interfaces, slave.robot.config.safety.loss, None, slave.clock.wall_time
    )
    assert fresh.input == "master" and fresh.monitor is fresh.monitors["master"]
    assert fresh.policy == "hold" and fresh.route_errors == 0
    master = slave.sim.peer("master", address=MASTER)
    master.send(slave.position(1))
    with pytest.raises(RuntimeError, match="StreamInputs.bind was not called"):
        fresh.drain(0.01, None)


def test_a_discrete_input_before_bind_has_nowhere_to_go() -> None:
    s = Slave(_with_tracker())
    try:
        robot = s.robot
        fresh = StreamInputs(robot.interfaces, robot.config.safety.loss, None, s.clock.wall_time)
        tracker = s.sim.peer("tracker", address=("127.0.0.1", 44000))
        tracker.send(
            igtl.VirtualFixtureMessage(
                hardness=0.5, spheres=((0.0, 0.0, 0.0, 1.0),), device_name="VF", header_version=2
            )
        )
        with pytest.raises(RuntimeError, match="StreamInputs.bind was not called"):
            fresh.drain(0.01, None)
    finally:
        s.close()


def test_judge_takes_the_earlier_of_the_arrival_and_the_previous_tick() -> None:
    from occ.core.safety import LossMonitor, Verdict

    mon = LossMonitor(0.002, 2, timestamp_tolerance_s=0.05)
    s1 = PoseSample("m", None, "Master", (0.0, 0.0, 0.0), seq=1, t_sample=1000.0, t_rx=0.0)
    assert judge(mon, s1, 0.0, 1000.0) is Verdict.ACCEPT  # offset 0
    # read at 0.09 (wall 1000.09), stamped at 1000.03: stale by its arrival, not by the
    # previous tick (0.02)
    s2 = PoseSample("m", None, "Master", (0.0, 0.0, 0.0), seq=2, t_sample=1000.03, t_rx=0.09)
    assert judge(mon, s2, 0.09, 1000.0, 0.02) is Verdict.ACCEPT
    s3 = PoseSample("m", None, "Master", (0.0, 0.0, 0.0), seq=3, t_sample=1000.03, t_rx=0.09)
    assert judge(mon, s3, 0.09, 1000.0, 0.09) is Verdict.STALE
    # arrived before the previous tick: its own arrival is the earliest (40 ms old then,
    # 100 ms at the previous tick)
    s4 = PoseSample("m", None, "Master", (0.0, 0.0, 0.0), seq=4, t_sample=1000.05, t_rx=0.09)
    assert judge(mon, s4, 0.2, 1000.0, 0.15) is Verdict.ACCEPT
    s4b = PoseSample("m", None, "Master", (0.0, 0.0, 0.0), seq=5, t_sample=1000.03, t_rx=0.09)
    assert judge(mon, s4b, 0.2, 1000.0, 0.15) is Verdict.STALE
    # no previous tick (since -inf): it may have come any time, never stale
    s5 = PoseSample("m", None, "Master", (0.0, 0.0, 0.0), seq=6, t_sample=1000.1, t_rx=0.2)
    assert judge(mon, s5, 0.2, 1000.0) is Verdict.ACCEPT


# ------------------------------------------------------------------ the polled path
def _polled_slave(cfg: Any = None) -> Robot:
    return loopback_robot(SLAVE if cfg is None else cfg, run=True)


def test_a_polled_socket_gives_a_tick_at_most_poll_limit_datagrams() -> None:
    robot = _polled_slave()
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        assert POLL_LIMIT == 4
        iface = robot.interfaces["master"]
        assert iface.transport.polled  # type: ignore[union-attr]
        seen = Seen(robot.streams)
        clock: Any = robot.clock
        address = iface.address
        assert address is not None
        for seq in range(1, 7):
            tx.sendto(
                igtl.PositionMessage(
                    (0.0, 50.0, 270.0), (0.0, 0.0, 0.0, 1.0), 24, device_name="Master",
                    header_version=2, message_id=seq, timestamp=clock.wall_time(),
                    metadata={"run": "1", "clutch": "0"},
                ).pack(),
                address,
            )  # fmt: skip
        ready = iface.transport._ready  # type: ignore[union-attr]
        end = time.monotonic() + 2.0
        while time.monotonic() < end:  # all six in the socket's buffer
            if ready(0) and robot.interfaces["master"].counters.received == 0:
                time.sleep(0.05)
                break
            time.sleep(0.0005)
        robot.streams.drain(0.001, seen)
        assert seen.seqs() == [1, 2, 3, 4]
        assert iface.streams["POSITION"].received == 4 and robot.streams.route_errors == 0
        robot.streams.drain(0.002, seen)
        assert seen.seqs() == [1, 2, 3, 4, 5, 6]
        assert [r[2] for r in seen.recorded] == ["master"] * 6
        assert robot.state is RobotState.RUNNING
    finally:
        tx.close()
        robot.shutdown()


def test_a_polled_master_not_in_control_is_judged_and_moves_nothing() -> None:
    robot = loopback_robot(COLLAB)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        seen = Seen(robot.streams)
        assert robot.streams.input == "mentor" and len(robot.streams._pollers) == 2
        for name, seq in (("trainee", 1), ("trainee", 2), ("mentor", 1)):
            iface = robot.interfaces[name]
            assert iface.transport.polled  # type: ignore[union-attr]
            address = iface.address
            assert address is not None
            msg = igtl.PositionMessage(
                (float(seq), 0.0, 0.0), device_name="Master", header_version=2,
                message_id=seq, timestamp=robot.clock.wall_time(),
            )  # fmt: skip
            tx.sendto(msg.pack(), address)
            ready = iface.transport._ready  # type: ignore[union-attr]
            end = time.monotonic() + 2.0
            while not ready(0) and time.monotonic() < end:
                time.sleep(0.0005)
            robot.streams.drain(0.001 * (seq + (name == "mentor") * 10), seen)
        assert [(s.interface, s.seq) for s, _ in seen.samples] == [("mentor", 1)]
        assert robot.streams.monitors["trainee"].accepted == 2
        assert robot.interfaces["trainee"].streams["POSITION"].received == 2
    finally:
        tx.close()
        robot.shutdown()


def test_every_polled_datagram_that_fails_to_route_is_counted(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import occ.net.interfaces as interfaces_mod

    robot = _polled_slave()
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        seen = Seen(robot.streams)
        iface = robot.interfaces["master"]
        address = iface.address
        assert address is not None

        def broken(*args: Any) -> None:
            raise RuntimeError("routing bug")

        monkeypatch.setattr(interfaces_mod, "pose_sample", broken)
        for seq in (1, 2, 3):
            msg = igtl.PositionMessage((0.0, 0.0, 0.0), device_name="Master", header_version=2,
                                       message_id=seq)  # fmt: skip
            tx.sendto(msg.pack(), address)
        ready = iface.transport._ready  # type: ignore[union-attr]
        end = time.monotonic() + 2.0
        while not ready(0) and time.monotonic() < end:
            time.sleep(0.0005)
        time.sleep(0.05)
        robot.streams.drain(0.001, seen)
        assert robot.streams.route_errors == 3 and seen.samples == []
    finally:
        tx.close()
        robot.shutdown()


def test_a_polled_datagram_is_counted_on_the_queue_of_its_type() -> None:
    robot = _polled_slave(_with_tracker())
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        iface = robot.interfaces["tracker"]
        assert iface.transport.polled and len(iface.streams) == 2  # type: ignore[union-attr]
        seen = Seen(robot.streams)
        address = iface.address
        assert address is not None
        vf = igtl.VirtualFixtureMessage(
            hardness=0.5, spheres=((0.0, 0.0, 0.0, 1.0),), device_name="VF", header_version=2
        )
        tx.sendto(vf.pack(), address)
        ready = iface.transport._ready  # type: ignore[union-attr]
        end = time.monotonic() + 2.0
        while not ready(0) and time.monotonic() < end:
            time.sleep(0.0005)
        robot.streams.drain(0.001, seen)
        assert [i.kind for i, _ in seen.inputs] == ["VFIXTURE"]
        assert iface.streams["VFIXTURE"].received == 1
        assert iface.streams["TRANSFORM"].received == 0
    finally:
        tx.close()
        robot.shutdown()


# ------------------------------------------------------------------ the typed sample
def test_a_position_becomes_a_sample_with_everything_the_controllers_use() -> None:
    msg = igtl.PositionMessage(
        (1.5, -2.0, 3.25), (0.1, -0.5, 0.3, 0.8), device_name="Master", header_version=2,
        message_id=77, timestamp=1234.5, metadata={"run": "0", "clutch": "1", "x": "y"},
    )  # fmt: skip
    s = pose_sample("master", "peer", msg, 0.25)
    assert s is not None
    assert (s.interface, s.peer, s.device, s.kind) == ("master", "peer", "Master", "POSITION")
    assert s.seq == 77 and s.t_sample == 1234.5 and s.t_rx == 0.25
    assert s.position_mm == (1.5, -2.0, 3.25)
    assert s.quaternion == pytest.approx((0.1, -0.5, 0.3, 0.8))
    assert all(type(v) is float for v in (*s.position_mm, *s.quaternion))
    assert s.run is False and s.clutch is True and s.meta["x"] == "y" and s.matrix is None
    # run defaults to 1, clutch to 0; only "1" means on
    for meta, run, clutch in (({}, True, False), ({"run": "1", "clutch": "0"}, True, False),
                              ({"run": "yes", "clutch": "yes"}, False, False)):  # fmt: skip
        m = igtl.PositionMessage((0.0, 0.0, 0.0), device_name="M", header_version=2,
                                 message_id=1, metadata=meta)  # fmt: skip
        p = pose_sample("master", None, m, 0.0)
        assert p is not None and (p.run, p.clutch) == (run, clutch)


def test_a_version_1_sample_has_no_sequence_number() -> None:
    msg = igtl.PositionMessage((1.0, 2.0, 3.0), device_name="M", header_version=1)
    s = pose_sample("master", None, msg, 0.0)
    assert s is not None and s.seq is None and s.meta == {} and s.run and not s.clutch


def test_a_transform_becomes_a_sample_with_its_translation_and_rotation() -> None:
    m = np.eye(4)
    m[:3, :3] = quaternion_to_rotation((0.0, 0.0, math.sin(0.3), math.cos(0.3)))
    m[:3, 3] = (10.0, 20.0, -30.0)
    msg = igtl.TransformMessage.from_matrix(m, device_name="Base", header_version=2, message_id=5)
    s = pose_sample("tracker", None, msg, 1.0)
    assert s is not None and s.kind == "TRANSFORM" and s.seq == 5 and s.device == "Base"
    assert s.position_mm == pytest.approx((10.0, 20.0, -30.0))
    assert s.quaternion == pytest.approx((0.0, 0.0, math.sin(0.3), math.cos(0.3)), abs=1e-6)
    assert s.matrix_mm() == pytest.approx(m, abs=1e-6)
    assert s.matrix is not None and s.matrix == pytest.approx(m, abs=1e-6)  # as sent


def test_any_other_message_is_no_sample() -> None:
    msg = igtl.StringMessage("x", device_name="CMD_1")
    assert pose_sample("operator", None, msg, 0.0) is None


def test_a_sample_made_by_hand_has_the_defaults_of_a_master_that_follows() -> None:
    s = PoseSample("a", None, "D", (1.0, 2.0, 3.0))
    assert s.quaternion == (0.0, 0.0, 0.0, 1.0) and s.kind == "POSITION" and s.seq is None
    assert s.t_sample == 0.0 and s.t_rx == 0.0 and s.run is True and s.clutch is False
    assert s.meta == {} and s.matrix is None
    m = s.matrix_mm()
    assert m.tolist() == [[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]]
    assert repr(s) == (
        "PoseSample('a', 'D', seq=None, position_mm=(1.0, 2.0, 3.0), run=True, clutch=False)"
    )


# rotations that take each branch of Shepperd's method: trace > 0, then the largest diagonal
# element x, y or z (a half turn about each axis, and near it)
@pytest.mark.parametrize(
    "q",
    [
        (0.1, -0.2, 0.3, 0.9),
        (1.0, 0.0, 0.0, 0.0),
        (0.0, 1.0, 0.0, 0.0),
        (0.0, 0.0, 1.0, 0.0),
        (0.9, 0.3, -0.2, 0.1),
        (0.3, 0.9, 0.1, -0.2),
        (-0.2, 0.1, 0.9, 0.3),
        (0.7, 0.1, 0.1, -0.7),
        (0.9, 0.3, -0.2, 0.2),
        (0.2, 0.9, -0.3, 0.1),
        (-0.3, 0.2, 0.9, 0.15),
        (0.5, 0.0, 0.5, 1e-6),  # x = z, no y: the y branch would divide by zero
        (0.5, 0.0, 0.5, -1e-6),
    ],
)
def test_a_rotation_matrix_gives_back_its_quaternion_with_w_not_negative(
    q: tuple[float, float, float, float],
) -> None:
    n = math.sqrt(sum(v * v for v in q))
    unit = tuple(v / n for v in q)
    want = unit if unit[3] >= 0 else tuple(-v for v in unit)
    r = quaternion_to_rotation(q)  # not a unit quaternion: normalised
    got = rotation_to_quaternion(r)
    assert got == pytest.approx(want, abs=1e-12) and got[3] >= 0.0
    assert rotation_to_quaternion(r.tolist()) == pytest.approx(want, abs=1e-12)
    assert quaternion_to_rotation(got) == pytest.approx(r, abs=1e-12)
    assert r @ r.T == pytest.approx(np.eye(3), abs=1e-12)


def _near_half_turns() -> list[tuple[float, float, float, float]]:
    """Rotations with one or two large components and a small one (1e-5, 1e-6; 0 for the
    rest): a branch that divides by a small component loses digits (1e-16 / 4e-6), the one
    by the largest keeps them."""
    out = []
    for big in range(4):
        for small in range(4):
            if small == big:
                continue
            for eps in (1e-5, -1e-6):
                for second in range(4):
                    q = [0.0] * 4
                    q[big] = 1.0
                    if second not in (big, small):
                        q[second] = 0.5
                    q[small] = eps
                    out.append((q[0], q[1], q[2], q[3]))
    return out


@pytest.mark.parametrize("q", _near_half_turns())
def test_rotations_near_a_half_turn_keep_every_digit(q: tuple[float, float, float, float]) -> None:
    r = quaternion_to_rotation(q)
    got = rotation_to_quaternion(r)
    n = math.sqrt(sum(v * v for v in q))
    want = tuple(v / n for v in q)
    if sum(a * b for a, b in zip(got, want, strict=True)) < 0.0:  # q and -q: one rotation
        want = tuple(-v for v in want)
    assert got[3] >= 0.0
    assert got == pytest.approx(want, abs=1e-13)


def test_a_zero_quaternion_is_no_rotation() -> None:
    assert quaternion_to_rotation((0.0, 0.0, 0.0, 0.0)).tolist() == np.eye(3).tolist()
