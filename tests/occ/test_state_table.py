"""The State Data Table (issue 12): the ring, its reader, GetStateTable, and the recording.

The ring is tested alone (wrap-around, windows, no allocation per row, a reader racing the
writer); then on the collaborative slave in simulated time: the table's rows against what the
recorder (occ/recording/record.py) wrote for the same ticks, and the NDARRAY an operator gets.
"""

from __future__ import annotations

import threading
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

import igtl
from occ.kinematics.frame import Frame
from occ.joint import Joint, JointLimits
from occ.core.loader import parse_config
from occ.recording.record import STATE_DEVICE, Recorder, read_recording
from occ.core.safety import RobotState
from occ.core.statetable import MAX_ROWS, StateTable, capacity_for
from occ_testkit.testing import SimRobot

from .test_collab import SLAVE, Collab, error_of, handover, ok, wait_for

NAMES = ("yaw", "pitch", "insertion")


def _joints() -> list[Joint]:
    return [Joint(n, "revolute", JointLimits(-1.0, 1.0, 1.0, 10.0), 0.0) for n in NAMES]


def _table(capacity: int) -> StateTable:
    return StateTable(NAMES, capacity, Frame.builtin("occ_slave"))


def _fill(table: StateTable, n: int, joints: list[Joint], t0: int = 0) -> None:
    for k in range(t0, t0 + n):
        for i, j in enumerate(joints):
            j.effort = k + i / 10
        q = [0.001 * k, 0.35, 0.05]
        table.write(k * 0.001, 3.0, float(k % 2), q, [v + 1e-4 for v in q], joints)


def test_the_ring_keeps_the_last_rows_in_order() -> None:
    joints = _joints()
    table = _table(100)
    _fill(table, 250, joints)
    raw = table.rows()
    assert len(raw) == 100 and table.count == 250
    assert np.allclose(raw[:, 0], np.arange(150, 250) * 0.001)  # oldest first
    out = table.window()
    c = table.columns
    assert out.shape == (100, len(c)) and c[:2] == ["t", "state"] and c[-1] == "owner"
    assert np.array_equal(out[:, c.index("eff.pitch")], np.arange(150, 250) + 0.1)
    assert np.array_equal(out[:, c.index("owner")], np.arange(150, 250) % 2)
    assert np.allclose(out[:, c.index("sp.yaw")] - out[:, c.index("q.yaw")], 1e-4)
    # the tip is forward kinematics of q (mm), computed by the reader
    frame = Frame.builtin("occ_slave")
    row = out[-1]
    tip = frame.fk([row[c.index("q.yaw")], row[c.index("q.pitch")], row[c.index("q.insertion")]])
    assert row[c.index("tip.x_mm")] == tip[0, 3] * 1000.0
    assert row[c.index("tip.z_mm")] == tip[2, 3] * 1000.0


def test_windows_since_and_decimation() -> None:
    joints = _joints()
    table = _table(1000)
    _fill(table, 500, joints)
    assert len(table.window(0.1)) == 101  # the newest row's time minus 0.1 s, both ends in
    assert table.window(since=0.4)[0, 0] == pytest.approx(0.401)
    assert len(table.window(since=0.499)) == 0
    every = table.window(0.01, every=5)
    assert np.allclose(every[:, 0], [0.489, 0.494, 0.499])  # the newest row always in
    assert len(_table(5).window()) == 0  # nothing written yet
    assert capacity_for(10.0, 1000.0) == 10_000 and MAX_ROWS == 65535


def test_a_row_costs_no_allocation() -> None:
    joints = _joints()
    table = _table(2000)
    _fill(table, 2000, joints)  # warm: every slot written once
    q, sp = [0.1, 0.2, 0.03], [0.1, 0.2, 0.03]
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for k in range(5000):
            table.write(k * 0.001, 3.0, 0.0, q, sp, joints)
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert grown < 1024, grown  # 5000 rows, the ring wrapped 2.5 times: nothing kept


