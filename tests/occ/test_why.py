"""``occ-record why DIR`` (occ/recording/why.py, whytext.py): the chain that led to a black box
dump, told from the dump alone. Each case stops a simulated robot the way it stops in the
field, then reads only the dump directory: exact runs, simulated time."""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path
from typing import Any

import pytest
import yaml

from occ.config import DaemonConfig
from occ.core.safety import RobotState
from occ.recording.cli import main as occ_record
from occ_testkit import CONFIGS
from occ_testkit.rigs import SlaveRig
from occ_testkit.testing import SimRobot
from tests.occ.test_collision import CEILING, command, ur5

pytestmark = pytest.mark.req("SR-WHY-1")

#: the whole text and JSON of ``why`` on each simulated stop, as reviewed (tests/occ/data/why/;
#: OCC_WHY_GOLDEN=write writes them again from this code: review the difference)
GOLDEN = Path(__file__).parent / "data" / "why"


def _slave(tmp_path: Path) -> SlaveRig:
    raw = yaml.safe_load((CONFIGS / "slave.yaml").read_text())
    raw["black_box"] = {"dir": str(tmp_path / "bb")}
    return SlaveRig(DaemonConfig.model_validate(raw, context={"base_dir": CONFIGS}))


def _dumps(box: Any) -> list[Path]:
    assert box.wait_idle(30.0)
    return sorted(p for p in box.dir.iterdir() if not p.name.startswith("."))


