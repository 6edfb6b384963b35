"""The black box piece by piece (occ/recording/blackbox.py, dump.py): the rings, the taps, the
checkpoints' schedule, the window a writer copies, the writer thread and the dump's files,
each driven by hand (no robot, no clock but the test's)."""

from __future__ import annotations

import json
import math
import os
import pickle
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

import igtl
from occ.core.safety import RobotState
from occ.recording import dump
from occ.recording.blackbox import (
    CHECKPOINT_S,
    CHUNK,
    CMD,
    HOOK,
    IN,
    MARGIN_S,
    NOTE,
    OUT,
    QUEUE_DEPTH,
    REQUEST,
    TRANSITION,
    VERDICT,
    BlackBox,
    Checkpoints,
    DumpRequest,
    DumpWriter,
    tick_columns,
)
from occ.recording.record import read_recording

NAN = math.nan
WALL = 1_700_000_123.25  # 2023-11-14T22:15:23.250Z


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t

    def wall_time(self) -> float:
        return WALL + self.t


@dataclass
class _Joint:
    position: float = 0.0


class _Drive:
    def __init__(self) -> None:
        self.raw_now: float | None = None
        self.raw: tuple[list[float], list[float], list[float]] = ([], [], [])


def _box(
    rate: float = 1000.0,
    seconds: float = 1.0,
    events_per_s: int = 1000,
    *,
    joints: tuple[str, ...] = ("a", "b"),
    writer: DumpWriter | None = None,
    directory: Path = Path("bb"),
    world: Any = None,
    drives: Any = (),
    streams: Any = None,
    guard: Any = None,
    on_loop: bool = True,
) -> tuple[BlackBox, SimpleNamespace]:
    box = BlackBox("r", joints, rate, seconds, events_per_s, world=world is not None)
    data = SimpleNamespace(clock=_Clock(), state=RobotState.READY)
    parts = SimpleNamespace(
        data=data, joints=[_Joint() for _ in joints], requests=[], writer=writer
    )
    if writer is None:
        writer = parts.writer = DumpWriter(parts.requests.append, "w", inline=True)
    box.bind(data, parts.joints, guard, writer, directory, drives, streams, world)
    if on_loop:
        box.on_loop()
    return box, parts


def _ticks(box: BlackBox, n: int, period: float = 0.001) -> None:
    for _ in range(n):
        k = box.count
        box.end_tick(k * period, k)


def _req(box: BlackBox, end: int | None = None, events_end: int | None = None) -> DumpRequest:
    return DumpRequest(
        "x",
        Path("x"),
        [("operator", "")],
        box.count if end is None else end,
        box.ev_count if events_end is None else events_end,
        0.0,
        0,
        WALL,
    )


# ---------------------------------------------------------------------- the rings
def test_the_columns_of_a_row() -> None:
    assert tick_columns(["a", "b"]) == [
        "t", "k", "state", "pos.a", "pos.b", "sp.a", "sp.b", "ew.a", "ew.b",
        "raw.pos.a", "raw.vel.a", "raw.eff.a", "raw.pos.b", "raw.vel.b", "raw.eff.b",
        "to_wall",
    ]  # fmt: skip
    assert tick_columns(["a"], world=True)[-5:] == [
        "to_wall", "world.fx", "world.fy", "world.fz", "world.contact",
    ]  # fmt: skip


def test_the_rings_are_sized_from_seconds_rate_and_events_with_their_margin() -> None:
    box = BlackBox("r", ["a", "b"], 100.0, 2.0, 150)
    assert (box.width, box.capacity, box.ev_capacity) == (16, 200, 300)
    margin = MARGIN_S + CHECKPOINT_S
    assert box._slots == 200 + math.ceil(margin * 100.0) == 500
    assert box._ev_slots == 300 + math.ceil(margin * 150) == 750
    assert box._view.shape == (500, 16) and len(box._ev_kind) == 750
    assert BlackBox("r", ["a"], 10.0, 0.5, 10).ev_capacity == 16  # at least 16 events
    assert BlackBox("r", ["a"], 10.0, 0.01, 100).capacity == 1  # at least one row
    off = BlackBox("r", ["a"], 100.0, 2.0, 150, enabled=False)
    assert (off.seconds, off.capacity, off._slots, off._ev_slots) == (0.0, 1, 1, 1)
    # the first row is written with no setpoint or reading until the loop writes one
    row = BlackBox("r", ["a", "b"], 100.0, 2.0, 150)._view[0]
    assert np.isnan(row[5:15]).all() and not np.isnan(row[:5]).any()


def test_a_world_needs_a_box_with_its_columns() -> None:
    world = SimpleNamespace(force_n=(0.0, 0.0, 0.0), in_contact=False)
    with pytest.raises(ValueError, match="world=True"):
        _box(world=None)[0].bind(
            SimpleNamespace(clock=_Clock(), state=RobotState.READY), [], None, None, Path("."),
            world=world,
        )  # fmt: skip
    box = BlackBox("r", ["a"], 100.0, 1.0, 100, world=True)
    with pytest.raises(ValueError, match="world=True"):
        box.bind(SimpleNamespace(clock=_Clock(), state=RobotState.READY), [], None, None, Path("."))


def test_a_row_holds_the_tick_the_joints_the_writes_the_readings_the_wall_and_the_world() -> None:
    drive = _Drive()
    streams = SimpleNamespace(_to_wall=12.5)
    world = SimpleNamespace(force_n=(1.5, -2.0, 3.25), in_contact=True)
    box, p = _box(drives=[(drive, (1, 0))], streams=streams, world=world)
    assert box.columns[-4:] == ["world.fx", "world.fy", "world.fz", "world.contact"]
    p.joints[0].position, p.joints[1].position = 0.5, -0.25
    drive.raw_now, drive.raw = 0.0, ([1.0, 2.0], [3.0, 4.0], [5.0, 6.0])
    box.wrote([0.1, 0.2], False)
    box.end_tick(0.0, 7)
    # the next tick: nothing written, the drive not read, no wall offset, no contact
    p.data.state = RobotState.RUNNING
    box.on_transition(RobotState.READY, RobotState.RUNNING, "Run", "", 0.001)
    streams._to_wall = None
    world.force_n, world.in_contact = (0.0, 0.0, -1.0), False
    box.end_tick(0.001, 8)
    box.wrote([9.0, 8.0], True)  # efforts
    drive.raw_now = 0.002
    box.end_tick(0.002, 9)
    assert box.count == 3
    rows = box._view[:3].tolist()
    # the drive's joints are (1, 0): its first reading is joint b's
    want0 = [0.0, 7.0, 1.0, 0.5, -0.25, 0.1, 0.2, NAN, NAN, 2.0, 4.0, 6.0, 1.0, 3.0, 5.0, 12.5]
    want0 += [1.5, -2.0, 3.25, 1.0]
    want1 = [0.001, 8.0, 3.0, 0.5, -0.25, NAN, NAN, NAN, NAN] + [NAN] * 6 + [NAN]
    want1 += [0.0, 0.0, -1.0, 0.0]
    want2 = [0.002, 9.0, 3.0, 0.5, -0.25, NAN, NAN, 9.0, 8.0, 2.0, 4.0, 6.0, 1.0, 3.0, 5.0]
    want2 += [NAN, 0.0, 0.0, -1.0, 0.0]
    for got, want in zip(rows, [want0, want1, want2], strict=True):
        np.testing.assert_array_equal(got, want)
    # the row under way has no setpoint or effort yet
    assert np.isnan(box._view[3, 5:9]).all()


def test_the_ring_wraps_and_clears_the_next_rows_writes() -> None:
    box, _ = _box(rate=10.0, seconds=1.0)  # 10 rows and 30 of margin: 40 slots
    assert box._slots == 40
    for _ in range(45):
        box.wrote([1.0, 2.0], False)
        box.wrote([3.0, 4.0], True)
        k = box.count
        box.end_tick(k * 0.1, k)
    assert box.count == 45 and box._pos == 5 * box.width
    assert box._view[0, 1] == 40.0 and box._view[4, 1] == 44.0 and box._view[5, 1] == 5.0
    assert np.isnan(box._view[5, 5:9]).all()  # slot 5 was tick 5's: the next tick wrote none
    w = box.window(_req(box))
    assert w.first_row == 35 and w.rows[:, 1].tolist() == list(range(35, 45))
    assert w.rows_lost == 0 and w.checkpoint is None
    # a disabled box keeps nothing and writes nothing
    off = BlackBox("r", ["a"], 10.0, 1.0, 10, enabled=False)
    off.bind(SimpleNamespace(clock=_Clock(), state=RobotState.READY), [_Joint(1.0)], None, None,
             Path("."))  # fmt: skip
    off.wrote([5.0], False)
    off.end_tick(1.0, 1)
    off.note("x", 1)
    assert off.count == 0 and off.ev_count == 0 and off._view[0, :4].tolist() == [0.0] * 4
    assert np.isnan(off._view[0, 4:6]).all()
    assert off.request("operator", "") == "no black box (black_box.enabled is false)"


