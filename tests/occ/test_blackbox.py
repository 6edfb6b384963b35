"""The black box (occ/recording/blackbox.py, dump.py): always on, dumped off the loop when the
robot stops for a safety reason, faults, is emergency-stopped or an operator asks, bounded on
disk, and read as a recording. Simulated time: every run is exact."""

from __future__ import annotations

import json
import math
import threading
import tracemalloc
from collections.abc import Iterator
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from occ.config import DaemonConfig
from occ.core.safety import RobotState
from occ.recording.blackbox import BlackBox
from occ.recording.cli import main as occ_record
from occ.recording.dump import read_manifest
from occ.recording.record import read_recording
from occ_testkit import CONFIGS
from occ_testkit.rigs import SlaveRig


def _slave(tmp_path: Path, **black_box: Any) -> SlaveRig:
    raw = yaml.safe_load((CONFIGS / "slave.yaml").read_text())
    raw["black_box"] = {"dir": str(tmp_path / "bb"), **black_box}
    cfg = DaemonConfig.model_validate(raw, context={"base_dir": CONFIGS})
    return SlaveRig(cfg)


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[SlaveRig]:
    r = _slave(tmp_path)
    yield r
    r.close()


def _dumps(rig: SlaveRig) -> list[Path]:
    box = rig.robot.black_box
    assert box.wait_idle(30.0)
    if not box.dir.is_dir():
        return []
    return sorted(p for p in box.dir.iterdir() if not p.name.startswith("."))


def _the_dump(rig: SlaveRig, cause: str) -> tuple[Path, dict[str, Any]]:
    (path,) = _dumps(rig)
    assert path.name.startswith(f"{rig.robot.name}-") and path.name.endswith(f"-{cause}")
    manifest = read_manifest(path)
    # the alert says where
    assert any(f"written to {path}" in a for a in rig.alerts()), rig.alerts()
    return path, manifest


@pytest.mark.req("SR-BOX-2")
def test_a_loss_stop_dumps_the_black_box_and_an_operator_stop_does_not(rig: SlaveRig) -> None:
    rig.running()
    rig.command("Stop")  # an operator's Stop: not a safety reason
    rig.command("Run")
    rig.step(100)
    assert _dumps(rig) == []
    rig.seq += 3  # three consecutive numbers lost: the latched stop
    rig.step(20)
    assert rig.robot.state is RobotState.STOPPED
    path, m = _the_dump(rig, "stopped")
    assert m["causes"][0]["cause"] == "stopped"
    assert "3 consecutive packets lost" in m["causes"][0]["reason"]
    rows = np.load(path / "ticks.npy")
    assert m["trigger"]["tick"] == m["window"]["first_tick"] + len(rows) - 1
    assert rows[-1, 2] == 4.0  # the trigger's tick ended STOPPED
    lines = [json.loads(s) for s in (path / "events.jsonl").read_text().splitlines()]
    stop = [e for e in lines if e["kind"] == "transition" and e["to"] == "STOPPED"]
    assert stop[-1]["tick"] == m["trigger"]["tick"] and "lost" in stop[-1]["reason"]


@pytest.mark.req("SR-BOX-2")
def test_a_drive_fault_dumps_with_the_config_version_and_hashes(rig: SlaveRig) -> None:
    rig.running()
    rig.step(50)
    rig.robot.hardware.drivers[0].inject("nan", 1)
    rig.step(5)
    assert rig.robot.state is RobotState.FAULT
    path, m = _the_dump(rig, "fault")
    assert "feedback" in m["causes"][0]["reason"] or "nan" in m["causes"][0]["reason"].lower()
    assert m["software"]["occ"] and m["software"]["build"] in ("pure", "compiled")
    urdf = Path(m["urdf"]["path"])
    import hashlib

    assert m["urdf"]["sha256"] == hashlib.sha256(urdf.read_bytes()).hexdigest()
    drivers = m["plugins"]["drivers"]
    (entry,) = drivers.values()
    assert entry["class"] == "occ.drivers.sim.SimDriver"
    assert entry["sha256"] == hashlib.sha256(Path(entry["file"]).read_bytes()).hexdigest()
    assert "teleop-slave" in m["plugins"]["controllers"]
    # the dumped configuration is the one that ran, and loads again
    text = (path / "config.yaml").read_text()
    assert m["config_sha256"] == hashlib.sha256(text.encode()).hexdigest()
    again = DaemonConfig.model_validate(yaml.safe_load(text))
    assert again == rig.robot.config
    # every file it holds (replay.pkl: the window starts at a checkpoint), in simulated time
    assert sorted(m["files"]) == sorted(p.name for p in path.iterdir())
    assert m["files"][-1] == "replay.pkl" and m["clock"] == "simulated"


