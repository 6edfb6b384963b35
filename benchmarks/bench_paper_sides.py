"""Where a simulated millisecond of the paper protocol goes, per side (issue 13).

    python benchmarks/bench_paper_sides.py [MINUTES]      # default 1 simulated minute

Runs ``tools/soak.py paper --jobs 1`` (both robots in this process) with the master's and the
slave's ``SimRobot.tick`` and every packet handed to the slave (decode, routing, queue) timed
apart, and prints per 1 ms tick: the mean, the minimum and the median of 1,000-tick means
(the minimum is the machine at its quietest; compare versions with runs next to each other).
With ``--jobs 2`` the master ticks in a child process, so a 12-hour run takes about
``max(master, slave + deliveries/2 + harness)`` per simulated ms.
"""

from __future__ import annotations

import collections
import runpy
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import occ_testkit.testing as testing  # noqa: E402


def main() -> None:
    minutes = sys.argv[1] if len(sys.argv) > 1 else "1"
    out = tempfile.mkdtemp(prefix="occ-paper-sides-")
    sys.argv = ["soak.py", "paper", "--minutes", minutes, "--jobs", "1", "--out", out]
    acc: dict[str, list[float]] = collections.defaultdict(list)
    pc = time.perf_counter
    tick, send = testing.SimRobot.tick, testing.SimPeer.send

    def timed_tick(self, *a, **k):  # type: ignore[no-untyped-def]
        t = pc()
        r = tick(self, *a, **k)
        acc[f"{self.config.robot.name} tick"].append(pc() - t)
        return r

    def timed_send(self, *a, **k):  # type: ignore[no-untyped-def]
        t = pc()
        r = send(self, *a, **k)
        acc["packet to the slave"].append(pc() - t)
        return r

    testing.SimRobot.tick = timed_tick  # type: ignore[method-assign]
    testing.SimPeer.send = timed_send  # type: ignore[method-assign]
    try:
        runpy.run_path(str(ROOT / "tools" / "soak.py"), run_name="__main__")
    except SystemExit:
        pass
    for name, v in acc.items():
        v = v[5000:]  # after start-up
        means = [sum(v[i : i + 1000]) / 1000 for i in range(0, len(v) - 999, 1000)]
        if not means:
            continue
        median = sorted(means)[len(means) // 2]
        print(
            f"{name:22s} n={len(v):7d}  mean {1e6 * sum(v) / len(v):6.1f} us  "
            f"min of 1000-means {1e6 * min(means):6.1f}  median {1e6 * median:6.1f}"
        )


if __name__ == "__main__":
    main()