def test_rows_the_loop_wrote_over_before_the_writer_copied_them_are_dropped_and_counted() -> None:
    box, _ = _box(rate=10.0, seconds=1.0)  # 40 slots
    _ticks(box, 45)
    req = _req(box)  # rows 35..44
    _ticks(box, 35)  # the loop went on: 80 rows written, slots of 35..40 written over
    w = box.window(req)
    # the row under way (80) may be half written in slot 0, so rows up to 40 are gone
    assert (w.rows_lost, w.first_row) == (6, 41)
    assert w.rows[:, 1].tolist() == [41.0, 42.0, 43.0, 44.0]
    _ticks(box, 1)
    w = box.window(req)
    assert (w.rows_lost, w.first_row, len(w.rows)) == (7, 42, 3)


def test_the_window_starts_at_the_last_checkpoint_before_its_seconds() -> None:
    box, p = _box(rate=100.0, seconds=1.0, events_per_s=4000)  # 400 rows
    taken: list[Any] = []
    box.make_checkpointer = lambda: SimpleNamespace(take=lambda: taken.append(1) or [len(taken)])
    box.inline_checkpoints = True
    p.data.clock.t = 5.0
    box.start()
    cps = box.checkpoints
    assert cps is not None and cps.every == 100 and cps.built_at == 5.0
    assert cps._ring.maxlen == math.ceil((1.0 + MARGIN_S) / CHECKPOINT_S) + 2 == 5
    assert cps.taken == 1 and cps.baseline == [1] and cps._ring[0][:2] == (0, 0)
    box.inline_checkpoints = False
    p.data.clock.t = 6.0
    box.start()  # started again on the real clock: the same checkpoints, none taken here
    assert box.checkpoints is cps and cps.taken == 1 and cps.built_at == 5.0
    box.inline_checkpoints = True
    for _ in range(250):
        box.note("tick", box.count)
        k = box.count
        box.end_tick(k * 0.01, k)
    # taken at the end of rows 99 and 199 (before 100 and 200), each after that tick's events
    assert [c[:2] for c in cps._ring] == [(0, 0), (100, 100), (200, 200)]
    assert cps.due == 300 and cps.late == 400
    w = box.window(_req(box))  # 100 rows from 150: the checkpoint of 100
    assert (w.first_row, len(w.rows), w.checkpoint) == (100, 150, [2])
    assert [ev[3] for ev in w.events] == list(range(100, 250))
    assert [ev[3] for ev in w.loop_events] == list(range(100, 250))
    w = box.window(_req(box, end=200, events_end=200))
    assert (w.first_row, w.checkpoint) == (100, [2])  # 200 is not before the window's end
    assert len(w.events) == 100
    w = box.window(_req(box, end=250, events_end=250))
    assert [ev[3] for ev in w.loop_events][:1] == [100]
    # no checkpoint at or before 150 still in the ring: the first one after it
    cps._ring.popleft()
    cps._ring.popleft()
    w = box.window(_req(box))
    assert (w.first_row, w.checkpoint) == (200, [3]) and w.events[0][3] == 200
    # the loop went on: the rows of the checkpoint of 100 may be written over as the writer
    # copies (it leaves MARGIN_S of rows to the loop), so the window starts at the next one
    cps._ring.appendleft((100, 100, [2]))
    box.note("tick", 250)
    _ticks(box, 100, 0.01)  # 350 rows: the oldest a checkpoint may be is 351 - 400 + 200
    assert box._copy_margin == 200
    w = box.window(_req(box, end=250, events_end=250))
    assert (w.first_row, w.checkpoint) == (200, [3])
    _ticks(box, 49, 0.01)  # 399 rows: the oldest is 200, still kept
    assert box.window(_req(box, end=250, events_end=250)).checkpoint == [3]
    _ticks(box, 1, 0.01)  # 400 rows: the oldest is 201, none of that window's is kept
    w = box.window(_req(box, end=250, events_end=250))
    assert (w.first_row, w.checkpoint, len(w.rows)) == (150, None, 100)
    # no checkpoint at all: the window's seconds, no replay's start
    cps._ring.clear()
    w = box.window(_req(box))
    assert (w.first_row, w.checkpoint, len(w.rows)) == (300, None, 100)


def test_checkpoints_take_the_state_and_say_where_a_window_starts() -> None:
    states = iter([["s0"], ["s1"], ["s2"], ["s3"]])
    cps = Checkpoints(lambda: next(states), 250.0, 3)
    assert (cps.every, cps.due, cps.late, cps.taken, cps.baseline) == (250, 0, 0, 0, None)
    assert Checkpoints(list, 0.1, 3).every == 1
    assert cps.cost_max_s == 0.0 and math.isnan(cps.built_at)  # none yet; never built
    cps.take(0, 0)
    assert (cps.due, cps.late, cps.taken, cps.baseline) == (250, 500, 1, ["s0"])
    assert 0.0 <= cps.cost_max_s < 1.0
    cps.take(250, 9)
    cps.take(600, 20)
    assert cps.baseline == ["s0"] and cps.taken == 3 and cps.cost_max_s >= 0.0
    assert (cps.due, cps.late) == (850, 1100)
    assert cps.start(300, 0, 1000) == (250, 9, ["s1"])
    assert cps.start(250, 0, 1000) == (250, 9, ["s1"])  # at it
    assert cps.start(249, 0, 1000) == (0, 0, ["s0"])
    assert cps.start(300, 1, 1000) == (250, 9, ["s1"])  # row 0 gone: still 250
    assert cps.start(100, 1, 1000) == (250, 9, ["s1"])  # none before kept: the first after
    assert cps.start(100, 251, 1000) == (600, 20, ["s2"])
    assert cps.start(100, 251, 600) is None  # not before the window's end
    assert cps.start(100, 601, 2000) is None
    cps.take(900, 30)  # keeps 3
    assert [c[0] for c in cps._ring] == [250, 600, 900]


def test_a_checkpoint_is_taken_when_due_with_room_or_an_interval_late() -> None:
    box, _ = _box(rate=10.0, seconds=1.0)
    assert not box.spare(True)  # no checkpoints: none
    box.checkpoints = cps = Checkpoints(list, 10.0, 4)
    assert box.spare(False) and cps.taken == 1
    box.count = 9
    assert not box.spare(True)
    box.count = 10
    assert box.spare(True) and cps.due == 20 and cps.late == 30
    box.count = 29
    assert not box.spare(False)
    box.count = 30
    assert box.spare(False) and cps._ring[-1][0] == 30


# ---------------------------------------------------------------------- events
def test_events_on_the_loop_go_to_the_ring_and_from_other_threads_beside_it() -> None:
    box, _ = _box()
    early = threading.Thread(target=box.note, args=("early", 0))  # before the first tick
    early.start()
    early.join()
    _ticks(box, 3)
    box.note("plan", {"p": 1})
    box.sent("reply", "operator")
    err = OSError(5, "bus gone")
    box.hook_failed("drive0", "read", err)
    box.took_request("req", "operator")
    assert box.ev_count == 4
    assert list(box._ev_tick[:4]) == [3, 3, 3, 3]
    assert list(box._ev_kind[:4]) == [NOTE, OUT, HOOK, CMD]
    assert box._ev_where[:4] == ["plan", "operator", ("drive0", "read"), "operator"]
    assert box._ev_obj[2] == ("builtins", "OSError", str(err), repr(err))
    _ticks(box, 2)
    t = threading.Thread(target=lambda: (box.sent("late reply", "op"), box.note("n", 2)))
    t.start()
    t.join()
    assert box.ev_count == 4 and list(box._off_loop) == [
        (0, NOTE, "early", 0), (5, OUT, "op", "late reply"), (5, NOTE, "n", 2)
    ]  # fmt: skip
    box.note("after", 3)  # the loop's own event of tick 5
    _ticks(box, 1)
    w = box.window(_req(box))
    assert [(e[0], e[1], e[3]) for e in w.events] == [
        (0, NOTE, 0), (3, NOTE, {"p": 1}), (3, OUT, "reply"), (3, HOOK, w.events[3][3]),
        (3, CMD, "req"),
        (5, NOTE, 3), (5, OUT, "late reply"), (5, NOTE, 2),
    ]  # fmt: skip
    # only the loop's own are what a replay feeds
    assert [e[3] for e in w.loop_events][-1] == 3 and len(w.loop_events) == 5
    # events of ticks outside the window are not in it
    w = box.window(_req(box, end=4, events_end=4))
    assert [e[0] for e in w.events] == [0, 3, 3, 3, 3]
    before = box.window(DumpRequest("x", Path("x"), [], 3, 0, 0.0, 0, WALL))
    assert before.events == [(0, NOTE, "early", 0)] and before.loop_events == []


