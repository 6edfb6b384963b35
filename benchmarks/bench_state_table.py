"""Benchmark: the State Data Table's row (what the loop pays) and a read (what the worker pays).

    python benchmarks/bench_state_table.py
    python benchmarks/bench_state_table.py --rows 100000 --rounds 7 --seconds 10

The slave's three joints; thread CPU time (the machine is shared), best of the rounds. ``write``
is one row as the loop writes it each tick; ``window(S)`` reads the last S seconds of a full
table at 1 kHz (copy, column order, the tip's forward kinematics per row).
"""

from __future__ import annotations

import argparse
import time

from occ.core.statetable import StateTable, capacity_for
from occ.joint import Joint, JointLimits
from occ.kinematics.frame import Frame

NAMES = ("yaw", "pitch", "insertion")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", type=int, default=100_000)
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--seconds", type=float, default=10.0, help="the table's length")
    args = p.parse_args()
    joints = [Joint(n, "revolute", JointLimits(-1.0, 1.0, 1.0, 10.0), 0.0) for n in NAMES]
    table = StateTable(NAMES, capacity_for(args.seconds, 1000.0), Frame.builtin("occ_slave"))
    q, sp = [0.1, 0.35, 0.05], [0.1, 0.35, 0.05]
    best = float("inf")
    for _ in range(args.rounds):
        t0 = time.thread_time()
        for k in range(args.rows):
            table.write(k * 0.001, 3.0, 0.0, q, sp, joints)
        best = min(best, (time.thread_time() - t0) / args.rows)
    print(f"write: {best * 1e6:.3f} µs per row (best of {args.rounds} x {args.rows} rows)")
    for seconds in (0.1, 1.0, args.seconds):
        took = float("inf")
        for _ in range(3):
            t0 = time.thread_time()
            rows = table.window(seconds)
            took = min(took, time.thread_time() - t0)
        print(f"window({seconds:g} s): {len(rows)} rows in {took * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
