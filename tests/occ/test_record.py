"""Recording: every message in/out plus loop state in one file that `igtl dump` reads; CSV; replay."""

from __future__ import annotations

import csv
import json
import threading
from pathlib import Path

import igtl
from igtl.transport import Peer, UDPEndpoint
from occ.recording.export import export_csv
from occ.recording.record import Recorder, original, read_recording, replay
from occ_testkit.testing import SimRobot

ROOT = Path(__file__).resolve().parents[2]


def record_some(path: Path, ticks: int = 300) -> int:
    rec = Recorder(path, rate_hz=100).start()
    sim = SimRobot(ROOT / "configs" / "slave.yaml", recorder=rec)
    master = sim.peer("master", address=("127.0.0.1", 5000))
    sim.peer("slicer")  # a Slicer that receives the Tip and Base outputs
    sim.robot.state_machine.request("enable")
    sim.robot.state_machine.request("run")
    sent = 0
    for k in range(ticks):
        if k % 2 == 0:
            sent += 1
            assert master.send_position((0.1 * k, 50.0, 270.0), seq=sent) == 1
        sim.tick()
    sim.close()
    rec.close()
    return sent


def test_recording_holds_messages_and_state(tmp_path: Path) -> None:
    path = tmp_path / "slave.igtl"
    sent = record_some(path)
    msgs = read_recording(path)
    ins = [m for m in msgs if m.metadata.get("rec.dir") == "in" and m.message_type == "POSITION"]
    assert len(ins) == sent
    assert [m.message_id for m in ins] == list(range(1, sent + 1))
    outs = [m for m in msgs if m.metadata.get("rec.dir") == "out"]
    assert any(m.message_type == "TRANSFORM" and m.device_name == "Tip" for m in outs)
    assert any(m.message_type == "STATUS" for m in outs)  # state transitions
    states = [m for m in msgs if m.message_type == "NDARRAY" and m.device_name == "OCCState"]
    assert len(states) == 30  # 100 Hz over 300 simulated ticks at 1 kHz: exactly
    cols = states[0].metadata["columns"].split(",")
    assert cols[:2] == ["t", "state"] and "tip.x_mm" in cols and len(cols) == states[0].array.size
    # the original wire form is recoverable
    o = original(ins[0])
    assert o.header_version == 2 and "rec.dir" not in o.metadata and o.metadata["run"] == "1"


def test_igtl_dump_reads_a_recording(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    from igtl.cli import main as igtl_main

    path = tmp_path / "r.igtl"
    record_some(path, ticks=50)
    assert igtl_main(["dump", str(path), "--json"]) == 0
    lines = [
        json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")
    ]
    assert {"POSITION", "NDARRAY", "TRANSFORM"} <= {d["type"] for d in lines}


def test_export_csv(tmp_path: Path) -> None:
    path = tmp_path / "r.igtl"
    record_some(path, ticks=100)
    state_csv, msg_csv = export_csv(path, tmp_path / "csv")
    rows = list(csv.reader(state_csv.open()))
    assert rows[0][0] == "t" and len(rows) > 5 and all(len(r) == len(rows[0]) for r in rows)
    # the state by its name, as an operator reads it
    assert {r[1] for r in rows[1:]} <= {"INIT", "READY", "ENABLED", "RUNNING", "STOPPED"}
    assert "RUNNING" in {r[1] for r in rows[1:]}
    mrows = list(csv.DictReader(msg_csv.open()))
    assert any(r["type"] == "POSITION" and r["dir"] == "in" for r in mrows)


def test_replay_sends_recorded_inputs(tmp_path: Path) -> None:
    path = tmp_path / "r.igtl"
    sent = record_some(path, ticks=60)
    got: list[igtl.Message] = []
    done = threading.Event()

    def on_message(peer: Peer, msg: igtl.Message) -> None:
        got.append(msg)
        if len(got) >= sent:
            done.set()

    ep = UDPEndpoint("127.0.0.1", 0, on_message=on_message).start()
    try:
        n = replay(path, ep.address, udp=True, speed=10.0, types={"POSITION"})
        assert n == sent
        assert done.wait(5.0)
    finally:
        ep.stop()
    assert [m.message_id for m in got] == list(range(1, sent + 1))
    assert all("rec.dir" not in m.metadata for m in got)