def test_a_stream_item_is_kept_as_its_bytes_and_rebuilt_in_the_window() -> None:
    from occ.net.interfaces import Inbound

    box, _ = _box()
    wire = igtl.PositionMessage(device_name="master", position=(1.0, 2.0, 3.0)).pack()
    msg = igtl.unpack(wire)
    peer = SimpleNamespace(id=7)
    item = Inbound("master", peer, msg, 0.25)
    box.took(item, "master")
    assert box._ev_kind[0] == 9 and box._ev_obj[0] is msg._wire and box._ev_t[0] == 0.25
    assert box._ev_peer[0] is peer and box._ev_where[0] == "master"
    heartbeat = SimpleNamespace(member="m2")  # a cell member's heartbeat: no message
    box.took(heartbeat, "cell")
    plain = Inbound("master", peer, igtl.PositionMessage(device_name="m"), 0.5)
    box.took(plain, "master")  # no wire bytes (made here): kept as the item
    _ticks(box, 1)
    w = box.window(_req(box))
    (tick, kind, where, obj), hb, pl = w.events
    assert (tick, kind, where) == (0, IN, "master") and obj.peer is peer and obj.t_rx == 0.25
    assert obj.msg.position == (1.0, 2.0, 3.0) and obj.msg.device_name == "master"
    assert obj.event is not None
    assert hb == (0, IN, "cell", heartbeat) and pl == (0, IN, "master", plain)
    assert w.loop_events == w.events
    # from another thread: the item itself, beside the ring
    t = threading.Thread(target=box.took, args=(item, "master"))
    t.start()
    t.join()
    assert list(box._off_loop) == [(1, IN, "master", item)]


def test_the_rebuilt_items_before_the_window_are_dropped_unbuilt() -> None:
    box, _ = _box(rate=100.0, seconds=1.0)
    wire = igtl.PositionMessage(device_name="master").pack()
    from occ.net.interfaces import Inbound

    for n in range(300):
        box.took(Inbound("master", None, igtl.unpack(wire), n * 0.01), "master")
        k = box.count
        box.end_tick(k * 0.01, k)
    w = box.window(_req(box))
    assert w.first_row == 200 and [e[3].t_rx for e in w.events] == [
        n * 0.01 for n in range(200, 300)
    ]
    # the ring wrapped: each item's bytes, time and peer copied across the wrap, together
    box, _ = _box(rate=100.0, seconds=2.0, events_per_s=100)  # 200 rows; 500 event slots
    assert (box._ev_slots, box._ev_copy_margin) == (500, 200)
    for n in range(700):
        box.took(Inbound("master", n, igtl.unpack(wire), n * 0.01), "master")
        k = box.count
        box.end_tick(k * 0.01, k)
    w = box.window(_req(box))  # events 400..699 copied (slots 400..499, 0..199)
    assert w.first_row == 500
    assert [(e[0], e[3].peer, e[3].t_rx) for e in w.events] == [
        (n, n, n * 0.01) for n in range(500, 700)
    ]


def test_events_the_loop_wrote_over_are_dropped_and_the_dump_says_from_which_tick() -> None:
    box, _ = _box(rate=100.0, seconds=1.0, events_per_s=1000)  # 1000 + 3000 event slots
    slots = box._ev_slots
    assert slots == 4000
    for n in range(600):  # 20 events a tick: 12000 events, the ring wrapped
        for e in range(20):
            box.note("e", (n, e))
        k = box.count
        box.end_tick(k * 0.01, k)
    req = _req(box)
    w = box.window(req)
    # the copy's margin: what the loop writes in MARGIN_S (fewer than a chunk)
    assert box._ev_copy_margin == math.ceil(MARGIN_S * 1000) == 2000 < CHUNK
    start = box.ev_count - slots + 2000
    assert w.events[0][3] == divmod(start, 20) == (500, 0) and len(w.events) == 12000 - start
    # the tick of the first event copied may have lost some: the next is the first whole
    assert w.events_whole_from == start // 20 + 1 == 501
    for _ in range(2100):  # the loop goes on while the writer copies, past the margin
        box.note("e", "later")
    w2 = box.window(req)
    lost = box.ev_count + 1 - slots - start
    assert lost == 101 and w2.events == w.events[lost:]
    assert w2.events_whole_from == (start + lost) // 20 + 1 == 506
    w3 = box.window(_req(box, events_end=1000))  # events before the ring: none
    assert w3.events == []
    # a window whose events were all kept: whole from its first tick
    box2, _ = _box(rate=100.0, seconds=1.0)
    _ticks(box2, 10)
    box2.note("n", 1)
    _ticks(box2, 1)
    assert box2.window(_req(box2)).events_whole_from == 0
    # a copy across the ring's end, shorter than a chunk: every event once, in order
    box3, _ = _box(rate=1000.0, seconds=1.0, events_per_s=1000)  # 4000 slots, margin 2000
    for n in range(401):
        for e in range(10):
            box3.note("e", 10 * n + e)
        k = box3.count
        box3.end_tick(k * 0.001, k)
    w = box3.window(_req(box3))  # events 2010..4009: slots 2010..3999, then 0..9
    assert w.first_row == 0 and [ev[3] for ev in w.events] == list(range(2010, 4010))
    assert w.events_whole_from == 202  # tick 201 lost its first event


# ---------------------------------------------------------------------- dump requests
def test_the_transitions_that_dump_the_box() -> None:
    box, p = _box()
    box.on_transition(RobotState.READY, RobotState.ENABLED, "Enable", "", 0.0)
    box.on_transition(RobotState.ENABLED, RobotState.RUNNING, "Run", "", 0.0)
    box.on_transition(RobotState.RUNNING, RobotState.STOPPED, "Stop", "operator Stop", 0.0)
    _ticks(box, 1)
    assert p.requests == [] and box.requested == 0
    assert box._ev_obj[1] == ("ENABLED", "RUNNING", "Run", "")
    assert box._view[0, 2] == 4.0  # the tick ended STOPPED
    box.on_transition(RobotState.STOPPED, RobotState.STOPPED, "loss", "operatorless silence", 0)
    box.on_transition(RobotState.STOPPED, RobotState.FAULT, "fault", "drive 0: nan", 0)
    box.on_transition(RobotState.FAULT, RobotState.ESTOP, "EStop", "operator EStop", 0)
    _ticks(box, 1)
    (req,) = p.requests
    assert req.causes == [
        ("stopped", "operatorless silence"), ("fault", "drive 0: nan"), ("estop", "operator EStop")
    ]  # fmt: skip
    assert box._view[1, 2] == 6.0
    assert [box._ev_kind[i] for i in range(box.ev_count)] == [
        TRANSITION, TRANSITION, TRANSITION, TRANSITION, REQUEST, TRANSITION, TRANSITION
    ]  # fmt: skip
    assert (box._ev_where[4], box._ev_obj[4]) == ("stopped", "operatorless silence")


def test_a_request_on_the_loop_closes_its_window_at_the_end_of_the_tick() -> None:
    box, p = _box()
    _ticks(box, 5)
    p.data.clock.t = 0.005
    path = box.request("Operator", "first")
    assert path == str(Path("bb") / "r-20231114T221523.255Z-operator") and p.requests == []
    assert box.request("fault", "second") == path  # the same dump
    assert box.requested == 2
    box.note("after", 1)
    _ticks(box, 1)
    (req,) = p.requests
    assert req.causes == [("Operator", "first"), ("fault", "second")]
    assert (req.end, req.events_end, req.k, req.t, req.wall) == (6, 2, 5, 0.005, WALL + 0.005)
    assert req.name == "r-20231114T221523.255Z-operator" and req.path == Path("bb") / req.name
    _ticks(box, 1)
    assert len(p.requests) == 1  # handed over once
    # another in the same millisecond: a name of its own
    p.data.clock.t = 0.005
    assert box.request("operator", "") == path + "-2"
    _ticks(box, 1)
    assert box.request("operator", "") == path + "-3"
    _ticks(box, 1)
    assert [r.name[-2:] for r in p.requests] == ["or", "-2", "-3"]


