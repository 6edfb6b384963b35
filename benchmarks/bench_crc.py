"""CRC-64 backends, the interpreter lock, and big bodies through the stream decoder.

    .venv/bin/python benchmarks/bench_crc.py                      # ~20 s
    .venv/bin/python benchmarks/bench_crc.py --big-mib 256        # the default max body size
    .venv/bin/python benchmarks/bench_crc.py --crcmod-only        # the big-body part as before

Three tables:

1. ``crc``: time per call of CRC-64/ECMA-182 on 100 B, 4 KiB, 256 KiB and 16 MiB for crcmod
   (the ``mkCrcFun`` function, as igtl called it before), crcmod's C function called directly,
   anycrc, and ``igtl.wire.crc64`` (what igtl uses: crcmod below ``CRC_SMALL`` bytes, anycrc
   above). Best of ``--repeat`` rounds.
2. ``lock``: whether a backend releases the interpreter lock. A second thread counts loop turns
   while the main thread checksums 16 MiB again and again; a backend that releases the lock
   lets it count at full speed on the other core, one that holds it lets it run only when the
   interpreter switches threads (every ``sys.getswitchinterval()``), so its longest gap between
   two turns is a whole CRC call.
3. ``big body``: one IMAGE of ``--big-mib`` MiB fed to ``igtl.StreamDecoder`` in 256 KiB pieces
   (a transport's receive size), iterating after every piece as the transports do: the longest
   single ``feed`` + iteration, and the total. ``--crcmod-only`` swaps anycrc out, to compare.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import threading
import time
import timeit
from collections.abc import Callable

import crcmod
import numpy as np

import igtl
from igtl import codec, wire

CHUNK = 256 * 1024


def _backends() -> dict[str, Callable[[bytes], int]]:
    closure = crcmod.mkCrcFun(0x142F0E1EBA9EA3693, rev=False, initCrc=0, xorOut=0)
    out: dict[str, Callable[[bytes], int]] = {
        "crcmod (mkCrcFun)": closure,
        "crcmod (C direct)": wire.crc64_crcmod,
    }
    try:
        import anycrc

        out["anycrc"] = anycrc.CRC(
            width=64, poly=wire.CRC_POLY, init=0, refin=False, refout=False, xorout=0
        ).calc
    except ImportError:
        print("note: anycrc is not installed", file=sys.stderr)
    out["igtl.wire.crc64"] = wire.crc64
    return out


def bench_crc(repeat: int) -> None:
    backends = _backends()
    # each timed as a bare call (no lambda around it), crcmod's C function with its table
    calls = {name: ("fn(data)", {"fn": fn}) for name, fn in backends.items()}
    calls["crcmod (C direct)"] = ("c(data, 0, t)", {"c": wire._crcmod_c, "t": wire._crcmod_table})
    sizes = (100, 4096, 256 * 1024, 16 * 1024 * 1024)
    print(f"{'bytes':>10} " + " ".join(f"{name:>18}" for name in calls) + "   (us per call)")
    for size in sizes:
        data = os.urandom(size)
        want = backends["crcmod (mkCrcFun)"](data)
        number = max(3, min(200_000, 20_000_000 // (size * 8 + 2000)))
        cells = []
        for name, fn in backends.items():
            if fn(data) != want:
                raise RuntimeError(f"{name} disagrees with crcmod")
            stmt, env = calls[name]
            best = min(
                timeit.repeat(stmt, globals={**env, "data": data}, number=number, repeat=repeat)
            )
            cells.append(f"{best / number * 1e6:18.3f}")
        print(f"{size:>10} " + " ".join(cells))


def bench_lock() -> None:
    data = os.urandom(16 * 1024 * 1024)
    print(f"switch interval {sys.getswitchinterval() * 1e3:.1f} ms; 16 MiB per call")
    print(f"{'backend':>18} {'call ms':>8} {'turns/ms':>9} {'max gap ms':>10}  lock")
    for name, fn in _backends().items():
        if name == "igtl.wire.crc64":
            continue
        stop = threading.Event()
        gaps = [0.0]
        turns = [0]

        def spin(stop: threading.Event, gaps: list[float], turns: list[int]) -> None:
            last = time.perf_counter()
            while not stop.is_set():
                now = time.perf_counter()
                if now - last > gaps[0]:
                    gaps[0] = now - last
                last = now
                turns[0] += 1

        t = threading.Thread(target=spin, args=(stop, gaps, turns))
        t.start()
        time.sleep(0.05)
        gaps[0], turns[0] = 0.0, 0
        calls = 3 if name.startswith("crcmod") else 40
        t0 = time.perf_counter()
        for _ in range(calls):
            fn(data)
        elapsed = time.perf_counter() - t0
        stop.set()
        t.join()
        held = gaps[0] >= 0.5 * elapsed / calls
        print(
            f"{name:>18} {elapsed / calls * 1e3:8.2f} {turns[0] / elapsed / 1e3:9.1f} "
            f"{gaps[0] * 1e3:10.2f}  {'held' if held else 'released'}"
        )


def bench_big(mib: int, crcmod_only: bool) -> None:
    if crcmod_only:
        # what igtl did before anycrc: every CRC by crcmod
        wire._crc_big = codec._crc_big = wire.crc64_crcmod
    side = int((mib * 1024 * 1024 / 2) ** 0.5)
    pixels = np.random.default_rng(1).integers(0, 65535, (1, side, side, 1), dtype=np.uint16)
    data = igtl.ImageMessage.from_array(pixels[0, :, :, 0], device_name="Big").pack()
    print(f"IMAGE of {len(data) / 2**20:.1f} MiB in {CHUNK // 1024} KiB pieces", end="")
    print(", crcmod only" if crcmod_only else f", CRC of big bodies: {wire.CRC_BACKEND}")
    del pixels
    dec = igtl.StreamDecoder(max_body_size=len(data))
    view = memoryview(data)
    calls = []
    got: list[igtl.Message] = []
    t_start = time.perf_counter()
    for off in range(0, len(data), CHUNK):
        t0 = time.perf_counter()
        dec.feed(view[off : off + CHUNK])
        got.extend(dec)  # kept: freeing 256 MiB (munmap) is the caller's cost, not the decoder's
        calls.append(time.perf_counter() - t0)
    total = time.perf_counter() - t_start
    assert len(got) == 1 and got[0].pixels.shape == (1, side, side, 1)
    last = calls[-1]
    calls.sort()
    print(
        f"per feed + iteration: median {calls[len(calls) // 2] * 1e3:.2f} ms, "
        f"p99 {calls[int(len(calls) * 0.99)] * 1e3:.2f} ms, longest {calls[-1] * 1e3:.2f} ms "
        f"(the last, which decodes: {last * 1e3:.2f} ms); total {total * 1e3:.1f} ms"
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--repeat", type=int, default=5, help="rounds for the crc table; best kept")
    p.add_argument("--big-mib", type=int, default=64, help="size of the big IMAGE")
    p.add_argument("--crcmod-only", action="store_true", help="big body: crcmod, no anycrc")
    args = p.parse_args(argv)
    print(
        f"python {platform.python_version()} on {platform.machine()}, "
        f"crcmod C extension: {'yes' if wire.CRC_ACCELERATED else 'NO'}, "
        f"big-body backend: {wire.CRC_BACKEND}, CRC_SMALL={wire.CRC_SMALL}"
    )
    print("\n## crc")
    bench_crc(args.repeat)
    print("\n## lock")
    bench_lock()
    print("\n## big body")
    bench_big(args.big_mib, args.crcmod_only)
    return 0


if __name__ == "__main__":
    sys.exit(main())
