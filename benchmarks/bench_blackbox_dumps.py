"""The loop's lateness while its black box is dumped: two slave+master pairs side by side.

    python benchmarks/bench_blackbox_dumps.py [SECONDS] [EVERY_S]

Both pairs run this tree's shipped configs (free loopback ports, ``--start running``, the pure
build) under the same load for SECONDS (default 90). After the black box's ring is full (35 s),
an operator asks the first pair's slave to ``DumpBlackBox`` every EVERY_S seconds (default 3):
each dump copies 30 s of rows and events out of the live ring, rebuilds the stream items and
writes about 20 MB, on the writer thread, handing the interpreter lock back every chunk. The
second pair is never dumped. Printed: each slave's lateness p50, p99, p99.9 and max, ticks
late over 1 ms, CPU, and the dumps written (with the time the writer took for each, from the
reply and the alert).
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
from slicer_standin import SlicerStandIn  # noqa: E402

from tools.loopback import pair_configs, stop_processes, wait_port, write_yaml  # noqa: E402

duration = float(sys.argv[1]) if len(sys.argv) > 1 else 90.0
every = float(sys.argv[2]) if len(sys.argv) > 2 else 3.0
FULL_S = 35.0  # the ring (30 s) full before the first dump

out = Path(tempfile.mkdtemp(prefix="occ-bb-dumps-"))
procs: list[subprocess.Popen[bytes]] = []
op_ports: list[int] = []
env = dict(os.environ, PYTHONPATH=str(ROOT), OCC_PURE="1")
dumps: list[dict[str, object]] = []
try:
    for n in range(2):
        slave, master, ports = pair_configs()
        slave["black_box"] = {"dir": str(out / f"bb{n}")}
        op_ports.append(ports["slave_op"])
        for role, cfg, port in (("slave", slave, "slave_op"), ("master", master, "master_tcp")):
            write_yaml(out / f"{n}{role}.yaml", cfg)
            cmd = [sys.executable, "-m", "occ.cli", str(out / f"{n}{role}.yaml")]
            cmd += ["--start", "running", "--stats", str(out / f"{n}{role}.json")]
            cmd += ["--log-level", "WARNING"]
            procs.append(subprocess.Popen(cmd, env=env, cwd=ROOT))
            if not wait_port(ports[port], 30.0, procs[-1]):
                raise SystemExit(f"pair {n}: {role} did not start")
    t0 = time.monotonic()
    op = SlicerStandIn("127.0.0.1", op_ports[0]).start()
    if not op.connected.wait(10.0):
        raise SystemExit("the operator could not connect")
    time.sleep(max(0.0, FULL_S - (time.monotonic() - t0)))
    while time.monotonic() - t0 < duration - every:
        sent = time.monotonic()
        cid = op.send_command("DumpBlackBox", '<Command Name="DumpBlackBox" Reason="bench"/>')
        reply = op.wait_reply(cid, timeout=5.0)
        dumps.append({"at_s": round(sent - t0, 1), "reply": getattr(reply, "command", None)})
        time.sleep(max(0.0, every - (time.monotonic() - sent)))
    time.sleep(max(0.0, duration - (time.monotonic() - t0)))
    op.stop()
finally:
    stop_processes(procs)
for n in range(2):
    s = json.loads((out / f"{n}slave.json").read_text())
    late = s["lateness_us"]
    print(
        f"pair {n} ({'dumped' if n == 0 else 'never dumped'}): slave late p50 {late['p50']:.1f} "
        f"p99 {late['p99']:.1f} p99.9 {late['p99_9']:.1f} max {late['max']:.1f} µs; "
        f"late>1ms {s['late_over_1ms']}; cpu {s['cpu_percent']:.2f} %; {s['final_state']}"
    )
written = sorted((out / "bb0").glob("slave-*/manifest.json"))
print(f"dumps asked {len(dumps)}, written {len(written)} ({out / 'bb0'})")
