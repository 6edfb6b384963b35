#!/usr/bin/env python3
"""The slave's loop tail with a recording started and stopped at run time, against none.

One pair of daemons under the full load of bench_daemon.py (the master streaming POSITION at
500 Hz over UDP, two Slicer stand-ins taking the 10 Hz outputs, the slave RUNNING), and one
operator who alternates windows of ``--window`` seconds: *off* (no recording) and *on* (a
``StartRecording`` at the window's start, a ``StopRecording`` at its end: both inside the
window, with the recording of every message and the state at 100 Hz in between). The order
goes off, on, on, off, ... (ABBA) so a drift in the machine's load falls on both. Each window's
lateness percentiles come from two ``GetStats Histogram="lateness"`` snapshots (the histogram of
the ticks in between), so both kinds are measured in the same daemon under the same
conditions, interleaved; a busy shared machine moves both. Prints a row per window, the pooled
p99 / p99.9 of each kind and their ratio, and writes result.json.

    python benchmarks/bench_runtime_recording.py --cycles 6 --window 10
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
sys.path.insert(0, str(ROOT))

from loopback import pair_configs, stop_processes, wait_port, write_yaml  # noqa: E402
from slicer_standin import SlicerStandIn  # noqa: E402

from occ.core.stats import Histogram  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cycles", type=int, default=6, help="ABBA pairs of windows")
    p.add_argument("--window", type=float, default=10.0, help="seconds per window")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="occ-bench-rtrec-"))
    out.mkdir(parents=True, exist_ok=True)
    slave, master, ports = pair_configs()
    slave["recording"] = {
        "path": None,
        "rate_hz": 100,
        "include_messages": True,
        "directory": str(out),
    }
    slave["stats"] = {"log_every_s": 3600.0}
    write_yaml(out / "slave.yaml", slave)
    write_yaml(out / "master.yaml", master)

    def occd(name: str) -> subprocess.Popen[bytes]:
        return subprocess.Popen(
            [sys.executable, "-m", "occ.cli", str(out / f"{name}.yaml"), "--start", "running"]
            + ["--stats", str(out / f"{name}.json"), "--log-level", "WARNING"],
            cwd=ROOT,
            stderr=open(out / f"{name}.log", "wb"),  # noqa: SIM115 - the process owns it
        )

    procs = [occd("slave")]
    clients: list[SlicerStandIn] = []
    rows: list[dict[str, Any]] = []
    pooled: dict[str, dict[int, int]] = {"off": {}, "on": {}}
    try:
        if not wait_port(ports["slave_tcp"]):
            print("slave did not start; see", out / "slave.log", file=sys.stderr)
            return 1
        procs.append(occd("master"))
        if not wait_port(ports["master_tcp"]):
            print("master did not start", file=sys.stderr)
            return 1
        clients = [SlicerStandIn("127.0.0.1", ports["slave_tcp"]).start() for _ in range(2)]
        op = SlicerStandIn("127.0.0.1", ports["slave_op"]).start()
        clients.append(op)
        for c in clients:
            c.connected.wait(5.0)
        seen = [0]

        def ask(name: str, xml: str = "") -> Any:
            reply = op.wait_reply(op.send_command(name, xml), 20.0)
            if reply is None:
                raise RuntimeError(f"no reply to {name}")
            return reply

        def rerun() -> None:
            # an operator: a loss stop (a master stalled on this shared machine) gets a Run
            sts = op.statuses
            for st in sts[seen[0] :]:
                if st.error_name == "STOPPED":
                    op.send_command("Run")
            seen[0] = len(sts)

        def buckets() -> dict[int, int]:
            reply = ask("GetStats", '<Command Name="GetStats" Histogram="lateness"/>')
            snap = json.loads(reply.metadata["Message"])
            return {int(k): int(v) for k, v in snap["lateness_buckets"].items()}

        def wait(seconds: float) -> None:
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                time.sleep(0.05)
                rerun()

        wait(5.0)  # warm up: the master's stream owns the slave, the loop settled
        order = []
        for k in range(args.cycles):
            order += ["off", "on", "on", "off"] if k % 2 == 0 else ["on", "off", "off", "on"]
        print(f"{len(order)} windows of {args.window:.0f} s; files in {out}", flush=True)
        print("window  kind  ticks   p99 us  p99.9 us  reply", flush=True)
        for i, kind in enumerate(order):
            before = buckets()
            note = ""
            if kind == "on":
                xml = f'<Command Name="StartRecording" OutputFilename="w{i:02d}"/>'
                r = ask("StartRecording", xml)
                if r.metadata.get("Status") != "SUCCESS":
                    raise RuntimeError(f"StartRecording: {r.metadata}")
            wait(args.window)
            if kind == "on":
                r = ask("StopRecording")
                if r.metadata.get("Status") != "SUCCESS":
                    raise RuntimeError(f"StopRecording: {r.metadata}")
                note = r.metadata.get("Message", "")
            after = buckets()
            diff = {idx: n - before.get(idx, 0) for idx, n in after.items()}
            diff = {idx: n for idx, n in diff.items() if n > 0}
            for idx, n in diff.items():
                pooled[kind][idx] = pooled[kind].get(idx, 0) + n
            h = Histogram.from_buckets(diff)
            p99, p999 = h.percentiles((99.0, 99.9))
            rows.append({"kind": kind, "ticks": h.count, "p99_us": p99, "p99_9_us": p999})
            print(
                f"{i:6d}  {kind:4s}  {h.count:6d}  {p99:7.0f}  {p999:8.0f}  {note[:60]}",
                flush=True,
            )
    finally:
        for c in clients:
            c.stop()
        stop_processes(procs, timeout=20)
    result: dict[str, Any] = {"window_s": args.window, "cycles": args.cycles, "windows": rows}
    for kind in ("off", "on"):
        h = Histogram.from_buckets(pooled[kind])
        p99, p999 = h.percentiles((99.0, 99.9))
        result[kind] = {"ticks": h.count, "p99_us": p99, "p99_9_us": p999}
    off, on = result["off"], result["on"]
    result["ratio_p99_9"] = on["p99_9_us"] / off["p99_9_us"] if off["p99_9_us"] else None
    result["ratio_p99"] = on["p99_us"] / off["p99_us"] if off["p99_us"] else None
    s = json.loads((out / "slave.json").read_text())
    result["slave_cpu_percent"] = s.get("cpu_percent")
    result["slave_final_state"] = s.get("final_state")
    (out / "result.json").write_text(json.dumps(result, indent=2))
    print(
        f"pooled: off p99 {off['p99_us']:.0f} us p99.9 {off['p99_9_us']:.0f} us "
        f"({off['ticks']} ticks); on p99 {on['p99_us']:.0f} us p99.9 {on['p99_9_us']:.0f} us "
        f"({on['ticks']} ticks); on/off p99.9 {result['ratio_p99_9']:.2f}x, "
        f"p99 {result['ratio_p99']:.2f}x"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