def test_a_reader_racing_the_writer_never_gets_a_torn_or_stale_row() -> None:
    joints = _joints()
    table = _table(64)
    stop = threading.Event()
    bad: list[str] = []

    def read() -> None:
        while not stop.is_set():
            raw = table.rows()
            t = raw[:, 0]
            # every row is whole (its q.yaw matches its time) and rows are consecutive
            if len(raw) and not np.allclose(raw[:, 3], t):
                bad.append("torn")
            if len(raw) > 1 and not np.allclose(np.diff(t), 0.001):
                bad.append("order")

    reader = threading.Thread(target=read)
    reader.start()
    try:
        for k in range(200_000):
            table.write(k * 0.001, 3.0, 0.0, (k * 0.001, 0.0, 0.0), (0.0, 0.0, 0.0), joints)
    finally:
        stop.set()
        reader.join()
    assert not bad, bad[:5]


def _with_table(seconds: float, *, recording: bool = False) -> str:
    text = SLAVE.read_text().replace(
        "state_table: {seconds: 10.0}", f"state_table: {{seconds: {seconds}}}"
    )
    if recording:
        text = text.replace(
            "recording: {path: null, rate_hz: 100}", "recording: {path: null, rate_hz: 1000}"
        )
    return text


def test_the_table_matches_the_recording(tmp_path: Path) -> None:
    """Same ticks, same numbers: the recorder's OCCState rows (written at the loop rate here)
    and the table's, column for column (t, state, q, setpoints, tip), across a hand-over."""
    cfg = parse_config(_with_table(2.0, recording=True), base_dir=SLAVE.parent)
    path = tmp_path / "run.igtl"
    recorder = Recorder(path, rate_hz=1000.0).start()
    c = Collab(cfg)
    c.sim.close()  # rebuilt with the recorder
    c.sim = SimRobot(cfg, recorder=recorder)
    c.robot = c.sim.robot
    c.masters = {
        "mentor": c.sim.peer("mentor", address=("127.0.0.1", 41000)),
        "trainee": c.sim.peer("trainee", address=("127.0.0.1", 42000)),
    }
    c.bedside = c.sim.peer("operator")
    c.desks = {"mentor": c.sim.peer("mentor_desk"), "trainee": c.sim.peer("trainee_desk")}
    try:
        c.running()
        c.step_ms(700)
        assert ok(c.command(c.desks["mentor"], "Handover", handover("trainee")))
        c.step_ms(1200)  # 2203 ticks in all: the 2 s ring has wrapped
        table = c.robot.state_table
        assert table is not None
        rows = table.window()
    finally:
        c.close()
        recorder.close()
    recorded = np.array([m.array for m in read_recording(path) if m.device_name == STATE_DEVICE])
    assert len(rows) == 2000 and len(recorded) > 1900
    width = recorded.shape[1]  # t, state, q, sp, tip: the table's first columns
    assert table.columns[:width] == recorded_columns(path)
    by_t = {row[0]: row for row in rows}
    common = [r for r in recorded if r[0] in by_t]
    assert len(common) > 1900  # every recorded tick the table still holds
    for r in common:
        assert np.array_equal(by_t[r[0]][:width], r), r[0]
    owner = rows[:, table.columns.index("owner")]
    assert set(owner[:500]) == {0.0} and owner[-1] == 1.0  # mentor, then trainee
    assert set(rows[:, 1]) == {3.0}  # RUNNING throughout


def recorded_columns(path: Path) -> list[str]:
    for m in read_recording(path):
        if m.device_name == STATE_DEVICE:
            return m.metadata["columns"].split(",")
    raise AssertionError("no state rows")


