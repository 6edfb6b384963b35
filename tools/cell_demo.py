#!/usr/bin/env python3
"""The cell demo (issue 40): two UR5 slaves 0.6 m apart, each teleoperated by its own master, one
safety (configs/cell/; ``bash scripts/cell``). Three scenarios (``--scenario``):

``circle`` (default)
  the four daemons of configs/cell/ (``--start running``; each slave's Run waits until the other
  slave is heard on the cell link), each slave drawing its master's circle; with
  ``--estop-after``/``--kill-after`` one arm's stop holds the other (below).
``toward``
  the two slaves without their masters: this tool is both masters, streaming POSITION at 500 Hz
  to each (as master-a and master-b do) and moving the two tools toward each other at 100 mm/s;
  both arms stop before they touch (each checks its links against the other's, from the cell's
  heartbeats), the alert naming both links, and the tool prints the clearance they kept.
``elbow``
  ur5-a teleoperated (with master-a) and ur5-b on keyframes (configs/cell/ur5-b-keyframe.yaml):
  ur5-b is given a keyframe that swings its wrist into ur5-a's forearm; ``KeyframePlan`` is
  refused before anything moves, naming both links.

In ``circle``:

1. starts the four daemons;
2. prints once a second each slave's state, what it holds for, and the other as it hears it
   (GetStats ``cell`` over its operator port);
3. with ``--estop-after S``: an operator's EStop on ur5-a after S seconds; ur5-b holds within
   milliseconds (its alert names ur5-a), its Run is refused until ur5-a runs again; after 2 s
   ur5-a is reset and run, then ur5-b; ``--kill-after S`` does the same with SIGKILL (ur5-b holds
   after the 100 ms grace) and a restart;
4. stops after ``--duration`` seconds (default 20; 0 = until Ctrl-C), all four with SIGINT.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

from fixture_e2e import Client  # noqa: E402
from loopback import stop_processes, wait_port  # noqa: E402

CELL = ROOT / "configs" / "cell"
SLAVES = {"ur5-a": 18947, "ur5-b": 19947}
MASTERS = ("master-a", "master-b")


def start(name: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "occ.cli", str(CELL / f"{name}.yaml"), "--start", "running",
         "--log-level", "WARNING"],
        cwd=ROOT,
    )  # fmt: skip


def line(name: str, st: dict[str, Any]) -> str:
    cell = st.get("cell") or {}
    held = "; ".join(f"{o}: {w}" for o, w in (cell.get("latched") or {}).items()) or "-"
    others = ", ".join(
        f"{n} {m.get('state')} ({m.get('heard_ms_ago')} ms)"
        for n, m in (cell.get("members") or {}).items()
    )
    return f"{name}: {st.get('state'):8s} holding for: {held:40.40s} hears {others}"


#: ur5-b's keyframe into ur5-a's forearm (ur5-a at home; tests/occ/test_cell_arms.py's geometry)
ELBOW = "2.8 -1.4 1.1 -0.8 -1.57 0.0"


def connect(procs: dict[str, subprocess.Popen[bytes]], names: Any) -> dict[str, Client]:
    clients = {}
    for n in names:
        port = SLAVES[n]
        if not wait_port(port, 30.0, procs[n]):
            raise RuntimeError(f"{n} did not start")
        clients[n] = Client(port)
        clients[n].client.start()
        clients[n].connected.wait(10.0)
    return clients


def toward(seconds: float) -> int:
    """Both slaves, this tool their masters: the tools driven toward each other."""
    import socket

    import igtl

    procs = {n: start(n) for n in SLAVES}
    clients: dict[str, Client] = {}
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        clients = connect(procs, SLAVES)
        streams = {"ur5-a": (18946, +1.0), "ur5-b": (19946, -1.0)}
        t0, seq = time.monotonic(), 0
        next_print = 1.0
        while (now := time.monotonic() - t0) < seconds:
            seq += 1
            # the first 2 s still (both start following), then 200 mm/s of the master each way
            x = max(0.0, now - 2.0) * 200.0
            for _name, (port, sign) in streams.items():
                msg = igtl.PositionMessage(
                    (sign * x, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 24, device_name="Master",
                    header_version=2, message_id=seq, metadata={"run": "1", "clutch": "0"},
                )  # fmt: skip
                sock.sendto(msg.pack(), ("127.0.0.1", port))
            if now >= next_print:
                next_print += 1.0
                for n, c in clients.items():
                    print(f"{now:5.1f} s  " + line(n, c.stats(timeout=2.0)), flush=True)
            time.sleep(0.002)
        for n, c in clients.items():
            st = c.stats(timeout=2.0)
            print(f"{n}: {st['state']}; last alert: {st.get('last_alert')}")
        return 0
    finally:
        sock.close()
        for c in clients.values():
            c.client.stop()
        stop_processes(procs.values())


def elbow() -> int:
    """ur5-a teleoperated, ur5-b on keyframes given a plan into ur5-a's forearm: refused."""
    names = {"ur5-a": "ur5-a", "master-a": "master-a", "ur5-b": "ur5-b-keyframe"}
    procs = {n: start(cfg) for n, cfg in names.items()}
    clients: dict[str, Client] = {}
    try:
        clients = connect(procs, ("ur5-a", "ur5-b"))
        b = clients["ur5-b"]
        time.sleep(1.0)
        text = f'<Command Name="KeyframeAdd" T="4" Pose="{ELBOW}" Space="joint"/>'
        b._ask("KeyframeAdd", text)
        time.sleep(0.5)
        cid = b._ask("KeyframePlan", "")
        reply = b._reply(
            "KeyframePlan",
            lambda m: m.message_type == "RTS_COMMAND" and getattr(m, "command_id", None) == cid,
            60.0,
        )
        meta = dict(reply.metadata)
        print(f"ur5-b KeyframePlan (wrist toward ur5-a's elbow): {meta.get('Status')}")
        print(f"    {meta.get('Error') or meta.get('Message')}")
        return 0 if meta.get("Status") == "FAIL" else 1
    finally:
        for c in clients.values():
            c.client.stop()
        stop_processes(procs.values())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", choices=("circle", "toward", "elbow"), default="circle")
    p.add_argument("--duration", type=float, default=20.0, help="seconds (0 = until Ctrl-C)")
    p.add_argument("--estop-after", type=float, default=None, metavar="S")
    p.add_argument("--kill-after", type=float, default=None, metavar="S")
    args = p.parse_args(argv)
    if args.scenario == "toward":
        return toward(args.duration if args.duration > 0 else 8.0)
    if args.scenario == "elbow":
        return elbow()
    procs = {n: start(n) for n in (*SLAVES, *MASTERS)}
    clients: dict[str, Client] = {}
    code = 0
    try:
        for n, port in SLAVES.items():
            if not wait_port(port, 30.0, procs[n]):
                print(f"{n} did not start", file=sys.stderr)
                return 1
            clients[n] = Client(port)
            clients[n].client.start()
            clients[n].connected.wait(10.0)
        t0 = time.monotonic()
        fault_at = args.estop_after if args.estop_after is not None else args.kill_after
        fault_done = recovered = False
        while args.duration <= 0 or time.monotonic() - t0 < args.duration:
            time.sleep(1.0)
            now = time.monotonic() - t0
            if fault_at is not None and not fault_done and now >= fault_at:
                fault_done = True
                if args.estop_after is not None:
                    print(f"--- {now:5.1f} s: EStop on ur5-a", flush=True)
                    clients["ur5-a"].command("EStop")
                else:
                    print(f"--- {now:5.1f} s: kill -9 ur5-a", flush=True)
                    clients["ur5-a"].connected.clear()
                    procs["ur5-a"].kill()
            elif fault_done and not recovered and now >= fault_at + 2.0:  # type: ignore[operator]
                recovered = True
                reply = clients["ur5-b"].command("Run")
                print(f"--- ur5-b Run before ur5-a runs: {reply.get('Status')} "
                      f"({reply.get('Error', '')})", flush=True)  # fmt: skip
                if args.kill_after is not None:
                    procs["ur5-a"] = start("ur5-a")
                    clients["ur5-a"].connected.wait(20.0)
                    time.sleep(1.0)
                else:
                    for cmd in ("Reset", "Enable", "Run"):
                        clients["ur5-a"].command(cmd)
                time.sleep(0.1)
                reply = clients["ur5-b"].command("Run")
                print(f"--- ur5-a runs again; ur5-b Run: {reply.get('Status')}", flush=True)
            for n, c in clients.items():
                try:
                    print(f"{now:5.1f} s  " + line(n, c.stats(timeout=2.0)), flush=True)
                except TimeoutError:
                    print(f"{now:5.1f} s  {n}: no answer", flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        for c in clients.values():
            c.client.stop()
        stop_processes(procs.values())
    return code


if __name__ == "__main__":
    sys.exit(main())
