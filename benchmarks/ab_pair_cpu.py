"""CPU of a slave+master pair run from a given source tree: for A/B runs of two versions.

    git worktree add /tmp/wt-old <commit>
    for i in 1 2 3; do
        python benchmarks/ab_pair_cpu.py /tmp/wt-old 15
        python benchmarks/ab_pair_cpu.py . 15
    done

Each run starts the tree's own configs/slave.yaml and configs/master.yaml on free loopback
ports (``--start running``, the tree's code on PYTHONPATH, this venv's Python) for the given
seconds and prints each daemon's CPU share and the slave's tick compute time p50 from their
``--stats`` files. Interleave the two versions: this VM's speed drifts by tens of percent
between minutes, so only runs next to each other compare. ``OCC_PURE=1`` in the environment
runs the tree's pure build (occ/_native.py); the line names the build the slave reported.
"""

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

root = Path(sys.argv[1]).resolve()
dur = float(sys.argv[2])
sys.path.insert(0, str(root))
from tools.loopback import pair_configs, stop_processes, wait_port, write_yaml  # noqa: E402

d = Path(tempfile.mkdtemp(prefix="occ-ab-"))
slave, master, ports = pair_configs(
    root / "configs" / "slave.yaml", root / "configs" / "master.yaml"
)
write_yaml(d / "s.yaml", slave)
write_yaml(d / "m.yaml", master)
env = dict(os.environ, PYTHONPATH=str(root))
py = sys.executable
ps = subprocess.Popen(
    [py, "-m", "occ.cli", str(d / "s.yaml"), "--start", "running", "--stats", str(d / "s.json")],
    env=env,
    cwd=root,
    stdout=subprocess.DEVNULL,
    stderr=subprocess.DEVNULL,
)
pm = subprocess.Popen(
    [py, "-m", "occ.cli", str(d / "m.yaml"), "--start", "running", "--stats", str(d / "m.json")],
    env=env,
    cwd=root,
    stdout=subprocess.DEVNULL,
    stderr=subprocess.DEVNULL,
)
wait_port(ports["slave_tcp"])
wait_port(ports["master_tcp"])
time.sleep(dur)
stop_processes([ps, pm])
s = json.loads((d / "s.json").read_text())
m = json.loads((d / "m.json").read_text())
print(
    f"{root.name:8s} {s.get('build', '?'):8s} "
    f"slave {s['cpu_percent']:.1f} %  master {m['cpu_percent']:.1f} %  "
    f"slave compute p50 {s['compute_us']['p50']}  "
    f"state {s.get('final_state', s.get('state'))}"
)
