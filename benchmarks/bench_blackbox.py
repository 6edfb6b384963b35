"""Benchmark: what writing a full black box dump costs its writer, in simulated time.

    python benchmarks/bench_blackbox.py             # the shipped slave, 30 s of ring
    python benchmarks/bench_blackbox.py --seconds 10

The shipped slave (configs/slave.yaml) RUNNING on its 500 Hz master stream for one second
more than ``--seconds``, so its ring is full; then an operator's ``DumpBlackBox``, written
inline as in simulated time (on the real clock a forked child writes it: occ/recording/dump.py,
``write_dump_forked``). Prints the dump's wall and CPU time, its ticks, events and size, and
each file's size. The per-tick cost on the loop is ``bench_tick.py``'s ``slave`` against
``slave-no-bb``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import yaml

from occ.config import DaemonConfig
from occ_testkit import CONFIGS
from occ_testkit.rigs import SlaveRig


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=30.0)
    args = p.parse_args()
    raw = yaml.safe_load((CONFIGS / "slave.yaml").read_text())
    with tempfile.TemporaryDirectory() as scratch:
        raw["black_box"] = {"dir": scratch, "seconds": args.seconds}
        rig = SlaveRig(DaemonConfig.model_validate(raw, context={"base_dir": CONFIGS}))
        try:
            rig.running()
            rig.step(int((args.seconds + 1.0) * 1000))
            wall, cpu = time.perf_counter(), time.thread_time()
            rig.sim.command(rig.operator, "DumpBlackBox")
            wall, cpu = time.perf_counter() - wall, time.thread_time() - cpu
            (said,) = [a for a in rig.alerts() if "written to" in a]
            files = sorted(
                (f.stat().st_size, str(f.relative_to(scratch)))
                for f in Path(scratch).rglob("*")
                if f.is_file()
            )
        finally:
            rig.close()
    print(f"dump of {args.seconds:g} s: wall {wall:.2f} s, CPU {cpu:.2f} s")
    print(said)
    for size, name in reversed(files):  # the largest first
        print(f"  {size / 1e6:8.2f} MB  {name}")


if __name__ == "__main__":
    main()
