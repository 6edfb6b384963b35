"""CI version of the "late is not lost, on a busy machine too" benchmark (issue 26, item 2):
``tools/soak.py real --drop-cycle 2,2,3 --hogs 2 --runs 1`` for 8 s, the shipped pair through
the loss relay of the OCC test (drops of 2, 2, then 3 packets, repeating) beside two CPU hogs.

The full measurement (20 runs of 30 s, its bar: no false latched stop, every triple loss
stopped within 20 ms) is in docs/BENCHMARKS.md; no wall-clock number is asserted here. What
must hold exactly: the relay dropped runs in the cycle's order; the hogs ran beside the soak
and are gone after it; every run of 3 that starts while the slave is RUNNING stops it once,
with an alert; no stop contradicts the loss rule (a sequence stop the relay's drops do not
explain, a silence shorter than the grace, or samples refused for their timestamp taken for
lost: the old rule). A latch past the 100 ms grace (no acceptable sample for that long: the
machine did not run the master, or the soak's own relay, for that long) is load, not the rule:
it is reported with who was late, and allowed.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from .tooling import load_tool

ROOT = Path(__file__).resolve().parents[2]
TOOLS = ROOT / "tools"

loss_proxy = load_tool("loss_proxy")


def test_the_drop_cycle_is_in_order_and_min_gap_apart() -> None:
    pattern = loss_proxy.LossPattern(
        drop_cycle=loss_proxy.parse_drop_cycle("2,2,3"), expected=2000, warmup=100, tail=100,
        min_gap=300,
    )
    # 100..1900: starts 100, 402, 704 (3), 1007, 1309, 1611 (3); the next would end past 1900
    assert pattern.schedule == [(100, 2), (402, 2), (704, 3), (1007, 2), (1309, 2), (1611, 3)]
    dropped = [i for i in range(2000) if pattern.decide() is not None]
    assert dropped == [i for start, n in pattern.schedule for i in range(start, start + n)]
    assert pattern.describe()["drop_cycle"] == "2,2,3"


def test_a_bad_drop_cycle_is_refused_with_its_text() -> None:
    for spec in ("2,x,3", "2,0"):
        with pytest.raises(ValueError, match="--drop-cycle"):
            loss_proxy.parse_drop_cycle(spec)
    with pytest.raises(ValueError, match="cannot be combined"):
        loss_proxy.LossPattern(drop_cycle=[2], drop_runs=[(1, 1)], expected=1000, min_gap=10)
    with pytest.raises(ValueError, match="no run fits"):
        loss_proxy.LossPattern(drop_cycle=[5], expected=10, warmup=8)


@pytest.mark.slow
@pytest.mark.realtime
def test_real_soak_beside_two_hogs_stops_only_on_triple_losses(tmp_path: Path) -> None:
    out = tmp_path / "hogs"
    cmd = [sys.executable, str(TOOLS / "soak.py"), "real", "--drop-cycle", "2,2,3",
           "--hogs", "2", "--runs", "1", "--duration", "8", "--min-gap", "150",
           "--out", str(out)]
    env = {**os.environ, "MPLBACKEND": "Agg"}
    # the soak bounds its daemons and its hogs; this timeout bounds the soak
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert (out / "report.json").exists(), proc.stdout + proc.stderr
    rep = json.loads((out / "report.json").read_text())
    n = rep["numbers"]
    assert rep["mode"] == "real-series" and n["runs"] == 1 and n["hogs"] == 2
    (row,) = n["per_run"]
    # the hogs ran beside the soak (each used CPU) and none outlived it
    assert len(row["hog_cpu_percent"]) == 2 and all(v and v > 0 for v in row["hog_cpu_percent"])
    for pid in row["hog_pids"]:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
    # the relay dropped 2, 2, 3, 2, 2, 3, ... in this order
    lengths = [int(r["length"]) for r in csv.DictReader((out / "run-01" / "proxy_runs.csv").open())]
    assert len(lengths) >= 6 and lengths == [(2, 2, 3)[i % 3] for i in range(len(lengths))]
    # every judged triple stopped the slave once, with an alert; at least one judged
    assert n["runs_ge3_missed"] == 0 and n["runs_ge3_stopped"] >= 1
    assert n["runs_ge3_stopped"] + n["runs_ge3_masked"] == n["runs_ge3"] == lengths.count(3)
    assert len(row["stop_latency_ms"]) == n["runs_ge3_stopped"]
    # no stop contradicts the rule; a false stop (if any) is a latch past the grace without a
    # drop (load), named in the slave's words
    one = json.loads((out / "run-01" / "report.json").read_text())
    checks = {c["name"]: c for c in one["checks"]}
    for name in ("every loss stop follows a run >= 3 (or a deadline)",
                 "runs of 1-2 drops caused no stop by themselves",
                 "every run >= 3 (slave RUNNING) stopped the robot exactly once",
                 "operator Run resumed after every stop", "daemons ran and wrote statistics"):
        assert checks[name]["passed"], checks[name]
    for stop in row["false_stops"]:
        assert "refused for their timestamp" not in stop["reason"], stop
        if "packet loss" in stop["reason"]:  # only a silence past the grace latches
            assert stop["kind"] in ("deadline (no drop)", "run<=2 + late delivery"), stop
            assert float(stop["reason"].split("no packet for ")[1].split(" ms")[0]) >= 100.0
    assert (out / "report.md").exists() and (out / "run-01" / "report.md").exists()