def _why(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = occ_record(["why", *args])
    out, err = capsys.readouterr()
    return code, out, err


def _explain(
    capsys: pytest.CaptureFixture[str], path: Path, golden: str | None = None
) -> tuple[dict[str, Any], str]:
    """The JSON and the text of ``why`` on ``path``, both exiting 0; with ``golden``, each
    equal to the reviewed one of that name (:func:`_same`)."""
    code, out, err = _why(capsys, str(path), "--json")
    assert code == 0, err
    x = json.loads(out)
    code, text, err = _why(capsys, str(path))
    assert code == 0, err
    if golden is not None:
        _same(golden, path, x, text)
    return x, text


def _masked(path: Path, x: Any, text: str) -> tuple[Any, str]:
    """The explanation without what is not the dump's: its directory and the software."""
    where = str(path)
    text = text.replace(where, "<dump>")
    text = re.sub(r"; occ \S+ \(\S+\)$", "; occ <version> (<build>)", text, flags=re.M)
    x = json.loads(json.dumps(x).replace(json.dumps(where)[1:-1], "<dump>"))
    x["software"] = "<software>"
    return x, text


def _close(a: Any, b: Any, where: str = "") -> None:
    """``a`` equal to ``b``, floats to 1e-9 (a compiled build may round a drive's reading
    in its last bits)."""
    if isinstance(b, float) and isinstance(a, float):
        assert a == pytest.approx(b, rel=1e-9, abs=1e-12), where
    elif isinstance(b, dict):
        assert isinstance(a, dict) and list(a) == list(b), where
        for k in b:
            _close(a[k], b[k], f"{where}.{k}")
    elif isinstance(b, list):
        assert isinstance(a, list) and len(a) == len(b), where
        for i, (u, v) in enumerate(zip(a, b, strict=True)):
            _close(u, v, f"{where}[{i}]")
    else:
        assert type(a) is type(b) and a == b, where


_TINY = re.compile(r"(vel|eff) -?\d\.\d+e-\d+")


def _same(name: str, path: Path, x: dict[str, Any], text: str) -> None:
    x, text = _masked(path, x, text)
    if os.environ.get("OCC_WHY_GOLDEN") == "write":
        GOLDEN.mkdir(parents=True, exist_ok=True)
        (GOLDEN / f"{name}.txt").write_text(text)
        (GOLDEN / f"{name}.json").write_text(json.dumps(x, indent=1) + "\n")
    # a simulated drive's speed and effort near zero: their digits are float noise
    assert _TINY.sub(r"\1 ~0", text) == _TINY.sub(r"\1 ~0", (GOLDEN / f"{name}.txt").read_text())
    _close(x, json.loads((GOLDEN / f"{name}.json").read_text()))


def test_a_loss_stop_names_the_three_numbers_judged_lost(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = _slave(tmp_path)
    try:
        rig.running()
        rig.step(99)  # the source sends before every even tick: the last one before tick 120
        good, good_t = rig.seq, (rig.sim.k - 1) * rig.sim.period
        rig.seq += 3  # three numbers never sent: lost
        proof_t = rig.sim.k * rig.sim.period + rig.sim.period  # the next sample, next tick
        rig.step(20)
        assert rig.robot.state is RobotState.STOPPED
        (path,) = _dumps(rig.robot.black_box)
    finally:
        rig.close()
    x, text = _explain(capsys, path, "loss")
    (chain,) = x["chains"]
    assert chain["kind"] == "loss" and chain["stream"] == "master"
    assert chain["from"] == "the loss monitor's note"  # the alarms' tap, not the reason's text
    assert chain["lost"] == [good + 1, good + 2, good + 3] and chain["count"] == 3
    assert chain["max_consecutive"] == 2 and chain["policy"] == "hold"
    assert chain["last_good"]["seq"] == good and chain["last_good"]["t"] == good_t
    assert chain["proved_by"]["seq"] == good + 4
    assert chain["proved_by"]["t"] == pytest.approx(proof_t, abs=1e-9)
    assert chain["judged"]["tick"] == x["trigger"]["tick"] == chain["proved_by"]["tick"]
    assert chain["judged"]["since_last_good_ms"] == pytest.approx(2.0)
    assert x["trigger"]["state"] == "STOPPED"
    assert x["transitions"][-1]["to"] == "STOPPED" and chain["lacks"] == []
    assert f"lost       seq {good + 1}, {good + 2}, {good + 3} (3 in a row" in text
    assert f"last good  seq {good}, taken by the loop at t={good_t:.6f} s" in text
    assert f"proved by  seq {good + 4}" in text


def test_a_late_stream_names_the_samples_late_and_by_how_much(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A hold that resumed (the stream silent 20 ms), then samples stamped 200 ms old until
    the grace latches: each is named with how much older than the stream's freshest it was."""
    rig = _slave(tmp_path)
    try:
        rig.timestamped = True
        rig.running()
        rig.step(40)
        rig.sending = False
        rig.step(20)
        rig.sending = True
        rig.step(20)
        last_good = rig.seq
        for _ in range(150):
            if rig.sim.k % 2 == 0:
                rig.seq += 1
                old = rig.sim.clock.wall_time() - 0.2
                rig.source.send_position(rig.target, seq=rig.seq, timestamp=old, device="Master")
            rig.sim.tick()
        assert rig.robot.state is RobotState.STOPPED
        (path,) = _dumps(rig.robot.black_box)
    finally:
        rig.close()
    x, text = _explain(capsys, path, "late")
    (chain,) = x["chains"]
    assert chain["kind"] == "late" and chain["last_good"]["seq"] == last_good
    assert chain["latched"]["cause"].startswith("no packet for 101.00 ms")
    assert chain["hold"]["after_ms"] == pytest.approx(7.0)
    samples = chain["samples"]
    assert [s["seq"] for s in samples] == list(range(last_good + 1, last_good + 51))
    # sent on time, stamped 200 ms old (to the microsecond: wall times near 1.7e9 s in float64)
    assert all(s["older_ms"] == pytest.approx(200.0, abs=1e-3) for s in samples)
    assert all(s["late_ms"] == pytest.approx(0.0, abs=1e-6) for s in samples)
    (hold,) = x["holds"]  # the earlier one, which resumed
    assert hold["ended"]["kind"] == "resume"
    (back,) = hold["samples"]
    assert back["seq"] == hold["last_good"]["seq"] + 1
    assert back["late_ms"] == pytest.approx(20.0)  # due 2 ms after the last good, came at 22
    assert "50 sample(s), none accepted" in text and "+200.0 ms older" in text


def test_a_drive_fault_names_the_drive_the_rule_and_the_reading(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = _slave(tmp_path)
    try:
        rig.running()
        rig.step(50)
        rig.robot.hardware.drivers[0].inject("nan", 1)  # pitch reads NaN
        rig.step(5)
        assert rig.robot.state is RobotState.FAULT
        pitch = rig.robot.joints[1]
        kept_from = pitch.stamp
        (path,) = _dumps(rig.robot.black_box)
    finally:
        rig.close()
    x, text = _explain(capsys, path, "drive")
    (chain,) = x["chains"]
    assert chain["kind"] == "drive"
    (f,) = chain["failures"]
    assert (f["driver"], f["action"], f["joint"], f["rule"]) == ("sim", "read", "pitch", "lost")
    before, at = f["readings"]["pitch"]
    assert at["tick"] == x["trigger"]["tick"] == before["tick"] + 1
    if at["raw"] is not None:  # the dump has the raw readings: the NaN itself
        assert at["raw"]["pos"] == "nan"
    else:  # what the loop kept: the last reading it believed, not this tick's
        assert at["kept"]["stamp"] == kept_from < at["t"]
        assert any("raw drive readings" in s for s in chain["lacks"])
    assert math.isfinite(before["kept"]["pos"])
    assert "drive 'sim': read failed" in text and "rule       lost:" in text


def test_an_operator_dump_and_an_estop_name_who_asked(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = _slave(tmp_path)
    try:
        rig.running()
        rig.step(30)
        xml = '<Command Name="DumpBlackBox" Reason="the tool twitched"/>'
        rig.operator.send_command("DumpBlackBox", xml)
        rig.step(1)
        rig.command("EStop")
        dumped, estop = _dumps(rig.robot.black_box)
    finally:
        rig.close()
    assert dumped.name.endswith("-operator") and estop.name.endswith("-estop")
    x, text = _explain(capsys, dumped, "operator")
    (chain,) = x["chains"]
    assert chain["kind"] == "request" and chain["command"] == "DumpBlackBox"
    assert chain["interface"] == "operator" and chain["args"] == {"Reason": "the tool twitched"}
    assert chain["sender"]["peer"] == "127.0.0.1:40001" and chain["sender"]["signed"] == "no"
    assert chain["reply"]["status"] == "SUCCESS" and str(dumped) in chain["reply"]["message"]
    assert "by 127.0.0.1:40001 (role operator" in text and 'Reason="the tool twitched"' in text
    x, text = _explain(capsys, estop, "estop")
    (chain,) = x["chains"]
    assert (chain["kind"], chain["command"], chain["interface"]) == ("request", "EStop", "operator")
    assert chain["tick"] == x["trigger"]["tick"] and chain["reply"]["status"] == "SUCCESS"
    assert "EStop asked on the interface 'operator' by 127.0.0.1:40001" in text


def test_a_collision_stop_names_the_link_and_the_clearance(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """configs/ur5.yaml teleoperated up into a ceiling (as tests/occ/test_collision.py)."""
    cfg = ur5({"margin_mm": 10.0, "regions": [CEILING]})
    cfg["black_box"] = {"dir": str(tmp_path / "bb")}
    sim = SimRobot(cfg)
    try:
        master = sim.peer("master")
        command(sim, "Enable")
        command(sim, "Run")
        for k in range(8000):
            if k % 2 == 0:  # the tool raised at 50 mm/s (the master twice that, scale 0.5)
                n = k // 2 + 1
                master.send_position((0.0, 0.0, 0.2 * n), seq=n, timestamp=sim.clock.wall_time())
            sim.step(1)
            if sim.robot.state is not RobotState.RUNNING:
                break
        assert sim.robot.state is RobotState.STOPPED
        (path,) = _dumps(sim.robot.black_box)
    finally:
        sim.close()
    x, text = _explain(capsys, path, "collision")
    (chain,) = x["chains"]
    assert chain["kind"] == "collision"
    v = chain["verdict"]
    assert v["link"] == "wrist_2_link" and v["near"] == "ceiling"
    assert v["margin_mm"] == pytest.approx(10.0)
    assert 0.0 < v["clearance_mm"] < 10.0 and v["inside_by_mm"] > 0.0
    assert f"{v['clearance_mm']:.2f} mm" in chain["reason"]  # the number the alert said
    assert v["tick"] <= x["trigger"]["tick"] and chain["before"]
    assert all(b["clearance_mm"] > v["clearance_mm"] for b in chain["before"])
    assert "link 'wrist_2_link' near 'ceiling': clearance" in text


def test_a_directory_that_is_not_a_dump_exits_1_and_a_wrong_command_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = _why(capsys, str(tmp_path))
    assert code == 1 and out == ""
    assert f"occ-record why: {tmp_path}: not a black box dump" in err
    code, out, err = _why(capsys, str(tmp_path / "nowhere"))
    assert code == 1 and err == (
        f"occ-record why: {tmp_path / 'nowhere'}: does not exist: a black box dump is a "
        "directory with a manifest.json\n"
    )
    (tmp_path / "manifest.json").write_text('{"format": "something else"}')
    code, out, err = _why(capsys, str(tmp_path))
    assert code == 1 and "not a black box dump (format 'something else')" in err
    for wrong in ([], [str(tmp_path), "--last", "-1"], [str(tmp_path), "--bogus"]):
        with pytest.raises(SystemExit) as exc:
            occ_record(["why", *wrong])
        assert exc.value.code == 2


# ------------------------------------------------------------------ dumps made by hand
# What the simulated stops above do not reach: a dump without the alarms' notes (written before
# they existed: each chain told from the transition's reason), the parts of a dump that could
# not be read, and the edges of each chain. Each dump is written here file by file.
WALL = 1_700_000_000.0


def _position(seq: int, *, stamp: float = 0.0, v1: bool = False) -> Any:
    import igtl

    return igtl.PositionMessage(
        (1.0, 2.0, 3.0),
        (0.0, 0.0, 0.0, 1.0),
        24,
        device_name="Master",
        timestamp=stamp,
        header_version=1 if v1 else 2,
        message_id=seq,
    )


def _made(
    tmp_path: Path,
    reason: str,
    *,
    cause: str = "stopped",
    tick: int = 10,
    events: list[dict[str, Any]] | None = None,
    messages: list[tuple[Any, str, str, int]] | None = None,
    columns: list[str] | None = None,
    rows: Any = None,
    config: dict[str, Any] | None = None,
    **manifest: Any,
) -> Path:
    """A dump of a robot at 1 kHz stopped in ``tick`` by ``reason``: ``messages`` as (message,
    direction, interface, tick), ``columns`` of ``rows`` (by default ``t`` and ``state``, the
    state RUNNING until the trigger's tick, STOPPED in it)."""
    import numpy as np

    from occ.recording.record import STATE_CODES, pack_message_record

    d = tmp_path / "dump"
    d.mkdir()
    if columns is None:
        columns = ["t", "state"]
        rows = np.array(
            [
                [k / 1000.0, STATE_CODES["RUNNING" if k < tick else "STOPPED"]]
                for k in range(tick + 1)
            ]
        )
    if rows is not None:
        np.save(d / "ticks.npy", rows)
    doc: dict[str, Any] = {
        "format": "occ-black-box",
        "robot": "arm",
        "causes": [{"cause": cause, "reason": reason}],
        "trigger": {"tick": tick, "t": tick / 1000.0, "wall": WALL + tick / 1000.0},
        "window": {
            "first_tick": 0,
            "ticks": tick + 1,
            "seconds": (tick + 1) / 1000.0,
            "events_whole_from_tick": 0,
            "rows_lost": 0,
        },
        "tick_columns": columns,
        "software": {"occ": "9.9", "build": "pure"},
    }
    doc.update(manifest)
    (d / "manifest.json").write_text(json.dumps(doc))
    (d / "events.jsonl").write_text("".join(json.dumps(e) + "\n" for e in events or []))
    with open(d / "recording.igtl", "wb") as f:
        for m, direction, interface, k in messages or []:
            f.write(pack_message_record(m, direction, interface, k / 1000.0, {"rec.tick": str(k)}))
    (d / "config.yaml").write_text(yaml.safe_dump(config or {}))
    return d


def _told(capsys: pytest.CaptureFixture[str], d: Path) -> tuple[dict[str, Any], list[str]]:
    x, text = _explain(capsys, d)
    return x, text.replace(str(d), "<dump>").splitlines()


LOSS = {
    "safety": {"loss": {"max_consecutive": 2, "policy": "hold", "grace_ms": 25, "period_ms": 4}}
}


def test_a_loss_without_the_monitors_note_is_told_from_the_reason_across_the_wrap(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Numbers wrap at 2**32: 4294967295, 0 and 1 lost between 4294967294 and 2."""
    reason = "packet loss on master: 3 consecutive packets lost (seq 4294967295-1 missing)"
    d = _made(
        tmp_path,
        reason,
        messages=[
            (_position(4294967294), "in", "master", 4),
            (_position(2), "in", "master", 10),
            (_position(3), "in", "master", 11),  # after the judgement: not the proof
        ],
        config=LOSS,
    )
    x, text = _told(capsys, d)
    (chain,) = x["chains"]
    assert chain == {
        "cause": "stopped",
        "reason": reason,
        "stream": "master",
        "policy": "hold",
        "from": "the transition's reason",
        "kind": "loss",
        "max_consecutive": 2,
        "lacks": [],
        "judged": {"tick": 10, "t": 0.01},
        "lost": [4294967295, 0, 1],
        "count": 3,
        "last_good": {"seq": 4294967294, "tick": 4, "t": 0.004},
        "proved_by": {"seq": 2, "tick": 10, "t": 0.01},
    }
    assert text[3:9] == [
        f"cause 1: stopped: {reason}",
        "  packet loss on the stream 'master' (from the transition's reason)",
        "  last good  seq 4294967294, taken by the loop at t=0.004000 s (tick 4, -6.000 ms)",
        "  lost       seq 4294967295, 0, 1 (3 in a row; more than safety.loss.max_consecutive"
        " = 2 latch the stop)",
        "  proved by  seq 2, taken by the loop at t=0.010000 s (tick 10, at the trigger)",
        "  judged     at t=0.010000 s (tick 10, at the trigger): latched, policy hold",
    ]
    assert x["trigger"] == {
        "tick": 10,
        "t": 0.01,
        "wall": WALL + 0.01,
        "utc": "2023-11-14 22:13:20.010 UTC",
        "state": "STOPPED",
    }
    assert text[0] == "why: arm at tick 10, t=0.010000 s (2023-11-14 22:13:20.010 UTC), STOPPED"
    assert text[-1] == (
        "window: 11 ticks (0.011 s) from tick 0; events whole from tick 0; rows lost 0; "
        "occ 9.9 (pure)"
    )
    assert "state transitions in the last 5 s:" in text and "  none" in text


def test_a_long_gap_lists_the_first_numbers_and_says_what_the_recording_lacks(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    reason = "packet loss on master: 100 consecutive packets lost (seq 100-199 missing)"
    d = _made(tmp_path, reason, messages=[(_position(7, v1=True), "in", "master", 3)])
    x, text = _told(capsys, d)
    (chain,) = x["chains"]
    assert chain["lost"] == list(range(100, 164)) and chain["count"] == 100
    assert chain["policy"] is None and chain["max_consecutive"] is None
    assert chain["last_good"] == {"seq": 99} and chain["proved_by"] == {"seq": 200}
    assert chain["lacks"] == [
        "seq 99 of master is not on the recording",
        "seq 200 of master is not on the recording",
    ]
    nums = ", ".join(str(n) for n in range(100, 164))
    assert text[4:10] == [
        "  packet loss on the stream 'master' (from the transition's reason)",
        "  last good  seq 99, in tick None (not on the recording)",
        f"  lost       seq {nums}, ... (100 in all) (100 in a row)",
        "  proved by  seq 200, in tick None (not on the recording)",
        "  judged     at t=0.010000 s (tick 10, at the trigger): latched, policy None",
        "  not in the dump: seq 99 of master is not on the recording",
    ]


def test_a_gap_told_by_time_stamps_has_no_numbers(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    reason = "packet loss on master: a gap of 30.0 ms in the sender's stamps"
    note = {
        "stream": "master",
        "event": {
            "kind": "latch",
            "source": "timestamp",
            "time": 0.0095,
            "since_last_good_s": 0.03,
            "cause": "a gap",
        },
    }
    d = _made(
        tmp_path,
        reason,
        events=[{"tick": 9, "t": 0.009, "kind": "note", "what": "loss", "value": note}],
        config=LOSS,
    )
    x, text = _told(capsys, d)
    (chain,) = x["chains"]
    assert chain["from"] == "the loss monitor's note" and chain["kind"] == "loss"
    assert chain["judged"] == {"tick": 9, "t": 0.0095, "since_last_good_ms": 30.0}
    assert chain["lacks"] == ["no sequence numbers: a gap of 30.0 ms in the sender's stamps"]
    assert "lost" not in chain and "last_good" not in chain
    assert x["stream_events"] == [
        {"tick": 9, "t": 0.0095, "stream": "master", "kind": "latch", "cause": "a gap"}
    ]
    assert (
        "  judged     at t=0.009500 s (tick 9, -0.500 ms), 30.000 ms after the last good "
        "sample: latched, policy hold" in text
    )
    assert "  at t=0.009500 s (tick 9, -0.500 ms)  master: latch: a gap" in text


def test_a_late_stream_without_the_note_is_told_from_the_silence_in_the_reason(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    reason = "packet loss on master: no packet for 8.00 ms (limit 6.0 ms)"
    d = _made(
        tmp_path,
        reason,
        messages=[(_position(5), "in", "master", 1), (_position(6), "in", "master", 2)],
        config=LOSS,
    )
    x, text = _told(capsys, d)
    (chain,) = x["chains"]
    assert chain == {
        "cause": "stopped",
        "reason": reason,
        "stream": "master",
        "policy": "hold",
        "from": "the transition's reason",
        "kind": "late",
        "latched": {"tick": 10, "t": 0.01, "cause": "no packet for 8.00 ms (limit 6.0 ms)"},
        "grace_ms": 25,
        "lacks": ["the loss monitor's note (the latch told by its reason)"],
        "last_good": {"seq": 6, "tick": 2, "t": 0.002},
        "period_ms": 4.0,
        "samples": [],
    }
    assert text[4:9] == [
        "  the stream 'master' came late (from the transition's reason)",
        "  last good  seq 6, taken by the loop at t=0.002000 s (tick 2, -8.000 ms)",
        "  after it   no sample came (the stream fell silent)",
        "  latched    at t=0.010000 s (tick 10, at the trigger): no packet for 8.00 ms (limit "
        "6.0 ms); safety.loss.grace_ms = 25; policy hold",
        "  not in the dump: the loss monitor's note (the latch told by its reason)",
    ]


def test_a_late_stream_whose_reason_names_no_silence_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    d = _made(tmp_path, "packet loss on master: stale samples", rows=None, columns=None)
    x, text = _told(capsys, d)
    (chain,) = x["chains"]
    assert chain["kind"] == "late" and chain["latched"]["t"] == 0.01  # the trigger's time
    assert chain["lacks"] == [
        "the loss monitor's note (the latch told by its reason)",
        "when the last sample was accepted",
    ]
    assert "samples" not in chain and "last_good" not in chain and chain["grace_ms"] is None
    assert (
        text[5]
        == "  latched    at t=0.010000 s (tick 10, at the trigger): stale samples; policy None"
    )


def test_drive_faults_told_from_the_reason_name_each_drive_its_joints_and_rule(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two drives in one reason, no note: the joint a cause names, else the driver's joints
    from the config; the kept readings (no raw columns), a reading kept from an earlier tick."""
    import numpy as np

    reason = (
        "driver arm: read failed: joint 'j1': feedback jump of 0.5 rad; "
        "driver hand: write failed: heartbeat lost"
    )
    cols = ["t", "state", "pos.j1", "vel.j1", "eff.j1", "stamp.j1", "sp.j1", "pos.g", "sp.g"]
    rows = np.array(
        [
            [0.008, 3, 0.1, 0.0, 0.0, 0.008, 0.1, 1.0, 1.0],
            [0.009, 3, 0.2, 0.5, 1.5, 0.009, 0.25, 1.0, 1.0],
            [0.010, 5, 0.2, 0.5, 1.5, 0.009, 0.3, 2.0, 1.0],
        ]
    )
    config = {
        "robot": {"drivers": [{"name": "arm", "joints": ["j1"]}, {"name": "hand", "joints": ["g"]}]}
    }
    d = _made(
        tmp_path,
        reason,
        cause="fault",
        columns=cols,
        rows=rows,
        config=config,
        window={"first_tick": 8},
    )
    x, text = _told(capsys, d)
    (chain,) = x["chains"]
    assert chain["kind"] == "drive"
    arm, hand = chain["failures"]
    assert (arm["driver"], arm["action"], arm["joint"]) == ("arm", "read", "j1")
    assert (arm["rule"], arm["setting"]) == ("jump", "feedback_jump")
    assert arm["rule_says"] == "a step faster than the joint can move"
    assert arm["cause"] == "joint 'j1': feedback jump of 0.5 rad"
    assert arm["readings"] == {
        "j1": [
            {
                "tick": 9,
                "t": 0.009,
                "raw": None,
                "setpoint": 0.25,
                "kept": {"pos": 0.2, "vel": 0.5, "eff": 1.5, "stamp": 0.009},
            },
            {
                "tick": 10,
                "t": 0.01,
                "raw": None,
                "setpoint": 0.3,
                "kept": {"pos": 0.2, "vel": 0.5, "eff": 1.5, "stamp": 0.009},
            },
        ]
    }
    assert (hand["driver"], hand["action"], hand["joint"], hand["rule"]) == (
        "hand",
        "write",
        None,
        "heartbeat",
    )
    assert hand["cause"] == "heartbeat lost" and hand["setting"] == ""
    assert [r["kept"]["pos"] for r in hand["readings"]["g"]] == [1.0, 2.0]
    assert chain["lacks"] == [
        "the drive failure note (the failure read back from the reason)",
        "the drive failure note (the failure read back from the reason)",
        "raw drive readings (no raw.* columns): the readings shown are what the loop kept, "
        "and a reading a check refused is not kept",
    ]
    assert x["trigger"]["state"] == "FAULT"
    assert text[4:14] == [
        "  drive 'arm': read failed: joint 'j1': feedback jump of 0.5 rad",
        "  rule       jump: a step faster than the joint can move (setting: feedback_jump)",
        "  joint j1:",
        "    at t=0.009000 s (tick 9, -1.000 ms): kept pos 0.2 vel 0.5 eff 1.5 stamp 0.009;"
        " setpoint 0.25",
        "    at t=0.010000 s (tick 10, at the trigger): kept pos 0.2 vel 0.5 eff 1.5 stamp"
        " 0.009; setpoint 0.3; kept since t=0.009000 s: this tick's reading was not taken",
        "  drive 'hand': write failed: heartbeat lost",
        "  rule       heartbeat: the drive's heartbeat was not heard in time",
        "  joint g:",
        "    at t=0.009000 s (tick 9, -1.000 ms): kept pos 1 vel None eff None stamp None;"
        " setpoint 1",
        "    at t=0.010000 s (tick 10, at the trigger): kept pos 2 vel None eff None stamp None;"
        " setpoint 1",
    ]


def test_a_drive_failure_note_and_raw_readings_are_preferred(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import numpy as np

    cols = ["t", "state", "pos.j1", "raw.pos.j1", "raw.vel.j1", "raw.pos.j10", "sp.j1"]
    rows = np.array([[0.009, 3, 0.1, 0.1, 0.0, 7.0, 0.1], [0.010, 5, 0.1, 9.0, 1.0, 7.0, 0.1]])
    note = {
        "failures": [
            {"driver": "arm", "action": "read", "cause": "limit: a reading"},
            "not a failure",
        ]
    }
    events = [
        {
            "tick": 9,
            "kind": "note",
            "what": "drive failure",
            "value": {"failures": [{"driver": "old"}]},
        },
        {"tick": 10, "kind": "note", "what": "drive failure", "value": note},
    ]
    d = _made(
        tmp_path,
        "driver arm: read failed: limit: a reading",
        cause="fault",
        columns=cols,
        rows=rows,
        events=events,
        window={"first_tick": 9},
        config={"robot": {"drivers": [{"name": "arm", "joints": ["j1"]}]}},
    )
    x, text = _told(capsys, d)
    (chain,) = x["chains"]
    (f,) = chain["failures"]
    assert f["rule"] == "the driver's own words" and f["rule_says"] == "" and f["setting"] == ""
    assert chain["lacks"] == []
    before, at = f["readings"]["j1"]
    assert at["raw"] == {"pos": 9.0, "vel": 1.0} and before["raw"] == {"pos": 0.1, "vel": 0.0}
    assert "  rule       the driver's own words" in text
    assert (
        "    at t=0.010000 s (tick 10, at the trigger): raw pos 9 vel 1; kept pos 0.1 vel None"
        " eff None stamp None; setpoint 0.1" in text
    )


@pytest.mark.parametrize(
    ("words", "rule", "setting"),
    [
        ("feedback lost", "lost", ""),
        ("outside its limits", "out of range", "limit_margin"),
        ("following error", "following error", "following_error"),
        ("feedback frozen", "frozen", "frozen_feedback_ms"),
    ],
)
def test_each_rule_of_the_feedback_checks_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], words: str, rule: str, setting: str
) -> None:
    d = _made(tmp_path, f"driver arm: read failed: joint j1: {words} (x)", cause="fault")
    x, _ = _told(capsys, d)
    (f,) = x["chains"][0]["failures"]
    assert (f["rule"], f["setting"], f["joint"]) == (rule, setting, "j1")
    assert f["readings"]["j1"][1] == {
        "tick": 10,
        "t": 0.01,
        "raw": None,
        "setpoint": None,
        "kept": {"pos": None, "vel": None, "eff": None, "stamp": None},
    }


def _verdict(
    tick: int, link: str, distance: float, slack: float, text: str = "", **more: Any
) -> dict[str, Any]:
    worst = {"link": link, "region": "ceiling", "distance": distance, "text": text}
    return {
        "tick": tick,
        "t": tick / 1000.0,
        "kind": "verdict",
        "value": {"worst": worst, "slack": slack, **more},
    }


def test_a_collision_stop_without_a_quoted_verdict_takes_the_last_inside_its_margin(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    events = [_verdict(k, "upper", 0.020 - k * 0.001, 0.010 - k * 0.001) for k in range(1, 8)]
    events += [
        _verdict(8, "wrist", 0.004, -0.006, peers=[["arm2", 0.25], [], "y", ["x"]]),
        _verdict(9, "upper", 0.012, 0.002),  # outside the margin again
        _verdict(10, "wrist", 0.001, -0.009),  # the trigger's own tick: the next check
        _verdict(11, "wrist", 0.0, -0.01),  # after the trigger
        {"tick": 9, "kind": "verdict", "value": {"worst": "not a verdict"}},
        {"tick": 9, "kind": "verdict", "value": None},
    ]
    d = _made(tmp_path, "collision: too near", events=events)
    x, text = _told(capsys, d)
    (chain,) = x["chains"]
    v = chain["verdict"]
    assert (v["tick"], v["link"], v["near"]) == (8, "wrist", "ceiling")
    assert v["clearance_mm"] == pytest.approx(4.0) and v["margin_mm"] == pytest.approx(10.0)
    assert v["inside_by_mm"] == pytest.approx(6.0)
    assert v["peers"] == [
        {"arm": "arm2", "clearance_mm": 250.0},
        {"arm": "x", "clearance_mm": "nan"},
    ]
    assert [b["tick"] for b in chain["before"]] == [3, 4, 5, 6, 7]  # the last five before it
    assert chain["lacks"] == []
    assert text[4:8] == [
        "  link 'wrist' near 'ceiling': clearance 4.00 mm, margin 10.00 mm (inside it by 6.00 mm)",
        "  verdict    seen by the loop at t=0.008000 s (tick 8, -2.000 ms)",
        "  other arm  arm2: clearance 250.00 mm",
        "  other arm  x: clearance nan mm",
    ]
    third = "link 'upper' near 'ceiling': clearance 17.00 mm"
    assert text[9] == f"    at t=0.003000 s (tick 3, -7.000 ms)  {third}"


def test_a_collision_stop_quoting_a_verdict_takes_it_even_in_the_trigger_tick(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    events = [
        _verdict(8, "wrist", 0.004, -0.006),
        _verdict(10, "elbow", 0.002, -0.008, "elbow close"),
    ]
    d = _made(tmp_path, "collision: elbow close (margin 10 mm)", events=events)
    x, text = _told(capsys, d)
    v = x["chains"][0]["verdict"]
    assert (v["tick"], v["link"], v["text"]) == (10, "elbow", "elbow close")
    assert [b["tick"] for b in x["chains"][0]["before"]] == [8]
    assert (
        "  verdict    seen by the loop at t=0.010000 s (tick 10, at the trigger): elbow close"
        in text
    )
    # none inside, none quoted: the last by the trigger
    (tmp_path / "b").mkdir()
    d = _made(
        tmp_path / "b",
        "collision: x",
        events=[_verdict(4, "a", 0.05, 0.04), _verdict(6, "b", 0.05, 0.04)],
    )
    x, _ = _told(capsys, d)
    assert x["chains"][0]["verdict"]["tick"] == 6 and x["chains"][0]["before"][0]["tick"] == 4


def test_a_collision_stop_without_verdicts_says_from_when_events_are_whole(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    window = {"first_tick": 0, "ticks": 11, "events_whole_from_tick": 4}
    d = _made(tmp_path, "collision: near", window=window)
    x, text = _told(capsys, d)
    assert x["chains"][0] == {
        "cause": "stopped",
        "reason": "collision: near",
        "kind": "collision",
        "lacks": ["no collision verdict in the window (events whole from tick 4)"],
    }
    assert text[4:6] == [
        "  collision stop",
        "  not in the dump: no collision verdict in the window (events whole from tick 4)",
    ]
    assert x["window"] == {
        "first_tick": 0,
        "ticks": 11,
        "seconds": None,
        "events_whole_from_tick": 4,
        "rows_lost": None,
    }


def test_a_request_not_on_the_recording_and_a_cause_with_no_chain(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    d = _made(tmp_path, "operator EStop", cause="estop")
    x, text = _told(capsys, d)
    assert x["chains"][0] == {
        "cause": "estop",
        "reason": "operator EStop",
        "kind": "request",
        "command": "EStop",
        "tick": 10,
        "lacks": ["the EStop request of tick 10 is not on the recording"],
    }
    assert text[4:6] == [
        "  EStop asked in tick 10",
        "  not in the dump: the EStop request of tick 10 is not on the recording",
    ]
    (tmp_path / "b").mkdir()
    d = _made(tmp_path / "b", "the watchdog bit", cause="stopped")
    x, text = _told(capsys, d)
    assert x["chains"][0]["kind"] == "other" and x["chains"][0]["lacks"] == []
    assert text[4] == "  no chain of its own in the dump: the reason above is what the robot said"
    # an estop whose reason names no one, and an operator's dump of another tick
    (tmp_path / "c").mkdir()
    events = [
        {"tick": 4, "kind": "dump", "cause": "operator", "reason": "operator DumpBlackBox: x"},
        {"tick": 6, "kind": "dump", "cause": "operator", "reason": "other"},
    ]
    d = _made(tmp_path / "c", "operator DumpBlackBox: x", cause="operator", events=events)
    x, _ = _told(capsys, d)
    assert x["chains"][0]["command"] == "DumpBlackBox" and x["chains"][0]["tick"] == 4
    (tmp_path / "e").mkdir()
    d = _made(tmp_path / "e", "operator", cause="estop")
    x, _ = _told(capsys, d)
    assert x["chains"][0]["kind"] == "other"


def test_what_a_dump_could_not_hold_is_named_and_the_rest_explained(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import numpy as np

    d = _made(tmp_path, "the watchdog bit", columns=["t", "state", "extra"], rows=np.zeros((11, 2)))
    (d / "events.jsonl").write_text('{"tick": 1, "kind": "x"}\n[1]\n{"tick": "1"}\nnot json\n')
    (d / "config.yaml").write_text(": : :\n  - [")
    whole = d / "recording.igtl"
    from occ.recording.record import pack_message_record

    blob = pack_message_record(_position(1), "in", "master", 0.001, {"rec.tick": "1"})
    whole.write_bytes(blob + blob[:30])
    x, text = _told(capsys, d)
    assert x["lacks"][0] == "ticks.npy has shape (11, 2), the manifest names 3 columns: not read"
    assert x["lacks"][1] == "events.jsonl: 3 line(s) that are not events, passed over"
    assert "recording.igtl: DAMAGED; salvaged 1 messages" in x["lacks"][2]
    assert "(the file ends inside a message, 30 bytes of it)" in x["lacks"][2]
    assert x["lacks"][3].startswith("config.yaml could not be read (")
    assert len(x["lacks"]) == 4 and x["trigger"]["state"] is None
    assert text[0] == "why: arm at tick 10, t=0.010000 s (2023-11-14 22:13:20.010 UTC)"
    said = "\n".join(f"not in the dump: {s}" for s in x["lacks"]).replace(str(d), "<dump>")
    assert "\n".join(text).endswith(said)
    # each file missing
    for f in ("ticks.npy", "events.jsonl", "recording.igtl", "config.yaml"):
        (d / f).unlink()
    x, _ = _told(capsys, d)
    assert [s.split(" (")[0] for s in x["lacks"]] == [
        "ticks.npy could not be read",
        "events.jsonl could not be read",
        "no recording.igtl: no messages",
        "config.yaml could not be read",
    ]
    assert x["lacks"][2] == "no recording.igtl: no messages (samples, requests)"
    assert x["lacks"][1].endswith("): no transitions, verdicts, notes")
    manifest = json.loads((d / "manifest.json").read_text())
    del manifest["tick_columns"]
    manifest["trigger"].pop("wall")
    (d / "manifest.json").write_text(json.dumps(manifest))
    (d / "config.yaml").write_text("[1, 2]")
    x, text = _told(capsys, d)
    assert x["lacks"][0] == "the manifest names no tick columns: ticks.npy not read"
    assert len(x["lacks"]) == 3 and x["trigger"]["utc"] is None and x["trigger"]["wall"] is None
    assert text[0] == "why: arm at tick 10, t=0.010000 s"


@pytest.mark.parametrize(
    "trigger", [None, {"t": 1.0}, {"tick": 1}, {"tick": "1", "t": 1.0}, {"tick": 1, "t": "1"}]
)
def test_a_manifest_without_a_whole_trigger_is_no_dump(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], trigger: Any
) -> None:
    d = _made(tmp_path, "x", trigger=trigger)
    code, out, err = _why(capsys, str(d))
    assert code == 1 and out == ""
    assert err == f"occ-record why: {d}: the manifest has no trigger (tick, t): not a whole dump\n"


def test_a_file_is_no_dump(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "f"
    f.write_text("x")
    code, _, err = _why(capsys, str(f))
    assert code == 1
    assert err == (
        f"occ-record why: {f}: is not a directory: a black box dump is a directory "
        "with a manifest.json\n"
    )


def test_a_hold_still_holding_at_the_trigger_and_samples_late_against_their_numbers(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A second stream held at the trigger: its samples after the last good one, each due a
    period per number after it (seq 12 came 4 ms late: 2 periods of 4 ms after seq 10, at
    0.008 + 0.008 = 0.016, came at 0.020), with its age against the freshest before."""

    def hold(k: int, stream: str, since: float, kind: str = "hold") -> dict[str, Any]:
        ev = {"kind": kind, "time": k / 1000.0, "since_last_good_s": since, "cause": f"{kind} c"}
        return {"tick": k, "kind": "note", "what": "loss", "value": {"stream": stream, "event": ev}}

    wall = WALL
    msgs = [
        (_position(9, stamp=wall + 0.0035), "in", "aux", 4),  # 0.5 ms old
        (_position(10, stamp=wall + 0.0075), "in", "aux", 8),  # 0.5 ms old: the freshest
        (_position(12, stamp=wall + 0.018), "in", "aux", 20),  # 2 ms old: 1.5 ms older
    ]
    events = [hold(1, "master", 0.5), hold(12, "aux", 0.004), hold(25, "aux", 0.0, "nothing")]
    events += [{"tick": 30, "kind": "note", "what": "loss", "value": {"stream": "aux", "event": 1}}]
    d = _made(
        tmp_path,
        "operator DumpBlackBox: look",
        cause="operator",
        tick=30,
        messages=msgs,
        events=events,
        config=LOSS,
    )
    x, text = _told(capsys, d)
    # the master's hold at tick 1 is 29 ms before the trigger: inside --last 0.025? no
    (h,) = [h for h in x["holds"] if h["stream"] == "aux"]
    assert h["ended"]["kind"] == "nothing" and h["ended"]["tick"] == 25
    assert h["held"] == {"tick": 12, "t": 0.012, "cause": "hold c"}
    # ages to the microsecond: stamps near 1.7e9 s in float64
    good = h["last_good"]
    assert (good["seq"], good["tick"], good["t"], good["stamp"]) == (10, 8, 0.008, wall + 0.0075)
    assert good["age_ms"] == pytest.approx(0.5, abs=1e-3)
    (s,) = h["samples"]
    assert s["seq"] == 12 and s["due"] == pytest.approx(0.016) and s["late_ms"] == 4.0
    assert s["age_ms"] == pytest.approx(2.0, abs=1e-3)
    assert s["older_ms"] == pytest.approx(1.5, abs=1e-3)
    assert h["freshest_age_ms"] == pytest.approx(0.5, abs=1e-3) and h["period_ms"] == 4.0
    code, out, _ = _why(capsys, str(d), "--json", "--last", "0.02")
    assert code == 0
    late = json.loads(out)
    assert [h["stream"] for h in late["holds"]] == ["aux"]  # the master's hold is older
    assert [e["tick"] for e in late["stream_events"]] == [12, 25]
    assert [h["stream"] for h in x["holds"]] == ["master", "aux"]
    (m,) = [h for h in x["holds"] if h["stream"] == "master"]
    assert m["ended"] == {"kind": "still holding", "tick": 30, "t": 0.03}
    assert "an earlier hold of the stream 'aux' (nothing)" in text
    assert (
        "    seq 12 came at t=0.020000 s (tick 20), +4.0 ms against its due t=0.016000 s; "
        "2.0 ms old on arrival: +1.5 ms older" in text
    )
    assert "  nothing    at t=0.025000 s (tick 25, -5.000 ms): nothing c" in text
    assert "  still holding at t=0.030000 s (tick 30, at the trigger)" in text


def _loss_note(
    k: int, stream: str, kind: str, time: float, since: float, **ev: Any
) -> dict[str, Any]:
    event = {"kind": kind, "time": time, "since_last_good_s": since, "cause": f"{kind} c", **ev}
    return {"tick": k, "kind": "note", "what": "loss", "value": {"stream": stream, "event": event}}


def test_a_latched_late_stream_is_judged_at_the_notes_time_and_its_own_hold(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The latch's note: its time, not the row's; the hold of its own stream (not another's,
    not a resume) after the last good sample; no period configured: 2 ms; samples without a
    number (v1) counted one period each; stamps on a wall clock near 1000 s (exact to 1e-13)."""
    import numpy as np

    from occ.recording.record import STATE_CODES

    wall = 1000.0
    rows = np.array([[k / 1000.0 + 0.0005, STATE_CODES["RUNNING"]] for k in range(31)])
    msgs = [
        (_position(5), "in", "master", 2),  # the last good one, no stamp
        (_position(0, v1=True, stamp=wall + 0.012), "in", "master", 12),  # v1: no number
        (_position(0, v1=True, stamp=wall + 0.0141234567), "in", "master", 14),
    ]
    events = [
        _loss_note(5, "master", "hold", 0.001, 0.0),  # before the last good one: not its hold
        _loss_note(6, "other", "hold", 0.006, 0.004),  # another stream's
        _loss_note(7, "master", "resume", 0.007, 0.005),  # not a hold
        _loss_note(8, "master", "hold", 0.0080005, 0.006),
        _loss_note(29, "master", "latch", 0.0290005, 0.027, source="grace"),
        _loss_note(30, "master", "hold", 0.030, 0.028),  # after the judgement
    ]
    d = _made(
        tmp_path,
        "packet loss on master: no packet for 27.00 ms (limit 25.0 ms)",
        tick=30,
        rows=rows,
        columns=["t", "state"],
        messages=msgs,
        events=events,
        trigger={"tick": 30, "t": 0.03, "wall": wall + 0.03},
        config={"safety": {"loss": {"grace_ms": 25}}},
    )
    x, text = _told(capsys, d)
    chain = x["chains"][0]
    assert chain["kind"] == "late" and chain["from"] == "the loss monitor's note"
    latched = {"tick": 29, "t": 0.0290005, "cause": "no packet for 27.00 ms (limit 25.0 ms)"}
    assert chain["latched"] == latched
    assert chain["hold"] == {"tick": 8, "t": 0.0080005, "after_ms": 6.0}
    assert chain["period_ms"] == 2.0 and chain["lacks"] == []
    assert chain["last_good"] == {"seq": 5, "tick": 2, "t": 0.002}
    first, second = chain["samples"]
    assert first["seq"] is None
    assert (first["due"], second["due"]) == pytest.approx((0.0040005, 0.0060005), abs=1e-12)
    assert first["age_ms"] == 0.0 and second["age_ms"] == pytest.approx(-0.123457, abs=1e-9)
    assert "older_ms" not in first and "freshest_age_ms" not in chain  # none before had a stamp
    assert text[6] == (
        "  held       at t=0.008001 s (tick 8, -21.999 ms), 6.0 ms after it (the deadline)"
    )


def test_older_than_the_freshest_to_the_nanosecond_and_never_minus_zero(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    wall = 1000.0
    msgs = [
        (_position(1, stamp=wall + 0.0015), "in", "master", 2),  # 0.5 ms old: the freshest
        (_position(2, stamp=wall + 0.0025000000001), "in", "master", 3),  # a hair fresher
        (_position(3, stamp=wall + 0.00387654321), "in", "master", 4),
    ]
    d = _made(
        tmp_path,
        "packet loss on master: no packet for 2.00 ms (limit 1.0 ms)",
        tick=4,
        messages=msgs,
        trigger={"tick": 4, "t": 0.004, "wall": wall + 0.004},
    )
    x, text = _told(capsys, d)
    a, b = x["chains"][0]["samples"]
    assert math.copysign(1.0, a["older_ms"]) == 1.0 and a["older_ms"] == 0.0  # not -0.0
    assert b["older_ms"] == -0.376543  # 0.12345679 ms old: 0.37654321 fresher, to the ns
    assert "+0.0 ms older" in "\n".join(text)


def test_a_hold_with_no_sample_before_it_and_exactly_eight_after(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    msgs = [(_position(n), "in", "master", 10 + n) for n in range(1, 9)]
    events = [_loss_note(5, "master", "hold", 0.005, 0.004)]
    d = _made(tmp_path, "the watchdog bit", tick=30, messages=msgs, events=events, config=LOSS)
    x, text = _told(capsys, d)
    (h,) = x["holds"]
    assert h["last_good"] == {"t": 0.001} and h["ended"]["kind"] == "still holding"
    assert [s["seq"] for s in h["samples"]] == list(range(1, 9))
    # no number before them: each due a period per sample after the last good time
    assert [s["due"] for s in h["samples"]][:2] == pytest.approx([0.005, 0.009])
    assert text[6] == "an earlier hold of the stream 'master' (still holding)"
    assert text[7:10] == [
        "  last good  a sample, at t=0.001000 s (tick None, -29.000 ms) (not on the recording)",
        "  held       at t=0.005000 s (tick 5, -25.000 ms): hold c",
        "  after it   8 sample(s), none accepted (due every 4 ms):",
    ]
    assert text[10:18] == [
        f"    seq {n} came at t=0.0{10 + n}000 s (tick {10 + n}), {10 + n - 1 - 4 * n:+.1f} ms "
        f"against its due t={0.001 + 0.004 * n:.6f} s"
        for n in range(1, 9)
    ]
    assert text[18] == "  still holding at t=0.030000 s (tick 30, at the trigger)"


def test_a_late_latch_with_no_good_sample_says_a_sample(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    d = _made(tmp_path, "packet loss on master: no packet for 5.00 ms (limit 4.0 ms)")
    x, text = _told(capsys, d)
    assert x["chains"][0]["last_good"] == {"t": 0.005}
    assert (
        text[5]
        == "  last good  a sample, at t=0.005000 s (tick None, -5.000 ms) (not on the recording)"
    )


def test_a_drive_failure_without_a_cause_or_a_configured_driver(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    note = {"failures": [{"driver": "ghost", "action": "read"}]}
    events = [{"tick": 10, "kind": "note", "what": "drive failure", "value": note}]
    d = _made(tmp_path, "driver ghost: read failed: x", cause="fault", events=events)
    x, text = _told(capsys, d)
    (f,) = x["chains"][0]["failures"]
    assert f["cause"] == "" and f["rule"] == "the driver's own words" and f["readings"] == {}
    assert "  drive 'ghost': read failed: " in text


def test_who_asked_is_the_request_of_the_tick_its_sender_and_its_own_reply(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Among the tick's messages: the EStop taken on the operator interface (not one of
    another tick, not one sent out, not a query, not another command); its sender's note (of
    its tick, interface and name); its reply among several (RTS_COMMAND naming it, or a
    STRING ACK_ on the same interface)."""
    import igtl

    def cmd(name: str, *, rts: bool = False, text: str = "") -> Any:
        cls = igtl.RTSCommandMessage if rts else igtl.CommandMessage
        return cls(
            command_id=1, command_name=name, command=text, device_name="command", header_version=2
        )

    def reply(name: str, status: str, *, rts: bool = True, device: str = "ACK_1") -> Any:
        xml = f'<CommandReply Name="{name}" Status="{status}"/>'
        if rts:
            return igtl.RTSCommandMessage(
                command_id=1,
                command_name="",
                command=xml,
                device_name="command",
                header_version=2,
                metadata={"Status": status},
            )
        return igtl.StringMessage(
            string=xml, device_name=device, header_version=2, metadata={"Status": status}
        )

    note = {
        "interface": "operator",
        "name": "estop",
        "peer": "10.0.0.9:1",
        "role": "operator",
        "signed": "yes",
    }
    events = [
        {"tick": 9, "kind": "note", "what": "request", "value": {**note, "peer": "old"}},
        {"tick": 10, "kind": "note", "what": "request", "value": {**note, "name": "Stop"}},
        {
            "tick": 10,
            "kind": "note",
            "what": "request",
            "value": {**note, "interface": "desk", "peer": "desk"},
        },
        {"tick": 10, "kind": "note", "what": "request", "value": note},
        {"tick": 10, "kind": "note", "what": "request", "value": "not a note"},
        {"tick": 12, "kind": "note", "what": "request", "value": {**note, "peer": "later"}},
    ]
    msgs = [
        (cmd("EStop", text='<Command Name="EStop" Why="old"/>'), "in", "operator", 9),
        (cmd("EStop", text='<Command Name="EStop" Why="out"/>'), "out", "operator", 10),
        (
            igtl.QueryMessage(type_name="GET_STATUS", device_name="x", header_version=2),
            "in",
            "operator",
            10,
        ),
        (cmd("Stop"), "in", "operator", 10),
        (cmd("EStop", text='<Command Name="EStop" Why="now"/>'), "in", "operator", 10),
        (reply("EStop", "WRONG-IF"), "out", "desk", 10),
        (reply("EStop", "OLD"), "out", "operator", 9),
        (reply("Stop", "OTHER"), "out", "operator", 10),
        (
            igtl.StringMessage(string="x", device_name="NOTACK", header_version=2),
            "out",
            "operator",
            10,
        ),
        (reply("EStop", "SUCCESS"), "out", "operator", 10),
    ]
    d = _made(tmp_path, "operator EStop", cause="estop", events=events, messages=msgs)
    x, text = _told(capsys, d)
    chain = x["chains"][0]
    assert (chain["tick"], chain["interface"], chain["args"]) == (10, "operator", {"Why": "now"})
    assert chain["message"] == "COMMAND 'command'" and chain["t"] == 0.01
    assert chain["sender"] == note and chain["lacks"] == []
    assert chain["reply"] == {
        "status": "SUCCESS",
        "message": '<CommandReply Name="EStop" Status="SUCCESS"/>',
    }
    assert text[4:7] == [
        "  EStop asked on the interface 'operator' by 10.0.0.9:1 (role operator, signed yes)",
        "  request    COMMAND 'command' Why=\"now\", taken at t=0.010000 s (tick 10, at the "
        "trigger)",
        '  reply      SUCCESS: <CommandReply Name="EStop" Status="SUCCESS"/>',
    ]
    # a STRING ACK_ reply, the only one of the tick: taken though it names none; no note
    (tmp_path / "b").mkdir()
    msgs = [
        (
            igtl.StringMessage(
                string='<Command Name="EStop"/>', device_name="CMD_1", header_version=2
            ),
            "in",
            "operator",
            10,
        ),
        (reply("Other", "FINE", rts=False), "out", "operator", 10),
    ]
    d = _made(tmp_path / "b", "operator EStop", cause="estop", messages=msgs)
    x, text = _told(capsys, d)
    chain = x["chains"][0]
    assert chain["message"] == "STRING 'CMD_1'" and chain["sender"] is None
    assert chain["lacks"] == ["the sender's address (no request note in this dump)"]
    assert chain["reply"]["status"] == "FINE"
    assert text[4] == "  EStop asked on the interface 'operator'"
    # two STRING replies: the one naming the request, though not the first
    (tmp_path / "c").mkdir()
    msgs = [
        (
            igtl.StringMessage(string="EStop", device_name="CMD_1", header_version=2),
            "in",
            "operator",
            10,
        ),
        (reply("Other", "FIRST", rts=False), "out", "operator", 10),
        (reply("estop", "NAMED", rts=False, device="ACK_2"), "out", "operator", 10),
        (reply("Other", "RTS", rts=True), "out", "operator", 10),
    ]
    d = _made(tmp_path / "c", "operator EStop", cause="estop", messages=msgs)
    x, _ = _told(capsys, d)
    assert x["chains"][0]["reply"]["status"] == "NAMED"
    assert x["chains"][0]["args"] == {}


def test_a_drive_failure_note_of_another_tick_is_not_the_triggers(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    note = {"failures": [{"driver": "old", "action": "write", "cause": "earlier"}]}
    events = [{"tick": 9, "kind": "note", "what": "drive failure", "value": note}]
    d = _made(tmp_path, "driver arm: read failed: now", cause="fault", events=events)
    x, _ = _told(capsys, d)
    (f,) = x["chains"][0]["failures"]
    assert (f["driver"], f["cause"]) == ("arm", "now")


def test_a_reading_is_written_with_nine_significant_digits(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import numpy as np

    cols = ["t", "state", "pos.j", "vel.j", "sp.j"]
    rows = np.array([[0.009, 3, 1.5e-8, 0.123456789012, 2.5e-10], [0.01, 5, 1.5e-8, 0.0, 1e20]])
    d = _made(
        tmp_path,
        "driver a: read failed: joint j: x",
        cause="fault",
        columns=cols,
        rows=rows,
        window={"first_tick": 9},
    )
    _, text = _told(capsys, d)
    assert text[7] == (
        "    at t=0.009000 s (tick 9, -1.000 ms): kept pos 1.5e-08 vel 0.123456789 eff None "
        "stamp None; setpoint 2.5e-10"
    )
    assert text[8].endswith("setpoint 1e+20")


def test_a_loss_notes_numbers_are_taken_over_the_reasons_and_only_its_streams_latch(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The latch of the stream named (not another stream's, not a hold), its ``lost`` pair
    over the reason's words; a note's ``lost`` that is no pair: the reason's."""

    def note(k: int, stream: str, kind: str, **ev: Any) -> dict[str, Any]:
        event = {"kind": kind, "time": k / 1000.0, "since_last_good_s": 0.002, "cause": "c", **ev}
        return {
            "tick": k,
            "kind": "note",
            "what": "loss",
            "value": {"stream": stream, "event": event},
        }

    events = [
        note(8, "master", "latch", source="sequence", lost=[7, 9]),
        note(9, "other", "latch", source="sequence", lost=[100, 101]),
        note(9, "master", "hold"),
        {"tick": 9, "kind": "note", "what": "loss", "value": "not a note"},
    ]
    msgs = [
        (_position(6), "in", "master", 4),
        (_position(6), "out", "master", 5),  # sent, not taken: no sample
        (_position(10), "in", "master", 8),
    ]
    reason = "packet loss on master: 3 consecutive packets lost"
    d = _made(tmp_path, reason, events=events, messages=msgs)
    x, _ = _told(capsys, d)
    chain = x["chains"][0]
    assert chain["kind"] == "loss" and chain["judged"]["tick"] == 8
    assert chain["lost"] == [7, 8, 9] and chain["last_good"]["tick"] == 4
    assert chain["proved_by"]["tick"] == 8
    (tmp_path / "b").mkdir()
    events = [note(8, "master", "latch", source="sequence", lost=[1, 2, 3])]
    d = _made(tmp_path / "b", reason + " (seq 61-63 missing)", events=events)
    x, _ = _told(capsys, d)
    assert x["chains"][0]["lost"] == [61, 62, 63]


def test_a_loss_reason_that_names_no_stream_and_a_stamp_under_a_second(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A sender's clock that counts from its start: a stamp of 0.5 s is a stamp."""
    import igtl

    msgs = [
        (_position(3, stamp=0.5), "in", "", 9),
        (igtl.CommandMessage(command_name="Stop", device_name="c", header_version=2), "in", "", 9),
    ]
    d = _made(
        tmp_path,
        "packet loss on master",
        messages=msgs,
        trigger={"tick": 10, "t": 0.01, "wall": 100.01},
    )
    x, _ = _told(capsys, d)
    chain = x["chains"][0]
    assert (chain["stream"], chain["kind"], chain["latched"]["cause"]) == (
        "",
        "late",
        "packet loss on master",
    )
    assert chain["lacks"][-1] == "when the last sample was accepted"
    (tmp_path / "b").mkdir()
    early = [(m, way, itf, 7) for m, way, itf, _ in msgs]
    d = _made(
        tmp_path / "b",
        "packet loss on : no packet for 2.00 ms",
        messages=early,
        trigger={"tick": 10, "t": 0.01, "wall": 100.01},
    )
    x, _ = _told(capsys, d)
    good = x["chains"][0]["last_good"]
    assert good["seq"] == 3 and good["stamp"] == 0.5  # the request on the same interface: no sample
    assert good["age_ms"] == pytest.approx((0.007 + 100.0 - 0.5) * 1e3)


def test_a_verdict_exactly_at_its_margin_is_not_inside_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    events = [_verdict(5, "a", 0.009, -0.001), _verdict(8, "b", 0.01, 0.0)]
    d = _made(tmp_path, "collision: x", events=events)
    x, _ = _told(capsys, d)
    assert x["chains"][0]["verdict"]["tick"] == 5


def test_a_transition_without_its_time_takes_its_rows_even_at_zero(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An event written without ``t``: its tick's row's time; a tick with no row is not in
    the last seconds. The row of tick 0 has t=0.0: before 2026-11-29 ``0.0 or -inf`` left that
    transition out."""
    events = [
        {
            "tick": 0,
            "kind": "transition",
            "from": "INIT",
            "to": "READY",
            "event": "configure",
            "reason": "configured",
        },
        {"tick": 99, "kind": "transition", "from": "A", "to": "B", "event": "e", "reason": "r"},
        {
            "tick": 10,
            "kind": "transition",
            "from": "RUNNING",
            "to": "STOPPED",
            "event": "stop",
            "reason": "the watchdog bit",
        },
    ]
    d = _made(tmp_path, "the watchdog bit", events=events, window={"first_tick": 0})
    x, text = _told(capsys, d)
    assert [e["tick"] for e in x["transitions"]] == [0, 10]
    assert [e["t"] for e in x["transitions"]] == [None, None]
    assert "  in tick 0  INIT -> READY (configure): configured" in text
    # no rows: no time, none in the last seconds
    (tmp_path / "b").mkdir()
    d = _made(tmp_path / "b", "x", events=events[:1], columns=["t", "state"], rows=None)
    x, _ = _told(capsys, d)
    assert x["transitions"] == []


def test_what_a_dump_may_lack_in_its_manifest_and_files(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """No window (its first tick 0), no software, causes without their words, a state code
    no name has, a rows file one tick short, a config whose safety is no mapping, a message
    without its tick (passed over, not the end), a recording that fails half way."""
    import numpy as np

    from occ.recording import why
    from occ.recording.record import pack_message_record

    rows = np.array([[k / 1000.0, 42.0] for k in range(10)])  # no row of the trigger's tick
    d = _made(tmp_path, "x", rows=rows, columns=["t", "state"], config={"safety": [1]})
    manifest = json.loads((d / "manifest.json").read_text())
    del manifest["window"], manifest["software"]
    manifest["causes"] = [{"reason": "no word"}, {"cause": "stopped"}, "not a cause"]
    (d / "manifest.json").write_text(json.dumps(manifest))
    good = pack_message_record(_position(1), "in", "master", 0.001, {"rec.tick": "1"})
    (d / "recording.igtl").write_bytes(
        pack_message_record(_position(0), "in", "master", 0.0) + good
    )
    x, text = _told(capsys, d)
    assert [(c["cause"], c["reason"]) for c in x["chains"]] == [("", "no word"), ("stopped", "")]
    assert x["trigger"]["state"] is None  # tick 10 has no row
    assert x["window"] == dict.fromkeys(
        ("first_tick", "ticks", "seconds", "events_whole_from_tick", "rows_lost")
    )
    assert text[-1] == (
        "window: None ticks (None s) from tick None; events whole from tick None; rows lost "
        "None; occ ? (?)"
    )
    loaded = why.load_dump(d)
    assert [m.seq for m in loaded.messages] == [1] and loaded.loss_config() == {}
    assert loaded.value("state", 9) == 42.0 and loaded.value("state", 10) is None
    assert why._state_name(loaded.value("state", 9)) == "code 42"
    assert why.explain(loaded)["last_s"] == 5.0
    out = why.to_json(why.explain(loaded))
    assert out.startswith('{\n "dump": ') and json.loads(out)["robot"] == "arm"

    whole = why.iter_recording

    def cut(path: Any, report: Any) -> Any:
        yield from whole(path, report)
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(why, "iter_recording", cut)
    lacks = why.load_dump(d).lacks
    assert (
        lacks[-1] == "recording.igtl could not be read after 1 messages ([Errno 5] "
        "Input/output error)"
    )


def test_ticks_holding_pickled_objects_are_not_loaded(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """ticks.npy is read without pickles: an object array (a pickle inside) is refused."""
    import numpy as np

    d = _made(tmp_path, "x")
    np.save(d / "ticks.npy", np.array([[object()]] * 11, dtype=object), allow_pickle=True)
    x, _ = _told(capsys, d)
    assert x["lacks"][0].startswith("ticks.npy could not be read (Object arrays cannot be loaded")


def test_holds_of_the_last_seconds_from_exactly_their_start_and_past_the_stops_own(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    events = [
        _loss_note(250, "a", "hold", 0.25, 0.004),  # exactly 0.25 s before: in
        _loss_note(260, "a", "latch", 0.26, 0.014),  # the stop's own: not an earlier hold
        _loss_note(270, "b", "hold", 0.27, 0.004),  # after it, another stream: still listed
        {
            "tick": 280,
            "kind": "note",
            "what": "old",
            "value": {
                "stream": "b",
                "event": {
                    "kind": "latch",
                    "time": 0.28,
                    "since_last_good_s": 0.0,
                    "cause": "not a loss",
                },
            },
        },
    ]
    d = _made(tmp_path, "the watchdog bit", tick=500, events=events)
    code, out, _ = _why(capsys, str(d), "--json", "--last", "0.25")
    assert code == 0
    x = json.loads(out)
    assert [(h["stream"], h["held"]["tick"]) for h in x["holds"]] == [("b", 270)]
    assert [e["tick"] for e in x["stream_events"]] == [250, 260, 270]
    (tmp_path / "b").mkdir()
    events = [_loss_note(250, "a", "hold", 0.25, 0.004)]
    d = _made(tmp_path / "b", "the watchdog bit", tick=500, events=events)
    code, out, _ = _why(capsys, str(d), "--json", "--last", "0.25")
    assert [h["held"]["tick"] for h in json.loads(out)["holds"]] == [250]


def test_a_stream_is_the_samples_taken_on_its_interface(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    msgs = [
        (_position(1), "in", "master", 1),
        (_position(50), "in", "aux", 2),  # another interface's
        (_position(51), "out", "master", 3),  # sent
    ]
    d = _made(
        tmp_path, "packet loss on master: no packet for 8.00 ms (limit 6.0 ms)", messages=msgs
    )
    x, _ = _told(capsys, d)
    assert x["chains"][0]["last_good"]["seq"] == 1 and x["chains"][0]["samples"] == []


def test_edges_of_a_manifest_a_reason_and_a_reply(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A window without its first tick (0), no causes at all, an EStop whose reason names
    no one after ``operator ``, a late stream told from the reason in a dump without rows (the
    trigger's time) and with rows whose time is not the manifest's (the row's), a request with
    two arguments, a later command of the tick that is not it, and replies without words."""
    import numpy as np

    import igtl
    from occ.recording import why

    d = _made(tmp_path, "x", window={})
    manifest = json.loads((d / "manifest.json").read_text())
    del manifest["causes"]
    (d / "manifest.json").write_text(json.dumps(manifest))
    loaded = why.load_dump(d)
    assert loaded.value("t", 3) == 0.003 and why.explain(loaded)["chains"] == []
    (tmp_path / "b").mkdir()
    x, _ = _told(capsys, _made(tmp_path / "b", "operator ", cause="estop"))
    assert x["chains"][0]["kind"] == "other"
    late = "packet loss on m: no packet for 4.00 ms (limit 3.0 ms)"
    (tmp_path / "c").mkdir()
    x, _ = _told(capsys, _made(tmp_path / "c", late, columns=["t", "state"], rows=None))
    assert x["chains"][0]["latched"]["t"] == 0.01
    (tmp_path / "h").mkdir()
    x, _ = _told(capsys, _made(tmp_path / "h", late, config=[1, 2]))  # type: ignore[arg-type]
    assert x["chains"][0]["policy"] is None and x["chains"][0]["grace_ms"] is None
    (tmp_path / "e").mkdir()
    rows = np.array([[k / 1000.0 + 0.0005, 3.0] for k in range(11)])
    x, _ = _told(capsys, _made(tmp_path / "e", late, columns=["t", "state"], rows=rows))
    assert x["chains"][0]["latched"]["t"] == 0.0105
    # the request
    cmd = igtl.CommandMessage(
        command_name="EStop",
        command='<Command Name="EStop" Why="now" Who="me"/>',
        device_name="command",
        header_version=2,
    )
    later = igtl.CommandMessage(command_name="Stop", device_name="command", header_version=2)
    empty = igtl.RTSCommandMessage(command_name="", device_name="command", header_version=2)
    msgs = [
        (cmd, "in", "operator", 10),
        (later, "in", "operator", 10),
        (empty, "out", "operator", 10),
    ]
    (tmp_path / "f").mkdir()
    x, text = _told(capsys, _made(tmp_path / "f", "operator EStop", cause="estop", messages=msgs))
    chain = x["chains"][0]
    assert chain["args"] == {"Why": "now", "Who": "me"}
    assert chain["reply"] == {"status": None, "message": ""}
    assert '  request    COMMAND \'command\' Why="now" Who="me", taken' in "\n".join(text)
    ack = igtl.StringMessage(string="done", device_name="ACK_1", header_version=2)
    msgs = [(cmd, "in", "operator", 10), (ack, "out", "operator", 10)]
    (tmp_path / "g").mkdir()
    x, _ = _told(capsys, _made(tmp_path / "g", "operator EStop", cause="estop", messages=msgs))
    assert x["chains"][0]["reply"] == {"status": None, "message": "done"}


def test_an_events_own_time_decides_and_a_transition_exactly_at_the_start_is_in(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A transition's own time, not its row's (tick 100's row is at 0.1 s, outside the last
    0.25 s; its own 0.3 s inside); one exactly 0.25 s before the trigger is in; a request
    with no reply has none."""
    import igtl

    events = [
        {
            "tick": 100,
            "t": 0.3,
            "kind": "transition",
            "from": "A",
            "to": "B",
            "event": "e",
            "reason": "own time",
        },
        {
            "tick": 250,
            "t": 0.25,
            "kind": "transition",
            "from": "B",
            "to": "C",
            "event": "e",
            "reason": "at the start",
        },
        {
            "tick": 300,
            "t": 0.1,
            "kind": "transition",
            "from": "C",
            "to": "D",
            "event": "e",
            "reason": "too old",
        },
    ]
    cmd = igtl.CommandMessage(command_name="EStop", device_name="command", header_version=2)
    d = _made(
        tmp_path,
        "operator EStop",
        cause="estop",
        tick=500,
        events=events,
        messages=[(cmd, "in", "operator", 500)],
    )
    code, out, _ = _why(capsys, str(d), "--json", "--last", "0.25")
    x = json.loads(out)
    assert [e["reason"] for e in x["transitions"]] == ["own time", "at the start"]
    assert x["chains"][0]["reply"] is None
    code, text, _ = _why(capsys, str(d), "--last", "0.25")
    assert "  reply " not in text