@pytest.mark.req("SR-BOX-2")
def test_an_estop_dumps_the_black_box(rig: SlaveRig) -> None:
    rig.running()
    rig.step(30)
    rig.command("EStop")
    assert rig.robot.state is RobotState.ESTOP
    _path, m = _the_dump(rig, "estop")
    assert m["causes"][0]["reason"] == "operator EStop"


@pytest.mark.req("SR-BOX-3")
def test_dump_black_box_is_written_off_the_loop_and_the_reply_says_where(rig: SlaveRig) -> None:
    threads: list[str] = []
    writer = rig.robot.black_box.writer
    assert writer is not None and writer.inline  # simulated time: in the tick, repeatable
    writer.inline = False  # as on the real clock: its own thread
    writer.start()
    write = writer._write
    writer._write = lambda req: (threads.append(threading.current_thread().name), write(req))
    rig.running()
    rig.step(40)
    cid = rig.operator.send_command("DumpBlackBox", '<Command Name="DumpBlackBox" Reason="x"/>')
    rig.step(1)
    reply = rig.operator.reply_to(cid)
    assert reply is not None and reply.metadata["Status"] == "SUCCESS"
    path, m = _the_dump(rig, "operator")
    assert str(path) in str(reply.metadata.get("Message", "")) + str(getattr(reply, "command", ""))
    assert m["causes"] == [{"cause": "operator", "reason": "operator DumpBlackBox: x"}]
    assert threads == [f"occ-{rig.robot.name}-blackbox"]  # never the loop's
    assert rig.robot.state is RobotState.RUNNING  # nothing moved for it


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ('<Command Name="DumpBlackBox" reason="y"/>', "operator DumpBlackBox: y"),
        ("", "operator DumpBlackBox"),
    ],
    ids=["lower-case-reason", "no-reason"],
)
def test_dump_black_box_takes_its_reason_in_either_case_or_none(
    tmp_path: Path, text: str, reason: str
) -> None:
    rig = _slave(tmp_path)
    try:
        rig.running()
        rig.step(40)
        reply = rig.sim.command(rig.operator, "DumpBlackBox", text)
        assert reply.metadata["Status"] == "SUCCESS"
        path, m = _the_dump(rig, "operator")
        assert f"black box: writing {path}" in str(reply.command)
        assert m["causes"] == [{"cause": "operator", "reason": reason}]
    finally:
        rig.close()


@pytest.mark.req("SR-BOX-1")
def test_the_ring_holds_what_the_loop_read_and_did(tmp_path: Path) -> None:
    rig = _slave(tmp_path, seconds=0.1)  # 100 rows: the ring wraps in this run
    try:
        rig.running()
        q, sp, t, k = [], [], [], []
        for _ in range(300):
            start = rig.sim.k
            if rig.sim.k % 2 == 0:
                rig.target[0] += 0.01
            rig.step(1)
            t.append(start * rig.sim.period)
            k.append(start)
            q.append(list(rig.robot.data.q))
            sp.append(list(rig.robot.data.setpoint))
        sent_at = rig.sim.k  # the next tick takes this sample
        rig.send()
        rig.sim.command(rig.operator, "DumpBlackBox")
        path, m = _the_dump(rig, "operator")
    finally:
        rig.close()
    rows = np.load(path / "ticks.npy")
    assert len(rows) >= 100 and m["window"]["rows_lost"] == 0
    # the window starts at the checkpoint at or before its 100 ticks (a replay's start)
    assert (
        m["replay"]["from_tick"]
        == m["window"]["first_tick"]
        == m["trigger"]["tick"] - (len(rows) - 1)
    )
    rows = rows[-100:]
    cols = m["tick_columns"]
    n = len(m["joints"])
    # the last 100 ticks before the dump's: the clock, the index, every reading, every setpoint
    last = slice(len(t) - 99, len(t))
    assert rows[:-1, 0].tolist() == t[last] and rows[:-1, 1].tolist() == k[last]
    pos = [cols.index(f"pos.{j}") for j in m["joints"]]
    assert rows[:-1, pos].tolist() == q[last]  # bit for bit
    spc = [cols.index(f"sp.{j}") for j in m["joints"]]
    assert rows[:-1, spc].tolist() == sp[last]
    assert all(math.isnan(v) for v in rows[0, cols.index(f"ew.{m['joints'][0]}") :][:n])
    # the sample the last tick consumed, with that tick
    msgs = read_recording(path)
    pos_in = [x for x in msgs if x.message_type == "POSITION" and x.metadata["rec.dir"] == "in"]
    assert int(pos_in[-1].metadata["rec.tick"]) == m["trigger"]["tick"]
    assert float(pos_in[-1].metadata["rec.t"]) == sent_at * 0.001
    assert len({int(x.metadata["rec.tick"]) for x in pos_in}) == len(pos_in)  # one a tick
    cmd = [x for x in msgs if x.message_type == "COMMAND"]
    # Enable and Run in the first two ticks (the window starts at the first checkpoint), then
    # the dump's request in the trigger's tick
    assert [c.metadata["rec.tick"] for c in cmd] == ["0", "1", str(m["trigger"]["tick"])]