def test_a_request_from_another_thread_closes_its_window_at_once() -> None:
    box, p = _box()
    _ticks(box, 4)
    box.note("n", 1)
    out: list[str] = []
    t = threading.Thread(target=lambda: out.append(box.request("worker", "why")))
    t.start()
    t.join()
    (req,) = p.requests
    assert (req.end, req.events_end) == (4, 1) and out == [str(req.path)]
    assert list(box._off_loop) == [(4, REQUEST, "worker", "why")]
    # the tick under way (4) is not in the window: nor are its events, the loop's or others'
    w = box.window(req)
    assert w.rows[:, 1].tolist() == [0.0, 1.0, 2.0, 3.0] and w.events == []


def test_a_dump_name_is_made_of_the_cause_in_words_and_digits() -> None:
    box, p = _box()
    assert box.request("Fault: drive 0/1", "").endswith("Z-fault--drive-0-1")
    _ticks(box, 1)
    assert box.request("x" * 40, "").endswith("Z-" + "x" * 32)
    _ticks(box, 1)
    assert box.request("", "").endswith("Z-dump")
    _ticks(box, 1)
    assert box.request("!", "").endswith("Z--")


def test_a_burst_of_dumps_beyond_the_writers_queue_is_refused_and_counted() -> None:
    writer = DumpWriter(lambda req: None, "w")  # not started: nothing taken from its queue
    box, _ = _box(writer=writer)
    for n in range(QUEUE_DEPTH + 2):
        box.request(f"c{n}", "")
        _ticks(box, 1)
    assert box.requested == QUEUE_DEPTH + 2 and box.refused == 2
    assert writer._outstanding == QUEUE_DEPTH
    t0 = time.monotonic()
    assert not writer.wait_idle(5.0)  # never started: not idle, and says so at once
    assert time.monotonic() - t0 < 2.0
    stats = box.stats()
    assert stats["requested"] == QUEUE_DEPTH + 2 and stats["refused"] == 2
    nobody, _ = _box()
    nobody.writer = None
    assert nobody.request("operator", "") == "no black box (black_box.enabled is false)"
    assert nobody.requested == 0 and nobody.wait_idle(0.0)


def test_stats_say_what_the_box_holds() -> None:
    box, _ = _box(rate=10.0, seconds=1.0, events_per_s=100)
    assert box.stats() == {
        "enabled": True, "seconds": 1.0, "ticks": 0, "events": 0, "requested": 0,
        "refused": 0, "checkpoints": 0, "checkpoint_max_ms": 0.0, "dir": "bb",
        "written": 0, "failed": 0, "last": "",
    }  # fmt: skip
    _ticks(box, 25)
    for _ in range(20):
        box.note("n", 0)
    box.checkpoints = Checkpoints(list, 10.0, 3)
    box.checkpoints.take(0, 0)
    box.checkpoints.cost_max_s = 0.0012344
    s = box.stats()
    assert (s["ticks"], s["events"], s["checkpoints"], s["checkpoint_max_ms"]) == (10, 20, 1, 1.234)
    _ticks(box, 1)
    for _ in range(100):
        box.note("n", 0)
    assert box.stats()["events"] == 100  # ev_capacity
    box.writer = None
    assert "written" not in box.stats()


def test_resync_and_the_outputs_tap() -> None:
    box, p = _box()
    p.data.state = RobotState.FAULT
    box.resync()
    _ticks(box, 1)
    assert box._view[0, 2] == 5.0
    assert box.outputs_tap(None) is None
    got: list[Any] = []
    rec = SimpleNamespace(record_message=lambda *a: got.append(a))
    tap = box.outputs_tap(rec)
    assert tap is not None
    tap("m", "slicer", 1.5)
    assert got == [("m", "out", "slicer", 1.5)] and box.ev_count == 0  # not kept


def test_a_new_collision_verdict_is_recorded_with_the_tick_the_loop_first_saw_it() -> None:
    guard = SimpleNamespace(verdict=None)
    box, _ = _box(guard=guard)
    _ticks(box, 2)
    assert box.ev_count == 0
    v1 = SimpleNamespace(ok=False)
    guard.verdict = v1
    _ticks(box, 3)
    guard.verdict = SimpleNamespace(ok=True)
    _ticks(box, 1)
    assert box.ev_count == 2
    assert [(box._ev_tick[i], box._ev_kind[i]) for i in range(2)] == [(2, VERDICT), (5, VERDICT)]
    assert box._ev_obj[0] is v1


# ---------------------------------------------------------------------- the writer thread
def test_the_writer_thread_writes_in_order_counts_and_survives_a_failure() -> None:
    done: list[str] = []
    started = threading.Event()
    go = threading.Event()

    def write(req: DumpRequest) -> None:
        started.set()
        go.wait(5.0)
        if req.name.startswith("bad"):
            raise OSError("disk")
        done.append(req.name)

    w = DumpWriter(write, "occ-test-writer")
    assert w.stats() == {"written": 0, "failed": 0, "last": ""}
    w.start()
    w.start()  # once
    reqs = [DumpRequest(n, Path(n), [], 0, 0, 0.0, 0, 0.0) for n in ("a", "bad", "bad2", "c")]
    assert all(w.submit(r) for r in reqs)
    assert started.wait(5.0)
    assert not w.wait_idle(0.05)  # still writing
    go.set()
    assert w.wait_idle(5.0)
    assert done == ["a", "c"] and w.stats() == {"written": 2, "failed": 2, "last": "c"}
    assert w._thread.name == "occ-test-writer" and w._thread.daemon
    w.stop()
    assert not w._thread.is_alive()
    w.stop()  # twice: nothing


def test_stopping_a_writer_never_started_or_one_stuck_in_a_write_returns() -> None:
    DumpWriter(lambda req: None, "w").stop()  # a robot never activated: nothing to end
    go = threading.Event()
    w = DumpWriter(lambda req: go.wait(10.0), "w")
    w.start()
    w.submit(DumpRequest("a", Path("a"), [], 0, 0, 0.0, 0, 0.0))
    t0 = time.monotonic()
    w.stop(0.1)  # the write under way: up to 0.1 s for it, then a second for the thread
    assert time.monotonic() - t0 < 5.0 and w._thread.is_alive()
    go.set()
    w._thread.join(5.0)
    assert not w._thread.is_alive() and w.written == 1


def test_an_inline_writer_writes_in_the_call_and_never_starts_a_thread() -> None:
    names: list[str] = []
    w = DumpWriter(lambda req: names.append(req.name), "w", inline=True)
    w.start()
    assert not w._thread.is_alive()
    assert w.submit(DumpRequest("a", Path("a"), [], 0, 0, 0.0, 0, 0.0))
    assert names == ["a"] and w.wait_idle(0.0) and w.written == 1
    w.stop()


def test_a_writer_that_stops_with_a_full_queue_does_not_wait_forever() -> None:
    go, started = threading.Event(), threading.Event()
    w = DumpWriter(lambda req: (started.set(), go.wait(5.0)), "w")
    w.start()
    assert w.submit(DumpRequest("first", Path("x"), [], 0, 0, 0.0, 0, 0.0))
    assert started.wait(5.0)  # the thread took it: the queue is empty again
    for n in range(QUEUE_DEPTH):
        assert w.submit(DumpRequest(str(n), Path("x"), [], 0, 0, 0.0, 0, 0.0))
    assert not w.submit(DumpRequest("over", Path("x"), [], 0, 0, 0.0, 0, 0.0))
    assert w._outstanding == QUEUE_DEPTH + 1
    t0 = time.monotonic()
    w.stop(0.1)  # the queue still full: the end cannot be queued
    assert time.monotonic() - t0 < 2.0 and w._thread.is_alive()
    go.set()
    assert w.wait_idle(5.0) and w.written == QUEUE_DEPTH + 1
    w.stop()
    assert not w._thread.is_alive()


# ---------------------------------------------------------------------- the dump's files
def _ctx(tells: list[tuple[str, bool]], **kw: Any) -> dump.DumpContext:
    args: dict[str, Any] = {
        "config_yaml": "robot: r\n",
        "provenance": {"software": {"occ": "1"}},
        "tip_mm": lambda q: (q[0] * 1000.0, q[1] * 1000.0, 5.0),
        "max_dumps": 10,
        "max_bytes": 10**9,
        "tell": lambda text, ok: tells.append((text, ok)),
    }
    args.update(kw)
    return dump.DumpContext(**args)


