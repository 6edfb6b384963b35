"""CI versions of the packet-loss soaks (tools/soak.py) and unit tests of the loss proxy.

- ``test_sim_*`` (``slow``): the slave in simulated time with deterministic runs of 1, 2, 3 and 5 lost
  packets: exact outcomes (every run >= 3 holds the robot at exactly 7 ms and latches the stop
  at the packet that proves it, runs of 1-2 never hold nor stop).
- ``test_real_soak_*`` (``realtime``): occd slave + master on loopback through the loss proxy for
  ~8 s with runs of 3 and runs of 1.

Timing tolerance of the real test (a loaded 2-core machine): no wall-clock latency is asserted.
A stop the slave attributes to silence ("no packet for X ms", past the 100 ms grace) with no
proxy drop in its silent interval is machine load (the master was not scheduled for that
long), reported by the soak as a warning, and allowed here. What must hold exactly: every
run of 3 drops that starts while the slave is RUNNING stops it once, no stop contradicts the
requirement (a sequence stop the proxy's drops do not explain, or a silence shorter than the
grace), and runs of 1 cause no stop except through such a deadline. A run of 3 that starts
while the slave is still stopped by a load-induced deadline stop is "masked" (not judged); the
test needs at least one judged run of 3.
"""

from __future__ import annotations

import csv
import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from .tooling import load_tool

ROOT = Path(__file__).resolve().parents[2]
TOOLS = ROOT / "tools"




loss_proxy = load_tool("loss_proxy")
soak = load_tool("soak")


# ------------------------------------------------------------------------------ loss pattern


def test_drop_runs_are_exact_seeded_and_apart() -> None:
    def make(seed: int):
        return loss_proxy.LossPattern(seed=seed, drop_runs=[(3, 4), (1, 10), (5, 2)], expected=5000,
                                      warmup=500, tail=500, min_gap=100)

    a, b, c = make(7), make(7), make(8)
    assert a.schedule == b.schedule != c.schedule
    decisions = [a.decide() is not None for _ in range(5000)]
    runs, n = [], 0
    for i, d in enumerate(decisions + [False]):
        if d:
            n += 1
        elif n:
            runs.append((i - n, n))
            n = 0
    assert sorted(length for _, length in runs) == sorted([3] * 4 + [1] * 10 + [5] * 2)
    assert runs == a.schedule
    assert runs[0][0] >= 500 and runs[-1][0] + runs[-1][1] <= 4500
    assert all(s2 - (s1 + l1) >= 100 for (s1, l1), (s2, _) in zip(runs, runs[1:], strict=False))


def test_drop_runs_that_do_not_fit_are_refused() -> None:
    with pytest.raises(ValueError, match="do not fit"):
        loss_proxy.LossPattern(drop_runs=[(3, 50)], expected=1000, min_gap=100)


def test_bernoulli_and_gilbert_elliott_rates() -> None:
    p = loss_proxy.LossPattern(seed=3, loss=0.1)
    lost = sum(p.decide() is not None for _ in range(20000))
    assert 1800 < lost < 2200
    # mean burst length 1/p_bg = 4, bursts start with probability 0.01 per packet
    g = loss_proxy.LossPattern(seed=3, burst=(0.01, 0.25, 1.0))
    seq = [g.decide() is not None for _ in range(50000)]
    lengths, n = [], 0
    for d in seq + [False]:
        if d:
            n += 1
        elif n:
            lengths.append(n)
            n = 0
    assert 3.0 < sum(lengths) / len(lengths) < 5.0


def test_igtl_seq_reads_the_v2_message_id() -> None:
    import igtl

    msg = igtl.PositionMessage((1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), 24, device_name="Master",
                               header_version=2, message_id=0xDEADBEEF, metadata={"run": "1"})
    assert loss_proxy.igtl_seq(msg.pack()) == 0xDEADBEEF
    v1 = igtl.PositionMessage((1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), 24, device_name="Master")
    assert loss_proxy.igtl_seq(v1.pack()) is None
    assert loss_proxy.igtl_seq(b"\x00\x02short") is None


