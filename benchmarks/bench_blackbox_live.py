"""What the black box costs the loop of a real slave daemon, measured inside it.

    python benchmarks/bench_blackbox_live.py [SECONDS]        # the black box on (default)
    python benchmarks/bench_blackbox_live.py [SECONDS] off    # the same run with it off

The shipped slave runs in this process on the real clock (``occd``'s own entry point, its
SCHED_FIFO settings where permitted) for SECONDS (default 20) beside the shipped master (a
subprocess streaming at 500 Hz). Every entry point of the black box the loop thread calls
(``end_tick``, ``took``, ``spare``, ``wrote``) and the whole ``Robot.tick`` are wrapped with
``time.perf_counter``: printed, each one's calls and mean microseconds (the wrapper's own
cost, about 0.3-0.5 µs a call, included), and the daemon's CPU and compute p50 from its
``--stats``. Side-by-side pairs (ab_pairs_side_by_side.py) compare whole daemons but on this
shared VM their order alone moves the CPU by 1-3 points; this measures the black box's own
share directly.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tools")]
import occ.core.robot as R  # noqa: E402
import occ.recording.blackbox as B  # noqa: E402
from occ.cli import main  # noqa: E402
from tools.loopback import pair_configs, stop_processes, write_yaml  # noqa: E402

acc = {
    "end_tick": [0.0, 0],
    "took": [0.0, 0],
    "tick": [0.0, 0],
    "spare": [0.0, 0],
    "wrote": [0.0, 0],
}
pc = time.perf_counter


def wrap(cls, name, key):
    orig = getattr(cls, name)

    def f(*a, **k):
        t = pc()
        r = orig(*a, **k)
        d = pc() - t
        s = acc[key]
        s[0] += d
        s[1] += 1
        return r

    setattr(cls, name, f)


for n in ("end_tick", "took", "spare", "wrote"):
    wrap(B.BlackBox, n, n)
wrap(R.Robot, "tick", "tick")
out = Path(tempfile.mkdtemp())
slave, master, ports = pair_configs()
seconds = sys.argv[1] if len(sys.argv) > 1 else "20"
if "off" in sys.argv[2:]:
    slave["black_box"] = {"enabled": False}
write_yaml(out / "s.yaml", slave)
write_yaml(out / "m.yaml", master)
env = dict(os.environ, PYTHONPATH=str(ROOT), OCC_PURE="1")
m = subprocess.Popen(
    [
        sys.executable,
        "-m",
        "occ.cli",
        str(out / "m.yaml"),
        "--start",
        "running",
        "--log-level",
        "ERROR",
    ],
    env=env,
)
try:
    main(
        [
            str(out / "s.yaml"),
            "--start",
            "running",
            "--duration",
            seconds,
            "--log-level",
            "ERROR",
            "--stats",
            str(out / "s.json"),
        ]
    )
finally:
    stop_processes([m])
for k, (t, n) in acc.items():
    if n:
        print(k, "calls", n, "mean us %.2f" % (t / n * 1e6), "total ms %.1f" % (t * 1e3))
s = json.load(open(out / "s.json"))
print("cpu", s["cpu_percent"], "compute p50", s["compute_us"]["p50"])
