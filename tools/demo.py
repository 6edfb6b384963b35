#!/usr/bin/env python3
"""The demo: slave + master daemons + a 3D Slicer stand-in, on simulated hardware, on loopback.

1. starts ``occd configs/slave.yaml`` and ``occd configs/master.yaml`` (both ``--start running``);
2. connects the Slicer stand-in to the slave (TCP 18944) like SlicerOpenIGTLink does;
3. shows a live status line once a second (the slave's state, packet rate and losses, loop
   timing, asked over IGTL with the operator command ``GetStats``) and the tip as Slicer sees it;
4. stops after ``--duration`` seconds (default 20) or on Ctrl-C, stops both daemons with SIGINT
   (they stop their drivers and write their statistics), and prints a summary.

``--kill-master-after S`` kills the master process (SIGKILL) after S seconds, to show the slave's
loss monitor stopping the robot and alerting the operator.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

from loopback import stop_processes, wait_port  # noqa: E402
from slicer_standin import SlicerStandIn  # noqa: E402


def occd(config: str, stats: Path, extra: list[str]) -> subprocess.Popen[bytes]:
    cmd = [
        sys.executable,
        "-m",
        "occ.cli",
        str(ROOT / "configs" / config),
        "--start",
        "running",
        "--stats",
        str(stats),
        "--log-level",
        "WARNING",
        *extra,
    ]
    return subprocess.Popen(cmd, cwd=ROOT)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--duration", type=float, default=20.0, help="seconds (default 20; 0 = until Ctrl-C)"
    )
    p.add_argument("--kill-master-after", type=float, default=None, metavar="S")
    p.add_argument("--record", type=Path, default=None, help="record the slave to this file")
    p.add_argument("--out", type=Path, default=None, help="folder for statistics JSON")
    args = p.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="occ-demo-"))
    out.mkdir(parents=True, exist_ok=True)
    for port in (18944, 18945, 18947):
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                print(
                    f"demo: port {port} is already in use (another demo running?)", file=sys.stderr
                )
                return 1
    slave_extra = ["--record", str(args.record)] if args.record else []
    slave = occd("slave.yaml", out / "slave-stats.json", slave_extra)
    procs = [slave]
    standin = None
    operator = None
    interrupted = False
    try:
        if not wait_port(18944, 15.0):
            print("demo: the slave did not start", file=sys.stderr)
            return 1
        master = occd("master.yaml", out / "master-stats.json", [])
        procs.append(master)
        if not wait_port(18945, 15.0):
            print("demo: the master did not start", file=sys.stderr)
            return 1
        standin = SlicerStandIn("127.0.0.1", 18944).start()
        # the status line is an operator's view (Slicer's port is a viewer: no sequence numbers)
        operator = SlicerStandIn("127.0.0.1", 18947).start()
        if not standin.connected.wait(5.0) or not operator.connected.wait(5.0):
            print("demo: the Slicer stand-in could not connect", file=sys.stderr)
            return 1
        print(
            f"demo: slave (TCP 18944 Slicer, 18947 operators, UDP 18946) and master (TCP 18945) "
            f"running; "
            f"statistics in {out}",
            flush=True,
        )
        t0 = time.monotonic()
        killed = False
        while args.duration <= 0 or time.monotonic() - t0 < args.duration:
            time.sleep(1.0)
            if (
                args.kill_master_after is not None
                and not killed
                and time.monotonic() - t0 >= args.kill_master_after
            ):
                master.send_signal(signal.SIGKILL)
                killed = True
                print("\ndemo: master killed (SIGKILL)", flush=True)
            print("\r" + live_line(standin, operator) + " " * 4, end="", flush=True)
            for proc in procs:
                if proc.poll() is not None and not (killed and proc is master):
                    print(f"\ndemo: a daemon exited with {proc.returncode}", file=sys.stderr)
                    return 1
        print()
    except KeyboardInterrupt:
        interrupted = True
        print()
    finally:
        summary = standin.summary() if standin is not None else {}
        if standin is not None:
            standin.stop()
        if operator is not None:
            operator.stop()
        stop_processes(procs)
    print(
        "Slicer stand-in saw:",
        json.dumps({k: v for k, v in summary.items() if not k.startswith("_")}, indent=1),
    )
    for s in summary.get("_statuses", []):
        print("  STATUS", s)
    for name in ("slave", "master"):
        f = out / f"{name}-stats.json"
        if f.exists():
            d = json.loads(f.read_text())
            lat = d["lateness_us"]
            state = d.get("final_state", d.get("state"))
            print(
                f"{name}: {d['ticks']} ticks, state {state}, lateness p50 {lat['p50']:.0f} "
                f"p99 {lat['p99']:.0f} max {lat['max']:.0f} us, cpu {d['cpu_percent']:.0f}%"
            )
            if state != "RUNNING" or d.get("last_alert"):
                print(f"  {name} ended {stopped_hint(state, d.get('last_alert', ''))}")
            if name == "slave" and "loss" in d:
                print(f"  loss monitor: {json.dumps(d['loss'])}")
            if name == "slave" and "sample_to_write_us" in d.get("controller", {}):
                print(f"  master sample -> slave write: {d['controller']['sample_to_write_us']}")
    return 130 if interrupted else 0


_last_rx: list[float] = []  # (time, count) of the previous status line, for the packet rate


def live_line(standin: SlicerStandIn, operator: SlicerStandIn) -> str:
    cid = operator.send_command("GetStats")
    reply = operator.wait_reply(cid, timeout=1.0)
    tip = standin.last.get("Tip")
    tip_txt = (
        "tip " + " ".join(f"{v:7.2f}" for v in tip.translation) + " mm"
        if tip is not None
        else "tip -"
    )
    if reply is None or reply.metadata.get("Status") != "SUCCESS":
        return f"slave: no answer | {tip_txt}"
    try:
        import re

        m = re.search(r'Message="([^"]*)"', reply.command)  # type: ignore[attr-defined]
        raw = m.group(1).replace("&quot;", '"').replace("&amp;", "&") if m else ""
        d = json.loads(raw or reply.metadata.get("Message", "{}"))
    except (ValueError, AttributeError):
        return f"slave: unreadable stats | {tip_txt}"
    loss = d.get("loss", {})
    ctrl = d.get("controller", {})
    lat = d["lateness_us"]
    master = d.get("interfaces", {}).get("master", {})
    now, rx = time.monotonic(), float(master.get("received", 0))
    rate = (rx - _last_rx[1]) / (now - _last_rx[0]) if _last_rx and now > _last_rx[0] else 0.0
    _last_rx[:] = [now, rx]
    tip_rate = standin.summary().get("Tip", {}).get("rate_hz") or 0.0
    line = (
        f"slave {d['state']:8s} | master {rate:5.0f} Hz lost {loss.get('lost_total', 0)} "
        f"holds {loss.get('holds', 0)} resumed {loss.get('resumes', 0)} "
        f"stops {loss.get('trips', 0)} | "
        f"loop p99 {lat['p99']:.0f}us max {lat['max']:.0f}us | seq {ctrl.get('last_seq')} | "
        f"{tip_txt} @ {tip_rate:.1f} Hz"
    )
    if d["state"] != "RUNNING":
        # never silently stuck: say why, and how to go on
        line += f"\n  {stopped_hint(d['state'], d.get('last_alert', ''))}"
    return line


RESUME = {
    "STOPPED": ["Run"],
    "FAULT": ["Reset", "Enable", "Run"],
    "ESTOP": ["Reset", "Enable", "Run"],
    "READY": ["Enable", "Run"],
    "ENABLED": ["Run"],
}


def stopped_hint(state: str, cause: str) -> str:
    """What stopped the slave and the commands that resume it."""
    steps = RESUME.get(state, [])
    how = "; ".join(f"igtl send 127.0.0.1:18947 --type COMMAND --command-name {c}" for c in steps)
    return f"{state}: {cause or 'no alert recorded'}" + (f" -> to resume: {how}" if how else "")


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