def test_proxy_forwards_drops_and_logs_on_loopback(tmp_path: Path) -> None:
    import igtl

    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.5)
    got: list[int] = []

    def receive() -> None:
        end = time.monotonic() + 10.0
        while time.monotonic() < end:
            try:
                got.append(igtl.unpack(rx.recv(65535)).message_id)
            except TimeoutError:
                return

    pattern = loss_proxy.LossPattern(seed=5, drop_runs=[(3, 2), (1, 4)], expected=600, warmup=50,
                                     tail=50, min_gap=40)
    proxy = loss_proxy.LossProxy(("127.0.0.1", 0), rx.getsockname(), pattern, duration=10.0)
    th = threading.Thread(target=receive, daemon=True)
    try:
        proxy.start()
        th.start()
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for i in range(1, 601):
            m = igtl.PositionMessage((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 24, device_name="Master",
                                     header_version=2, message_id=i)
            tx.sendto(m.pack(), proxy.address)
            if i % 20 == 0:
                time.sleep(0.002)  # keep the socket buffers shallow
        tx.close()
        th.join(8.0)
    finally:
        proxy.stop()
        rx.close()
    dropped = {d.seq for d in proxy.drops}
    assert len(dropped) == 10 and proxy.counters.dropped == 10
    assert sorted(got) == sorted(set(range(1, 601)) - dropped)
    assert sorted(r.length for r in proxy.runs) == [1, 1, 1, 1, 3, 3]
    log = tmp_path / "drops.csv"
    proxy.write_csv(log)
    rows = list(csv.DictReader(log.open()))
    assert {int(r["seq"]) for r in rows} == dropped


def test_proxy_refuses_non_loopback() -> None:
    with pytest.raises(ValueError, match="loopback"):
        loss_proxy.LossProxy(("0.0.0.0", 0), ("127.0.0.1", 9), None)


# ------------------------------------------------------------------------------ sim soak


@pytest.mark.slow
def test_sim_soak_exact_outcomes(tmp_path: Path) -> None:
    out = tmp_path / "sim"
    code = soak.main(["sim", "--sim-seconds", "30", "--seed", "11", "--drop-runs", "1:12",
                      "--drop-runs", "2:12", "--drop-runs", "3:6", "--drop-runs", "5:4",
                      "--pause-ms", "80", "--out", str(out)])
    rep = json.loads((out / "report.json").read_text())
    assert code == 0, rep["checks"]
    n = rep["numbers"]
    assert n["run_length_histogram_all"] == {"1": 12, "2": 12, "3": 6, "5": 4}
    assert n["runs_by_outcome"] == {"no-stop": 24, "stop": 10}
    assert n["stops"] == n["stops_expected"] == 10
    assert n["stops_unexpected"] == n["stops_missed"] == 0
    assert n["hold_latency_ms"]["max"] == n["hold_latency_ms"]["min"] == 7.0  # motion held at +7
    # latched when the next packet proves the gap: +8 ms after a run of 3, +12 after a run of 5
    assert n["stop_latency_histogram_ms"] == {"8": 6, "12": 4}
    assert n["holds_unexpected"] == 0
    assert n["status_alerts_stopped"] == 10 and n["loss_monitor"]["trips"] == 10
    assert n["operator_runs"] == 10 and n["operator_runs_failed"] == 0
    assert all(c["passed"] for c in rep["checks"])
    for f in ("report.md", "runs.csv", "drops_over_time.png", "run_lengths.png", "stop_latency.png"):
        assert (out / f).stat().st_size > 0, f


@pytest.mark.slow
def test_sim_soak_catches_a_wrong_threshold(tmp_path: Path) -> None:
    """The oracle is independent of the loss monitor: tolerate only 1 -> runs of 2 stop: FAIL."""
    cfg = tmp_path / "slave.yaml"
    cfg.write_text((ROOT / "configs" / "slave.yaml").read_text().replace("max_consecutive: 2",
                                                                         "max_consecutive: 1"))
    out = tmp_path / "sim"
    code = soak.main(["sim", "--sim-seconds", "6", "--drop-runs", "2:3", "--drop-runs", "3:2",
                      "--config", str(cfg), "--out", str(out)])
    assert code == 1
    checks = {c["name"]: c["passed"] for c in json.loads((out / "report.json").read_text())["checks"]}
    assert not checks["stop iff run >= 3"] and not checks["runs of 1-2 never stop"]


@pytest.mark.slow
def test_sim_soak_random_pattern_across_the_sequence_wrap(tmp_path: Path) -> None:
    out = tmp_path / "sim"
    code = soak.main(["sim", "--sim-seconds", "10", "--burst", "0.01,0.5,1.0", "--loss", "0.01",
                      "--first-seq", str(2**32 - 2000), "--out", str(out)])
    rep = json.loads((out / "report.json").read_text())
    assert code == 0, rep["checks"]
    assert rep["numbers"]["last_seq"] < 5000  # wrapped
    assert rep["numbers"]["stops"] > 0 and rep["numbers"]["runs_evaluated"] > 20


# ------------------------------------------------------------------------------ real soak


@pytest.mark.realtime
def test_real_soak_stops_exactly_on_runs_of_three(tmp_path: Path) -> None:
    out = tmp_path / "real"
    cmd = [sys.executable, str(TOOLS / "soak.py"), "real", "--duration", "8", "--seed", "5",
           "--drop-runs", "3:3", "--drop-runs", "1:12", "--min-gap", "150", "--pause-ms", "50",
           "--tolerate-other-stops", "--out", str(out)]
    env = {**os.environ, "MPLBACKEND": "Agg"}
    # the soak bounds its own daemons (SIGINT, then kill); this timeout bounds the soak
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=90)
    assert (out / "report.json").exists(), proc.stdout + proc.stderr
    rep = json.loads((out / "report.json").read_text())
    n = rep["numbers"]
    checks = {c["name"]: c for c in rep["checks"]}
    assert proc.returncode == 0, json.dumps(rep["checks"], indent=1)
    assert n["proxy"]["run_length_histogram"] == {"1": 12, "3": 3}
    assert n["run_length_histogram"] == {"1": 12, "3": 3}
    outcomes = n["runs_by_outcome"]
    rows = list(csv.DictReader((out / "runs.csv").open()))
    threes = [r["category"] for r in rows if r["length"] == "3"]
    ones = [r["category"] for r in rows if r["length"] == "1"]
    # every judged run of 3 stopped the robot once, none missed; at least one was judged
    assert len(threes) == 3 and set(threes) <= {"stop", "masked"} and "stop" in threes
    assert n["stops_by_kind"].get("run>=3", 0) == threes.count("stop") == outcomes["stop"]
    # runs of 1 never stopped it, except through the deadline (late delivery: machine load)
    assert len(ones) == 12 and set(ones) <= {"no-stop", "deadline-stop", "masked"}
    for name in ("every loss stop follows a run >= 3 (or a deadline)",
                 "runs of 1-2 drops caused no stop by themselves",
                 "every run >= 3 (slave RUNNING) stopped the robot exactly once",
                 "operator Run resumed after every stop", "daemons ran and wrote statistics"):
        assert checks[name]["passed"], checks[name]
    # the master stops first at the end of the soak; the slave ends STOPPED by it (exit 4, see
    # occd --help) if the grace ran out before the slave itself was stopped, else RUNNING (0)
    assert n["exit_codes"]["master"] == 0 and n["exit_codes"]["slave"] in (0, 4)
    assert n["slave_loss_monitor"]["trips"] >= outcomes["stop"]
    for f in ("drops.csv", "slave-stats.json", "master-stats.json", "report.md", "drops_over_time.png"):
        assert (out / f).exists(), f


