"""CPU of two slave+master pairs run at the same time, one from each of two source trees.

    git worktree add --detach /tmp/wt-main main
    python benchmarks/ab_pairs_side_by_side.py /tmp/wt-main . 30      # then swap the order
    python benchmarks/ab_pairs_side_by_side.py . /tmp/wt-main 30

``benchmarks/ab_pair_cpu.py`` runs one tree's pair after the other's; on this shared VM the
load moves by tens of percent between minutes, so two versions compare best side by side: both
pairs here (the shipped configs of each tree on free loopback ports, ``--start running``, each
tree's code on PYTHONPATH, this venv's Python, ``OCC_PURE=1``: the pure build) run for the same
seconds under the same load, no clients and no hog. Prints each daemon's CPU share and tick
compute time p50 from their ``--stats`` files.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

trees = [Path(a).resolve() for a in sys.argv[1:3]]
duration = float(sys.argv[3]) if len(sys.argv) > 3 else 30.0
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tools.loopback import pair_configs, stop_processes, wait_port, write_yaml  # noqa: E402

out = Path(tempfile.mkdtemp(prefix="occ-ab-side-"))
procs: list[subprocess.Popen[bytes]] = []
try:
    for n, root in enumerate(trees):
        slave, master, ports = pair_configs(
            root / "configs" / "slave.yaml", root / "configs" / "master.yaml"
        )
        env = dict(os.environ, PYTHONPATH=str(root), OCC_PURE="1")
        for role, cfg, port in (("slave", slave, "slave_tcp"), ("master", master, "master_tcp")):
            write_yaml(out / f"{n}{role}.yaml", cfg)
            cmd = [
                sys.executable,
                "-m",
                "occ.cli",
                str(out / f"{n}{role}.yaml"),
                "--start",
                "running",
                "--stats",
                str(out / f"{n}{role}.json"),
                "--log-level",
                "WARNING",
            ]
            procs.append(subprocess.Popen(cmd, env=env, cwd=root))
            if not wait_port(ports[port], 30.0, procs[-1]):
                raise SystemExit(f"{root}: {role} did not start")
    time.sleep(duration)
    rss = {}  # resident memory at the end (kB), before the daemons are stopped
    for i, proc in enumerate(procs):
        try:
            status = Path(f"/proc/{proc.pid}/status").read_text()
            rss[i] = int(
                next(ln for ln in status.splitlines() if ln.startswith("VmRSS")).split()[1]
            )
        except (OSError, StopIteration, ValueError):
            rss[i] = 0
finally:
    stop_processes(procs)
for n, root in enumerate(trees):
    s = json.loads((out / f"{n}slave.json").read_text())
    m = json.loads((out / f"{n}master.json").read_text())
    print(
        f"{str(root):40s} slave {s['cpu_percent']:5.2f} %  master {m['cpu_percent']:5.2f} %  "
        f"compute p50 slave {s['compute_us']['p50']:5.1f} µs  master {m['compute_us']['p50']:5.1f}"
        f" µs  late p99.9 slave {s['lateness_us']['p99_9']:6.1f} µs  master "
        f"{m['lateness_us']['p99_9']:6.1f} µs  RSS {rss.get(2 * n, 0) / 1024:5.1f}/"
        f"{rss.get(2 * n + 1, 0) / 1024:5.1f} MB  {s['final_state']}/{m['final_state']}"
    )
