"""Recording started and stopped at run time: PLUS's StartRecording / StopRecording and
GetRecordingStatus, over COMMAND and over STRING ``CMD_<id>``.

The in-process rig checks the rules (file names, refusals, what the file holds); the last test
does the same over real TCP sockets against a running ``occd``.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from itertools import pairwise
from pathlib import Path
from typing import Any

import pytest
import yaml

import igtl
from occ.recording.record import STATE_DEVICE, Recorder, read_recording
from occ_testkit.testing import SimPeer, SimRobot, wait_until

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))


def slave_config(directory: Path) -> dict[str, Any]:
    cfg = yaml.safe_load((ROOT / "configs" / "slave.yaml").read_text())
    cfg["recording"]["directory"] = str(directory)
    return cfg


def command(sim: SimRobot, op: SimPeer, name: str, xml: str = "") -> Any:
    """Send a COMMAND; tick the loop until its RTS_COMMAND comes (the worker answers some)."""
    cid = op.send_command(name, xml)
    reply = None

    def answered() -> bool:
        nonlocal reply
        sim.tick()
        reply = op.reply_to(cid)
        return reply is not None

    assert wait_until(answered, 10.0, every=0.001), f"no reply to {name}"
    return reply


def string_command(sim: SimRobot, op: SimPeer, uid: str, text: str) -> str:
    """A PLUS-style STRING CMD_<uid>; returns the content of its ACK_<uid>."""
    op.send(igtl.StringMessage(text, device_name=f"CMD_{uid}", header_version=2))

    def ack() -> Any:
        sim.tick()
        acks = op.messages("STRING", f"ACK_{uid}")
        return acks[-1] if acks else None

    msg = wait_until(ack, 10.0, every=0.001)
    assert msg is not None, f"no ACK_{uid}"
    return str(msg.string)


@pytest.fixture
def rig(tmp_path: Path):  # type: ignore[no-untyped-def]
    sim = SimRobot(slave_config(tmp_path / "recs"))
    op = sim.peer("operator")
    sim.peer("slicer")
    master = sim.peer("master", address=("127.0.0.1", 5000))
    yield sim, op, master, tmp_path / "recs"
    sim.close()


def test_start_run_stop_reads_back(rig) -> None:  # type: ignore[no-untyped-def]
    sim, op, master, recs = rig
    assert command(sim, op, "GetRecordingStatus").metadata["Message"] == "recording=false"
    sim.step(100)  # before the recording: not in the file
    t_start = sim.now
    reply = command(
        sim, op, "StartRecording", '<Command Name="StartRecording" OutputFilename="run1"/>'
    )
    assert reply.metadata["Status"] == "SUCCESS", reply.metadata
    path = recs / "run1.igtl"
    assert str(path) in reply.metadata["Message"]
    assert command(sim, op, "Enable").metadata["Status"] == "SUCCESS"
    for seq in range(1, 251):  # 0.5 s of the master's stream at 500 Hz
        master.send_position((0.1 * seq, 50.0, 270.0), seq=seq)
        sim.step(2)
    status = command(sim, op, "GetRecordingStatus").metadata["Message"]
    assert status.startswith(f"recording=true; file={path}; records="), status
    stop = command(sim, op, "StopRecording")
    assert stop.metadata["Status"] == "SUCCESS", stop.metadata
    assert (
        stop.metadata["Message"].startswith("Recording ") and str(path) in stop.metadata["Message"]
    )
    t_stop = sim.now
    sim.step(100)  # after: not in the file either
    msgs = read_recording(path)
    states = [m for m in msgs if m.device_name == STATE_DEVICE]
    times = [float(m.array[0]) for m in states]  # type: ignore[attr-defined]
    assert t_start <= min(times) and max(times) <= t_stop
    # 100 Hz over the recorded span, the robot's name in the metadata
    assert len(states) > 40
    assert all(0.0095 < b - a < 0.0115 for a, b in pairwise(times))
    assert states[0].metadata["robot"] == "slave"
    positions = [m for m in msgs if m.message_type == "POSITION" and m.metadata["rec.dir"] == "in"]
    assert [m.message_id for m in positions] == list(range(1, 251))
    assert any(m.message_type == "TRANSFORM" and m.device_name == "Tip" for m in msgs)
    # the state change in between, broadcast by the alarms (which hold the recorder too)
    changes = [m for m in msgs if m.message_type == "STATUS" and m.metadata["rec.if"] == "*"]
    assert [m.error_name for m in changes] == ["ENABLED"]  # type: ignore[attr-defined]
    # the commands in between are in it, with their replies
    names = [getattr(m, "command_name", "") for m in msgs if m.message_type == "COMMAND"]
    assert names == ["Enable", "GetRecordingStatus", "StopRecording"]
    n_records = int(stop.metadata["Message"].split()[1])
    assert n_records == len(msgs)
    done = command(sim, op, "GetRecordingStatus").metadata["Message"]
    assert done == f"recording=false; last={path}"


def test_plus_string_commands_and_refusals(rig) -> None:  # type: ignore[no-untyped-def]
    sim, op, _, recs = rig
    # stop when not recording
    ack = string_command(sim, op, "1", '<Command Name="StopRecording"/>')
    assert 'Status="FAIL"' in ack and "not recording" in ack
    # bad names: a directory, a traversal, an absolute path, a hidden file, an export format
    for i, bad in enumerate(["sub/x", "../x", "/tmp/x", ".x", "x.seq.mha", "", "a b"]):
        ack = string_command(
            sim, op, f"b{i}", f'<Command Name="StartRecording" OutputFilename="{bad}"/>'
        )
        if bad == "":  # no name: a default one
            assert 'Status="SUCCESS"' in ack, ack
            assert recs.joinpath(f"slave_{time.strftime('%Y%m%d')}").name in ack
            stop = command(sim, op, "StopRecording")
            assert stop.metadata["Status"] == "SUCCESS"
            continue
        assert 'Status="FAIL"' in ack, (bad, ack)
        assert "OutputFilename" in ack or "own format" in ack, ack
    assert not (recs.parent / "x").exists() and not Path("/tmp/x.igtl").exists()
    assert [p.name for p in recs.iterdir()][0].startswith("slave_")
    # start, then start again: refused, the first one goes on
    ack = string_command(sim, op, "s1", '<Command Name="StartRecording" OutputFilename="a.igtl"/>')
    assert 'Status="SUCCESS"' in ack and str(recs / "a.igtl") in ack
    ack = string_command(sim, op, "s2", '<Command Name="StartRecording" OutputFilename="b"/>')
    assert 'Status="FAIL"' in ack and "already recording" in ack
    assert not (recs / "b.igtl").exists()
    sim.step(50)
    ack = string_command(sim, op, "s3", "GetRecordingStatus")
    assert 'Status="SUCCESS"' in ack and "recording=true" in ack and "a.igtl" in ack
    ack = string_command(sim, op, "s4", "StopRecording")
    assert 'Status="SUCCESS"' in ack and "successful to file" in ack
    # a file that exists is never replaced
    before = (recs / "a.igtl").read_bytes()
    ack = string_command(sim, op, "s5", '<Command Name="StartRecording" OutputFilename="a"/>')
    assert 'Status="FAIL"' in ack and "exists" in ack
    assert (recs / "a.igtl").read_bytes() == before
    assert "recording=false" in string_command(sim, op, "s6", "GetRecordingStatus")


def test_stop_renames_and_viewer_cannot_record(rig) -> None:  # type: ignore[no-untyped-def]
    sim, op, _, recs = rig
    assert command(sim, op, "StartRecording").metadata["Status"] == "SUCCESS"
    sim.step(30)
    stop = command(
        sim, op, "StopRecording", '<Command Name="StopRecording" OutputFilename="kept"/>'
    )
    assert stop.metadata["Status"] == "SUCCESS", stop.metadata
    assert (recs / "kept.igtl").is_file() and len(list(recs.iterdir())) == 1
    assert read_recording(recs / "kept.igtl")
    # renaming onto an existing file: the recording is kept under its own name, the reply says so
    assert command(sim, op, "StartRecording").metadata["Status"] == "SUCCESS"
    sim.step(30)
    stop = command(
        sim, op, "StopRecording", '<Command Name="StopRecording" OutputFilename="kept"/>'
    )
    assert (
        stop.metadata["Status"] == "FAIL" and "cannot name it kept.igtl" in stop.metadata["Message"]
    )
    assert len(list(recs.iterdir())) == 2
    # 3D Slicer's viewer port may not start a recording
    viewer = sim.peer("slicer")
    refused = command(sim, viewer, "StartRecording")
    assert refused.metadata["Status"] == "FAIL" and "viewer" in refused.metadata["Message"]


def test_shutdown_closes_a_running_recording(tmp_path: Path) -> None:
    sim = SimRobot(slave_config(tmp_path))
    op = sim.peer("operator")
    assert (
        command(sim, op, "StartRecording", '<Command Name="x" OutputFilename="end"/>').metadata[
            "Status"
        ]
        == "FAIL"
    )  # the XML's Name wins: "x" is no command
    assert (
        command(
            sim, op, "StartRecording", '<Command Name="StartRecording" OutputFilename="end"/>'
        ).metadata["Status"]
        == "SUCCESS"
    )
    sim.step(200)
    rec = sim.robot.recorder
    sim.close()  # no StopRecording: the shutdown closes it, every record on disk
    assert rec is not None and rec.stats()["bytes"] == (tmp_path / "end.igtl").stat().st_size > 0
    states = [m for m in read_recording(tmp_path / "end.igtl") if m.device_name == STATE_DEVICE]
    assert len(states) >= 19


def start_slave(tmp_path: Path, *args: str) -> tuple[subprocess.Popen[bytes], dict[str, int]]:
    """``occd`` of the shipped slave on free ports, not recording (``args``: its options); the
    process and the ports of its TCP interfaces by name."""
    import socket

    from loopback import free_port, write_yaml

    cfg = slave_config(tmp_path / "recs")
    ports = {}
    for itf in cfg["interfaces"]:
        if itf["transport"] == "tcp-server":
            itf["port"] = ports[itf["name"]] = free_port()
        else:
            itf["port"] = free_port(socket.SOCK_DGRAM)
    cfg["recording"]["path"] = None
    write_yaml(tmp_path / "slave.yaml", cfg)
    proc = subprocess.Popen(
        [sys.executable, "-m", "occ.cli", str(tmp_path / "slave.yaml"), *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    return proc, ports


# ---------------------------------------------------------------------- a running daemon, TCP
@pytest.mark.realtime
def test_start_stop_on_a_running_daemon(tmp_path: Path) -> None:
    from loopback import stop_processes, wait_port
    from slicer_standin import SlicerStandIn

    proc, ports = start_slave(tmp_path, "--log-level", "WARNING")
    try:
        assert wait_port(ports["operator"]), (
            proc.stderr.read().decode() if proc.poll() else "no port"
        )
        with SlicerStandIn("127.0.0.1", ports["operator"]) as op:
            assert op.connected.wait(5.0)

            def ask(name: str, xml: str = "") -> Any:
                if xml:
                    cid = op.send_command(name, xml)
                else:
                    cid = op.send_command(name)
                reply = op.wait_reply(cid, 10.0)
                assert reply is not None, f"no reply to {name}"
                return reply

            assert ask("GetRecordingStatus").metadata["Message"] == "recording=false"
            assert ask("StopRecording").metadata["Status"] == "FAIL"
            bad = ask("StartRecording", '<Command Name="StartRecording" OutputFilename="../x"/>')
            assert bad.metadata["Status"] == "FAIL" and "bare file name" in bad.metadata["Message"]
            start = ask("StartRecording", '<Command Name="StartRecording" OutputFilename="live"/>')
            assert start.metadata["Status"] == "SUCCESS", start.metadata
            again = ask("StartRecording", '<Command Name="StartRecording" OutputFilename="b"/>')
            assert (
                again.metadata["Status"] == "FAIL"
                and "already recording" in again.metadata["Message"]
            )
            t0 = time.monotonic()
            time.sleep(1.5)
            status = ask("GetRecordingStatus").metadata["Message"]
            assert status.startswith("recording=true") and "live.igtl" in status
            stop = ask("StopRecording")
            elapsed = time.monotonic() - t0
            assert stop.metadata["Status"] == "SUCCESS", stop.metadata
        path = tmp_path / "recs" / "live.igtl"
        assert str(path) in stop.metadata["Message"]
        msgs = read_recording(path)
        states = [m for m in msgs if m.device_name == STATE_DEVICE]
        # state rows at 100 Hz for the time it ran (a loaded machine may stretch the replies)
        assert 100 <= len(states) <= elapsed * 100 + 5, (len(states), elapsed)
        tips = [m for m in msgs if m.message_type == "TRANSFORM" and m.device_name == "Tip"]
        assert 10 <= len(tips) <= elapsed * 10 + 2
        assert int(stop.metadata["Message"].split()[1]) == len(msgs)
        t = [float(m.array[0]) for m in states]  # type: ignore[attr-defined]
        assert all(b > a for a, b in pairwise(t))
    finally:
        stop_processes([proc])
    assert proc.returncode == 0, proc.stderr.read().decode() if proc.stderr else ""


# ---------------------------------------------------------------------- the worker's side
@contextmanager
def held_worker(sim: SimRobot, *, fill: bool = False) -> Iterator[None]:
    """The robot's worker busy with a job that waits for the end of the block (a GetStats
    snapshot or a slow disk would do the same); ``fill``: its queue full too (8 jobs)."""
    worker = sim.robot.worker.start()
    taken, gate = threading.Event(), threading.Event()

    def hold() -> None:
        taken.set()
        gate.wait(10.0)

    assert worker.submit(hold) and taken.wait(5.0)
    try:
        if fill:
            while worker.submit(lambda: None):
                pass
        yield
    finally:
        gate.set()
    # and the queue drained before the test goes on
    drained = threading.Event()
    assert wait_until(lambda: worker.submit(drained.set), 5.0, every=0.001)
    assert drained.wait(5.0)


def stats(sim: SimRobot, op: SimPeer) -> dict[str, Any]:
    """GetStats' ``recording`` part."""
    reply = command(sim, op, "GetStats")
    assert reply.metadata["Status"] == "SUCCESS", reply.metadata
    return json.loads(reply.metadata["Message"])["recording"]  # type: ignore[no-any-return]