def test_getstatetable_answers_an_ndarray() -> None:
    c = Collab(parse_config(_with_table(1.0), base_dir=SLAVE.parent))
    try:
        c.running()
        c.step_ms(1500)
        op = c.desks["trainee"]
        cid = op.send_command("GetStateTable", '<Command Name="GetStateTable" Seconds="0.5"/>')
        c.tick()
        assert wait_for(lambda: op.reply_to(cid) is not None)
        reply = op.reply_to(cid)
        assert reply is not None and ok(reply), reply.metadata
        (arr,) = op.messages("NDARRAY", "StateTable")
        data = arr.array  # type: ignore[attr-defined]
        columns = arr.metadata["columns"].split(",")
        assert data.shape == (501, len(columns)) and columns[-1] == "owner"
        assert arr.metadata["owners"] == "mentor,trainee"
        assert np.allclose(np.diff(data[:, 0]), 0.001)  # every tick: full rate
        assert "501 rows" in reply.metadata["Message"]
        assert reply.metadata["Message"].endswith("; columns " + ",".join(columns))
        # a viewer may read it too (it only reads)
        view = c.slicer
        cid = view.send_command(
            "GetStateTable", '<Command Name="GetStateTable" Since="1.6" Every="10"/>'
        )
        c.tick()
        assert wait_for(lambda: view.reply_to(cid) is not None)
        (small,) = view.messages("NDARRAY", "StateTable")
        assert 0 < len(small.array) <= 11 and small.array[0, 0] > 1.6  # type: ignore[attr-defined]
        # bad arguments are answered at once, and change nothing
        for text in ('Seconds="-1"', 'Every="0"', 'Seconds="soon"'):
            cid = op.send_command("GetStateTable", f'<Command Name="GetStateTable" {text}/>')
            c.tick()
            reply = op.reply_to(cid)
            assert reply is not None and "GetStateTable" in error_of(reply)
        assert c.robot.state is RobotState.RUNNING
    finally:
        c.close()


def test_no_table_no_cost_and_a_clear_refusal() -> None:
    sim = SimRobot(SLAVE.parent.parent / "slave.yaml")
    try:
        assert sim.robot.state_table is None
        op = sim.peer("operator")
        cid = op.send_command("GetStateTable")
        sim.tick()
        reply = op.reply_to(cid)
        assert reply is not None and "state_table.seconds" in error_of(reply)
        assert isinstance(reply, igtl.Message)
    finally:
        sim.close()


# ---------------------------------------------------------------------------- the ring's edges
# (issue 29: the mutation run of occ/core/statetable.py, docs/VERIFICATION.md)


def test_a_table_of_one_row_keeps_the_newest_and_none_is_refused() -> None:
    joints = _joints()
    one = _table(1)
    assert one.window().shape == (0, len(one.columns))
    _fill(one, 3, joints)
    assert one.rows()[:, 0].tolist() == [0.002]  # the newest of the three
    assert one.stats() == {"rows": 1, "capacity": 1, "written": 3}
    with pytest.raises(ValueError, match=r"^capacity must be >= 1, got 0$"):
        _table(0)
    # seconds x rate, rounded up, and never less than one row
    assert capacity_for(0.0001, 1000.0) == 1
    assert capacity_for(0.0011, 1000.0) == 2
    assert capacity_for(2.0, 250.0) == 500


def test_stats_report_the_rows_held_the_capacity_and_the_rows_written() -> None:
    joints = _joints()
    table = _table(10)
    assert table.stats() == {"rows": 0, "capacity": 10, "written": 0}
    _fill(table, 4, joints)
    assert table.stats() == {"rows": 4, "capacity": 10, "written": 4}
    _fill(table, 30, joints, t0=4)
    assert table.stats() == {"rows": 10, "capacity": 10, "written": 34}


def test_every_second_row_keeps_the_newest() -> None:
    joints = _joints()
    table = _table(100)
    _fill(table, 10, joints)
    assert np.allclose(table.window(every=2)[:, 0], [0.001, 0.003, 0.005, 0.007, 0.009])
    assert np.allclose(table.window(every=1)[:, 0], np.arange(10) * 0.001)


def test_a_reply_holds_at_most_max_rows_the_newest() -> None:
    """An NDARRAY dimension is a uint16: a longer window is cut to its newest 65535 rows."""
    joints = _joints()
    table = _table(MAX_ROWS + 10)
    q = [0.0, 0.35, 0.05]
    for k in range(MAX_ROWS + 10):
        table.write(float(k), 3.0, 0.0, q, q, joints)
    out = table.window()
    assert out.shape == (MAX_ROWS, len(table.columns))
    assert out[0, 0] == 10.0 and out[-1, 0] == MAX_ROWS + 9.0


