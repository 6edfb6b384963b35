#!/usr/bin/env python3
"""Print the hardware fault matrix: every drive fault injected into the shipped slave, and what
the robot did (occ_testkit/faultmatrix.py; docs/SAFETY.md SR-HW-1..22, SR-HW-30..39).

    python tools/fault_matrix.py                 # every row, a Markdown table
    python tools/fault_matrix.py --row nan jump  # some rows
    python tools/fault_matrix.py --repeat 20     # fault -> last drive safe: median and max

Each run is in simulated time (deterministic outcomes); the "fault -> last drive safe" column
is the wall-clock time (time.perf_counter) from the tick's detection of the failure to the
moment the last drive was powered off, in the same tick. Exit status 1 when a row fails.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from occ_testkit.faultmatrix import ROWS, Outcome, run_row, table  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--row", nargs="+", choices=[r.name for r in ROWS], help="rows to run")
    ap.add_argument("--repeat", type=int, default=1, help="runs per row (latency statistics)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.CRITICAL)  # the faults are meant: keep their logs out
    rows = [r for r in ROWS if args.row is None or r.name in args.row]
    outcomes: list[Outcome] = []
    spread: list[str] = []
    for row in rows:
        runs = [run_row(row) for _ in range(max(1, args.repeat))]
        first = runs[0]
        first.ok_all = all(o.ok for o in runs)  # type: ignore[attr-defined]
        outcomes.append(first)
        lat = [o.fault_to_safe_us for o in runs if o.fault_to_safe_us is not None]
        if args.repeat > 1 and lat:
            spread.append(
                f"{row.name}: detection -> last drive safe median {statistics.median(lat):.0f} us, "
                f"max {max(lat):.0f} us over {len(lat)} runs; "
                f"{sum(o.ok for o in runs)}/{len(runs)} PASS"
            )
        for o in runs:
            for note in o.notes:
                print(f"{row.name}: {note}", file=sys.stderr)
    print(table(outcomes))
    if spread:
        print()
        print("\n".join(spread))
    return 0 if all(getattr(o, "ok_all", o.ok) for o in outcomes) else 1


if __name__ == "__main__":
    sys.exit(main())