def start_xml(name: str) -> str:
    return f'<Command Name="StartRecording" OutputFilename="{name}"/>'


def test_a_start_being_opened_and_a_busy_worker(rig) -> None:  # type: ignore[no-untyped-def]
    sim, op, _, recs = rig
    path = recs / "held.igtl"
    idle = command(sim, op, "StopRecording")
    assert idle.metadata["Message"] == "StopRecording: not recording"
    with held_worker(sim):
        cid = op.send_command("StartRecording", start_xml("held"))
        # answered on the loop, after the start (one peer's commands are taken in order)
        status = command(sim, op, "GetRecordingStatus").metadata["Message"]
        assert status == f"recording=starting; file={path}"
        again = command(sim, op, "StartRecording", start_xml("other"))
        assert again.metadata["Status"] == "FAIL"
        assert f"already starting a recording ({path})" in again.metadata["Message"]
        stop = command(sim, op, "StopRecording")
        assert stop.metadata["Status"] == "FAIL"
        assert f"the recording {path} is still being opened" in stop.metadata["Message"]
        assert op.reply_to(cid) is None and sim.robot.recorder is None
    started = wait_until(lambda: (sim.tick(), op.reply_to(cid))[1], 10.0, every=0.001)
    assert started is not None and started.metadata["Status"] == "SUCCESS", started
    assert sim.robot.recorder is not None and sim.robot.recorder.path == path
    assert not (recs / "other.igtl").exists()
    # a stop the worker cannot take: refused, and the recording goes on
    with held_worker(sim, fill=True):
        before = sim.robot.recorder.stats()["records"]
        stop = command(sim, op, "StopRecording")
        assert stop.metadata["Status"] == "FAIL"
        assert stop.metadata["Message"] == (
            "StopRecording: busy (the worker's queue is full); try again"
        )
        sim.step(20)
        assert sim.robot.recorder is not None and sim.robot.recorder.stats()["records"] > before
        status = command(sim, op, "GetRecordingStatus").metadata["Message"]
        assert status.startswith(f"recording=true; file={path}; records="), status
    assert command(sim, op, "StopRecording").metadata["Status"] == "SUCCESS"
    # a start the worker cannot take: refused, nothing pending, no file
    with held_worker(sim, fill=True):
        busy = command(sim, op, "StartRecording", start_xml("late"))
        assert busy.metadata["Status"] == "FAIL"
        assert busy.metadata["Message"] == (
            "StartRecording: busy (the worker's queue is full); try again"
        )
        status = command(sim, op, "GetRecordingStatus").metadata["Message"]
        assert status == f"recording=false; last={path}"
    assert command(sim, op, "StartRecording", start_xml("late")).metadata["Status"] == "SUCCESS"
    assert sim.robot.recorder is not None and sim.robot.recorder.path == recs / "late.igtl"


