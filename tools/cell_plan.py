#!/usr/bin/env python3
"""Run a cell keyframe set on every arm of a cell as one (issue 40, item 5).

    python tools/cell_plan.py cell-turns.yaml                  # the shipped cell's two arms
    python tools/cell_plan.py SET --member ur5-a=127.0.0.1:18947 --member ur5-b=127.0.0.1:19947
    python tools/cell_plan.py cell-turns.yaml --start          # also start both daemons

Talks to each member's operator port over OpenIGTLink (COMMAND, RTS_COMMAND, NDARRAY), as any
operator client does, and runs occ_testkit/cellplan.py's coordinator: ``KeyframeLoad`` the set
on every member, ``KeyframePlan`` each, ``KeyframeCellPath`` each (its planned path, an NDARRAY
``CellPath``), gives every member the others' paths, ``KeyframeCellCheck`` each (its path against
the others' at the same times: one identity from all, or a refusal naming both arms, both links
and the time), then ``KeyframeAck Plan=N StartAt=<now + --lead> Cell=<identity>`` on every member,
or none. Each member must be RUNNING (``Enable``, ``Run``; ``--start`` starts
configs/cell/ur5-a-keyframe.yaml and ur5-b-keyframe.yaml with ``--start running``). Prints each
step and exits 0 when every member acknowledged, 1 otherwise.
"""

from __future__ import annotations

import argparse
import itertools
import queue
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import igtl  # noqa: E402
from igtl.transport import TCPClient  # noqa: E402
from occ_testkit.cellplan import coordinate  # noqa: E402

SHIPPED = {"ur5-a": "127.0.0.1:18947", "ur5-b": "127.0.0.1:19947"}
CONFIGS = {"ur5-a": "ur5-a-keyframe", "ur5-b": "ur5-b-keyframe"}


class TcpMember:
    """One member's operator port (occ_testkit/cellplan.py ``MemberLink``)."""

    def __init__(self, name: str, address: str, timeout: float) -> None:
        host, port = address.rsplit(":", 1)
        self.name, self.timeout = name, timeout
        self._ids = itertools.count(1)
        self._replies: queue.Queue[Any] = queue.Queue()
        self._arrays: dict[str, Any] = {}
        self._lock = threading.Lock()
        self.connected = threading.Event()
        self.client = TCPClient(
            host, int(port), on_message=self._on, on_connect=self._hello, name=f"cell-plan-{name}"
        )

    def _hello(self, peer: Any) -> None:
        self.client.send(igtl.StatusMessage(header_version=2, metadata={"client": "cell_plan"}))
        self.connected.set()

    def _on(self, peer: Any, msg: Any) -> None:
        if msg.message_type == "RTS_COMMAND":
            self._replies.put(msg)
        elif msg.message_type == "NDARRAY":
            with self._lock:
                self._arrays[msg.device_name] = msg

    def ask(self, command: str, **args: str) -> tuple[bool, str]:
        cid = next(self._ids)
        attrs = "".join(f' {k}="{v}"' for k, v in args.items())
        self.client.send(
            igtl.CommandMessage(
                command_id=cid,
                command_name=command,
                command=f'<Command Name="{command}"{attrs}/>',
                device_name="command",
                header_version=2,
            )
        )
        end = time.monotonic() + self.timeout
        while time.monotonic() < end:
            try:
                msg = self._replies.get(timeout=0.2)
            except queue.Empty:
                continue
            if getattr(msg, "command_id", None) == cid:
                meta = msg.metadata
                return meta.get("Status") == "SUCCESS", meta.get("Message") or meta.get("Error", "")
        return False, f"no reply to {command} within {self.timeout:g} s"

    def last_array(self, device: str) -> Any:
        with self._lock:
            return self._arrays.get(device)

    def give(self, msg: Any) -> None:
        self.client.send(msg)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("set", help="the cell keyframe set, a name in each member's keyframe_dir")
    ap.add_argument("--member", action="append", default=[], help="NAME=HOST:PORT (operator)")
    ap.add_argument("--lead", type=float, default=2.0, help="the common start, s from now")
    ap.add_argument("--timeout", type=float, default=60.0, help="per command, s")
    ap.add_argument("--start", action="store_true", help="start the shipped keyframe cell")
    ap.add_argument("--watch", type=float, default=0.0, help="then print states for S seconds")
    args = ap.parse_args(argv)
    addresses = dict(m.split("=", 1) for m in args.member) if args.member else dict(SHIPPED)
    procs = []
    if args.start:
        for name in addresses:
            cfg = ROOT / "configs" / "cell" / f"{CONFIGS[name]}.yaml"
            procs.append(
                subprocess.Popen(
                    [
                        sys.executable,
                        "-m",
                        "occ.cli",
                        str(cfg),
                        "--start",
                        "running",
                        "--log-level",
                        "WARNING",
                    ],
                    cwd=ROOT,
                )
            )
    members = [TcpMember(n, a, args.timeout) for n, a in addresses.items()]
    try:
        for m in members:
            m.client.start()
            if not m.connected.wait(30.0):
                print(f"{m.name}: no operator port at {addresses[m.name]}")
                return 1
        if args.start:
            time.sleep(3.0)  # --start running: each Run waits for the other to be heard
        out = coordinate(members, args.set, time.time, args.lead)
        for name, command, ok, text in out.replies:
            print(f"{name:8} {command:18} {'ok ' if ok else 'NO '} {text}")
        if not out.ok:
            print(f"not acknowledged: {out.why}")
            return 1
        print(f"cell plan {out.identity} acknowledged by all; starts at {out.start_at:.3f}")
        end = time.monotonic() + args.watch
        while time.monotonic() < end:
            time.sleep(1.0)
            for m in members:
                print(f"{m.name:8} {m.ask('KeyframeList')[1].splitlines()[0]}")
        return 0
    finally:
        for m in members:
            m.client.stop()
        for p in procs:
            p.send_signal(2)
        for p in procs:
            p.wait(10)


if __name__ == "__main__":
    sys.exit(main())
