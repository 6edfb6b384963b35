"""The black box and the garbage collector, in simulated time.

    python benchmarks/bench_blackbox_gc.py on
    python benchmarks/bench_blackbox_gc.py off

The shipped slave with its command stream (occ_testkit's SlaveRig) runs 2000 ticks, then 40000
ticks of a moving stream with the collector on (Python's default thresholds), timed with
``time.process_time``. Printed: µs a tick, the collections of each generation during the run,
how long one full collection takes afterwards, and how many objects the collector tracks. What
the black box keeps alive for its 30 s is what the collector walks.
"""

import gc
import sys
import tempfile
import time

import yaml

from occ.config import DaemonConfig
from occ_testkit import CONFIGS
from occ_testkit.rigs import SlaveRig


def run(enabled: bool, n: int = 40000) -> None:
    raw = yaml.safe_load((CONFIGS / "slave.yaml").read_text())
    raw["black_box"] = {"enabled": enabled, "dir": tempfile.mkdtemp(prefix="occ-gcb-")}
    cfg = DaemonConfig.model_validate(raw, context={"base_dir": CONFIGS})
    rig = SlaveRig(cfg)
    rig.running()
    rig.step(2000)
    gc.collect()
    before = [s["collections"] for s in gc.get_stats()]
    t = time.process_time()
    for _ in range(n // 100):
        rig.target[0] += 0.001
        rig.step(100)
    dt = time.process_time() - t
    during = [
        b - a for a, b in zip(before, [s["collections"] for s in gc.get_stats()], strict=True)
    ]
    t2 = time.perf_counter()
    gc.collect()
    full = time.perf_counter() - t2
    print(
        f"black box {'on' if enabled else 'off'}: {dt / n * 1e6:.1f} µs a tick; collections "
        f"{during}; a full one {full * 1e3:.1f} ms; {len(gc.get_objects())} objects tracked"
    )
    rig.close()


if __name__ == "__main__":
    run(sys.argv[1:2] != ["off"])
