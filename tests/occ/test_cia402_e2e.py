"""``occd configs/slave-cia402.yaml`` against the CiA 402 drive emulator in another process, on
python-can's ``udp_multicast`` bus, in a network namespace of its own (multicast routed to
its loopback, nothing leaves the host): tools/cia402_e2e.py does the run and reports; the
checks are here. The master daemon's simulated hand moves the slave; an EMCY typed on the
emulator's standard input faults it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from occ_testkit.netns import available

ROOT = Path(__file__).resolve().parents[2]
TOOL = ROOT / "tools" / "cia402_e2e.py"

pytestmark = pytest.mark.realtime


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    why = available()
    if why is not None:
        if os.environ.get("CI"):
            pytest.fail(f"no network namespace in CI: {why}")
        pytest.skip(why)
    tmp = tmp_path_factory.mktemp("cia402-e2e")
    out = tmp / "report.json"
    cmd = ["unshare", "-n", sys.executable, str(TOOL), "--lo-up", "--seconds", "4",
           "--fault", "emcy 2 0x2310", "--out-dir", str(tmp), "--json", str(out)]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=180, env=env)
    logs = "\n".join(f"--- {p.name}\n{p.read_text()[-3000:]}" for p in tmp.glob("*.log"))
    assert res.returncode == 0, f"{res.stdout[-3000:]}\n{res.stderr[-5000:]}\n{logs}"
    data: dict[str, Any] = json.loads(out.read_text())
    return data


def test_the_slave_runs_on_three_emulated_cia402_nodes_and_moves(report: dict[str, Any]) -> None:
    before = report["before"]["drivers"]["arm"]
    assert before["bus_load"] == pytest.approx(0.57, abs=0.01)
    assert {n["nmt"] for n in before["nodes"].values()} == {"OPERATIONAL"}
    assert report["enable"]["Status"] == "SUCCESS", report["enable"]
    assert report["run"]["Status"] == "SUCCESS", report["run"]
    samples = report["samples"]
    assert samples and all(s["state"] in ("RUNNING", "STOPPED") for s in samples), samples
    assert samples[-1]["state"] == "RUNNING", samples
    for s in samples:
        assert set(s["nodes"].values()) == {"OPERATION ENABLED"}, s
    tips = [s["tip_mm"] for s in samples if s["tip_mm"] is not None]
    moved = max(max(abs(a - b) for a, b in zip(t, tips[0], strict=True)) for t in tips)
    assert moved > 1.0, tips  # mm: the master's hand, scaled 10:1, through the CiA 402 drives
    # the loop sends a SYNC every 2 ticks and gets two TPDOs per node back for each
    first, last = samples[0], samples[-1]
    syncs = last["sync_frames"] - first["sync_frames"]
    assert syncs > 0 and last["tpdo_frames"] - first["tpdo_frames"] >= 5 * syncs
    assert report["arm"]["echoes"] > 0  # udp_multicast handed the slave its own frames


def test_the_emulator_times_the_slaves_cycle(report: dict[str, Any]) -> None:
    """The cycle as the drives received it while the slave followed (the emulator's ``timing``):
    a SYNC every 2 ms with three RPDOs before it, each answered by TPDOs."""
    cycle = report["cycle"]
    syncs = cycle["syncs"]
    assert syncs > 0 and cycle["syncs_without_rpdo"] <= syncs // 100, cycle
    for key in ("rpdo_to_sync_us", "setpoints_ready_us", "sync_to_tpdo_us"):
        figures = cycle[key]
        assert figures["n"] >= syncs - cycle["syncs_without_rpdo"] - 1, (key, cycle)
        assert 0.0 <= figures["min"] <= figures["p50"] <= figures["p99"] <= figures["max"]
    # the first RPDO of a cycle comes no later than its last
    assert cycle["rpdo_to_sync_us"]["p50"] >= cycle["setpoints_ready_us"]["p50"]


@pytest.mark.req("SR-HW-33")
def test_an_emcy_from_the_emulator_process_faults_the_slave_naming_the_node(
    report: dict[str, Any],
) -> None:
    fault = report["fault"]
    assert fault["state"] == "FAULT", fault
    alert = fault["last_alert"]
    assert "node 2 (joint pitch): EMCY 0x2310 (continuous overcurrent" in alert, alert
    nodes = fault["arm"]["nodes"]
    assert nodes["pitch"]["last_emcy"]["code"] == "0x2310"
    assert nodes["yaw"]["cia402"] != "OPERATION ENABLED"
    assert nodes["insertion"]["cia402"] != "OPERATION ENABLED"
