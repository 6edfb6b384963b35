"""Benchmark: what one control tick costs the shipped slave and master, in simulated time.

    python benchmarks/bench_tick.py                # 20,000 ticks each, best of 5 rounds
    python benchmarks/bench_tick.py --ticks 5000 --rounds 3 --sleep-us 900
    python benchmarks/bench_tick.py --cpu --alternate \
        --robots slave,slave+table,collab-no-table,collab

Robots: ``slave`` and ``master`` (the shipped pair), ``slave+table`` (the slave with a 10 s State
Data Table), ``collab`` (configs/collab/slave.yaml: two master streams, each sample judged by its
own loss monitor, the table on) and ``collab-no-table`` (the same without the table),
``slave-no-bb`` and ``master-no-bb`` (the pair with the black box off: it is on by default, in
every other robot here).

The robots are built from configs/slave.yaml and configs/master.yaml on a SimClock and put
RUNNING; the slave's master stream is a POSITION every other tick (the paper's 500 Hz motion),
sent as a real datagram to the slave's stream socket before the tick, so the tick polls, decodes
and routes it as the daemon does, and answers on its return link (the SlaveTip at 500 Hz) to the
sending socket. The master streams to a socket that answers as the slave does: a SlaveTip every
other tick, which the master decodes and judges (its fixtures' tool). Packing, sending and
reading the robot's datagrams happen outside the timed region. ``--sleep-us`` sleeps between
ticks, as the real loop does: the tick then runs from colder caches, which is what a daemon pays
(the real loop's compute time is 2-4x this benchmark's warm figure on this VM). ``--jitter-us``
starts each tick up to that many µs after its deadline (uniform, seeded), as the real loop's
wake-ups do: code that caches per period (the sim drive's exact step) then sees a new interval
each tick. Garbage collection is off while timing. ``--opcodes N`` counts instead the
interpreter's bytecodes per tick by function (``sys.settrace`` opcode events) and prints the N
largest: where a pure-Python tick spends its work, without a profiler's timing noise.
"""

from __future__ import annotations

import argparse
import gc
import math
import random
import socket
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import igtl
from occ.clock import SimClock
from occ.core.loader import load_config
from occ.core.robot import build_robot

ROOT = Path(__file__).resolve().parents[1]


#: robot -> (config file, stream interfaces fed, state table seconds: None = as configured);
#: the master's interface ``slave`` gets the slave's return stream instead (see ``run``)
ROBOTS: dict[str, tuple[str, tuple[str, ...], float | None]] = {
    "slave": ("slave.yaml", ("master",), None),
    "master": ("master.yaml", ("slave",), None),
    "slave+table": ("slave.yaml", ("master",), 10.0),
    "collab": ("collab/slave.yaml", ("mentor", "trainee"), None),
    "collab-no-table": ("collab/slave.yaml", ("mentor", "trainee"), 0.0),
    "slave+cell": ("slave.yaml", ("master",), None),
    "slave-no-bb": ("slave.yaml", ("master",), None),
    "master-no-bb": ("master.yaml", ("slave",), None),
}
#: robots run with the black box off (``black_box.enabled: false``; it is on in the others)
NO_BLACK_BOX = ("slave-no-bb", "master-no-bb")
#: robots that are a member of a two-member cell (occ/core/cell.py): the other member is a socket
#: of this benchmark sending a heartbeat every 5 ticks (its 5 ms period), as a peer daemon does
CELL_ROBOTS = ("slave+cell",)

#: the slave's return-channel metadata (occ/haptics/returnlink.py): following, RUNNING, its 10:1 map
RETURN_META = {"following": "1", "state": "RUNNING", "map": "0.1,0,0,0,0.1,0,0,0,0.1"}