def _filled(tmp_path: Path, **kw: Any) -> tuple[BlackBox, SimpleNamespace, DumpRequest]:
    box, p = _box(rate=100.0, seconds=0.1, directory=tmp_path, **kw)  # 10 rows
    status = igtl.StatusMessage(device_name="r", code=1, status_message="ok")
    for n in range(15):
        p.joints[0].position, p.joints[1].position = 0.001 * n, -0.002 * n
        if n in (3, 12):
            box.wrote([0.5 * n, 0.25 * n], False)
        if n == 11:
            p.data.clock.t = 0.11  # the trigger's time: the rows' wall times are offset by it
            box.sent(status, "*")
            box.on_transition(RobotState.RUNNING, RobotState.STOPPED, "loss", "3 lost", 0.0)
            box.note("loss", {"seq": [4, 5, 6], "inf": math.inf})
        k = box.count
        box.end_tick(k * 0.01, k)
    (req,) = p.requests
    return box, p, req


def test_a_dump_holds_its_ticks_recording_events_and_manifest(tmp_path: Path) -> None:
    tells: list[tuple[str, bool]] = []
    box, p, req = _filled(tmp_path)
    assert (req.end, req.k) == (12, 11)
    ctx = _ctx(tells)
    path = dump.write_dump(box, req, ctx)
    assert path == tmp_path / req.name and path.is_dir()
    assert not list(tmp_path.glob(".*partial"))
    ((text, ok),) = tells
    assert ok and text.startswith(f"black box of stopped (3 lost) written to {path} (10 ticks")
    assert text.endswith(" ticks, 0.1 s, 4 events, 0.0 MB)")
    m = dump.read_manifest(path)
    rows = np.load(path / "ticks.npy")
    assert rows[:, 1].tolist() == list(range(2, 12))
    assert m["format"] == "occ-black-box" and m["version"] == 1 and m["robot"] == "r"
    assert m["causes"] == [{"cause": "stopped", "reason": "3 lost"}]
    assert m["trigger"] == {"tick": 11, "t": 0.11, "wall": WALL + 0.11}
    assert m["window"] == {
        "first_tick": 2, "ticks": 10, "seconds": 0.1, "t_first": 0.02, "t_last": 0.11,
        "rows_lost": 0, "messages": 1, "events": 3, "events_whole_from_tick": 2,
    }  # fmt: skip
    assert m["rate_hz"] == 100.0 and m["clock"] == "real" and m["joints"] == ["a", "b"]
    box.inline_checkpoints = True  # simulated time: collision verdicts taken inline
    req.path = tmp_path / "again"
    again = dump.write_dump(box, req, ctx)
    assert again is not None and dump.read_manifest(again)["clock"] == "simulated"
    assert m["tick_columns"] == box.columns and m["software"] == {"occ": "1"}
    assert m["config_sha256"] == __import__("hashlib").sha256(b"robot: r\n").hexdigest()
    assert m["replay"] == {
        "possible": False,
        "why": "no checkpoint of the robot's state in the window",
    }
    assert m["not_recorded"] == dump.NOT_RECORDED
    # every file it holds, and only those (no replay.pkl without a checkpoint)
    assert m["files"] == sorted(os.listdir(path), key=m["files"].index)
    assert m["files"] == ["manifest.json", "config.yaml", "ticks.npy", "recording.igtl",
                          "events.jsonl"]  # fmt: skip
    assert (path / "config.yaml").read_text() == "robot: r\n"
    assert not (path / dump.REPLAY).exists()
    lines = [json.loads(s) for s in (path / "events.jsonl").read_text().splitlines()]
    assert lines == [
        {"tick": 11, "t": 0.11, "kind": "transition", "from": "RUNNING", "to": "STOPPED",
         "event": "loss", "reason": "3 lost"},
        {"tick": 11, "t": 0.11, "kind": "dump", "cause": "stopped", "reason": "3 lost"},
        {"tick": 11, "t": 0.11, "kind": "note", "what": "loss",
         "value": {"seq": [4, 5, 6], "inf": "inf"}},
    ]  # fmt: skip
    msgs = read_recording(path)
    # tick 11's status, then its row, and a row for every tick
    assert [x.message_type for x in msgs].count("NDARRAY") == 10
    i = [x.message_type for x in msgs].index("STATUS")
    st, row11 = msgs[i], msgs[i + 1]
    assert st.metadata["rec.dir"] == "out" and st.metadata["rec.tick"] == "11"
    assert float(st.metadata["rec.t"]) == 0.11 and st.status_message == "ok"
    assert msgs[i - 1].array.tolist()[0] == 0.1
    assert row11.metadata["columns"] == "t,state,q.a,q.b,sp.a,sp.b,tip.x_mm,tip.y_mm,tip.z_mm"
    assert row11.metadata["robot"] == "r"
    a = row11.array.tolist()
    # the state the tick ended in, the joints, the last setpoint (tick 3's), the tip
    assert a[:2] == [0.11, 4.0] and a[2:4] == [0.011, -0.022] and a[4:6] == [1.5, 0.75]
    assert a[6:] == pytest.approx([11.0, -22.0, 5.0])
    assert req.t == 0.11 and row11.timestamp == pytest.approx(WALL + 0.11, abs=1e-6)
    first = msgs[0].array.tolist()
    assert first[:2] == [0.02, 1.0] and all(math.isnan(v) for v in first[4:6])


def test_a_dump_of_an_effort_robot_with_messages_in_and_out(tmp_path: Path) -> None:
    """A haptic master's rows end with its efforts; every message in and out is in the
    recording with its tick, a cell heartbeat and a driver's error only in the events."""
    from occ.net.interfaces import Inbound

    tells: list[tuple[str, bool]] = []
    box, p = _box(rate=100.0, seconds=0.1, directory=tmp_path)
    cmd = igtl.StringMessage(device_name="CMD_1", string="x")
    for n in range(6):
        if n == 1:
            box.wrote([2.0, 3.0], True)
        if n == 2:
            box.took(
                Inbound(
                    "master",
                    None,
                    igtl.unpack(
                        igtl.PositionMessage(device_name="m", position=(4.0, 5.0, 6.0)).pack()
                    ),
                    0.015,
                ),
                "master",
            )
            box.took(SimpleNamespace(member="m2"), "cell")
            box.took_request(Inbound("operator", None, cmd, 0.02), "operator")
            box.hook_failed("d0", "read", OSError("bus"))
            box.note("verdictless", None)
        k = box.count
        box.end_tick(k * 0.01, k)
    box.request("operator", "")
    _ticks(box, 1)
    (req,) = p.requests
    path = dump.write_dump(box, req, _ctx(tells))
    assert path is not None and tells[0][1]
    msgs = read_recording(path)
    kinds = [(x.message_type, x.metadata.get("rec.dir"), x.metadata.get("rec.tick")) for x in msgs]
    assert kinds[:3] == [("NDARRAY", None, None)] * 2 + [("POSITION", "in", "2")]
    assert kinds[3] == ("STRING", "in", "2") and kinds[4][0] == "NDARRAY"
    assert msgs[3].metadata["rec.if"] == "operator" and msgs[2].metadata["rec.if"] == "master"
    rows = [x for x in msgs if x.message_type == "NDARRAY"]
    assert rows[0].metadata["columns"].endswith(",tip.z_mm,eff.a,eff.b")
    assert rows[0].array.tolist()[-2:] == [0.0, 0.0]  # no effort written yet: zero
    assert rows[1].array.tolist()[-2:] == [2.0, 3.0] == rows[4].array.tolist()[-2:]
    assert math.isnan(rows[1].array.tolist()[4])  # no position setpoint ever
    m = dump.read_manifest(path)
    assert m["window"]["messages"] == 2 and m["window"]["events"] == 2
    lines = [json.loads(s) for s in (path / "events.jsonl").read_text().splitlines()]
    assert lines == [
        {"tick": 2, "t": 0.02, "kind": "note", "value": None, "what": "verdictless"},
        {"tick": 6, "t": 0.006, "kind": "dump", "cause": "operator", "reason": ""},
    ]