def test_the_columns_of_a_two_joint_robot() -> None:
    """Not only the shipped three-joint arms: the column groups follow the joint count."""
    frame = Frame.from_urdf(Path(__file__).parent / "data" / "robots" / "tiny.urdf", "tool_tip")
    joints = [
        Joint("yaw", "revolute", JointLimits(-1.0, 1.0, 2.0, 10.0), 0.0),
        Joint("insertion", "prismatic", JointLimits(0.0, 0.1, 0.05, 20.0), 0.0),
    ]
    table = StateTable(["yaw", "insertion"], 4, frame)
    joints[0].effort, joints[1].effort = 1.5, -2.5
    table.write(0.25, 4.0, 1.0, [0.3, 0.02], [0.31, 0.021], joints)
    (row,) = table.window()
    assert table.columns == [
        "t", "state", "q.yaw", "q.insertion", "sp.yaw", "sp.insertion",
        "tip.x_mm", "tip.y_mm", "tip.z_mm", "eff.yaw", "eff.insertion", "owner",
    ]  # fmt: skip
    tip = frame.fk([0.3, 0.02])[:3, 3] * 1000.0
    assert row.tolist() == [0.25, 4.0, 0.3, 0.02, 0.31, 0.021, *tip.tolist(), 1.5, -2.5, 1.0]


def test_a_long_read_hands_the_interpreter_lock_back_every_16_rows(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The reader computes forward kinematics row by row on a worker thread: every 16 rows it
    lets the loop thread run (``time.sleep(0)``), so a 10 s table never holds the loop off
    for the whole read."""
    import occ.core.statetable as statetable

    joints = _joints()
    table = _table(100)
    _fill(table, 64, joints)
    yields: list[float] = []
    monkeypatch.setattr(statetable.time, "sleep", yields.append)
    table.window()
    assert yields == [0, 0, 0, 0]  # once every 16 rows


class _Interrupted(Exception):
    pass


class _Stalled:
    """A joint whose effort cannot be read: the writer stops in the middle of its row (the
    row's time, state, q and setpoints written, its efforts not), as the loop thread does
    when the reader's thread runs in between."""

    @property
    def effort(self) -> float:
        raise _Interrupted


class _RacedTable(StateTable):
    """A table whose reader is interrupted by the writer right after it read the row count:
    ``rows()`` then copies slots the writer has meanwhile overwritten (``race`` rows whole
    and one half-written)."""

    def __init__(self, capacity: int, race: int) -> None:
        self._race = 0
        super().__init__(NAMES, capacity, Frame.builtin("occ_slave"))
        self._race = race
        self.joints = _joints()

    @property  # type: ignore[override]
    def count(self) -> int:
        n = self._count
        if self._race:
            race, self._race = self._race, 0
            _fill(self, race, self.joints, t0=n)
            with pytest.raises(_Interrupted):
                self.write(
                    (n + race) * 0.001,
                    3.0,
                    0.0,
                    [0.001 * (n + race), 0.35, 0.05],
                    [0.0, 0.0, 0.0],
                    [*self.joints[:2], _Stalled()],
                )  # type: ignore[list-item]
        return n

    @count.setter
    def count(self, value: int) -> None:
        self._count = value


@pytest.mark.parametrize(
    ("written", "race"),
    [(5, 1), (5, 3), (20, 3), (20, 1), (3, 4)],
    ids=["full-one-row", "full-three-rows", "wrapped-three-rows", "wrapped-one-row", "young"],
)
def test_a_read_overtaken_by_the_writer_drops_the_overwritten_rows(written: int, race: int) -> None:
    """The writer runs between the reader's first count and its copy (deterministically):
    whatever it overwrote, whole or halfway, is not returned; what is returned is whole,
    consecutive and ends with the newest row the reader counted."""
    table = _RacedTable(5, 0)
    _fill(table, written, table.joints)
    table._race = race
    raw = table.rows()
    k = np.rint(raw[:, 0] * 1000.0)
    assert len(raw) >= 1 and k[-1] == written - 1
    assert np.array_equal(np.diff(k), np.ones(len(k) - 1))  # consecutive, oldest first
    assert np.array_equal(raw[:, 3], raw[:, 0])  # q.yaw: the row's own
    # eff.yaw: written last in a row, so a half-written row keeps the old one
    assert np.array_equal(raw[:, 3 + 2 * len(NAMES)], k)
    # and no row lost that the writer cannot have reached: only those it wrote over
    newest = written + race  # the half-written row's number
    assert k[0] == max(0, written - 5, newest - 5)
