"""What the black box costs a real slave daemon: paired runs, on and off, and the machine's floor.

    python benchmarks/bench_blackbox_ab.py                      # 8 rounds of 20 s, on vs off
    python benchmarks/bench_blackbox_ab.py --rounds 6 --seconds 15
    python benchmarks/bench_blackbox_ab.py --arms off,off       # the same runs, both arms off

Each round runs the shipped slave twice, one after the other, once with ``black_box`` as
shipped (on) and once with it off, the order swapped every round; each run is a fresh ``occd``
process (``--start running --duration S --stats``, the pure build, SCHED_FIFO where permitted)
beside the shipped master streaming to it at 500 Hz. From the slave's own statistics: its CPU
share (``cpu_percent``, a percent of one core: the issue's "points"), its tick's compute time
(p50) and its loop's lateness (p99.9). A round's difference is its on run minus its off run: this
VM's speed drifts between minutes, so only runs next to each other compare, and the mean of
the rounds' differences, with its standard error, is the cost. ``--arms off,off`` runs both
arms the same: its differences are the machine's own floor (what a paired difference shows when
nothing differs).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]
from tools.loopback import pair_configs, stop_processes, wait_port, write_yaml  # noqa: E402

METRICS = ("cpu", "compute_p50", "late_p999")


def run(on: bool, seconds: float) -> dict[str, float]:
    """One slave run beside the master: the slave's CPU %, compute p50 and lateness p99.9."""
    d = Path(tempfile.mkdtemp(prefix="occ-bbab-"))
    slave, master, ports = pair_configs()
    if not on:
        slave["black_box"] = {"enabled": False}
    else:
        slave.setdefault("black_box", {})["dir"] = str(d / "bb")
    write_yaml(d / "s.yaml", slave)
    write_yaml(d / "m.yaml", master)
    env = dict(os.environ, PYTHONPATH=str(ROOT), OCC_PURE="1")
    quiet = {"env": env, "cwd": ROOT, "stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    py = sys.executable
    pm = subprocess.Popen([py, "-m", "occ.cli", str(d / "m.yaml"), "--start", "running"], **quiet)
    try:
        wait_port(ports["master_tcp"])
        ps = subprocess.run(
            [py, "-m", "occ.cli", str(d / "s.yaml"), "--start", "running"]
            + ["--duration", str(seconds), "--stats", str(d / "s.json")],
            **quiet,
            timeout=seconds + 60,
        )
    finally:
        stop_processes([pm])
    if ps.returncode not in (0, None):
        raise SystemExit(f"the slave exited with {ps.returncode} ({d})")
    s = json.loads((d / "s.json").read_text())
    if s.get("final_state") != "RUNNING":
        raise SystemExit(f"the slave ended {s.get('final_state')}, not RUNNING ({d})")
    late = s["lateness_us"]
    return {
        "cpu": float(s["cpu_percent"]),
        "compute_p50": float(s["compute_us"]["p50"]),
        "late_p999": float(late["p99_9"]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--arms", default="on,off", help="the two arms: on,off or off,off")
    args = ap.parse_args()
    arms = [a == "on" for a in args.arms.split(",")]
    diffs: dict[str, list[float]] = {m: [] for m in METRICS}
    for r in range(args.rounds):
        order = [0, 1] if r % 2 == 0 else [1, 0]
        got: dict[int, dict[str, float]] = {}
        for i in order:
            got[i] = run(arms[i], args.seconds)
        line = []
        for m in METRICS:
            diffs[m].append(got[0][m] - got[1][m])
            line.append(f"{m} {got[0][m]:.2f} / {got[1][m]:.2f}")
        first = args.arms.split(",")[order[0]]
        print(f"round {r + 1} ({first} first): " + ", ".join(line), flush=True)
    n = len(diffs["cpu"])
    print(f"\n{args.arms.replace(',', ' minus ')}, {n} rounds of {args.seconds:g} s:")
    for m in METRICS:
        xs = diffs[m]
        mean = statistics.fmean(xs)
        se = statistics.stdev(xs) / n**0.5 if n > 1 else float("nan")
        print(
            f"  {m:12s} mean {mean:+.2f}  (standard error {se:.2f})  median "
            f"{statistics.median(xs):+.2f}  min {min(xs):+.2f}  max {max(xs):+.2f}"
        )


if __name__ == "__main__":
    main()
