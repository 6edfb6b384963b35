"""CI version of the OCC paper's stability test (tools/stability.py): one simulated minute.

The master and slave robots run in simulated time (two SimRobots on one SimClock, no sockets,
no threads) and the loss pattern is seeded, so every number below is the same on every run and
every machine: nothing here depends on the wall clock or the machine's load. The tracking error
bounds are therefore not timing tolerances: the run gives mean |e| ~0.023 mm and max ~0.041 mm
(X and Y) with seed 7; the asserted 0.05 mm (mean) and 0.1 mm (max) leave room only for
floating-point differences between numpy builds, and the mean bound is half the paper's result
(0.094 / 0.097 mm), so a regression in the slave's following (a later re-index, a lost sample
used late, a slower drive) shows up here.
"""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import pytest

from .tooling import load_tool

stability = load_tool("stability")


@pytest.mark.slow  # ~6 s: two robots ticked 60 000 times each
def test_one_simulated_minute_is_stable(tmp_path: Path) -> None:
    out = tmp_path / "stab"
    code = stability.main(["--minutes", "1", "--seed", "7", "--window", "10", "--out", str(out)])
    report = json.loads((out / "report.json").read_text())
    assert code == 0, [c for c in report["checks"] if not c["passed"]]
    assert report["passed"] and all(c["passed"] for c in report["checks"])
    n = report["numbers"]
    assert n["simulated_seconds"] == 60.0
    # the double losses happened: 2 % of the packets lost, all in runs of exactly two
    assert n["packets_sent"] >= 30_000
    assert n["double_losses_scheduled"] == round(0.02 * n["packets_sent"] / 2)
    assert n["packets_dropped"] == 2 * n["double_losses_scheduled"]
    assert abs(n["drop_fraction"] - 0.02) < 0.001
    # the slave saw each of them as one 6 ms gap (Fig. 11), every other packet 2 ms apart
    hist = n["interarrival_histogram_ms"]
    assert set(hist) == {"2", "6"}
    assert hist["6"] == n["double_losses_scheduled"]
    # tolerated, never latched, never held
    lm = n["loss_monitor"]
    assert lm["trips"] == 0 and lm["max_run"] == 2 and lm["holds"] == 0
    assert lm["lost_total"] == n["packets_dropped"]
    assert n["slave_controller"]["reindexes"] == 1
    # tracking error: finite and small (deterministic, see the module docstring)
    for axis in ("x", "y"):
        e = n["tracking_error_mm"][axis]
        assert e["n"] > 50_000
        assert math.isfinite(e["mean_abs_mm"]) and math.isfinite(e["max_abs_mm"])
        assert 0.0 < e["mean_abs_mm"] <= 0.05
        assert e["max_abs_mm"] <= 0.1
    for png in ("interarrival.png", "trajectories.png", "tracking_error.png"):
        if "matplotlib" in sys.modules or importlib.util.find_spec("matplotlib"):
            assert (out / png).stat().st_size > 0
    assert "Stability test" in (out / "report.md").read_text()


def _simulated_numbers(out: Path) -> dict:
    n = json.loads((out / "report.json").read_text())["numbers"]
    for k in (
        "wall_seconds",
        "cpu_seconds",
        "speed_x_realtime",
        "wall_hours_for_12h",
        "jobs",
        "cpu_seconds_slave_process",
        "cpu_seconds_master_process",
    ):
        n.pop(k)
    return n


def test_same_seed_same_numbers(tmp_path: Path) -> None:
    """Simulated time: two short runs with one seed agree on every simulated number, whether
    the master runs in this process (--jobs 1) or in a child process (--jobs 2)."""
    nums = []
    for i, jobs in enumerate(("1", "2")):
        out = tmp_path / f"r{i}"
        argv = ["--minutes", "0.1", "--seed", "3", "--jobs", jobs, "--out", str(out)]
        assert stability.main(argv) == 0
        nums.append(_simulated_numbers(out))
    assert nums[0] == nums[1]
    # and the run did something: packets crossed, double losses were seen, errors measured
    n = nums[0]
    assert n["packets_delivered"] > 2000 and n["interarrival_histogram_ms"]["6"] > 0
    e = n["tracking_error_mm"]["x"]
    assert e["n"] > 4000 and 0.0 < e["mean"] <= e["p99"] <= e["max"]


def test_tracking_error_percentile() -> None:
    """The p99 comes from 0.1 um bins: exact to a bin, never above the max."""
    ax = stability._Axis()
    values = [i * 1e-3 for i in range(1, 1001)]  # 0.001 .. 1.0 mm
    for v in values[:500]:
        ax.add(-v)
    import numpy as np

    ax.add_many(np.array(values[500:]))
    s = ax.summary()
    assert s["n"] == 1000 and s["max"] == 1.0
    assert abs(s["p99"] - 0.99) <= 1e-4
    assert abs(s["mean"] - sum(values) / 1000) < 1e-5
    assert stability._Axis().percentile(99) == 0.0
