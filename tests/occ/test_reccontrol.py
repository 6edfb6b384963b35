"""Recording started and stopped at run time: PLUS's StartRecording / StopRecording and
GetRecordingStatus, over COMMAND and over STRING ``CMD_<id>``.

The in-process rig checks the rules (file names, refusals, what the file holds); the last test
does the same over real TCP sockets against a running ``occd``.
"""

from __future__ import annotations

import subprocess
import sys
import time
from itertools import pairwise
from pathlib import Path
from typing import Any

import pytest
import yaml

import igtl
from occ.record import STATE_DEVICE, read_recording
from occ.testing import SimPeer, SimRobot, wait_until

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


# ---------------------------------------------------------------------- a running daemon, TCP
@pytest.mark.realtime
def test_start_stop_on_a_running_daemon(tmp_path: Path) -> None:
    from loopback import free_port, stop_processes, wait_port, write_yaml
    from slicer_standin import SlicerStandIn

    cfg = slave_config(tmp_path / "recs")
    ports = {}
    for itf in cfg["interfaces"]:
        if itf["transport"] == "tcp-server":
            itf["port"] = ports[itf["name"]] = free_port()
        else:
            import socket

            itf["port"] = free_port(socket.SOCK_DGRAM)
    cfg["recording"]["path"] = None
    write_yaml(tmp_path / "slave.yaml", cfg)
    proc = subprocess.Popen(
        [sys.executable, "-m", "occ.cli", str(tmp_path / "slave.yaml"), "--log-level", "WARNING"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
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