def test_an_event_outside_the_rows_has_no_time_and_a_note_without_a_name_no_what(
    tmp_path: Path,
) -> None:
    box, _ = _box(rate=100.0, seconds=0.1)
    _ticks(box, 3)
    from occ.recording.blackbox import Window

    rows = box._view[:3].copy()
    events = [(5, NOTE, None, 1.5), (3, NOTE, None, 2), (-1, VERDICT, None, (1, 2))]
    events += [(0, NOTE, "first", 0), (1, 99, "x", "y"), (2, NOTE, "last", 1)]
    w = Window(rows, 0, events)
    assert dump._write_events(tmp_path / "e.jsonl", w) == 6
    lines = [json.loads(s) for s in (tmp_path / "e.jsonl").read_text().splitlines()]
    assert lines == [
        {"tick": 5, "t": None, "kind": "note", "value": 1.5},
        {"tick": 3, "t": None, "kind": "note", "value": 2},  # the tick after the last row
        {"tick": -1, "t": None, "kind": "verdict", "value": [1, 2]},
        {"tick": 0, "t": 0.0, "kind": "note", "what": "first", "value": 0},
        {"tick": 1, "t": 0.001, "kind": 99, "what": "x", "value": "y"},
        {"tick": 2, "t": 0.002, "kind": "note", "what": "last", "value": 1},
    ]
    w = Window(rows[1:], 1, [(1, NOTE, None, 0), (0, NOTE, None, 0)])
    dump._write_events(tmp_path / "f.jsonl", w)
    assert [json.loads(s)["t"] for s in (tmp_path / "f.jsonl").read_text().splitlines()] == [
        0.001, None
    ]  # fmt: skip


def test_jsonable_holds_what_json_can() -> None:
    @dataclass
    class V:
        ok: bool
        d: float

        def describe(self) -> str:
            return "described"

    @dataclass
    class Plain:
        x: Any

    class Named:
        name = "link3"

    class Described:
        def describe(self) -> str:
            return "a region"

    class Nameless:
        name = 3

        def __repr__(self) -> str:
            return "N" * 300

    j = dump.jsonable
    assert [j(None), j(True), j(3), j("s"), j(1.5)] == [None, True, 3, "s", 1.5]
    assert [j(math.inf), j(-math.inf), j(math.nan)] == ["inf", "-inf", "nan"]
    assert j(np.array([[1.0, math.inf]])) == [[1.0, "inf"]]
    assert j((1, [2.5])) == [1, [2.5]] and j({1: math.nan}) == {"1": "nan"}
    assert j(V(False, -math.inf)) == {"ok": False, "d": "-inf", "text": "described"}
    assert j(Plain(np.array([1.0]))) == {"x": [1.0]}
    assert j(Named()) == "link3" and j(Described()) == "a region"
    assert j(Nameless()) == "N" * 200 and j(object()).startswith("<object object at")
    # four levels down is the last whole one; below, each container by its repr
    assert j([[[np.array([1.0])]]]) == [[[[1.0]]]]
    assert j([[[[np.array([1.0])]]]]) == [[[["[1.0]"]]]]
    assert j([[[{"a": [1.0]}]]]) == [[[{"a": [1.0]}]]]
    assert j([[[[{"a": [1.0]}]]]]) == [[[[{"a": "[1.0]"}]]]]
    assert j([[[Plain([1.0])]]]) == [[[{"x": [1.0]}]]]
    assert j([[[[Plain([1.0])]]]]) == [[[[{"x": "[1.0]"}]]]]
    assert j([[[[[list(range(100))]]]]]) == [[[[[repr(list(range(100)))[:200]]]]]]
    deep: Any = [[[[[[1.0]]]]]]
    assert j(deep) == [[[[["[1.0]"]]]]]  # four levels down, the rest by its repr
    assert j([[[[[1.0]]]]]) == [[[[[1.0]]]]]


def test_a_dump_goes_beside_another_of_its_name_and_over_a_stale_partial(tmp_path: Path) -> None:
    tells: list[tuple[str, bool]] = []
    box, p, req = _filled(tmp_path)
    (tmp_path / req.name).mkdir()  # another daemon's, in the same millisecond
    (tmp_path / f".{req.name}.partial" / "junk").mkdir(parents=True)
    path = dump.write_dump(box, req, _ctx(tells))
    assert path == tmp_path / f"{req.name}-{os.getpid()}" and (path / dump.MANIFEST).is_file()
    assert not (tmp_path / f".{req.name}.partial").exists()
    assert sorted(os.listdir(tmp_path / req.name)) == []


def test_a_dump_that_cannot_be_written_is_removed_and_told(tmp_path: Path) -> None:
    tells: list[tuple[str, bool]] = []
    box, p, req = _filled(tmp_path)
    ctx = _ctx(tells, config_yaml=None)  # writing it fails half way: not an OSError
    with pytest.raises(TypeError):
        dump.make_dump(box, req, ctx)
    (tmp_path / "blocker").write_text("")
    req.path = tmp_path / "blocker" / req.name  # its parent is a file
    assert dump.write_dump(box, req, _ctx(tells)) is None
    ((text, ok),) = tells
    assert not ok and text.startswith(f"black box of stopped (3 lost) NOT written to {req.path}: ")
    assert "(ENOTDIR)" in text


def test_the_dumps_of_a_robot_are_bounded_oldest_first_the_newest_kept(tmp_path: Path) -> None:
    def made(name: str, size: int, mtime: float) -> Path:
        d = tmp_path / name
        (d / "sub").mkdir(parents=True)
        (d / dump.MANIFEST).write_text("{}")
        (d / "sub" / "f").write_bytes(b"x" * size)
        os.utime(d, (mtime, mtime))
        return d

    a = made("r-3", 100, 1000.0)  # the oldest: not first by name
    b = made("r-1", 100, 2000.0)
    c = made("r-2", 100, 3000.0)
    other = made("q-1", 100, 10.0)  # another robot's
    (tmp_path / "r-4").mkdir()  # no manifest: not a dump
    (tmp_path / "r-file").write_text("")
    (tmp_path / ".r-9.partial").mkdir()  # a crash's
    (tmp_path / ".q-9.partial").mkdir()
    assert sorted(p.name for p in dump.dumps_of(tmp_path, "r")) == ["r-1", "r-2", "r-3"]
    assert list(dump.dumps_of(tmp_path / "none", "r")) == []
    assert dump._size(a) == 102
    assert dump.prune(tmp_path, "r", 3, 10**6, keep=c) == []
    assert not (tmp_path / ".r-9.partial").exists() and (tmp_path / ".q-9.partial").exists()
    assert dump.prune(tmp_path, "r", 2, 10**6, keep=c) == [a]
    a = made("r-3", 100, 1000.0)
    assert dump.prune(tmp_path, "r", 3, 204, keep=c) == [a]  # 306 bytes: one goes
    assert dump.prune(tmp_path, "r", 3, 204, keep=c) == []  # exactly the bound
    assert dump.prune(tmp_path, "r", 1, 10**6, keep=b) == [c]  # the one kept is skipped
    assert [p.name for p in dump.dumps_of(tmp_path, "r")] == ["r-1"] and other.is_dir()
    # the same time: by name
    made("r-6", 10, 5000.0)
    made("r-5", 10, 5000.0)
    assert dump.prune(tmp_path, "r", 1, 10**6, keep=tmp_path / "r-6") == [b, tmp_path / "r-5"]