@pytest.mark.req("SR-BOX-1")
def test_a_tick_keeps_nothing_it_allocates(tmp_path: Path) -> None:
    """The loop's side of the black box grows nothing: over 2000 ticks of rows, messages and
    writes (the ring wrapping), no memory allocated in occ/recording/blackbox.py stays."""
    rig = _slave(tmp_path, seconds=0.5)
    try:
        rig.running()
        box = rig.robot.black_box
        rig.step(1200)  # every slot of both rings used once
        msg = rig.source.messages()[:1] or [object()]
        tracemalloc.start()
        before = tracemalloc.take_snapshot()
        for i in range(2000):
            box.took(msg[0], "master")
            box.wrote(rig.robot.data.setpoint, False)
            box.end_tick(i * 0.001, i)
        after = tracemalloc.take_snapshot()
        tracemalloc.stop()
    finally:
        rig.close()
    mine = tracemalloc.Filter(True, str(Path(BlackBox.__module__.replace(".", "/") + ".py")))
    grown = after.filter_traces([mine]).compare_to(before.filter_traces([mine]), "filename")
    assert sum(s.size_diff for s in grown) <= 0, grown


@pytest.mark.req("SR-BOX-4")
def test_dumps_are_bounded_in_count_and_disk(tmp_path: Path) -> None:
    rig = _slave(tmp_path, max_dumps=2)
    try:
        rig.running()
        names = []
        for _ in range(4):
            rig.step(20)
            reply = rig.sim.command(rig.operator, "DumpBlackBox")
            names.append(str(reply.metadata.get("Message", reply)).rsplit("/", 1)[-1])
            assert rig.robot.black_box.wait_idle(30.0)
        kept = _dumps(rig)
        assert [p.name for p in kept] == sorted(p.name for p in kept)
        assert len(kept) == 2 and kept[-1].name in names[-1]
        assert any("older dump(s) removed" in a for a in rig.alerts())
    finally:
        rig.close()
    rig = _slave(tmp_path / "small", max_mb=0.001)  # any dump is over: only the newest stays
    try:
        rig.running()
        for _ in range(3):
            rig.step(20)
            rig.sim.command(rig.operator, "DumpBlackBox")
            assert rig.robot.black_box.wait_idle(30.0)
        assert len(_dumps(rig)) == 1
    finally:
        rig.close()


@pytest.mark.req("SR-BOX-4")
def test_a_dump_that_cannot_be_written_is_told_and_the_robot_goes_on(tmp_path: Path) -> None:
    (tmp_path / "bb").write_text("a file where the directory should be")
    rig = _slave(tmp_path)
    try:
        rig.running()
        rig.sim.command(rig.operator, "DumpBlackBox")
        assert rig.robot.black_box.wait_idle(30.0)
        assert any("NOT written" in a for a in rig.alerts()), rig.alerts()
        rig.step(20)
        assert rig.robot.state is RobotState.RUNNING
    finally:
        rig.close()


@pytest.mark.req("SR-BOX-5")
def test_a_dump_exports_like_any_recording(rig: SlaveRig, tmp_path: Path) -> None:
    rig.running()
    rig.step(300)
    rig.command("EStop")
    path, m = _the_dump(rig, "estop")
    assert occ_record(["export", str(path), str(tmp_path / "csv")]) == 0
    state = (tmp_path / "csv" / "state.csv").read_text().splitlines()
    assert len(state) == m["window"]["ticks"] + 1  # a header and a row a tick
    assert occ_record(["export", str(path), str(tmp_path / "out.seq.mha")]) == 0
    assert "Seq_Frame0000" in (tmp_path / "out.seq.mha").read_text(errors="replace")
    if find_spec("rosbags") is not None:
        assert occ_record(["export", str(path), str(tmp_path / "out.mcap")]) == 0
        assert (tmp_path / "out.mcap").stat().st_size > 0