def test_shutdown_while_a_start_is_being_opened(rig) -> None:  # type: ignore[no-untyped-def]
    """The daemon's shutdown (Robot.shutdown) gives the worker 1 s to finish; a start it has
    not opened by then finds the shutdown done: its file is closed, the start fails, and no
    start is taken after it."""
    sim, op, _, recs = rig
    control = sim.robot.operators.recording
    writers = sum(t.name == "occ-recorder" for t in threading.enumerate())
    with held_worker(sim):
        cid = op.send_command("StartRecording", start_xml("late"))
        assert (
            command(sim, op, "GetRecordingStatus")
            .metadata["Message"]
            .startswith("recording=starting")
        )
        control.close_all()
    reply = wait_until(lambda: (sim.tick(), op.reply_to(cid))[1], 10.0, every=0.001)
    assert reply is not None and reply.metadata["Status"] == "FAIL"
    assert reply.metadata["Message"] == "StartRecording: the daemon is shutting down"
    assert sim.robot.recorder is None
    assert control.stats()["failed"] == 1 and control.stats()["started"] == 0
    # the file it had opened is closed: every record (none) on disk, the writer gone
    assert (recs / "late.igtl").stat().st_size == 0
    assert sum(t.name == "occ-recorder" for t in threading.enumerate()) == writers
    refused = command(sim, op, "StartRecording", start_xml("later"))
    assert refused.metadata["Status"] == "FAIL"
    assert refused.metadata["Message"] == "StartRecording: the daemon is shutting down"
    assert command(sim, op, "GetRecordingStatus").metadata["Message"] == "recording=false"
    assert not (recs / "later.igtl").exists()


