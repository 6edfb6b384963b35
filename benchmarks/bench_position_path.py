"""Benchmark: what one master POSITION costs the slave's tick, from its UDP socket to the
controller: Python function calls, crossings between source files, and time.

    python benchmarks/bench_position_path.py                 # 2,000 POSITIONs, calls and µs
    python benchmarks/bench_position_path.py --trace         # also print the call path

The shipped slave (configs/slave.yaml on free ports, the daemon's clock, RUNNING) with its master
interface's real UDP socket, polled by the tick as in the daemon. A socket in this process
sends a POSITION (v2, sequence number, ``run``/``clutch`` metadata, as the master does) before
every other tick; each tick is timed. The per-POSITION figures are the difference between a
tick that reads a datagram and one that does not (the same tick otherwise: the return
channel's output is sent on both, at 500 Hz, on the ticks where the POSITION arrives).

Calls are counted with ``sys.setprofile`` on one tick of each kind: every Python function
entered (C functions apart, counted separately), and every call whose callee lives in another
source file than its caller (a *file crossing*).
"""

from __future__ import annotations

import argparse
import gc
import math
import socket
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import igtl
from occ.clock import RealClock
from occ.core.loader import load_config
from occ.core.robot import build_robot

ROOT = Path(__file__).resolve().parents[1]


def build() -> tuple[Any, RealClock, tuple[str, int]]:
    cfg = load_config(ROOT / "configs" / "slave.yaml")
    ifaces = tuple(i.model_copy(update={"port": 0}) for i in cfg.interfaces)
    cfg = cfg.model_copy(update={"interfaces": ifaces})
    clock = RealClock(spin_us=0.0)
    robot = build_robot(cfg, clock=clock)
    robot.configure()
    robot.activate()
    robot.state_machine.request("enable", "bench")
    robot.state_machine.request("run", "bench")
    return robot, clock, robot.interfaces["master"].address


def position(clock: RealClock, seq: int) -> bytes:
    t = seq * 0.002
    return igtl.PositionMessage(
        (50 * math.sin(0.2 * math.pi * t), 50 * math.cos(0.2 * math.pi * t), 20.0),
        (0.0, 0.0, 0.0, 1.0),
        24,
        device_name="Master",
        header_version=2,
        message_id=seq,
        timestamp=clock.wall_time(),
        metadata={"run": "1", "clutch": "0"},
    ).pack()


def wait_readable(sock_owner: Any) -> None:
    """Until the datagram sent is in the slave's socket (loopback: at once, almost)."""
    ready = sock_owner.transport._ready
    deadline = time.monotonic() + 0.5
    while ready is not None and not ready(0) and time.monotonic() < deadline:
        time.sleep(0.0001)


class Calls:
    """Function entries and file crossings while ``scope`` (a function name) runs, or all."""

    def __init__(self, scope: str | None = None) -> None:
        self.scope = scope
        self.depth = 0 if scope is None else -1  # -1: outside the scope
        self.py = 0
        self.c = 0
        self.crossings = 0
        self.path: list[str] = []
        self.files: Counter[str] = Counter()

    def __call__(self, frame: Any, event: str, arg: Any) -> None:
        if self.depth < 0:
            if event == "call" and frame.f_code.co_name == self.scope:
                self.depth = 0
            return
        if event == "call":
            self.depth += 1
        elif event == "return":
            self.depth -= 1
            if self.depth < 0 and self.scope is None:
                self.depth = 0
            return
        if event == "call":
            self.py += 1
            here = frame.f_code.co_filename
            back = frame.f_back
            self.files[_short(here)] += 1
            if back is not None and back.f_code.co_filename != here:
                self.crossings += 1
                self.path.append(
                    f"{_short(back.f_code.co_filename)} -> {_short(here)}:{frame.f_code.co_name}"
                )
        elif event == "c_call":
            self.c += 1


def _short(path: str) -> str:
    p = Path(path)
    try:
        return str(p.relative_to(ROOT))
    except ValueError:
        return p.name


def one_tick(robot: Any, clock: RealClock, k: int, profiles: list[Calls]) -> float:
    now = clock.now()
    if profiles:
        sys.setprofile(lambda frame, event, arg: [c(frame, event, arg) for c in profiles])
    t0 = time.perf_counter()
    robot.tick(now, k)
    dt = time.perf_counter() - t0
    if profiles:
        sys.setprofile(None)
    return dt


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=2000)
    p.add_argument("--trace", action="store_true", help="print the file crossings of a POSITION")
    args = p.parse_args()
    robot, clock, address = build()
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    iface = robot.interfaces["master"]
    try:
        k = 0
        with_pos: list[float] = []
        without: list[float] = []
        # the tick with a POSITION and the tick two later (same outputs due), whole and drain
        tick_with, tick_without = Calls(), Calls()
        drain_with, drain_without = Calls("drain"), Calls("drain")
        gc.disable()
        for seq in range(1, args.samples + 51):
            tx.sendto(position(clock, seq), address)
            wait_readable(iface)
            last = seq == args.samples + 50
            dt = one_tick(robot, clock, k, [tick_with, drain_with] if last else [])
            one_tick(robot, clock, k + 1, [])
            dt0 = one_tick(robot, clock, k + 2, [tick_without, drain_without] if last else [])
            one_tick(robot, clock, k + 3, [])
            k += 4
            if seq > 50:  # warm
                with_pos.append(dt)
                without.append(dt0)
        gc.enable()
        ctl = robot.controller.controllers[0]
        assert ctl.samples == args.samples + 50, f"controller saw {ctl.samples} samples"
        with_pos.sort()
        without.sort()
        med = len(with_pos) // 2
        print(
            f"slave, one POSITION through its polled UDP socket ({args.samples} samples, "
            f"state {robot.state.value}, {ctl.samples} followed):"
        )
        for what, a, b in (
            ("the stream drain", drain_with, drain_without),
            ("the whole tick", tick_with, tick_without),
        ):
            print(
                f"  {what}: {a.py - b.py} Python calls per POSITION ({a.py} with one, "
                f"{b.py} without), {a.c - b.c} C calls, {a.crossings - b.crossings} file "
                f"crossings ({a.crossings} with, {b.crossings} without)"
            )
        print(
            f"  tick µs p50 with a POSITION {with_pos[med] * 1e6:.1f}, "
            f"without {without[med] * 1e6:.1f}: {(with_pos[med] - without[med]) * 1e6:.1f} µs "
            "per POSITION (its IK solve included)"
        )
        if args.trace:
            extra = drain_with.files - drain_without.files
            print("  calls per file in the drain (with a POSITION minus without):")
            for name, n in extra.most_common():
                print(f"    {n:4d} {name}")
            print("  file crossings in the drain with a POSITION:")
            for line in drain_with.path:
                print(f"    {line}")
    finally:
        tx.close()
        robot.shutdown()


if __name__ == "__main__":
    main()
