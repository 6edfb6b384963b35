"""One-way latency of POSITION over UDP on loopback at 500 Hz, between two processes.

    .venv/bin/python benchmarks/bench_udp_latency.py                     # 10 s at 500 Hz
    .venv/bin/python benchmarks/bench_udp_latency.py --seconds 60 --rate 1000

A sender process (its own ``igtl.transport.UDPEndpoint``) sends header-version-2 POSITION
messages on absolute deadlines. Just before building each message it reads two clocks and puts
them in the message: ``time.monotonic_ns()`` in the metadata entry ``t_mono_ns`` and
``time.time()`` in the header timestamp. The receiving ``UDPEndpoint`` (this process) reads the
same clocks first thing in its ``on_message`` callback. Both processes run on one host, so
CLOCK_MONOTONIC is one clock for both: no synchronisation is needed.

Latency therefore covers: build + pack (CRC) + sendto in the sender, the kernel, the receiver's
wake-up, recvfrom, unpack (CRC verified) and the callback dispatch. The first ``--warmup``
seconds are not counted. The header-timestamp column is the same measurement through the
protocol's 64-bit timestamp (quantised to 2**-32 s, then a float), as a cross-check.
"""

from __future__ import annotations

import argparse
import itertools
import math
import multiprocessing as mp
import platform
import statistics
import sys
import threading
import time
from typing import Any

import igtl
from igtl.transport import UDPEndpoint


def _sender(
    address: tuple[str, int], rate: float, count: int, spin_ns: int, ready: Any, report: Any
) -> None:
    """Child process: send ``count`` POSITION messages at ``rate`` Hz to ``address``; reports
    per message the time from the stamp to ``send`` returning (build + pack + sendto), in us."""
    ep = UDPEndpoint("127.0.0.1", 0, remote=address)
    ep.start()
    period_ns = int(1e9 / rate)
    template = igtl.PositionMessage(
        position=(0.0, 0.0, 0.0), device_name="Master", header_version=2
    )
    ready.set()
    start = time.monotonic_ns() + 50_000_000
    sleep, mono, wall = time.sleep, time.monotonic_ns, time.time
    send_us = [0.0] * count
    try:
        for i in range(count):
            due = start + i * period_ns
            delay = due - spin_ns - mono()
            if delay > 0:
                sleep(delay * 1e-9)
            while mono() < due:  # spin the last spin_ns (none by default)
                pass
            t_mono = mono()
            msg = template.replace(
                position=(i * 0.01, 0.0, 100.0),
                message_id=i,
                metadata={"t_mono_ns": str(t_mono)},
                timestamp=wall(),
            )
            ep.send(msg)
            send_us[i] = (mono() - t_mono) / 1000.0
    finally:
        ep.stop()
        report.put(send_us)


def _percentile(sorted_values: list[float], q: float) -> float:
    """Nearest-rank percentile of an ascending list."""
    k = max(0, min(len(sorted_values) - 1, math.ceil(q / 100 * len(sorted_values)) - 1))
    return sorted_values[k]


def run(rate: float, seconds: float, warmup: float, spin_us: float = 0.0) -> dict[str, Any]:
    count = int(rate * seconds)
    lat_mono: list[float] = []  # microseconds
    lat_wall: list[float] = []
    ids: list[int] = []
    arrival: list[int] = []
    last = threading.Event()
    mono, wall = time.monotonic_ns, time.time

    def on_message(peer: Any, msg: Any) -> None:
        t_mono = mono()
        t_wall = wall()
        lat_mono.append((t_mono - int(msg.metadata["t_mono_ns"])) / 1000.0)
        lat_wall.append((t_wall - msg.timestamp) * 1e6)
        ids.append(msg.message_id)
        arrival.append(t_mono)
        if msg.message_id == count - 1:
            last.set()

    errors: list[BaseException] = []
    receiver = UDPEndpoint(
        "127.0.0.1", 0, on_message=on_message, on_error=lambda peer, exc: errors.append(exc)
    )
    receiver.start()
    ctx = mp.get_context("spawn")
    ready = ctx.Event()
    report = ctx.Queue()
    proc = ctx.Process(
        target=_sender,
        args=(receiver.address, rate, count, int(spin_us * 1000), ready, report),
        daemon=True,
    )
    proc.start()
    try:
        if not ready.wait(30):
            raise RuntimeError("sender process did not start")
        send_us = report.get(timeout=seconds + 30)
        proc.join(30)
        last.wait(1.0)  # the last datagram may still be in flight when the sender exits
    finally:
        receiver.stop()
        if proc.is_alive():
            proc.kill()
    skip = int(rate * warmup)
    keep = [k for k, i in enumerate(ids) if i >= skip]
    mono_us = sorted(lat_mono[k] for k in keep)
    wall_us = sorted(lat_wall[k] for k in keep)
    sender_us = sorted(send_us[i] for i in range(skip, count))
    got = set(ids)
    gaps = [(arrival[k] - arrival[k - 1]) / 1000.0 for k in keep[1:]]
    return {
        "count": count,
        "received": len(ids),
        "lost": count - len(got),
        "reordered": sum(1 for a, b in itertools.pairwise(ids) if b < a),
        "errors": len(errors),
        "measured": len(mono_us),
        "mono": mono_us,
        "wall": wall_us,
        "sender": sender_us,
        "rate": (len(gaps) / (sum(gaps) / 1e6)) if gaps else 0.0,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--rate", type=float, default=500.0, help="messages per second")
    p.add_argument("--seconds", type=float, default=10.0, help="duration of the run")
    p.add_argument("--warmup", type=float, default=0.2, help="seconds not counted at the start")
    p.add_argument(
        "--spin-us",
        type=float,
        default=0.0,
        help="sender: sleep until this many us before each deadline, then spin (keeps its core "
        "awake, as the control loop does; default 0 = plain sleep)",
    )
    args = p.parse_args(argv)

    print(
        f"python {platform.python_version()}, POSITION v2 over UDP 127.0.0.1, "
        f"{args.rate:g} Hz for {args.seconds:g} s (first {args.warmup:g} s not counted), "
        + (f"sender spins the last {args.spin_us:g} us" if args.spin_us else "sender sleeps")
    )
    r = run(args.rate, args.seconds, args.warmup, args.spin_us)
    print(
        f"sent {r['count']}, received {r['received']}, lost {r['lost']}, "
        f"reordered {r['reordered']}, decode errors {r['errors']}, "
        f"arrival rate {r['rate']:.1f} Hz"
    )
    print(
        f"{'clock':<28} {'n':>6} {'p50 us':>8} {'p90 us':>8} {'p99 us':>8} {'p99.9 us':>9} "
        f"{'max us':>8} {'mean us':>8}"
    )
    for label, values in (
        ("monotonic_ns (metadata)", r["mono"]),
        ("header timestamp (time.time)", r["wall"]),
        ("  of which sender (build+send)", r["sender"]),
    ):
        if not values:
            continue
        print(
            f"{label:<28} {len(values):>6} {_percentile(values, 50):8.1f} "
            f"{_percentile(values, 90):8.1f} {_percentile(values, 99):8.1f} "
            f"{_percentile(values, 99.9):9.1f} {values[-1]:8.1f} {statistics.fmean(values):8.1f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