def test_getstats_counts_starts_stops_and_failures(rig, caplog) -> None:  # type: ignore[no-untyped-def]
    sim, op, _, recs = rig
    caplog.set_level(logging.INFO, logger="occ.core.robot")
    assert stats(sim, op) == {
        "active": False,
        "file": None,
        "recorder": None,
        "started": 0,
        "stopped": 0,
        "failed": 0,
        "last": None,
    }
    assert command(sim, op, "StartRecording", start_xml("one")).metadata["Status"] == "SUCCESS"
    sim.step(30)
    # the writer asks for SCHED_FIFO below the loop's (slave.yaml: the loop at 60) as it starts
    wait_until(lambda: "SCHED_FIFO" in stats(sim, op)["recorder"]["writer"], 5.0, every=0.01)
    running = stats(sim, op)
    assert running["active"] is True and running["file"] == str(recs / "one.igtl")
    assert running["recorder"]["records"] > 0 and running["recorder"]["dropped"] == 0
    assert "SCHED_FIFO" in running["recorder"]["writer"], running["recorder"]
    assert (running["started"], running["stopped"], running["failed"]) == (1, 0, 0)
    assert running["last"] is None
    # a start over an existing file fails and is counted, each time
    first_stop = command(sim, op, "StopRecording").metadata
    assert first_stop["Status"] == "SUCCESS"
    summary = first_stop["Message"].removeprefix("Recording ").split(" successful to file ")[0]
    assert re.fullmatch(r"\d+ records \(\d+ bytes, 0 dropped\)", summary), summary
    for _ in range(2):
        again = command(sim, op, "StartRecording", start_xml("one"))
        assert (
            again.metadata["Message"]
            == f"StartRecording: {recs / 'one.igtl'} exists; not overwriting"
        )
    done = stats(sim, op)
    # the operator's log says what became of each: the stop with its summary, each refusal
    logged = [(r.levelno, r.getMessage()) for r in caplog.records if r.name == "occ.core.robot"]
    one = recs / "one.igtl"
    started = [m for lvl, m in logged if lvl == logging.INFO and m.startswith("recording started")]
    assert started == [f"recording started at run time: {one}"]
    stopped = [m for lvl, m in logged if lvl == logging.INFO and m.startswith("recording stopped")]
    assert stopped == [f"recording stopped: {summary} in {one}"]
    refusal = f"StartRecording: {one} exists; not overwriting"
    assert [m for lvl, m in logged if lvl == logging.WARNING and m == refusal] == [refusal] * 2
    assert (done["active"], done["file"], done["recorder"]) == (False, None, None)
    assert (done["started"], done["stopped"], done["failed"]) == (1, 1, 2)
    assert done["last"] == str(recs / "one.igtl")
    # a rename that cannot be made: stopped, counted as failed, the file kept as it was
    assert command(sim, op, "StartRecording", start_xml("two")).metadata["Status"] == "SUCCESS"
    stop = command(sim, op, "StopRecording", start_xml("one").replace("Start", "Stop"))
    assert stop.metadata["Status"] == "FAIL"
    assert stop.metadata["Message"].endswith(
        f"in {recs / 'two.igtl'}; cannot name it one.igtl: File exists"
    )
    after = stats(sim, op)
    assert (after["started"], after["stopped"], after["failed"]) == (2, 2, 3)
    assert after["last"] == str(recs / "two.igtl")
    status = command(sim, op, "GetRecordingStatus").metadata["Message"]
    assert status == f"recording=false; last={recs / 'two.igtl'}"
    # a rename that is made: the reply and the status name the new file
    assert command(sim, op, "StartRecording", start_xml("three")).metadata["Status"] == "SUCCESS"
    stop = command(sim, op, "StopRecording", start_xml("four").replace("Start", "Stop"))
    assert stop.metadata["Status"] == "SUCCESS"
    assert stop.metadata["Message"].endswith(f" successful to file {recs / 'four.igtl'}")
    assert not (recs / "three.igtl").exists() and (recs / "four.igtl").is_file()
    status = command(sim, op, "GetRecordingStatus").metadata["Message"]
    assert status == f"recording=false; last={recs / 'four.igtl'}"
    assert stats(sim, op)["last"] == str(recs / "four.igtl")


