#!/usr/bin/env python3
"""What an operator query costs the control loop.

The slave robot (configs/slave.yaml, simulated drives) is built on a simulated clock and fed
the master's 500 Hz stream; every tenth tick an operator request is queued (parsed on the
calling thread, as the interface threads do) and the tick that handles it is timed against
the ticks that handle none. Replies go nowhere (no sockets). Reports, per request, the extra
time the handling tick took: median and p99 over ``--n`` requests, in µs.

    python benchmarks/bench_operator.py --n 2000
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

import igtl  # noqa: E402
from igtl.transport import Peer  # noqa: E402
from occ.clock import SimClock  # noqa: E402
from occ.loader import load_config  # noqa: E402
from occ.robot import build_robot  # noqa: E402

MASTER = Peer(1, ("127.0.0.1", 40000))
OPERATOR = Peer(2, ("127.0.0.1", 40001))


def requests() -> dict[str, igtl.Message]:
    command = igtl.REGISTRY["COMMAND"]
    get = igtl.REGISTRY["GET_STATUS"]
    return {
        "GetState (COMMAND)": command(command_id=1, command_name="GetState", command="",
                                      device_name="cmd", header_version=2),
        "GetStats (COMMAND)": command(command_id=2, command_name="GetStats", command="",
                                      device_name="cmd", header_version=2),
        "GetStats (STRING CMD_, XML)": igtl.StringMessage('<Command Name="GetStats"/>',
                                                          device_name="CMD_3"),
        "GET_STATUS": igtl.unpack(get(type_name="GET_STATUS").pack()),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--n", type=int, default=2000)
    args = p.parse_args(argv)
    clock = SimClock()
    robot = build_robot(load_config(ROOT / "configs" / "slave.yaml"), clock=clock)
    robot.configure()
    slicer, master = robot.interfaces["slicer"], robot.interfaces["master"]
    slicer.send = lambda msg, peer=None: 1  # type: ignore[method-assign]
    slicer.send_to_peer = lambda msg, peer: True  # type: ignore[method-assign]
    robot.state_machine.request("enable")
    robot.state_machine.request("run")
    k = 0
    seq = 0

    def tick() -> float:
        nonlocal k, seq
        now = k * 0.001
        clock.set(now)
        if k % 2 == 0:
            seq += 1
            master._on_message(MASTER, igtl.PositionMessage(
                (0.0, 50.0, 270.0), (0.0, 0.0, 0.0, 1.0), 24, device_name="Master",
                header_version=2, message_id=seq, metadata={"run": "1", "clutch": "0"}))
        t0 = time.perf_counter()
        robot.tick(now, k)
        k += 1
        return (time.perf_counter() - t0) * 1e6

    for _ in range(500):
        tick()
    result = {}
    for name, msg in requests().items():
        base, with_req = [], []
        for _ in range(args.n):
            for _ in range(9):  # an operator console asking 100 times a second
                base.append(tick())
            slicer._on_message(OPERATOR, msg)  # parsed here, on the "interface thread"
            with_req.append(tick())
        extra = sorted(w - statistics.median(base) for w in with_req)
        result[name] = {
            "tick_without_us_p50": round(statistics.median(base), 1),
            "extra_us_p50": round(extra[len(extra) // 2], 1),
            "extra_us_p99": round(extra[int(len(extra) * 0.99)], 1),
        }
    robot.shutdown()
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
