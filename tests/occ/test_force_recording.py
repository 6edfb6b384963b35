"""Forces in recordings, their plot and their exports (issue 27, "Visible").

The wall pair (configs/master.yaml + configs/wall.yaml, :class:`occ_testkit.testing.SimPair`)
recorded on both sides for 10 s of the paper's motion pressing into the tissue: the slave's
recording holds its return channel's ``SlaveTip`` (``force_n``, 500 Hz) and its
``TipForce``/``ForceArrow`` outputs to Slicer (10 Hz); the master's holds the ``SlaveTip`` it
received and its ``Force`` output (the displayed force, 50 Hz). The expected values are read from
the recorded messages themselves; the MCAP is decoded by mcap-ros2-support, the sequence metafile by
the rules of Slicer's reader (tests/occ/test_recexport.py).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from occ.haptics.forceviz import parse_force
from occ.recording.record import Recorder, read_recording
from occ.recording.cli import main
from occ.recording.plot import plot_recording, summarize_recording
from occ_testkit.testing import CONFIGS, SimPair

from .test_recexport import decode_mcap, require, slicer_parse


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("forcerec")
    paths = {"master": d / "master.igtl", "slave": d / "slave.igtl"}
    cfg = yaml.safe_load((CONFIGS / "wall.yaml").read_text())
    with SimPair(CONFIGS / "master.yaml", cfg) as p:
        p.slave.peer("slicer")  # someone to send TipForce and ForceArrow to
        p.m_op.send_command("GetState")  # the operator interface has a client: Force goes out
        recs = {k: Recorder(v, rate_hz=100).start() for k, v in paths.items()}
        p.master.robot.set_recorder(recs["master"])
        p.slave.robot.set_recorder(recs["slave"])
        p.start()
        p.run_for(10.0)
        for r in recs.values():
            r.close()
    return paths


def forces_in(path: Path, mtype: str, device: str, direction: str) -> list[tuple[float, Any]]:
    """(rec.t, force) of every recorded message of that kind, straight from the messages."""
    out = []
    for m in read_recording(path):
        meta = m.metadata
        if m.message_type != mtype or m.device_name != device or meta["rec.dir"] != direction:
            continue
        if mtype == "SENSOR":
            f: Any = tuple(float(v) for v in m.data[:3])  # type: ignore[attr-defined]
        else:
            f = parse_force(meta["force_n"])
        out.append((float(meta["rec.t"]), f))
    return out


def test_the_recordings_hold_both_forces(recordings: dict[str, Path]) -> None:
    sent = forces_in(recordings["slave"], "POSITION", "SlaveTip", "out")
    got = forces_in(recordings["master"], "POSITION", "SlaveTip", "in")
    hand = forces_in(recordings["master"], "SENSOR", "Force", "out")
    shown = forces_in(recordings["slave"], "TRANSFORM", "TipForce", "out")
    assert len(sent) > 4900 and len(got) > 4900 and len(hand) > 490 and len(shown) > 95
    assert {f for _, f in got} <= {f for _, f in sent}  # what arrived is what was sent
    assert max(np.linalg.norm(f) for _, f in sent) > 1.0


def test_the_plot_summary_has_hand_and_instrument(recordings: dict[str, Path]) -> None:
    m = summarize_recording(recordings["master"])
    got = forces_in(recordings["master"], "POSITION", "SlaveTip", "in")
    hand = forces_in(recordings["master"], "SENSOR", "Force", "out")
    assert np.allclose(m.cf_t, [t for t, _ in got]) and np.allclose(m.cf, [f for _, f in got])
    assert np.allclose(m.hand_t, [t for t, _ in hand])
    assert np.allclose(m.hand, [f for _, f in hand])
    # the return channel is not taken for a master stream: a master's recording has none
    assert len(m.in_t) == 0 and m.error_kind.startswith("setpoint - measured")
    st = m.force_stats()
    # the hand feels the instrument: force_scale 1, the map a scale (no rotation), so the two
    # are comparable component by component; fades, clamp and passivity make them differ a little
    assert st["instrument_peak_n"] > 1.0 and st["hand_peak_n"] > 1.0
    assert st["rms_difference_n"] < 0.1 * st["instrument_peak_n"], st
    # the slave's own recording: its 500 Hz return channel (not its 10 Hz Slicer output); the
    # hand from the master's recording
    s = summarize_recording(recordings["slave"], master=recordings["master"])
    sent = forces_in(recordings["slave"], "POSITION", "SlaveTip", "out")
    assert len(s.cf_t) == len(sent) and np.allclose(s.cf, [f for _, f in sent])
    assert len(s.hand_t) == len(hand)
    assert s.force_stats()["rms_difference_n"] < 0.1 * st["instrument_peak_n"]
    assert summarize_recording(recordings["slave"]).hand_t.size == 0


def test_the_plot_gains_a_force_panel(recordings: dict[str, Path], tmp_path: Path) -> None:
    pytest.importorskip("matplotlib", reason="pip install -e .[plot]")
    import matplotlib.image as mpimg

    out = plot_recording(recordings["master"], tmp_path / "master.png", dpi=40)
    img = mpimg.imread(out)
    # 5 panels: taller than the 4-panel figure (11 x 12 in at 40 dpi: 480 px)
    assert img.shape[0] == round((12 + 2.6) * 40)


def test_mcap_has_measured_cf(recordings: dict[str, Path], tmp_path: Path) -> None:
    require("rosbags", "pip install -e .[record]")
    out = tmp_path / "slave.mcap"
    assert main(["export", str(recordings["slave"]), str(out)]) == 0
    topics = decode_mcap(out)
    sent = forces_in(recordings["slave"], "POSITION", "SlaveTip", "out")
    cf = topics["/occ/slave/measured_cf"]
    assert len(cf) == len(sent)
    for (msg, _), (_, f) in zip(cf, sent, strict=True):
        assert msg.header.frame_id == "world"
        w = msg.wrench
        assert (w.force.x, w.force.y, w.force.z) == pytest.approx(f, abs=1e-12)
        assert (w.torque.x, w.torque.y, w.torque.z) == (0.0, 0.0, 0.0)
    # the 10 Hz Slicer output is a force stream of its own, not a pose
    shown = forces_in(recordings["slave"], "TRANSFORM", "TipForce", "out")
    assert len(topics["/occ/slave/tipforce/measured_cf"]) == len(shown) > 95
    assert "/occ/slave/tipforce/measured_cp" not in topics
    # the master's: its displayed force in its base frame, the slave's as it arrived
    out = tmp_path / "master.mcap"
    assert main(["export", str(recordings["master"]), str(out)]) == 0
    topics = decode_mcap(out)
    hand = forces_in(recordings["master"], "SENSOR", "Force", "out")
    assert [m.header.frame_id for m, _ in topics["/occ/master/measured_cf"]] == (
        ["master_base"] * len(hand)
    )
    got = topics["/occ/master/slavetip/measured_cf"]
    assert {m.header.frame_id for m, _ in got} == {"slavetip_reference"}
    assert len(got) == len(forces_in(recordings["master"], "POSITION", "SlaveTip", "in"))


def test_seq_plays_the_force_transform_back(recordings: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "slave.seq.mha"
    assert main(["export", str(recordings["slave"]), str(out), "--device", "TipForce"]) == 0
    _, sequences, _ = slicer_parse(out)
    assert set(sequences) == {"TipForceToWorld"}
    seq = sequences["TipForceToWorld"]
    recorded = [
        m.matrix  # type: ignore[attr-defined]
        for m in read_recording(recordings["slave"])
        if m.device_name == "TipForce" and m.metadata["rec.dir"] == "out"
    ]
    assert len(seq) == len(recorded)
    for got, want in zip((seq[k] for k in sorted(seq, key=float)), recorded, strict=True):
        assert np.abs(got - want).max() < 1e-4