def test_names_the_daemon_takes_and_refuses(rig) -> None:  # type: ignore[no-untyped-def]
    sim, op, _, recs = rig
    # PLUS's attribute in any case, spaces around the name dropped; a suffix of any case kept
    for attr, value, name in (
        ("outputfilename", " padded ", "padded.igtl"),
        ("OUTPUTFILENAME", "Upper.IGTL", "Upper.IGTL"),
        ("OutputFilename", "x" * 200, "x" * 200 + ".igtl"),
        ("OutputFilename", "a-b_c.1", "a-b_c.1.igtl"),
    ):
        xml = f'<Command Name="StartRecording" {attr}="{value}"/>'
        start = command(sim, op, "StartRecording", xml)
        assert start.metadata["Status"] == "SUCCESS", (value, start.metadata)
        assert start.metadata["Message"] == f"recording to {recs / name}"
        assert command(sim, op, "StopRecording").metadata["Status"] == "SUCCESS"
        assert (recs / name).is_file()
    # too long; each export format (the advice to export instead); nothing created
    too_long = command(sim, op, "StartRecording", start_xml("x" * 201))
    assert too_long.metadata["Status"] == "FAIL"
    assert too_long.metadata["Message"] == (
        "StartRecording: OutputFilename must be a bare file name (letters, digits, '.', '_', "
        f"'-'; at most 200; no directory, not starting with '.'), got '{'x' * 201}'"
    )
    for suffix in (".mha", ".MHD", ".nrrd", ".nhdr", ".mcap", ".csv", ".db3", ".bag"):
        bad = command(sim, op, "StartRecording", start_xml("out" + suffix))
        assert bad.metadata["Status"] == "FAIL", suffix
        assert bad.metadata["Message"] == (
            f"StartRecording: 'out{suffix}': the daemon records in its own format (.igtl); "
            "record to NAME.igtl, then occ-record export NAME.igtl OUT.seq.mha (or OUT.mcap)"
        )
    assert len(list(recs.iterdir())) == 4
    # a stop's new name is checked the same way before anything stops: the recording goes on
    assert command(sim, op, "StartRecording", start_xml("go")).metadata["Status"] == "SUCCESS"
    bad = command(
        sim, op, "StopRecording", '<Command Name="StopRecording" OutputFilename="g.mcap"/>'
    )
    assert bad.metadata["Status"] == "FAIL"
    assert bad.metadata["Message"].startswith("StopRecording: 'g.mcap': the daemon records in")
    assert sim.robot.recorder is not None and sim.robot.recorder.path == recs / "go.igtl"
    assert command(sim, op, "StopRecording").metadata["Status"] == "SUCCESS"


def test_the_configured_directory_rate_and_messages(tmp_path: Path) -> None:
    """recording.directory (made, parents too), rate_hz and include_messages are the
    recording's; a directory that cannot be made is a clear refusal, not a crash."""
    cfg = slave_config(tmp_path / "deep" / "er" / "recs")
    cfg["recording"].update(rate_hz=50, include_messages=False)
    sim = SimRobot(cfg)
    try:
        op = sim.peer("operator")
        assert command(sim, op, "StartRecording", start_xml("r")).metadata["Status"] == "SUCCESS"
        sim.step(400)
        assert command(sim, op, "StopRecording").metadata["Status"] == "SUCCESS"
        msgs = read_recording(tmp_path / "deep" / "er" / "recs" / "r.igtl")
        assert {m.device_name for m in msgs} == {STATE_DEVICE}  # no messages
        times = [float(m.array[0]) for m in msgs]  # type: ignore[attr-defined]
        assert all(0.019 < b - a < 0.021 for a, b in pairwise(times))
    finally:
        sim.close()
    (tmp_path / "file").write_text("not a directory")
    sim = SimRobot(slave_config(tmp_path / "file" / "recs"))
    try:
        op = sim.peer("operator")
        bad = command(sim, op, "StartRecording", start_xml("r"))
        assert bad.metadata["Status"] == "FAIL"
        assert bad.metadata["Message"] == (
            f"StartRecording: cannot write {tmp_path / 'file' / 'recs' / 'r.igtl'}: Not a directory"
        )
        assert sim.robot.recorder is None
        assert command(sim, op, "GetRecordingStatus").metadata["Message"] == "recording=false"
    finally:
        sim.close()
    # a directory that is there but takes no new file (/proc: no one creates files in it)
    sim = SimRobot(slave_config(Path("/proc")))
    try:
        op = sim.peer("operator")
        bad = command(sim, op, "StartRecording", start_xml("r"))
        assert bad.metadata["Status"] == "FAIL"
        assert bad.metadata["Message"] == (
            "StartRecording: cannot write /proc/r.igtl: No such file or directory"
        )
        assert command(sim, op, "GetRecordingStatus").metadata["Message"] == "recording=false"
        assert sim.robot.operators.recording.stats()["failed"] == 1
    finally:
        sim.close()


