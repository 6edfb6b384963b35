"""Per-tick cost of the virtual-fixture force (run: .venv/bin/python benchmarks/bench_fixtures.py).

The master calls ``FixtureSet.force`` once a tick of its 1 kHz loop, so that call's cost for 1,
10 and 100 primitives is what matters; a new definition is validated and compiled on the loop
thread too (bounded by ``max_fixtures``), so its cost is printed as well. For each size, the
tool walks a circle that takes it in and out of contact, and the median of ``repeat`` runs is
reported in microseconds per call, for four sets: accessible spheres only (the paper's union),
forbidden spheres only, a mix of every kind (spheres, planes, guides), and the tool free versus
in contact.
"""

from __future__ import annotations

import argparse
import math
import platform
import random
import statistics
import time
from collections.abc import Callable

import igtl
from occ.haptics.fixture_defs import Defaults, PatientMapping, compile_definitions, from_event
from occ.haptics.fixtures import (
    AccessibleSphere,
    FixtureSet,
    ForbiddenPlane,
    ForbiddenSphere,
    Guide,
    Primitive,
)
from occ.net.decoders import event_of


def sets(n: int, rng: random.Random) -> dict[str, list[Primitive]]:
    def c() -> tuple[float, float, float]:
        return (rng.uniform(-60, 60), rng.uniform(-60, 60), rng.uniform(-20, 20))

    mix: list[Primitive] = []
    for i in range(n):
        kind = i % 4
        if kind == 0:
            mix.append(AccessibleSphere(c(), rng.uniform(20, 60)))
        elif kind == 1:
            mix.append(ForbiddenSphere(c(), rng.uniform(2, 10)))
        elif kind == 2:
            mix.append(ForbiddenPlane(c(), (rng.uniform(-1, 1), rng.uniform(-1, 1), 1.0)))
        else:
            mix.append(Guide(tuple(c() for _ in range(4)), stiffness=0.01))
    return {
        # the circle of radius 50 leaves the union now and then
        "accessible": [AccessibleSphere(c(), rng.uniform(25, 45)) for _ in range(n)],
        "forbidden": [ForbiddenSphere(c(), rng.uniform(2, 10)) for _ in range(n)],
        "mix": mix,
    }


def per_call_us(func: Callable[[], object], number: int, repeat: int) -> float:
    """Median µs per call, in this thread's CPU time (``--wall``: elapsed time): the machine is
    shared, and time spent waiting for a core is not the computation's cost."""
    clock = time.perf_counter if WALL else time.thread_time
    runs = []
    for _ in range(repeat):
        start = clock()
        for _ in range(number):
            func()
        runs.append(clock() - start)
    return statistics.median(runs) / number * 1e6


WALL = False


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--number", type=int, default=10_000, help="calls per run (ticks)")
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--wall", action="store_true", help="elapsed time instead of CPU time")
    args = p.parse_args()
    global WALL
    WALL = args.wall
    rng = random.Random(7)  # the same sets every run
    # the tool's path: the paper's circle (50 mm radius) at 0.1 Hz, one sample a tick
    path = [
        (
            50.0 * math.sin(2 * math.pi * 0.1 * k * 1e-3),
            50.0 * math.cos(2 * math.pi * 0.1 * k * 1e-3),
            0.0,
        )
        for k in range(args.number)
    ]
    print(
        f"python {platform.python_version()}, {args.number} ticks x {args.repeat} runs, "
        f"µs per force() call (median run, {'elapsed' if WALL else 'thread CPU'} time)"
    )
    print("| primitives | accessible | forbidden | mix (all kinds) | contacts entered (mix) |")
    print("|---|---|---|---|---|")
    for n in (1, 10, 100):
        row = []
        entered = 0
        for name, prims in sets(n, rng).items():
            fs = FixtureSet(prims, max_force_n=10.0)
            it = iter(path * (args.repeat + 1))
            row.append(
                per_call_us(lambda fs=fs, it=it: fs.force(next(it), 1e-3), args.number, args.repeat)
            )
            if name == "mix":
                entered = fs.contacts_entered
        print(f"| {n} | {row[0]:.1f} | {row[1]:.1f} | {row[2]:.1f} | {entered} |")
    empty = FixtureSet([])
    bare = per_call_us(lambda: empty.force((1.0, 2.0, 3.0), 1e-3), args.number, args.repeat)
    print(f"\nno fixture: {bare:.2f} µs")

    # a definition arriving: decode is the interface thread's; validation + compilation the loop's
    print("\n| VFIXTURE spheres | validate + compile + new set (µs, on the loop) |")
    print("|---|---|")
    for n in (1, 10, 64):
        msg = igtl.VirtualFixtureMessage(
            hardness=1.0,
            spheres=tuple(
                (rng.uniform(-50, 50), rng.uniform(-50, 50), 0.0, 30.0) for _ in range(n)
            ),
            device_name="VF",
        )
        mapping = PatientMapping(0.1)

        def apply(msg: igtl.Message = msg, mapping: PatientMapping = mapping) -> None:
            defs = from_event(event_of(msg), Defaults())
            assert defs is not None
            FixtureSet(compile_definitions(defs, mapping))

        print(f"| {n} | {per_call_us(apply, 200, args.repeat):.0f} |")


if __name__ == "__main__":
    main()
