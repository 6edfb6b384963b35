"""``occ-record plot``: the numbers behind the figure (tracking error, states with causes, timing)
from recordings made in simulated time, the PNG itself, and the clear errors."""

from __future__ import annotations

import builtins
import math
from pathlib import Path

import pytest

from occ.recording.record import Recorder
from occ.recording.cli import main as record_main
from occ.recording.plot import PlotError, plot_recording, summarize_recording
from occ_testkit.testing import SimRobot

ROOT = Path(__file__).resolve().parents[2]


def record_slave(path: Path, seconds: float = 3.0, stop_at: float | None = 1.5) -> None:
    """The shipped slave following the paper's master motion (500 Hz POSITION), recorded at
    1 kHz; an operator's Stop at ``stop_at`` and Run 0.2 s later (a second re-index)."""
    rec = Recorder(path, rate_hz=1000).start()
    sim = SimRobot(ROOT / "configs" / "slave.yaml", recorder=rec)
    master = sim.peer("master", address=("127.0.0.1", 5000))
    op = sim.peer("operator", address=("127.0.0.1", 5001))
    for name in ("Enable", "Run"):
        op.send_command(name)
        sim.tick()
    seq = 0
    ticks = int(seconds * 1000)
    for k in range(ticks):
        t = k / 1000.0
        if stop_at is not None and k == int(stop_at * 1000):
            op.send_command("Stop")
        if stop_at is not None and k == int((stop_at + 0.2) * 1000):
            op.send_command("Run")
        if k % 2 == 0:
            seq += 1
            w = 2 * math.pi * 0.1 * t
            master.send_position((50 * math.sin(w), 50 * math.cos(w), 270.0), seq=seq)
        sim.tick()
    sim.close()
    rec.close()


@pytest.fixture(scope="module")
def slave_rec(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "slave.rec"
    record_slave(path)
    return path


def test_master_vs_slave_tracking_error(slave_rec: Path) -> None:
    s = summarize_recording(slave_rec, scale=0.1)
    assert s.error_labels == ["X", "Y", "Z"] and s.error_kind.startswith("master vs slave")
    # two re-indexes: at the first Run and after the operator's Stop + Run
    assert s.reindexes == 2
    st = s.error_stats()
    # the simulated drives follow within a few hundredths of a mm (tools/stability.py: ~0.023)
    for axis in ("X", "Y"):
        assert 0.0 < st[axis]["mean"] < 0.1 and st[axis]["max"] < 0.5
    # the error is measured only while RUNNING (not during the 0.2 s stop)
    assert len(s.error_t) < len(s.t) - 150
    # a wrong scale gives a visibly wrong error: the measure is against the real references
    wrong = summarize_recording(slave_rec, scale=0.2).error_stats()
    assert wrong["X"]["mean"] > 10 * st["X"]["mean"]


def test_states_by_name_with_causes(slave_rec: Path) -> None:
    s = summarize_recording(slave_rec)
    assert {"ENABLED", "RUNNING", "STOPPED"} <= set(s.state_names)
    names = [name for _, name, _ in s.statuses]
    assert names[:3] == ["READY", "ENABLED", "RUNNING"] and "STOPPED" in names
    stop_cause = next(cause for _, name, cause in s.statuses if name == "STOPPED")
    assert "RUNNING -> STOPPED" in stop_cause
    # the input stream at the loop: one packet every 2 ms in simulated time
    gaps = {round(g * 1000) for g in (s.in_t[1:] - s.in_t[:-1]).tolist()}
    assert gaps == {2}


def test_setpoint_vs_measured_without_an_input_stream(tmp_path: Path) -> None:
    path = tmp_path / "master.rec"
    rec = Recorder(path, rate_hz=500).start()
    sim = SimRobot(ROOT / "configs" / "master.yaml", recorder=rec)
    sim.robot.state_machine.request("enable")
    sim.robot.state_machine.request("run")
    sim.step(1000)
    sim.close()
    rec.close()
    s = summarize_recording(path)
    assert s.error_kind.startswith("setpoint - measured")
    assert s.error_labels == ["x", "y", "z"]
    st = s.error_stats()
    assert st["x"]["max"] > 0.0 and st["z"]["max"] < 1e-3  # x moves (sine), z holds still


def test_plot_writes_a_png(slave_rec: Path, tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    out = tmp_path / "r.png"
    assert record_main(["plot", str(slave_rec), "-o", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 20_000
    # default path: beside the recording
    assert plot_recording(slave_rec) == Path(str(slave_rec) + ".png")


def test_plot_errors_are_clear(slave_rec: Path, tmp_path: Path, monkeypatch, capsys) -> None:  # type: ignore[no-untyped-def]
    # not a recording of a robot: no state rows
    bad = tmp_path / "empty.rec"
    bad.write_bytes(b"")
    assert record_main(["plot", str(bad)]) == 1
    assert "no state rows" in capsys.readouterr().err
    # a damaged file: a decode error, not a traceback
    junk = tmp_path / "junk.rec"
    junk.write_bytes(slave_rec.read_bytes()[:100] + b"\xff" * 200)
    assert record_main(["plot", str(junk)]) == 1
    assert "occ-record:" in capsys.readouterr().err
    # matplotlib missing: exit 2 and how to install it
    real_import = builtins.__import__

    def no_mpl(name: str, *args, **kw):  # type: ignore[no-untyped-def]
        if name == "matplotlib" or name.startswith("matplotlib."):
            raise ImportError(name)
        return real_import(name, *args, **kw)

    monkeypatch.setattr(builtins, "__import__", no_mpl)
    assert record_main(["plot", str(slave_rec), "-o", str(tmp_path / "x.png")]) == 2
    assert "pip install 'occ-igtl[plot]'" in capsys.readouterr().err
    with pytest.raises(PlotError):
        plot_recording(slave_rec, tmp_path / "y.png")
