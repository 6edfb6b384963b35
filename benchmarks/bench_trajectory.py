"""Time ``Trajectory.position`` and ``velocity`` per call (run: .venv/bin/python
benchmarks/bench_trajectory.py).

A keyframe plan is played by a controller that asks for one setpoint per tick of the 1 kHz loop,
so the per-call cost of position() is what matters (plan() runs once, off the loop). Prints the
median of ``repeat`` timeit runs in microseconds per call, for the four interpolation x mode
combinations, over times spread across the whole plan.
"""

from __future__ import annotations

import argparse
import itertools
import platform
import statistics
import time
from collections.abc import Callable

import numpy as np

from occ.kinematics.trajectory import Keyframe, plan


def per_call_us(func: Callable[[float], object], ts: list[float], repeat: int) -> float:
    """Median µs per call of func over the times ts (the loop's overhead included, ~0.05 µs)."""
    runs = []
    for _ in range(repeat):
        start = time.perf_counter()
        for t in ts:
            func(t)
        runs.append(time.perf_counter() - start)
    return statistics.median(runs) / len(ts) * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--keyframes", type=int, default=10)
    parser.add_argument("--dim", type=int, default=6, help="pose dimension (e.g. 6 joints)")
    parser.add_argument("--number", type=int, default=20_000)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()

    # fixed seed: the same plan every run, so runs compare
    rng = np.random.default_rng(11)
    times = np.cumsum(rng.uniform(0.5, 3.0, args.keyframes))
    frames = [Keyframe(float(t), rng.uniform(-1.0, 1.0, args.dim)) for t in times]
    print(f"python {platform.python_version()}, {args.keyframes} keyframes, dim {args.dim}")
    print("| interpolation | mode | plan() ms | position() µs | velocity() µs |")
    print("|---|---|---|---|---|")
    for interpolation, mode in itertools.product(("linear", "spline"), ("stop", "continuous")):
        start = time.perf_counter()
        traj = plan(frames, interpolation, mode)  # type: ignore[arg-type]
        plan_ms = (time.perf_counter() - start) * 1e3
        ts = np.linspace(traj.start, traj.end, args.number).tolist()
        pos_us = per_call_us(traj.position, ts, args.repeat)
        vel_us = per_call_us(traj.velocity, ts, args.repeat)
        print(f"| {interpolation} | {mode} | {plan_ms:.2f} | {pos_us:.1f} | {vel_us:.1f} |")


if __name__ == "__main__":
    main()