def run(
    name: str,
    ticks: int,
    sleep_s: float,
    cpu: bool = False,
    jitter_s: float = 0.0,
    opcodes: Counter[str] | None = None,
) -> float:
    """Mean µs per tick of one robot over ``ticks`` ticks (``cpu``: the thread's CPU time
    instead of the elapsed time, less disturbed by other processes on a shared machine).
    ``opcodes``: count the bytecodes each function executes in the ticks into it (the times
    are then meaningless: every bytecode goes through a trace function)."""
    timer = time.thread_time if cpu else time.perf_counter
    file, fed, table = ROBOTS[name]
    cfg = load_config(ROOT / "configs" / file)
    if table is not None:
        st = cfg.state_table.model_copy(update={"seconds": table or None})
        cfg = cfg.model_copy(update={"state_table": st})
    if name in NO_BLACK_BOX:
        bb = cfg.black_box.model_copy(update={"enabled": False})
        cfg = cfg.model_copy(update={"black_box": bb})
    # the peers: one socket per fed interface. An interface with a ``remote`` (the master's
    # link to its slave) sends to that socket, which answers as the slave does (SlaveTip, the
    # return channel); one without (the slave's stream) is sent the master's POSITIONs.
    socks = {}
    for i in fed:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", 0))
        sock.setblocking(False)
        socks[i] = sock
    ifaces = tuple(
        i.model_copy(
            update={
                "port": 0,
                **(
                    {"remote": f"127.0.0.1:{socks[i.name].getsockname()[1]}"}
                    if i.name in socks
                    else {"remote": "127.0.0.1:9"}
                    if i.remote
                    else {}
                ),
            }
        )
        for i in cfg.interfaces
    )
    cfg = cfg.model_copy(update={"interfaces": ifaces})
    peer_beats = None
    if name in CELL_ROBOTS:
        cfg, peer_beats = _cell_member(cfg)
    clock = SimClock()
    robot = build_robot(cfg, clock=clock)
    robot.configure()
    robot.state_machine.request("enable", "bench")
    robot.state_machine.request("run", "bench")
    robot.interfaces.start()  # the sockets, as the daemon's activate (no supervisor)
    if robot.cell is not None:
        robot.cell.start()  # after Run: its guard would wait for the peer's first heartbeat
        robot.cell.link.polled = False  # as on the real clock: the link's I/O thread reads
    senders = []
    for i, sock in socks.items():
        returning = robot.config.interfaces[[c.name for c in robot.config.interfaces].index(i)]
        senders.append((sock, robot.interfaces[i].transport.address, bool(returning.remote)))
    rng = random.Random(1)
    gc.disable()
    total = 0.0
    try:
        for k in range(ticks):
            now = k * 0.001 + rng.uniform(0.0, jitter_s)
            clock.set(now)
            if k % 2 == 0 and senders:
                t = k * 0.001
                forward = igtl.PositionMessage(
                    (50 * math.sin(0.2 * math.pi * t), 50 * math.cos(0.2 * math.pi * t), 20.0),
                    (0.0, 0.0, 0.0, 1.0),
                    24,
                    device_name="Master",
                    header_version=2,
                    message_id=k // 2 + 1,
                    timestamp=clock.wall_time(),
                    metadata={"run": "1", "clutch": "0"},
                ).pack()
                back = igtl.PositionMessage(
                    (5 * math.sin(0.2 * math.pi * t), 5 * math.cos(0.2 * math.pi * t), -40.0),
                    (0.0, 0.0, 0.0, 1.0),
                    28,
                    device_name="SlaveTip",
                    header_version=2,
                    message_id=k // 2 + 1,
                    timestamp=clock.wall_time(),
                    metadata=RETURN_META,
                ).pack()
                for sock, addr, returning in senders:
                    if returning and k == 0:
                        continue  # the master has not streamed yet: a slave would not answer
                    sock.sendto(back if returning else forward, addr)
                    _drain(sock)  # what the robot sent this peer: read, as the peer does
            if peer_beats is not None and k % 5 == 0:
                peer_beats(k, clock.wall_time())
            t0 = timer()
            if opcodes is not None:
                sys.settrace(_opcode_counter(opcodes))
            robot.tick(now, k)
            if opcodes is not None:
                sys.settrace(None)
            total += timer() - t0
            if sleep_s:
                time.sleep(sleep_s)
    finally:
        gc.enable()
        robot.shutdown()
        for sock in socks.values():
            sock.close()
    return total / ticks * 1e6


