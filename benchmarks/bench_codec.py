"""Codec throughput: pack and unpack (CRC-64 verified) per message type, igtl vs pyigtl.

    .venv/bin/python benchmarks/bench_codec.py                 # short run (~10 s)
    .venv/bin/python benchmarks/bench_codec.py --n 100000 --repeat 7
    .venv/bin/python benchmarks/bench_codec.py --type TRANSFORM

The goal (docs/BENCHMARKS.md): TRANSFORM pack + unpack with CRC verification at least 3x faster
than pyigtl's pack + unpack (which never verifies the CRC). The timing code is shared with
``igtl bench`` (igtl/bench.py).
"""

from __future__ import annotations

import argparse
import platform
import sys

from igtl import bench, wire

GOAL_SPEEDUP = 3.0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--type",
        action="append",
        choices=bench.BENCH_TYPES,
        help="type to time (repeatable; default: all)",
    )
    p.add_argument("--n", type=int, default=20_000, help="calls per round (IMAGE: n/200)")
    p.add_argument("--repeat", type=int, default=5, help="rounds; the best is kept")
    p.add_argument("--no-pyigtl", action="store_true", help="time igtl only")
    args = p.parse_args(argv)

    print(
        f"python {platform.python_version()} on {platform.machine()}, "
        f"crcmod C extension: {'yes' if wire.CRC_ACCELERATED else 'NO'}; "
        f"n={args.n}, best of {args.repeat}"
    )
    results = bench.run_codec_bench(
        args.type or bench.BENCH_TYPES,
        n=args.n,
        repeat=args.repeat,
        with_pyigtl=not args.no_pyigtl,
        warn=lambda text: print(f"note: {text}", file=sys.stderr),
    )
    print(bench.format_table(results))

    by_key = {(r.type_name, r.impl): r for r in results}
    ours, theirs = by_key.get(("TRANSFORM", "igtl")), by_key.get(("TRANSFORM", "pyigtl"))
    if ours and theirs:
        speedup = theirs.roundtrip_us / ours.roundtrip_us
        verdict = "met" if speedup >= GOAL_SPEEDUP else "NOT met"
        print(
            f"TRANSFORM pack+unpack speedup vs pyigtl: {speedup:.3f}x "
            f"(goal >= {GOAL_SPEEDUP:g}x: {verdict})"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
