"""Benchmark: the real control loop, empty, at 1 kHz, with and without SCHED_FIFO + pinning.

    python benchmarks/bench_loop.py                 # 20 s plain, then 20 s SCHED_FIFO 80 + cpu 1
    python benchmarks/bench_loop.py -s 5 --mode rt --cpu 0 --json out.json
    python benchmarks/bench_loop.py --load-threads 2  # with Python threads competing for the GIL

Each run uses occ.core.loop.ControlLoop on a RealClock in its own thread (scheduling settings are
per thread and restored afterwards). When SCHED_FIFO or pinning is refused, the run falls
back and the "realtime:" line says so. Prints one row per run; ``--json`` writes the
snapshots.
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from typing import Any

from occ.clock import RealClock
from occ.core.loop import ControlLoop


def _load_thread(stop: threading.Event, period_s: float) -> None:
    """A stand-in for an interface thread: a little Python work at 500 Hz."""
    while not stop.is_set():
        sum(i * i for i in range(200))
        time.sleep(period_s)


def run_once(
    name: str, seconds: float, rate: float, spin_us: float, realtime: dict[str, Any], load: int
) -> dict[str, Any]:
    loop = ControlLoop(rate, lambda now, k: None, clock=RealClock(spin_us), realtime=realtime)
    stop_load = threading.Event()
    loaders = [
        threading.Thread(target=_load_thread, args=(stop_load, 0.002), daemon=True)
        for _ in range(load)
    ]
    for t in loaders:
        t.start()
    try:
        loop.run_in_thread(duration=seconds, name=f"bench-{name}")
        loop.join()
    finally:
        stop_load.set()
        for t in loaders:
            t.join()
    if loop.error is not None:
        raise loop.error
    snap = loop.stats.snapshot()
    snap["name"] = name
    snap["realtime"] = loop.realtime_report
    snap["spin_us"] = spin_us
    snap["load_threads"] = load
    return snap


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("-s", "--seconds", type=float, default=20.0, help="per run (default 20)")
    ap.add_argument("--rate", type=float, default=1000.0, help="Hz (default 1000)")
    ap.add_argument("--spin-us", type=float, default=200.0, help="RealClock spin margin")
    ap.add_argument("--prio", type=int, default=80, help="SCHED_FIFO priority for the rt run")
    ap.add_argument("--cpu", type=int, default=1, help="CPU to pin the rt run to")
    ap.add_argument("--gc", choices=("freeze", "off", "default"), default="freeze")
    ap.add_argument("--mode", choices=("both", "plain", "rt"), default="both")
    ap.add_argument("--load-threads", type=int, default=0, help="competing Python threads")
    ap.add_argument("--json", help="write the snapshots to this file")
    args = ap.parse_args(argv)

    runs: list[tuple[str, dict[str, Any]]] = []
    if args.mode in ("both", "plain"):
        runs.append(("plain", {"gc": args.gc}))
    if args.mode in ("both", "rt"):
        runs.append(("fifo+pin", {"gc": args.gc, "fifo_priority": args.prio, "cpu": args.cpu}))

    results = []
    header = (
        f"{'run':<9} {'ticks':>6} {'p50':>7} {'p99':>8} {'p99.9':>8} {'max':>9} "
        f"{'late>1ms':>9} {'missed':>6} {'cpu%':>6}   (lateness, µs)"
    )
    print(
        f"empty loop at {args.rate:g} Hz, {args.seconds:g} s per run, spin {args.spin_us:g} µs, "
        f"gc {args.gc}, {args.load_threads} load threads"
    )
    print(header)
    for name, rt in runs:
        snap = run_once(name, args.seconds, args.rate, args.spin_us, rt, args.load_threads)
        results.append(snap)
        late = snap["lateness_us"]
        print(
            f"{name:<9} {snap['ticks']:>6} {late['p50']:>7.1f} {late['p99']:>8.1f} "
            f"{late['p99_9']:>8.1f} {late['max']:>9.1f} "
            f"{snap['late_over_1ms']:>4} ({snap['late_over_1ms_percent']:.3f}%) "
            f"{snap['missed_ticks']:>3} {snap['cpu_percent']:>6.1f}"
        )
        print(f"          {snap['realtime']}")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(results, fh, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