def test_a_directory_that_is_a_file_is_no_existing_recording(tmp_path: Path) -> None:
    """recording.directory naming a file: the start says it cannot write there, not that the
    recording's file exists (it does not)."""
    (tmp_path / "recs").write_text("a file where the directory should be")
    sim = SimRobot(slave_config(tmp_path / "recs"))
    try:
        op = sim.peer("operator")
        bad = command(sim, op, "StartRecording", start_xml("r"))
        assert bad.metadata["Status"] == "FAIL"
        path = tmp_path / "recs" / "r.igtl"
        assert bad.metadata["Message"] == (
            f"StartRecording: cannot write {path}: {path.parent} is not a directory"
        )
    finally:
        sim.close()


# ---------------------------------------------------------------------- a recording that fails
def alerts(peer: SimPeer) -> list[Any]:
    """The RECORDING alerts a peer received."""
    return [m for m in peer.messages("STATUS") if m.error_name == "RECORDING"]


def failed(sim: SimRobot, rec: Recorder, peer: SimPeer) -> Any:
    """Tick until the recorder's writer (its own thread, every 50 ms) has met the failure and
    ``peer`` has its alert; the failure."""
    assert wait_until(lambda: (sim.tick(), alerts(peer))[1], 10.0, every=0.001)
    return rec.failure


def recorder_errors(caplog: pytest.LogCaptureFixture) -> list[logging.LogRecord]:
    return [
        r for r in caplog.records if r.name == "occ.recording.record" and r.levelno >= logging.ERROR
    ]


@pytest.mark.req("SR-REC-1")
def test_a_full_disk_is_one_alert_and_stop_is_answered(tmp_path: Path, caplog) -> None:  # type: ignore[no-untyped-def]
    """``occd --record /dev/full`` (issue 41): the robot goes on, every operator and viewer
    hears it once with the cause, the log says it once without a traceback, the status says
    failed, StopRecording is answered with what was lost."""
    caplog.set_level(logging.INFO)
    rec = Recorder("/dev/full", rate_hz=100).start()
    sim = SimRobot(slave_config(tmp_path / "recs"), recorder=rec)
    try:
        op, slicer = sim.peer("operator"), sim.peer("slicer")
        assert command(sim, op, "Enable").metadata["Status"] == "SUCCESS"
        assert failed(sim, rec, op) == "No space left on device (ENOSPC)"
        for _ in range(5):  # more records, more flushes: no second alert, no second line
            sim.step(20)
            rec._flush()
        for peer in (op, slicer):
            (alert,) = alerts(peer)
            assert alert.code == igtl.StatusCode.RESOURCE_ERROR
            assert alert.status_message.startswith(
                "recording /dev/full failed: No space left on device (ENOSPC); 0 records "
                "(0 bytes) on disk, "
            )
        (line,) = recorder_errors(caplog)
        assert line.exc_info is None and "ENOSPC" in line.getMessage()
        assert sim.robot.state.value == "ENABLED"  # the robot goes on
        status = command(sim, op, "GetRecordingStatus").metadata["Message"]
        assert status.startswith(
            "recording=failed; file=/dev/full; cause=No space left on device (ENOSPC); "
        ), status
        assert "written=0; bytes=0; not_written=" in status
        stop = command(sim, op, "StopRecording")
        assert stop.metadata["Status"] == "FAIL"
        text = stop.metadata["Message"]
        assert text.startswith(
            "StopRecording: recording stopped; it had FAILED: No space left on device (ENOSPC); "
            "0 records (0 bytes) in /dev/full up to the failure, "
        ), text
        lost = int(re.search(r"failure, (\d+) records not written", text).group(1))  # type: ignore[union-attr]
        assert lost == rec.stats()["records"] + rec.stats()["dropped"] > 0
        after = command(sim, op, "GetRecordingStatus").metadata["Message"]
        assert after == "recording=false; last=/dev/full"
        assert len(alerts(op)) == 1 and len(recorder_errors(caplog)) == 1
    finally:
        sim.close()
        rec.close()  # twice: never raises


class FillsUp:
    """A real file on a file system that fills up after ``budget`` bytes, as a disk does: a
    short write, then ENOSPC."""

    def __init__(self, path: Path, budget: int) -> None:
        self.f = open(path, "wb", buffering=0)  # noqa: SIM115 - closed by the recorder
        self.budget = budget

    def write(self, data: Any) -> int:
        if self.budget <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        n = min(len(data), self.budget)
        self.f.write(bytes(data[:n]))
        self.budget -= n
        return n

    def fileno(self) -> int:
        return self.f.fileno()

    def close(self) -> None:
        self.f.close()


