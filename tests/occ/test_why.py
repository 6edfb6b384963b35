"""``occ-record why DIR`` (occ/recording/why.py, whytext.py): the chain that led to a black box
dump, told from the dump alone. Each case stops a simulated robot the way it stops in the
field, then reads only the dump directory: exact runs, simulated time."""

from __future__ import annotations

import json
import math
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


def _explain(capsys: pytest.CaptureFixture[str], path: Path) -> tuple[dict[str, Any], str]:
    """The JSON and the text of ``why`` on ``path``, both exiting 0."""
    code, out, err = _why(capsys, str(path), "--json")
    assert code == 0, err
    x = json.loads(out)
    code, text, err = _why(capsys, str(path))
    assert code == 0, err
    return x, text


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
    x, text = _explain(capsys, path)
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
    x, text = _explain(capsys, path)
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
    x, text = _explain(capsys, path)
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
    x, text = _explain(capsys, dumped)
    (chain,) = x["chains"]
    assert chain["kind"] == "request" and chain["command"] == "DumpBlackBox"
    assert chain["interface"] == "operator" and chain["args"] == {"Reason": "the tool twitched"}
    assert chain["sender"]["peer"] == "127.0.0.1:40001" and chain["sender"]["signed"] == "no"
    assert chain["reply"]["status"] == "SUCCESS" and str(dumped) in chain["reply"]["message"]
    assert "by 127.0.0.1:40001 (role operator" in text and 'Reason="the tool twitched"' in text
    x, text = _explain(capsys, estop)
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
    x, text = _explain(capsys, path)
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
    assert code == 1 and "does not exist" in err
    (tmp_path / "manifest.json").write_text('{"format": "something else"}')
    code, out, err = _why(capsys, str(tmp_path))
    assert code == 1 and "not a black box dump (format 'something else')" in err
    for wrong in ([], [str(tmp_path), "--last", "-1"], [str(tmp_path), "--bogus"]):
        with pytest.raises(SystemExit) as exc:
            occ_record(["why", *wrong])
        assert exc.value.code == 2
