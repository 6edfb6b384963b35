#!/usr/bin/env python3
"""What an operator query costs the control loop.

The slave robot (configs/slave.yaml, simulated drives) is built on a simulated clock and fed
the master's 500 Hz stream on in-process interfaces (occ_testkit.testing.SimRobot); every tenth tick
an operator request arrives on the operator interface (parsed on the sending thread, as the
interface threads do) and the tick that handles it is timed against the ticks that handle
none. Replies go to the asking peer, through the codec. Reports, per request, the extra
time the handling tick took: median and p99 over ``--n`` requests, in µs.

    python benchmarks/bench_operator.py --n 2000
    python benchmarks/bench_operator.py --n 300 --config configs/collab/slave.yaml --stream mentor

``all_ticks_us_p99`` is the p99 of every tick while that request flows: the worker thread's
share (GetStats, GetStateTable are built there) shows up in the ticks after the handling one.
With a State Data Table configured, ``GetStateTable`` is asked too, last, as a monitoring
client polls it: the last 0.1 s, ten times a second (every 100th tick); each series starts
once the worker has finished the previous one's jobs.
"""

from __future__ import annotations

import argparse
import gc
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

import igtl  # noqa: E402
from occ_testkit.testing import SimRobot  # noqa: E402


def requests(table: bool = False) -> dict[str, igtl.Message]:
    command = igtl.REGISTRY["COMMAND"]
    get = igtl.REGISTRY["GET_STATUS"]
    extra = (
        {
            "GetStateTable 0.1 s at 10 Hz (COMMAND)": command(
                command_id=4,
                command_name="GetStateTable",
                command='<Command Name="GetStateTable" Seconds="0.1"/>',
                device_name="cmd",
                header_version=2,
            )
        }
        if table
        else {}
    )
    return {
        "GetState (COMMAND)": command(
            command_id=1, command_name="GetState", command="", device_name="cmd", header_version=2
        ),
        "GetStats (COMMAND)": command(
            command_id=2, command_name="GetStats", command="", device_name="cmd", header_version=2
        ),
        "GetStats (STRING CMD_, XML)": igtl.StringMessage(
            '<Command Name="GetStats"/>', device_name="CMD_3"
        ),
        "GET_STATUS": igtl.unpack(get(type_name="GET_STATUS").pack()),
        **extra,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--n", type=int, default=2000)
    p.add_argument("--config", default=str(ROOT / "configs" / "slave.yaml"))
    p.add_argument("--stream", default="master", help="the interface the master stream is on")
    args = p.parse_args(argv)
    # the robot on in-process interfaces: a send is delivered (and a request parsed) at once,
    # on the sender's thread, as an interface thread would; replies go to the asking peer
    with SimRobot(args.config) as sim:
        master = sim.peer(args.stream, address=("127.0.0.1", 40000))
        # replies are decoded and dropped: a peer keeping thousands would make the garbage
        # collector's pauses, not the request, the tail of this benchmark
        operator = sim.peer("operator", address=("127.0.0.1", 40001), on_message=lambda m: None)
        sim.robot.state_machine.request("enable")
        sim.robot.state_machine.request("run")
        seq = 0

        def tick() -> float:
            nonlocal seq
            if sim.k % 2 == 0:
                seq += 1
                master.send_position((0.0, 50.0, 270.0), seq=seq)
            t0 = time.perf_counter()
            sim.tick()
            return (time.perf_counter() - t0) * 1e6

        gc.collect()
        gc.freeze()  # as the daemon does (robot.realtime.gc: freeze)
        for _ in range(500):
            tick()
        result = {}
        for name, msg in requests(sim.robot.state_table is not None).items():
            while not sim.robot.worker._jobs.empty():  # the previous series' jobs done
                time.sleep(0.01)
            every = 100 if name.startswith("GetStateTable") else 10
            base, with_req = [], []
            for _ in range(args.n):
                for _ in range(every - 1):  # an operator console asking 100 times a second
                    base.append(tick())
                operator.send(msg)  # parsed here, on the "interface thread"
                with_req.append(tick())
            extra = sorted(w - statistics.median(base) for w in with_req)
            result[name] = {
                "tick_without_us_p50": round(statistics.median(base), 1),
                "extra_us_p50": round(extra[len(extra) // 2], 1),
                "extra_us_p99": round(extra[int(len(extra) * 0.99)], 1),
                "all_ticks_us_p99": round(
                    sorted(base + with_req)[int(len(base + with_req) * 0.99)], 1
                ),
            }
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
