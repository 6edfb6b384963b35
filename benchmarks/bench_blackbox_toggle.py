"""The black box's cost inside one live slave, switched on and off every 0.7 s.

    python benchmarks/bench_blackbox_toggle.py [--seconds 60] [--phase-ticks 700]
    python benchmarks/bench_blackbox_toggle.py --control      # the same, nothing switched

Separate runs of a daemon (bench_blackbox_ab.py) compare minutes of this VM whose speed moves
by a factor of two from one minute to the next. This runs the shipped slave in this process on
the real clock (``occd``'s own entry point, the pure build, its SCHED_FIFO settings where
permitted) beside the shipped master streaming at 500 Hz (a subprocess), and flips the black
box's ``enabled`` between two ticks every ``--phase-ticks`` ticks: the same process, the same
caches and the same sleeping loop, the two arms 0.7 s apart (not a divisor of the checkpoints'
1000 ticks: in ``--control`` they fall in both arms, not always in one). With ``enabled`` false
every entry point of the black box returns at its first line (its checkpoints too: no row is
counted, so none falls due), which is what ``black_box.enabled: false`` runs.

Per phase it takes the loop thread's CPU per tick (``time.thread_time`` around ``Robot.tick``:
the black box's row, its inputs and its writes are all inside the tick) and the whole process's
CPU (``time.process_time`` from one switch to the next: the checkpoints the loop takes between
ticks, the interface threads, the collector); the process's CPU is reported in points of a
core (percent), the issue's unit. Each on phase is paired with the off phase before it; the
mean of the pairs' differences and its standard error are printed, the first two pairs
dropped (warm-up). ``--control`` labels the phases the same way but never switches (the black
box stays on): its differences are this machine's floor for the same statistic.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tools")]
os.environ.setdefault("OCC_PURE", "1")  # the shipped build
import occ.core.loop as L  # noqa: E402
import occ.core.robot as R  # noqa: E402
from occ.cli import main  # noqa: E402
from tools.loopback import pair_configs, stop_processes, write_yaml  # noqa: E402


class Phases:
    """Per-phase sums, written by the loop thread only."""

    def __init__(self, phase_ticks: int, control: bool) -> None:
        self.phase_ticks = phase_ticks
        self.control = control
        self.n = 0
        #: per phase: [on?, ticks, thread CPU s in ticks, process CPU s, wall s, tick CPU s
        #: list]
        self.rows: list[list[Any]] = []
        #: per arm (off, on): each tick's lateness (start minus deadline) and wall duration, s
        self.late: tuple[list[float], list[float]] = ([], [])
        self.took: tuple[list[float], list[float]] = ([], [])
        self.loop: Any = None
        self._t0 = self._c0 = 0.0

    def switch(self, robot: Any) -> None:
        on = (self.n // self.phase_ticks) % 2 == 1  # off first
        now, cpu = time.perf_counter(), time.process_time()
        if self.rows:
            last = self.rows[-1]
            last[3], last[4] = cpu - self._c0, now - self._t0
        self._t0, self._c0 = now, cpu
        if not self.control:
            robot.black_box.enabled = on
        self.rows.append([on, 0, 0.0, 0.0, 0.0, []])


def run(args: argparse.Namespace) -> dict[str, Any]:
    ph = Phases(args.phase_ticks, args.control)
    orig = R.Robot.tick
    orig_run = L.ControlLoop._run
    tt, pc = time.thread_time, time.perf_counter

    def tick(self: Any, now: float, k: int) -> None:
        if ph.n % ph.phase_ticks == 0:
            ph.switch(self)
        w, c = pc(), tt()
        orig(self, now, k)
        d, wd = tt() - c, pc() - w
        row = ph.rows[-1]
        row[1] += 1
        row[2] += d
        row[5].append(d)
        arm = 1 if row[0] else 0
        loop = ph.loop
        ph.late[arm].append(now - (loop.t0 + k * loop.period_s))
        ph.took[arm].append(wd)
        ph.n += 1

    def run_loop(self: Any, *a: Any) -> None:
        ph.loop = self
        orig_run(self, *a)

    R.Robot.tick = tick  # type: ignore[method-assign]
    L.ControlLoop._run = run_loop  # type: ignore[method-assign]
    out = Path(tempfile.mkdtemp())
    slave, master, _ports = pair_configs()
    write_yaml(out / "s.yaml", slave)
    write_yaml(out / "m.yaml", master)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cmd = [sys.executable, "-m", "occ.cli", str(out / "m.yaml"), "--start", "running"]
    m = subprocess.Popen([*cmd, "--log-level", "ERROR"], env=env)
    try:
        main(
            [
                str(out / "s.yaml"),
                "--start",
                "running",
                "--duration",
                str(args.seconds),
                "--log-level",
                "ERROR",
                "--stats",
                str(out / "s.json"),
            ]
        )
    finally:
        stop_processes([m])
    stats = json.loads((out / "s.json").read_text())
    rows = [r for r in ph.rows[:-1] if r[1] == ph.phase_ticks]  # whole phases only
    pairs = []
    for a, b in zip(rows, rows[1:], strict=False):
        if not a[0] and b[0]:  # off then on
            pairs.append(
                (
                    (b[2] / b[1] - a[2] / a[1]) * 1e6,  # loop CPU per tick, µs
                    (b[3] / b[4] - a[3] / a[4]) * 100.0,  # process CPU, points
                    (statistics.median(b[5]) - statistics.median(a[5])) * 1e6,
                )
            )
    pairs = pairs[2:]

    def summary(i: int) -> dict[str, float]:
        xs = [p[i] for p in pairs]
        sd = statistics.stdev(xs) if len(xs) > 1 else math.nan
        return {
            "mean": round(statistics.fmean(xs), 3),
            "se": round(sd / math.sqrt(len(xs)), 3),
            "median": round(statistics.median(xs), 3),
        }

    off = [r for r in rows if not r[0]]

    def tails(xs: list[float]) -> dict[str, float]:
        xs = sorted(xs[2 * ph.phase_ticks :])
        q = statistics.quantiles(xs, n=1000)
        return {
            "p50": round(q[499] * 1e6, 1),
            "p99": round(q[989] * 1e6, 1),
            "p99.9": round(q[998] * 1e6, 1),
            "max": round(xs[-1] * 1e6, 1),
        }

    return {
        "mode": "control (never switched, on throughout)" if args.control else "on vs off",
        "seconds": args.seconds,
        "phase_ticks": args.phase_ticks,
        "pairs": len(pairs),
        "loop_cpu_us_per_tick": summary(0),
        "process_cpu_points": summary(1),
        "tick_cpu_p50_us": summary(2),
        "off_process_cpu_percent": round(
            100.0 * sum(r[3] for r in off) / max(1e-9, sum(r[4] for r in off)), 2
        ),
        "off_loop_cpu_us_per_tick": round(
            1e6 * sum(r[2] for r in off) / max(1, sum(r[1] for r in off)), 2
        ),
        "lateness_us": {"off": tails(ph.late[0]), "on": tails(ph.late[1])},
        "tick_wall_us": {"off": tails(ph.took[0]), "on": tails(ph.took[1])},
        "daemon_cpu_percent": stats["cpu_percent"],
        "black_box_checkpoints": stats.get("black_box", {}).get("checkpoints"),
    }


def cli() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--phase-ticks", type=int, default=700)
    ap.add_argument("--control", action="store_true", help="never switch: the floor")
    ap.add_argument("--json", type=Path, help="also write the result here")
    args = ap.parse_args()
    result = run(args)
    print(json.dumps(result, indent=1))
    if args.json is not None:
        args.json.write_text(json.dumps(result))


if __name__ == "__main__":
    cli()
