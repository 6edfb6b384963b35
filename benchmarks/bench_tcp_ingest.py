"""TCP ingest over loopback: how many TRANSFORM messages per second one connection can decode.

    .venv/bin/python benchmarks/bench_tcp_ingest.py                    # 200k messages per mode
    .venv/bin/python benchmarks/bench_tcp_ingest.py --n 500000 --repeat 3
    .venv/bin/python benchmarks/bench_tcp_ingest.py --header-version 2  # v2 + 2 metadata entries

A sender *process* connects once and blasts pre-packed messages (1000 distinct TRANSFORMs,
repeated, written with ``sendall`` in 64 KiB slices) as fast as the socket takes them; the sender
costs almost nothing, so the receiver is the bottleneck. Two receivers, each timed from its first
byte (decoder) / connection (server) to the N-th decoded message:

- ``decoder``: a plain socket read with ``recv_into`` and fed to ``igtl.StreamDecoder`` (CRC
  verified), i.e. the codec alone;
- ``server``: ``igtl.transport.TCPServer`` with an ``on_message`` callback that counts, i.e.
  everything a real server pays for (selector loop, per-peer counters, callback guard).

Goal (docs/BENCHMARKS.md): >= 100,000 messages/s decoded.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import platform
import socket
import statistics
import sys
import threading
import time
from typing import Any

import igtl

GOAL = 100_000
DISTINCT = 1000
SLICE = 64 * 1024


def _messages(header_version: int) -> bytes:
    out = []
    for i in range(DISTINCT):
        meta = {"MRMLNodeName": "Tip", "TransformStatus": "OK"} if header_version == 2 else {}
        msg = igtl.TransformMessage.from_position(
            (i * 0.5, -i * 0.25, 100.0 + i),
            device_name="Tip",
            timestamp=1_700_000_000.0 + i * 0.001,
            header_version=header_version,
            metadata=meta,
            message_id=i if header_version == 2 else 0,
        )
        out.append(msg.pack())
    return b"".join(out)


def _sender(address: tuple[str, int], n: int, header_version: int) -> None:
    """Child process: connect, send exactly n messages, close."""
    block = _messages(header_version)
    per = len(block) // DISTINCT  # every message of one run has the same size
    with socket.create_connection(address) as s:
        full, rest = divmod(n, DISTINCT)
        view = memoryview(block)
        for _ in range(full):
            for off in range(0, len(block), SLICE):
                s.sendall(view[off : off + SLICE])
        if rest:
            s.sendall(view[: rest * per])
        s.shutdown(socket.SHUT_WR)
        s.recv(1)  # wait for the receiver to close: the child outlives the measurement


def _spawn_sender(address: tuple[str, int], n: int, header_version: int) -> Any:
    proc = mp.get_context("spawn").Process(
        target=_sender, args=(address, n, header_version), daemon=True
    )
    proc.start()
    return proc


def run_decoder(n: int, header_version: int) -> float:
    """Raw socket + StreamDecoder; returns messages/s."""
    with socket.create_server(("127.0.0.1", 0)) as listener:
        proc = _spawn_sender(listener.getsockname()[:2], n, header_version)
        conn, _ = listener.accept()
    dec = igtl.StreamDecoder(crc_check=True)
    buf = bytearray(256 * 1024)
    view = memoryview(buf)
    count = 0
    with conn:
        k = conn.recv_into(buf)
        t0 = time.perf_counter()
        while k:
            dec.feed(view[:k])
            for _msg in dec:
                count += 1
            if count >= n:
                break
            k = conn.recv_into(buf)
        elapsed = time.perf_counter() - t0
    proc.join(10)
    if count != n:
        raise RuntimeError(f"decoded {count} of {n} messages")
    return n / elapsed


def run_server(n: int, header_version: int) -> float:
    """TCPServer with a counting on_message; returns messages/s."""
    from igtl.transport import TCPServer

    done = threading.Event()
    count = 0
    t0 = 0.0
    t_end = 0.0

    def on_connect(peer: Any) -> None:
        nonlocal t0
        t0 = time.perf_counter()

    def on_message(peer: Any, msg: Any) -> None:
        nonlocal count, t_end
        count += 1
        if count == n:
            t_end = time.perf_counter()
            done.set()

    server = TCPServer("127.0.0.1", 0, on_message=on_message, on_connect=on_connect)
    server.start()
    try:
        proc = _spawn_sender(server.address, n, header_version)
        if not done.wait(max(60.0, n / 10_000)):
            raise RuntimeError(f"TCPServer decoded {count} of {n} messages before the deadline")
        stats = server.stats()
    finally:
        server.stop()
    proc.join(10)
    if stats.get("malformed"):
        raise RuntimeError(f"TCPServer reported {stats['malformed']} malformed messages")
    return n / (t_end - t0)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--n", type=int, default=200_000, help="messages per run")
    p.add_argument("--repeat", type=int, default=1, help="runs per mode (table: best, median)")
    p.add_argument("--header-version", type=int, choices=(1, 2), default=1)
    p.add_argument(
        "--mode",
        choices=("decoder", "server"),
        action="append",
        help="receiver(s) to time (default: both)",
    )
    args = p.parse_args(argv)

    modes = args.mode or ["decoder", "server"]
    size = len(_messages(args.header_version)) // DISTINCT
    print(
        f"python {platform.python_version()}, TRANSFORM v{args.header_version} ({size} B each),"
        f" n={args.n:,}, {args.repeat} run(s) per mode, CRC verified"
    )
    runners = {"decoder": run_decoder, "server": run_server}
    rows = []
    for mode in modes:
        rates = [runners[mode](args.n, args.header_version) for _ in range(args.repeat)]
        rows.append((mode, max(rates), statistics.median(rates), size))
    print(
        f"{'receiver':<10} {'best msgs/s':>12} {'median msgs/s':>14} "
        f"{'MB/s (best)':>12} {'goal':>6}"
    )
    for mode, best, median, sz in rows:
        ok = "met" if best >= GOAL else "NOT"
        print(f"{mode:<10} {best:12,.0f} {median:14,.0f} {best * sz / 1e6:12.1f} {ok:>6}")
    print(f"goal: >= {GOAL:,} messages/s decoded (CRC verified)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