@pytest.mark.req("SR-REC-1")
def test_a_disk_full_mid_record_keeps_every_whole_record(tmp_path: Path, caplog) -> None:  # type: ignore[no-untyped-def]
    """A write cut by a full disk: the file is cut back to its last whole record (it reads
    without damage), the counts say what is on disk and what is not, close never raises, and
    the failure is told once, also to a callback set after it."""
    path = tmp_path / "r.igtl"
    rec = Recorder(path).start()
    rec._file.close()
    rec._file = FillsUp(path, 1000)
    told: list[str] = []
    for k in range(40):
        msg = igtl.StatusMessage(code=1, error_name="E", status_message=f"m{k}", device_name="D")
        rec.record_message(msg, "out", "*", float(k))
    rec.close()
    assert rec.failure == "No space left on device (ENOSPC)"
    rec.on_failure(told.append)  # after the failure: told at once, once
    rec.on_failure(told.append)
    assert len(told) == 1 and told[0] == rec.describe_failure()
    msgs = read_recording(path)  # no damage: whole records only
    assert 0 < rec.written == len(msgs) < 40
    assert path.stat().st_size == rec.bytes_written < 1000
    assert rec.not_written() == 40 - rec.written
    assert [m.status_message for m in msgs] == [f"m{k}" for k in range(rec.written)]  # type: ignore[attr-defined]
    assert told[0] == (
        f"recording {path} failed: No space left on device (ENOSPC); {rec.written} records "
        f"({rec.bytes_written} bytes) on disk, {40 - rec.written} not written"
    )
    assert len(recorder_errors(caplog)) == 1


@pytest.mark.req("SR-REC-1")
def test_a_recording_whose_directory_is_removed_fails_aloud(rig) -> None:  # type: ignore[no-untyped-def]
    """The directory of a running recording deleted: its bytes would vanish at close; the
    recorder says so at once, and StopRecording is answered."""
    sim, op, _, recs = rig
    assert command(sim, op, "StartRecording", start_xml("gone")).metadata["Status"] == "SUCCESS"
    rec = sim.robot.recorder
    shutil.rmtree(recs)
    assert failed(sim, rec, op) == "the file was removed while recording (its directory deleted?)"
    (alert,) = alerts(op)
    assert "gone.igtl failed: the file was removed" in alert.status_message
    status = command(sim, op, "GetRecordingStatus").metadata["Message"]
    assert status.startswith("recording=failed; file=") and "removed" in status
    stop = command(sim, op, "StopRecording")
    assert stop.metadata["Status"] == "FAIL"
    assert "it had FAILED: the file was removed" in stop.metadata["Message"]
    assert stats(sim, op)["failed"] == 1
    # a new recording may start again (the directory is made again); removed too, and stopped
    # with a new name that cannot be given: both said, and counted once more
    assert command(sim, op, "StartRecording", start_xml("again")).metadata["Status"] == "SUCCESS"
    rec = sim.robot.recorder
    shutil.rmtree(recs)
    assert wait_until(lambda: (sim.tick(), len(alerts(op)) == 2)[1], 10.0, every=0.001)
    stop = command(sim, op, "StopRecording", start_xml("kept").replace("Start", "Stop"))
    assert stop.metadata["Status"] == "FAIL"
    assert stop.metadata["Message"].endswith(
        f" in {recs / 'again.igtl'}; cannot name it kept.igtl: No such file or directory"
        f"; it had FAILED: {rec.failure}"
    ), stop.metadata["Message"]
    assert stats(sim, op)["failed"] == 2
    assert command(sim, op, "StartRecording", start_xml("last")).metadata["Status"] == "SUCCESS"
    assert command(sim, op, "StopRecording").metadata["Status"] == "SUCCESS"
    assert len(alerts(op)) == 2


@pytest.mark.req("SR-REC-1")
def test_a_writer_that_dies_is_a_failure_not_a_silent_recording(rig, caplog) -> None:  # type: ignore[no-untyped-def]
    """A bug in the writer thread: its traceback logged once, an alert, nothing more queued
    (the queue would grow without a writer), StopRecording answered."""
    sim, op, _, _ = rig
    assert command(sim, op, "StartRecording", start_xml("bug")).metadata["Status"] == "SUCCESS"
    rec = sim.robot.recorder

    def broken(item: Any) -> bytes:
        raise RuntimeError("a bug in the writer")

    rec._encode = broken
    assert failed(sim, rec, op) == "the writer thread ended: RuntimeError: a bug in the writer"
    (line,) = recorder_errors(caplog)
    assert line.exc_info is not None  # a bug's traceback, once
    queued = len(rec._q)
    sim.step(50)
    assert len(rec._q) == queued  # nothing more taken
    (alert,) = alerts(op)
    assert "the writer thread ended" in alert.status_message
    stop = command(sim, op, "StopRecording")
    assert stop.metadata["Status"] == "FAIL" and "not written" in stop.metadata["Message"]


def test_a_start_whose_open_raises_is_answered_logged_and_counted(rig, monkeypatch, caplog) -> None:  # type: ignore[no-untyped-def]
    """A start that fails in a way the file checks do not foresee (a bug in the recorder):
    StartRecording is answered with the cause, the operator's log has the exception with the
    file, the failure is counted, and a start after it is not held up by it."""
    sim, op, _, recs = rig
    caplog.set_level(logging.INFO, logger="occ.core.robot")

    def broken(self: Recorder, *, exclusive: bool = False) -> Recorder:
        raise RuntimeError("a bug in the recorder")

    monkeypatch.setattr(Recorder, "start", broken)
    reply = command(sim, op, "StartRecording", start_xml("b"))
    assert reply.metadata["Status"] == "FAIL"
    assert reply.metadata["Message"] == (
        f"StartRecording: cannot record to {recs / 'b.igtl'}: a bug in the recorder"
    )
    errors = [
        r for r in caplog.records if r.name == "occ.core.robot" and r.levelno >= logging.ERROR
    ]
    assert [(r.levelno, r.getMessage()) for r in errors] == [
        (logging.ERROR, f"StartRecording: {recs / 'b.igtl'}")
    ]
    assert errors[0].exc_info is not None and isinstance(errors[0].exc_info[1], RuntimeError)
    assert stats(sim, op)["failed"] == 1
    monkeypatch.undo()
    assert command(sim, op, "StartRecording", start_xml("b")).metadata["Status"] == "SUCCESS"
    assert command(sim, op, "StopRecording").metadata["Status"] == "SUCCESS"