def _cell_member(cfg: Any) -> tuple[Any, Any]:
    """``cfg`` as member ``slave`` of a cell with one other member, ``peer``: a socket here that
    sends its heartbeat when asked and reads (drops) the robot's."""
    import dataclasses

    from occ.config import CellConfig
    from occ.net.celllink import Beat, pack_beat

    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    peer.setblocking(False)
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    own = probe.getsockname()[1]
    probe.close()
    cell = CellConfig.model_validate(
        {
            "name": "bench",
            "members": [
                {"name": "slave", "address": f"127.0.0.1:{own}"},
                {"name": "peer", "address": f"127.0.0.1:{peer.getsockname()[1]}"},
            ],
        }
    )
    base = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    beat = Beat("bench", "peer", 1, 0, "RUNNING", "", "", 0.0, "", (0.0, 0.35, 0.05), base)

    def send(k: int, wall: float) -> None:
        msg = pack_beat(dataclasses.replace(beat, seq=k // 5 + 1, sent_wall=wall), None)
        peer.sendto(msg.pack(), ("127.0.0.1", own))
        _drain(peer)

    return cfg.model_copy(update={"cell": cell}), send


def _drain(sock: socket.socket) -> None:
    while True:
        try:
            sock.recv(65536)
        except BlockingIOError:
            return


def _opcode_counter(counts: Counter[str]) -> Any:
    """A trace function counting every bytecode by ``file:function``."""

    def trace(frame: Any, event: str, arg: Any) -> Any:
        if event == "call":
            frame.f_trace_opcodes = True
            frame.f_trace_lines = False
        elif event == "opcode":
            code = frame.f_code
            counts[f"{Path(code.co_filename).name}:{code.co_name}"] += 1
        return trace

    return trace


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ticks", type=int, default=20000)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--sleep-us", type=float, default=0.0, help="sleep between ticks")
    p.add_argument("--robots", default="slave,master", help=f"comma-separated, of {list(ROBOTS)}")
    p.add_argument("--jitter-us", type=float, default=0.0, help="late start of each tick, max")
    p.add_argument("--cpu", action="store_true", help="time the thread's CPU, not elapsed time")
    p.add_argument(
        "--alternate", action="store_true", help="round-robin the robots (drift cancels out)"
    )
    p.add_argument(
        "--opcodes",
        type=int,
        default=0,
        metavar="N",
        help="count the bytecodes per tick instead, by function (the N largest; one round)",
    )
    args = p.parse_args()
    names = args.robots.split(",")
    if args.opcodes:
        for name in names:
            counts: Counter[str] = Counter()
            run(name, args.ticks, 0.0, jitter_s=args.jitter_us * 1e-6, opcodes=counts)
            total = sum(counts.values())
            print(f"{name}: {total / args.ticks:.0f} bytecodes per tick ({args.ticks} ticks)")
            for fn, n in counts.most_common(args.opcodes):
                print(f"  {n / args.ticks:8.1f}  {n / total:6.1%}  {fn}")
        return
    results: dict[str, list[float]] = {n: [] for n in names}
    order = (
        [n for _ in range(args.rounds) for n in names]
        if args.alternate
        else [n for n in names for _ in range(args.rounds)]
    )
    for name in order:
        results[name].append(
            run(name, args.ticks, args.sleep_us * 1e-6, args.cpu, args.jitter_us * 1e-6)
        )
    for name in names:
        runs = results[name]
        runs.sort()
        print(
            f"{name:12s} µs/tick: best {runs[0]:.1f}  median {runs[len(runs) // 2]:.1f}  "
            f"({args.rounds} rounds of {args.ticks} ticks, sleep {args.sleep_us:g} µs)"
        )


if __name__ == "__main__":
    main()
