#!/usr/bin/env python3
"""The slave daemon's loop under full load, and the teleoperation latencies.

Load (issue "occ core", section 6): the slave occd with recording on; the master occd in another
process streaming POSITION at 500 Hz over UDP; two TCP clients (Slicer stand-ins) receiving the
10 Hz TRANSFORMs. Runs for --duration seconds (default 60) and reports, from the daemons' own
statistics JSON and the stand-ins:

- slave loop lateness p50 / p99 / p99.9 / max, ticks > 1 ms late, overruns, CPU %;
- master sample -> slave driver write latency p50 / p99 (master's POSITION timestamp to the
  slave tick whose write used it; both on this machine's wall clock);
- the tip stream at each stand-in: rate and interval jitter;
- losses seen by the slave's loss monitor.

Examples::

    python benchmarks/bench_daemon.py --duration 60
    python benchmarks/bench_daemon.py --duration 60 --no-fifo      # SCHED_OTHER for comparison
    python benchmarks/bench_daemon.py --duration 60 --record-at-run-time  # StartRecording live
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

from loopback import free_port, pair_configs, stop_processes, wait_port, write_yaml  # noqa: E402
from slicer_standin import SlicerStandIn  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--duration", type=float, default=60.0)
    p.add_argument("--no-fifo", action="store_true", help="run both loops SCHED_OTHER")
    p.add_argument("--cpu", type=int, default=None, help="pin the slave loop to this CPU")
    p.add_argument("--spin-us", type=float, default=None, help="override robot.realtime.spin_us")
    p.add_argument(
        "--switch-us",
        type=float,
        default=None,
        help="override robot.realtime.switch_interval_us (both daemons)",
    )
    p.add_argument(
        "--phase-lock-us",
        type=float,
        default=None,
        help="override the slave controller's phase_lock_us (negative = off)",
    )
    p.add_argument(
        "--no-load",
        action="store_true",
        help="the slave alone (no master stream, no TCP clients): the baseline",
    )
    p.add_argument(
        "--cpu-load-only",
        action="store_true",
        help="the master runs (same CPU use) but streams to an unused port, and no "
        "TCP clients connect: separates machine load from the slave's own I/O",
    )
    p.add_argument("--no-record", action="store_true", help="the slave without recording")
    p.add_argument(
        "--record-at-run-time",
        action="store_true",
        help="the slave starts without recording; the operator sends StartRecording once the "
        "load runs and StopRecording at the end (PLUS-style, occ/recording/control.py)",
    )
    p.add_argument(
        "--thread-streams",
        action="store_true",
        help="robot.realtime.poll_streams false: an interface thread receives the stream",
    )
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="occ-bench-"))
    out.mkdir(parents=True, exist_ok=True)
    slave, master, ports = pair_configs()
    tcp, mtcp = ports["slave_tcp"], ports["master_tcp"]
    if args.cpu_load_only:  # the master streams to a port nobody reads
        for itf in master["interfaces"]:
            if itf["transport"] == "udp":
                itf["remote"] = f"127.0.0.1:{free_port(socket.SOCK_DGRAM)}"
    if args.no_fifo:
        slave["robot"]["realtime"]["fifo_priority"] = None
        master["robot"]["realtime"]["fifo_priority"] = None
    if args.cpu is not None:
        slave["robot"]["realtime"]["cpu"] = args.cpu
    if args.phase_lock_us is not None:
        slave["controller"]["params"]["phase_lock_us"] = (
            None if args.phase_lock_us < 0 else args.phase_lock_us
        )
    if args.switch_us is not None:
        slave["robot"]["realtime"]["switch_interval_us"] = args.switch_us
        master["robot"]["realtime"]["switch_interval_us"] = args.switch_us
    if args.spin_us is not None:
        slave["robot"]["realtime"]["spin_us"] = args.spin_us
        master["robot"]["realtime"]["spin_us"] = args.spin_us
    if args.thread_streams:
        slave["robot"]["realtime"]["poll_streams"] = False
    if args.record_at_run_time:
        slave["recording"] = {
            "path": None,
            "rate_hz": 100,
            "include_messages": True,
            "directory": str(out),
        }
    elif not args.no_record:
        slave["recording"] = {
            "path": str(out / "slave.igtl"),
            "rate_hz": 100,
            "include_messages": True,
        }
    slave["stats"] = {"log_every_s": 3600.0}
    write_yaml(out / "slave.yaml", slave)
    write_yaml(out / "master.yaml", master)

    def occd(name: str) -> subprocess.Popen[bytes]:
        return subprocess.Popen(
            [
                sys.executable,
                "-m",
                "occ.cli",
                str(out / f"{name}.yaml"),
                "--start",
                "running",
                "--stats",
                str(out / f"{name}.json"),
                "--log-level",
                "WARNING",
            ],
            cwd=ROOT,
            stderr=open(out / f"{name}.log", "wb"),
        )

    procs = [occd("slave")]
    clients: list[SlicerStandIn] = []
    operator: SlicerStandIn | None = None
    run_time_recording: dict[str, str] = {}
    extra: list[SlicerStandIn] = []  # an operator only for the run-time recording

    def ask(name: str, xml: str = "") -> str:
        """An operator command and its reply (Status: Message), for the run-time recording."""
        op = operator
        if op is None:
            op = SlicerStandIn("127.0.0.1", ports["slave_op"]).start()
            extra.append(op)
        op.connected.wait(5.0)
        reply = op.wait_reply(op.send_command(name, xml), 20.0)
        if reply is None:
            return "no reply"
        return f"{reply.metadata.get('Status')}: {reply.metadata.get('Message')}"

    try:
        if not wait_port(tcp):
            print("slave did not start; see", out / "slave.log", file=sys.stderr)
            return 1
        if not args.no_load:
            procs.append(occd("master"))
            if not wait_port(mtcp):
                print("master did not start", file=sys.stderr)
                return 1
            clients = (
                []
                if args.cpu_load_only
                else [SlicerStandIn("127.0.0.1", tcp).start() for _ in range(2)]
            )
            for c in clients:
                c.connected.wait(5.0)
            # the operator's console (Slicer's connection is a viewer: it may not send Run)
            operator = (
                None
                if args.cpu_load_only
                else SlicerStandIn("127.0.0.1", ports["slave_op"]).start()
            )
        print(
            f"running {args.duration:.0f} s "
            f"({'SCHED_OTHER' if args.no_fifo else 'SCHED_FIFO where permitted'}); "
            f"files in {out}",
            flush=True,
        )
        if args.record_at_run_time:
            run_time_recording["start"] = ask(
                "StartRecording", '<Command Name="StartRecording" OutputFilename="slave.igtl"/>'
            )
            print("StartRecording:", run_time_recording["start"], flush=True)
        # an operator: a loss stop (e.g. a master stall on this busy VM) is followed by Run
        end = time.monotonic() + args.duration
        seen = 0
        reruns = 0
        while time.monotonic() < end:
            time.sleep(0.05)
            if operator is not None:
                sts = operator.statuses
                for st in sts[seen:]:
                    if st.error_name == "STOPPED":
                        operator.send_command("Run")
                        reruns += 1
                seen = len(sts)
        if args.record_at_run_time:
            run_time_recording["stop"] = ask("StopRecording")
            print("StopRecording:", run_time_recording["stop"], flush=True)
        summaries = [c.summary() for c in clients]
    finally:
        for c in clients + extra + ([operator] if operator is not None else []):
            c.stop()
        stop_processes(procs, timeout=20)
    s = json.loads((out / "slave.json").read_text())
    m = json.loads((out / "master.json").read_text()) if not args.no_load else None
    result = {
        "duration_s": args.duration,
        "fifo": not args.no_fifo,
        "slave_realtime": s.get("realtime"),
        "slave_loop": {
            k: s[k]
            for k in (
                "ticks",
                "lateness_us",
                "compute_us",
                "late_over_1ms",
                "late_over_1ms_percent",
                "overruns",
                "missed_ticks",
                "cpu_percent",
            )
        },
        "no_load": args.no_load,
        "cpu_load_only": args.cpu_load_only,
        "master_loop": (
            {k: m[k] for k in ("ticks", "lateness_us", "late_over_1ms", "cpu_percent")}
            if m
            else None
        ),
        "sample_to_write_us": s.get("controller", {}).get("sample_to_write_us"),
        "loss": s.get("loss"),
        "operator_reruns": reruns if not args.no_load else 0,
        "slave_state_at_end": s.get("state"),
        "udp_in": s["interfaces"]["master"],
        "tip_stream": [x.get("Tip") for x in summaries],
        "run_time_recording": run_time_recording or None,
        "recording_bytes": (out / "slave.igtl").stat().st_size
        if (out / "slave.igtl").exists()
        else 0,
    }
    (out / "result.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