def test_black_box_defaults_and_off() -> None:
    raw = yaml.safe_load((CONFIGS / "slave.yaml").read_text())
    cfg = DaemonConfig.model_validate(raw, context={"base_dir": CONFIGS})
    bb = cfg.black_box
    assert (bb.enabled, bb.seconds, bb.dir) == (True, 30.0, CONFIGS / "black_box")
    raw["black_box"] = {"enabled": False}
    rig = SlaveRig(DaemonConfig.model_validate(raw, context={"base_dir": CONFIGS}))
    try:
        rig.running()
        cid = rig.operator.send_command("DumpBlackBox")
        rig.step(1)
        reply = rig.operator.reply_to(cid)
        assert reply is not None and reply.metadata["Status"] == "FAIL"
        assert reply.metadata["Error"] == "DumpBlackBox: no black box (black_box.enabled is false)"
        rig.command("EStop")
        assert rig.robot.black_box.stats()["requested"] == 0
    finally:
        rig.close()


@pytest.mark.req("SR-BOX-6")
def test_a_checkpoint_waits_for_a_tick_that_leaves_room_but_never_a_whole_interval() -> None:
    """Checkpoints (a replay's start) are taken in the time a tick leaves; on a machine so
    loaded that no tick leaves room for a whole interval after one is due, after the next
    tick anyway: a window always starts at a checkpoint within two intervals of its seconds."""
    from occ.recording.blackbox import Checkpoints

    box = BlackBox("r", ["j"], 1000.0, 1.0, 100)
    box.checkpoints = cps = Checkpoints(list, 1000.0, 4)

    def taken() -> list[int]:
        return [row for row, _events, _state in cps._ring]

    assert box.spare(False) and taken() == [0]  # the first: at once, room or not
    box.count = 999
    assert not box.spare(True)  # not due yet
    box.count = 1000
    assert not box.spare(False)  # due, but the tick left no room: later
    box.count = 1999
    assert not box.spare(False)
    box.count = 2000  # a whole interval past due: after this tick anyway
    assert box.spare(False) and taken() == [0, 2000]
    box.count = 3000
    assert box.spare(True) and taken() == [0, 2000, 3000]


@pytest.mark.req("SR-BOX-1")
def test_a_small_event_ring_dumps_the_loops_events_and_says_truly_whether_they_are_whole(
    tmp_path: Path,
) -> None:
    """The fewest events a second (100) and a short box: the ring's margin (300 events) is
    smaller than the writer's copy margin (a chunk, 2048). Until 2026-11-29 such a dump held
    none of the loop's events and its manifest said they were whole (replay possible, no
    inputs); now it holds them, and says from which tick on they are whole."""
    rig = _slave(tmp_path, seconds=1.0, events_per_s=100)
    try:
        rig.running()
        rig.step(40)
        rig.command("EStop")
        path, m = _the_dump(rig, "estop")
        box = rig.robot.black_box
        assert box.ev_count < box.ev_capacity  # every event of the run is in the window
    finally:
        rig.close()
    lines = [json.loads(s) for s in (path / "events.jsonl").read_text().splitlines()]
    assert [e["to"] for e in lines if e["kind"] == "transition"][-2:] == ["RUNNING", "ESTOP"]
    assert m["window"]["events_whole_from_tick"] == m["window"]["first_tick"]
    assert m["replay"]["possible"] and m["replay"]["inputs"] > 30
    # a longer run: more events than the ring holds, and the dump says so
    rig = _slave(tmp_path / "long", seconds=1.0, events_per_s=100)
    try:
        rig.running()
        rig.step(600)  # a sample every other tick: 300 events, 100 a window holds
        rig.command("EStop")
        path, m = _the_dump(rig, "estop")
    finally:
        rig.close()
    whole = m["window"]["events_whole_from_tick"]
    assert m["window"]["first_tick"] < whole < m["trigger"]["tick"]
    assert not m["replay"]["possible"] and f"before tick {whole}" in m["replay"]["why"]
    msgs = read_recording(path)
    ticks = [int(x.metadata["rec.tick"]) for x in msgs if x.message_type == "POSITION"]
    assert ticks and ticks[0] >= whole - 1 and ticks[-1] >= m["trigger"]["tick"] - 2