# ------------------------------------------------------------------------------ paper protocol


def test_paper_sim_is_the_stability_protocol(tmp_path: Path) -> None:
    """``soak.py paper`` runs tools/stability.py's protocol (same arguments, same report)."""
    out = tmp_path / "paper"
    code = soak.main(["paper", "--minutes", "0.1", "--seed", "3", "--jobs", "1", "--out", str(out)])
    rep = json.loads((out / "report.json").read_text())
    assert code == 0, rep["checks"]
    n = rep["numbers"]
    assert n["expected_stops"] == 0 and n["false_stops"] == 0
    for axis in ("x", "y", "z"):
        e = n["tracking_error_mm"][axis]
        assert set(e) >= {"mean", "p99", "max"} and e["mean"] <= e["p99"] <= e["max"]
    assert set(n["interarrival_histogram_ms"]) == {"2", "6"}
    assert n["wall_seconds"] >= 0 and n["cpu_seconds"] > 0
    assert rep["command"].startswith("tools/soak.py paper")


@pytest.mark.realtime
def test_paper_real_against_the_daemons(tmp_path: Path) -> None:
    """The protocol against occd slave + master through the loss proxy for 8 s: double losses
    only, no stop, the tracking error measured from the two recordings.

    Timing tolerance (a loaded 2-core machine): holds (a 6 ms gap plus scheduling delay) and
    the inter-arrival histogram are reported, not asserted; the tracking error bound is the
    paper's level (0.1 mm), four times what the simulated drives give (~0.025 mm)."""
    out = tmp_path / "paper-real"
    cmd = [sys.executable, str(TOOLS / "soak.py"), "paper", "--real", "--duration", "8",
           "--seed", "2", "--window", "5", "--out", str(out)]
    env = {**os.environ, "MPLBACKEND": "Agg"}
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert (out / "report.json").exists(), proc.stdout + proc.stderr
    rep = json.loads((out / "report.json").read_text())
    checks = {c["name"]: c for c in rep["checks"]}
    assert proc.returncode == 0, json.dumps(rep["checks"], indent=1)
    n = rep["numbers"]
    # the paper's pattern at the proxy: 2 % lost, in runs of exactly two
    assert set(n["proxy"]["run_length_histogram"]) == {"2"}
    assert n["double_losses"] == round(0.02 * 8 * 500 / 2)
    assert n["expected_stops"] == 0 and n["false_stops"] == 0
    assert checks["no stop, no fault"]["passed"]
    assert n["slave_controller"]["reindexes"] == 1
    for axis in ("x", "y"):
        e = n["tracking_error_mm"][axis]
        assert e["n"] > 1000 and 0.0 < e["mean"] <= 0.1 and e["mean"] <= e["p99"] <= e["max"]
    assert n["references_mm"]["master_ref"] is not None
    assert n["cpu_seconds"]["slave"] is not None and n["wall_seconds"] >= 7.5
    for f in ("slave.rec", "master.rec", "report.md", "interarrival.png", "trajectories.png"):
        assert (out / f).exists(), f


@pytest.mark.slow
@pytest.mark.req("SR-FORCE-1")
def test_paper_real_with_the_wall_has_a_force_panel(tmp_path: Path) -> None:
    """The same protocol with the wall slave (configs/wall.yaml): the return channel comes back
    through the proxy, and the report has the forces (the instrument's from the slave's
    recording, the hand's from the master's) and their panel (forces.png)."""
    out = tmp_path / "paper-wall"
    cmd = [sys.executable, str(TOOLS / "soak.py"), "paper", "--real", "--duration", "8",
           "--seed", "2", "--window", "5", "--slave-config", str(ROOT / "configs" / "wall.yaml"),
           "--out", str(out)]  # fmt: skip
    env = {**os.environ, "MPLBACKEND": "Agg"}
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert (out / "report.json").exists(), proc.stdout + proc.stderr
    n = json.loads((out / "report.json").read_text())["numbers"]
    f = n["forces"]
    assert f["instrument_peak_n"] > 0.5 and f["hand_peak_n"] > 0.5, f
    assert f["rms_difference_n"] <= 0.1 * f["instrument_peak_n"], f
    assert (out / "forces.png").stat().st_size > 10_000