def test_a_dump_or_partial_that_cannot_be_removed_does_not_fail_the_bound(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    for name in ("r-1", "r-2"):
        (tmp_path / name).mkdir()
        (tmp_path / name / dump.MANIFEST).write_text("{}")
    (tmp_path / ".r-0.partial").mkdir()
    tried: list[str] = []

    def rmtree(path: Any, ignore_errors: bool = False) -> None:
        tried.append(Path(path).name)
        if not ignore_errors:
            raise PermissionError(13, "busy")

    monkeypatch.setattr(dump.shutil, "rmtree", rmtree)
    os.utime(tmp_path / "r-1", (1.0, 1.0))
    assert dump.prune(tmp_path, "r", 1, 10**6, keep=tmp_path / "r-2") == [tmp_path / "r-1"]
    assert tried == [".r-0.partial", "r-1"]


def test_a_manifest_is_read_only_from_a_dump(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="not a black box dump"):
        dump.read_manifest(tmp_path)
    (tmp_path / dump.MANIFEST).write_text("{")
    with pytest.raises(ValueError, match="not a black box dump"):
        dump.read_manifest(tmp_path)
    (tmp_path / dump.MANIFEST).write_text('{"format": "other"}')
    with pytest.raises(ValueError, match=r"not a black box dump \(format 'other'\)"):
        dump.read_manifest(str(tmp_path))
    (tmp_path / dump.MANIFEST).write_text('{"format": "occ-black-box", "x": 1}')
    assert dump.read_manifest(tmp_path) == {"format": "occ-black-box", "x": 1}


class _Cp:
    """A checkpointer's pickling (occ/core/checkpoint.py) as a dump's writer calls it."""

    def __init__(self, fail: bool = False) -> None:
        self.fail = fail
        self.paced: list[Any] = []

    def dumps(self, values: Any, baseline: Any, pace: Any) -> bytes:
        self.paced.append(pace)
        return pickle.dumps(("cp", values, baseline))

    def dumps_values(self, values: Any) -> bytes:
        if self.fail:
            raise RuntimeError("unpicklable")
        return pickle.dumps(values)


def test_replay_pkl_holds_the_checkpoint_and_the_loops_inputs(tmp_path: Path) -> None:
    box, p = _box(rate=100.0, seconds=0.2, events_per_s=100)
    box.make_checkpointer = lambda: SimpleNamespace(take=lambda: ["state", box.count])
    box.inline_checkpoints = True
    p.data.clock.t = 2.5
    box.start()
    box.checkpointer = _Cp()
    for n in range(40):
        box.took(SimpleNamespace(member=n), "cell")  # an input
        box.note("n", n)  # not an input
        box.sent(f"out{n}", "*")
        if n == 20:
            box.took_request(f"cmd{n}", "operator")
            box.hook_failed("d", "write", ValueError("v"))
            box.on_transition(RobotState.RUNNING, RobotState.FAULT, "fault", "x", 0.0)
        k = box.count
        box.end_tick(k * 0.01, k)
    (req,) = p.requests
    w = box.window(req)
    assert w.first_row == 0 and w.checkpoint == ["state", 0]
    entry = dump._write_replay(tmp_path / "r.pkl", box, w)
    inputs = [e for e in w.loop_events if e[1] in (IN, CMD, HOOK, TRANSITION)]
    assert entry == {"possible": True, "from_tick": 0, "inputs": len(inputs)} and len(inputs) == 24
    blob = pickle.loads((tmp_path / "r.pkl").read_bytes())
    assert blob["built_at"] == 2.5
    assert pickle.loads(blob["checkpoint"]) == ("cp", ["state", 0], ["state", 0])
    assert box.checkpointer.paced == [box.pace]
    got = [e for piece in blob["inputs"] for e in pickle.loads(piece)]
    assert len(blob["inputs"]) == 2 and got == [tuple(e) for e in inputs]
    # events overwritten before the window's first tick: written, but not whole
    w.events_whole_from = 5
    entry = dump._write_replay(tmp_path / "r2.pkl", box, w)
    assert entry["possible"] is False and entry["why"] == "inputs before tick 5 were overwritten"
    assert entry["from_tick"] == 0 and (tmp_path / "r2.pkl").is_file()
    w.events_whole_from = 0
    box.checkpointer = _Cp(fail=True)
    entry = dump._write_replay(tmp_path / "r3.pkl", box, w)
    assert entry == {
        "possible": False,
        "why": "inputs could not be written: RuntimeError('unpicklable')",
    }
    assert not (tmp_path / "r3.pkl").exists()
    for cut in ("checkpointer", "checkpoints"):
        saved = getattr(box, cut)
        setattr(box, cut, None)
        assert dump._write_replay(tmp_path / "r4.pkl", box, w) == {
            "possible": False, "why": "no checkpoint of the robot's state in the window"
        }  # fmt: skip
        setattr(box, cut, saved)
    w.checkpoint = None
    assert dump._write_replay(tmp_path / "r4.pkl", box, w) == {
        "possible": False, "why": "no checkpoint of the robot's state in the window"
    }  # fmt: skip
    assert not (tmp_path / "r4.pkl").exists()


@pytest.mark.skipif(not hasattr(os, "fork"), reason="the real clock's writer forks")
def test_the_real_clocks_writer_writes_in_a_child_and_tells_in_the_parent(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The child writes and ends with os._exit (0 written, 1 not: never returning into the
    daemon's code it is a copy of); the parent (this process) never exits, reaps the child
    and tells the alert once."""
    me, real_exit, real_waitpid = os.getpid(), os._exit, os.waitpid
    exits = tmp_path / "exits"
    reaped: list[int] = []

    def _exit(code: Any) -> None:
        if os.getpid() == me:
            raise AssertionError(f"the parent called os._exit({code!r})")
        with open(exits, "a") as f:  # the child's last word, for the parent to read
            f.write(f"{code!r}\n")
        real_exit(code if isinstance(code, int) else 3)

    def waitpid(pid: int, options: int) -> tuple[int, int]:
        got = real_waitpid(pid, options)
        reaped.append(os.waitstatus_to_exitcode(got[1]))
        return got

    monkeypatch.setattr(os, "_exit", _exit)
    monkeypatch.setattr(os, "waitpid", waitpid)
    tells: list[tuple[str, bool]] = []
    box, p, req = _filled(tmp_path / "bb")
    paced: list[int] = []
    box.pace = lambda: paced.append(os.getpid())
    path = dump.write_dump_forked(box, req, _ctx(tells), timeout_s=20.0)
    assert path == tmp_path / "bb" / req.name and (path / dump.MANIFEST).is_file()
    ((text, ok),) = tells  # told once, by the parent
    assert ok and text.startswith(f"black box of stopped (3 lost) written to {path} (10 ticks")
    assert paced == [me]  # the parent paced the fork; the child never paces
    assert np.load(path / "ticks.npy")[:, 1].tolist() == list(range(2, 12))
    assert exits.read_text() == "0\n" and reaped == [0]
    # a child that fails: told as a failure, with its reason
    tells.clear()
    bad = _ctx(tells, config_yaml=None)
    assert dump.write_dump_forked(box, req, bad, timeout_s=20.0) is None
    ((text, ok),) = tells
    assert not ok and text.startswith("black box of stopped (3 lost) NOT written: TypeError(")
    assert exits.read_text() == "0\n1\n" and reaped == [0, 1]
    # a child that cannot write: its own words
    tells.clear()
    (tmp_path / "blocker").write_text("")
    req.path = tmp_path / "blocker" / req.name
    assert dump.write_dump_forked(box, req, _ctx(tells), timeout_s=20.0) is None
    ((text, ok),) = tells
    assert not ok and text.startswith(f"black box of stopped (3 lost) NOT written to {req.path}")
    assert reaped == [0, 1, 0]


@pytest.mark.skipif(not hasattr(os, "fork"), reason="the real clock's writer forks")
def test_a_dumps_child_that_does_not_answer_is_killed_and_told(tmp_path: Path) -> None:
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # a child that says nothing
        os.close(r)
        time.sleep(30)
        os._exit(0)
    os.close(w)
    t0 = time.monotonic()
    assert dump._child_answer(r, pid, 0.3) == {}
    assert 0.3 <= time.monotonic() - t0 < 5.0
    with pytest.raises(ChildProcessError):
        os.waitpid(pid, os.WNOHANG)  # killed and reaped
    with pytest.raises(OSError):
        os.close(r)  # closed
    # an answer in pieces, and one that is no JSON
    for said, want in ((b'{"ok": true, "path": "p", "text": "t"}', {"ok": True, "path": "p",
                        "text": "t"}), (b"garbage", {}), (b"", {})):  # fmt: skip
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:
            os.close(r)
            for i in range(0, len(said), 5):
                os.write(w, said[i : i + 5])
                time.sleep(0.01)
            os._exit(0)
        os.close(w)
        assert dump._child_answer(r, pid, 10.0) == want
    # a timeout before the child answers tells a failure with no answer
    tells: list[tuple[str, bool]] = []
    box, p, req = _filled(tmp_path)
    ctx = _ctx(tells, tip_mm=lambda q: (time.sleep(0.05), (0.0, 0.0, 0.0))[1])
    assert dump.write_dump_forked(box, req, ctx, timeout_s=0.2) is None
    assert tells == [("black box of stopped (3 lost) NOT written: no answer", False)]


def test_a_dump_asked_from_another_thread_before_the_first_tick_has_no_rows(
    tmp_path: Path,
) -> None:
    tells: list[tuple[str, bool]] = []
    box, p = _box(rate=100.0, seconds=0.1, directory=tmp_path)
    out: list[str] = []
    t = threading.Thread(target=lambda: out.append(box.request("operator", "early")))
    t.start()
    t.join()
    (req,) = p.requests
    assert (req.end, req.events_end) == (0, 0)
    path = dump.write_dump(box, req, _ctx(tells))
    assert path is not None and tells[0][1]
    m = dump.read_manifest(path)
    assert m["window"]["ticks"] == 0 and m["window"]["t_first"] is None
    assert m["window"]["t_last"] is None and m["window"]["events"] == 0  # no tick: no events
    assert np.load(path / "ticks.npy").shape == (0, box.width)
    assert [x.message_type for x in read_recording(path)] == []


def test_waiting_for_the_writer_gives_up_after_its_timeout() -> None:
    go = threading.Event()
    w = DumpWriter(lambda req: go.wait(5.0), "w")
    box, _ = _box(writer=w)
    w.start()
    box.request("operator", "")
    _ticks(box, 1)
    t0 = time.monotonic()
    assert not box.wait_idle(0.1) and time.monotonic() - t0 < 3.0
    go.set()
    assert box.wait_idle(5.0)
    box.stop()
    assert not w._thread.is_alive()


def test_a_dump_that_fails_half_way_leaves_no_partial_directory(tmp_path: Path) -> None:
    tells: list[tuple[str, bool]] = []
    box, p, req = _filled(tmp_path)

    def tip_mm(q: list[float]) -> tuple[float, float, float]:
        raise OSError(28, "No space left on device")

    assert dump.write_dump(box, req, _ctx(tells, tip_mm=tip_mm)) is None
    assert os.listdir(tmp_path) == []
    ((text, ok),) = tells
    assert not ok and text.endswith(": No space left on device (ENOSPC)")


def test_the_manifest_holds_what_the_software_says_of_itself_paths_as_text(
    tmp_path: Path,
) -> None:
    tells: list[tuple[str, bool]] = []
    box, p, req = _filled(tmp_path)
    prov = {"software": {"occ": "1"}, "urdf": {"path": tmp_path / "arm.urdf", "sha256": "00"}}
    path = dump.write_dump(box, req, _ctx(tells, provenance=prov))
    assert path is not None
    m = dump.read_manifest(path)
    assert m["urdf"] == {"path": str(tmp_path / "arm.urdf"), "sha256": "00"}


def test_the_loops_events_before_a_checkpoint_are_not_replayed_after_it() -> None:
    """A replay starts from a checkpoint's state: the loop's events of that tick taken before
    it (the configuration's and enabling's transitions before the first tick) are in the
    dump but not among the inputs fed again."""
    box, p = _box(rate=100.0, seconds=1.0)
    box.make_checkpointer = lambda: SimpleNamespace(take=lambda: ["state"])
    box.inline_checkpoints = True
    box.note("before", 0)
    box.start()  # the first checkpoint: row 0, after one event
    box.note("after", 1)
    _ticks(box, 3)
    w = box.window(_req(box))
    assert w.first_row == 0 and [e[3] for e in w.events] == [0, 1]
    assert [e[3] for e in w.loop_events] == [1]


def test_a_checkpoint_whose_rows_were_written_over_is_no_replays_start() -> None:
    box, p = _box(rate=10.0, seconds=1.0)  # 10 rows, 40 slots, a checkpoint every 10
    box.make_checkpointer = lambda: SimpleNamespace(take=lambda: ["state", box.count])
    box.inline_checkpoints = True
    box.start()
    _ticks(box, 45)
    req = _req(box)
    w = box.window(req)
    assert (w.first_row, w.checkpoint, w.rows_lost) == (30, ["state", 30], 0)
    advanced: list[int] = []

    def pace() -> None:  # the loop goes on while the writer copies: rows 30..35 written over
        if not advanced:
            advanced.append(box.count)
            _ticks(box, 30)

    box.pace = pace
    w = box.window(req)
    assert advanced == [45] and box.count == 75
    assert w.rows_lost == 6 and w.first_row == 36 and w.checkpoint is None
    assert w.rows[:, 1].tolist() == list(range(36, 45))


def _one_event_a_tick(box: BlackBox, n: int) -> None:
    for _ in range(n):
        box.note("tick", box.count)
        k = box.count
        box.end_tick(k * 0.01, k)


def _advance_at(box: BlackBox, call: int, n: int) -> list[int]:
    """The loop goes on by ``n`` ticks at the writer's ``call``-th hand-back (its copy)."""
    calls: list[int] = []

    def pace() -> None:
        calls.append(box.count)
        if len(calls) == call:
            _one_event_a_tick(box, n)

    box.pace = pace
    return calls


def test_events_written_over_during_the_copy_are_dropped_and_whole_from_says_so() -> None:
    # 100 rows, 400 row and 400 event slots; the writer leaves 200 events to the loop
    box, _ = _box(rate=100.0, seconds=1.0, events_per_s=100)
    assert (box._ev_slots, box._ev_copy_margin) == (400, 200)
    _one_event_a_tick(box, 150)
    req = _req(box)  # events 0..149: all in the ring, copied from 0
    _advance_at(box, 2, 300)  # the rows copied, then the loop writes 300 more events
    w = box.window(req)
    # event 450 may be half written in slot 50: events up to 50 are gone
    assert w.first_row == 50 and [e[3] for e in w.events] == list(range(51, 150))
    assert w.events_whole_from == 52  # tick 51 is whole (one event a tick); the rule says 52
    # a copy that starts one event in: that event's tick may have lost it
    box, _ = _box(rate=100.0, seconds=1.0, events_per_s=100)
    for _ in range(67):
        for e in range(3):
            box.note("e", e)
        k = box.count
        box.end_tick(k * 0.01, k)
    w = box.window(_req(box))  # 201 events: from event 1
    assert w.first_row == 0 and len(w.events) == 200 and w.events_whole_from == 1
    # every event of the window written over as it was copied: none whole
    box, _ = _box(rate=100.0, seconds=1.0, events_per_s=100)
    _one_event_a_tick(box, 30)
    req = _req(box)
    _advance_at(box, 2, 500)
    w = box.window(req)
    assert w.events == [] and w.events_whole_from == w.first_row + len(w.rows) == 30


def test_the_loops_events_after_the_checkpoint_survive_a_copy_the_loop_overtook() -> None:
    box, _ = _box(rate=100.0, seconds=1.0, events_per_s=100)
    box.make_checkpointer = lambda: SimpleNamespace(take=lambda: ["state", box.count])
    box.inline_checkpoints = True
    box.start()
    _one_event_a_tick(box, 300)
    req = _req(box)  # rows 200..299 from the checkpoint of 200; events copied from 100
    calls = _advance_at(box, 2, 250)  # after the rows: events 100..150 written over
    w = box.window(req)
    assert calls[:2] == [300, 300] and w.first_row == 200 and w.checkpoint == ["state", 200]
    assert [e[3] for e in w.events] == list(range(200, 300)) == [e[3] for e in w.loop_events]
    assert w.events_whole_from == 200


def test_a_box_without_a_checkpointer_starts_and_one_disabled_says_so_in_its_stats() -> None:
    box, _ = _box()
    box.start()  # no checkpointer (a tool's box): no checkpoints, no replay's start
    assert box.checkpoints is None and box.checkpointer is None
    _ticks(box, 2)
    assert not box.spare(True) and box.window(_req(box)).checkpoint is None
    off = BlackBox("r", ["a"], 100.0, 2.0, 150, enabled=False)  # never bound (wiring)
    assert off.stats() == {
        "enabled": False, "seconds": 0.0, "ticks": 0, "events": 0, "requested": 0,
        "refused": 0, "checkpoints": 0, "checkpoint_max_ms": 0.0, "dir": ".",
    }  # fmt: skip


def test_the_events_of_other_threads_are_bounded() -> None:
    from occ.recording.blackbox import OFF_LOOP_EVENTS

    box, _ = _box()

    def burst() -> None:
        for n in range(OFF_LOOP_EVENTS + 10):
            box.note("n", n)

    t = threading.Thread(target=burst)
    t.start()
    t.join()
    assert len(box._off_loop) == OFF_LOOP_EVENTS and box._off_loop[0][3] == 10


def test_an_alert_names_every_cause_and_its_reason_when_it_has_one() -> None:
    req = DumpRequest("x", Path("x"), [("fault", "drive 0"), ("operator", "")], 0, 0, 0.0, 0, 0.0)
    assert dump._causes(req) == "fault (drive 0); operator"


def test_a_one_joint_robots_dump_has_its_setpoints_and_efforts(tmp_path: Path) -> None:
    tells: list[tuple[str, bool]] = []
    box, p = _box(rate=100.0, seconds=0.1, joints=("a",), directory=tmp_path)
    box.wrote([0.5], False)
    box.wrote([2.0], True)
    _ticks(box, 2)
    box.request("operator", "")
    _ticks(box, 1)
    (req,) = p.requests
    path = dump.write_dump(box, req, _ctx(tells, tip_mm=lambda q: (q[0], 0.0, 0.0)))
    assert path is not None and tells[0][1]
    rows = [x.array.tolist() for x in read_recording(path) if x.message_type == "NDARRAY"]
    # t, state, q, sp, the tip, the effort: the last written kept
    assert [r[3] for r in rows] == [0.5] * 3 and [r[-1] for r in rows] == [2.0] * 3