@pytest.mark.req("SR-REC-1")
def test_a_stop_whose_close_raises_is_still_answered(rig, monkeypatch, caplog) -> None:  # type: ignore[no-untyped-def]
    """Whatever the close does, StopRecording gets its answer (before: the worker's job raised
    and the operator waited forever), the failure is counted on top of the others and the
    operator's log has the exception with the file it was closing."""
    sim, op, _, recs = rig
    caplog.set_level(logging.INFO, logger="occ.core.robot")
    recs.mkdir(parents=True)
    (recs / "taken.igtl").write_bytes(b"")
    assert command(sim, op, "StartRecording", start_xml("taken")).metadata["Status"] == "FAIL"
    assert stats(sim, op)["failed"] == 1  # a failure before: the next one is counted on it
    assert command(sim, op, "StartRecording", start_xml("c")).metadata["Status"] == "SUCCESS"
    rec = sim.robot.recorder

    def bad_close() -> None:
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(rec, "close", bad_close)
    stop = command(sim, op, "StopRecording")
    assert stop.metadata["Status"] == "FAIL"
    assert stop.metadata["Message"] == (
        f"StopRecording: recording stopped; closing {recs / 'c.igtl'} failed: "
        "[Errno 5] Input/output error"
    )
    done = stats(sim, op)
    assert (done["active"], done["started"], done["stopped"], done["failed"]) == (False, 1, 0, 2)
    errors = [
        r for r in caplog.records if r.name == "occ.core.robot" and r.levelno >= logging.ERROR
    ]
    assert [(r.levelno, r.getMessage()) for r in errors] == [
        (logging.ERROR, f"StopRecording: {recs / 'c.igtl'}")
    ]
    assert errors[0].exc_info is not None and isinstance(errors[0].exc_info[1], OSError)
    monkeypatch.undo()
    rec.close()


@pytest.mark.slow
@pytest.mark.req("SR-REC-1")
def test_occd_recording_to_dev_full(tmp_path: Path) -> None:
    """The issue's own case, on a real ``occd --record /dev/full`` over TCP: one alert to the
    connected operator, one line in the log and no traceback, the daemon running, StopRecording
    answered, exit 0."""
    from loopback import stop_processes, wait_port
    from slicer_standin import SlicerStandIn

    proc, ports = start_slave(tmp_path, "--record", "/dev/full")
    try:
        assert wait_port(ports["operator"]), (
            proc.stderr.read().decode() if proc.poll() else "no port"
        )
        with SlicerStandIn("127.0.0.1", ports["operator"]) as op:
            assert op.connected.wait(5.0)

            def ask(name: str) -> Any:
                reply = op.wait_reply(op.send_command(name), 10.0)
                assert reply is not None, f"no reply to {name}"
                return reply

            def recording_alerts() -> list[Any]:
                return [s for s in op.statuses if s.error_name == "RECORDING"]

            # the writer meets the full disk at its first flush, 50 ms in (maybe before the
            # operator connected: then the status says it)
            status = wait_until(
                lambda: (
                    (m := ask("GetRecordingStatus").metadata["Message"]).startswith(
                        "recording=failed"
                    )
                    and m
                ),
                10.0,
                every=0.05,
            )
            assert "cause=No space left on device (ENOSPC)" in status
            time.sleep(0.5)  # ten more flushes of the writer: still one alert, one log line
            assert len(recording_alerts()) <= 1  # 0 when it failed before the connection
            assert ask("GetStats").metadata["Status"] == "SUCCESS"  # the daemon serves
            stop = ask("StopRecording")
            assert stop.metadata["Status"] == "FAIL"
            assert "it had FAILED: No space left on device (ENOSPC)" in stop.metadata["Message"]
            assert "records not written" in stop.metadata["Message"]
    finally:
        stop_processes([proc])
    err = proc.stderr.read().decode() if proc.stderr else ""
    assert proc.returncode == 0, err
    assert err.count("recording /dev/full failed: No space left on device (ENOSPC)") == 1, err
    assert "Traceback" not in err, err


@pytest.mark.req("SR-REC-1")
def test_close_waits_for_a_writer_that_drains_a_backlog(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A backlog that takes the writer longer than close's wait: close waits as long as the
    writer takes records (before: it gave up after 5 s and flushed from a second thread while
    the writer still wrote, losing records); only a writer that takes nothing is given up."""
    from occ.recording import record

    # the wait: well above a loaded machine's scheduling gaps (the writer must get going),
    # well below the backlog's time (20000 records take the writer 1-2 s here)
    monkeypatch.setattr(record, "CLOSE_WAIT_S", 0.3)
    path = tmp_path / "backlog.igtl"
    rec = Recorder(path, max_backlog=10**6).start()
    n = 20000
    for k in range(n):
        msg = igtl.StatusMessage(code=1, error_name="E", status_message=f"m{k}", device_name="D")
        rec.record_message(msg, "out", "*", float(k))
    rec.close()
    assert rec.failure is None, rec.failure
    assert rec.written == n and rec.not_written() == 0
    msgs = read_recording(path)
    assert [m.status_message for m in msgs] == [f"m{k}" for k in range(n)]  # type: ignore[attr-defined]
