#!/usr/bin/env python3
"""What the staff console costs: the daemon per GetStats answer, and the console per answer.

The console asks each daemon ``GetStats`` (``Format="json"``, ``Histogram="lateness"``)
``--poll-hz`` times a second. The daemon builds the answer on its worker thread, off the loop
(``OperatorDesk._reply_stats``: the statistics snapshot, the raw lateness buckets, the JSON);
the console then folds it into its view and serves snapshots to the page. Both are timed here
on the slave (configs/slave.yaml, simulated drives, ``occ_testkit.testing.SimRobot``) after
``--ticks`` ticks, its lateness histogram filled with ``--ticks`` values spread as a busy
machine spreads them (log-normal, median 25 µs, a tail past 10 ms; seeded), so the answer has
as many buckets as a real daemon's after a while. Reports median and p99 over ``--n`` calls,
and the answer's size.

    python benchmarks/bench_console.py --n 300
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

from occ_console.model import DaemonView  # noqa: E402
from occ_testkit.testing import SimRobot  # noqa: E402


def timed(fn, n: int) -> tuple[float, float]:  # type: ignore[no-untyped-def]
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t0) * 1e6)
    out.sort()
    return statistics.median(out), out[int(0.99 * (len(out) - 1))]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--n", type=int, default=300)
    p.add_argument("--ticks", type=int, default=200_000)
    args = p.parse_args()
    sim = SimRobot(ROOT / "configs" / "slave.yaml")
    try:
        sim.step(1000)
        rng = random.Random(13)
        lateness = sim.robot.stats.lateness
        for _ in range(args.ticks):
            lateness.add(rng.lognormvariate(3.2, 1.1))
        r = sim.robot

        def answer() -> str:  # what the daemon's worker does for one answer
            snap = r.snapshot()
            snap["lateness_buckets"] = r.stats.lateness.buckets()
            return json.dumps(snap, separators=(",", ":"), default=str)

        text = answer()
        d50, d99 = timed(answer, args.n)
        view = DaemonView("0", "127.0.0.1", 18947)
        k = [0]

        def fold() -> str:  # what the console does per answer (one page update included)
            k[0] += 1
            stats = json.loads(text)
            stats["ticks"] = k[0]
            view.on_stats(float(k[0]), float(k[0]) * 0.5, stats)
            return json.dumps(view.snapshot(), separators=(",", ":"))

        page = fold()
        c50, c99 = timed(fold, args.n)
    finally:
        sim.close()
    buckets = len(json.loads(text)["lateness_buckets"])
    print(f"answer: {len(text)} bytes, {buckets} buckets; page update: {len(page)} bytes")
    print(f"daemon (worker thread) per answer: median {d50:.0f} µs, p99 {d99:.0f} µs")
    print(f"console per answer (fold + snapshot JSON): median {c50:.0f} µs, p99 {c99:.0f} µs")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
