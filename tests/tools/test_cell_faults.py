"""CI version of tools/cell_faults.py: one fault of each kind in one member of a cell of three
real daemons, and what the other two did.

Asserted: every other member held, naming the origin; none of them could Run before the origin
ran again; a silent member (kill -9, SIGSTOP) was not taken for stopped before the grace of its
last heartbeat (measured from that heartbeat's send time, not from the fault: the last one may
be a period or more older than the fault), and sent no heartbeat after the fault. The
propagation times are printed, not judged here (a loaded 2-core machine);
the 100-fault figures are in docs/BENCHMARKS.md.
"""

from __future__ import annotations

import pytest

from .tooling import load_tool

cell_faults = load_tool("cell_faults")

pytestmark = [pytest.mark.realtime, pytest.mark.req("SR-CELL-1", "SR-CELL-4")]


def test_one_fault_of_each_kind_stops_every_other_member() -> None:
    result = cell_faults.run(4, 3)
    s = result["summary"]
    print(s)
    for row in result["rows"]:
        assert all(row["held"].values()), row
        assert all(row["named"].values()), row
        assert row["early_runs"] == 0, row
        if row["kind"] in ("kill", "stop"):
            # silent: never before the grace after its last heartbeat (the judgement runs on
            # the monotonic clock, this on the wall clock: 1 ms for the two and the rounding)
            assert set(row["silence_ms"]) == set(row["held"]), row
            assert min(row["silence_ms"].values()) >= cell_faults.GRACE_MS - 1.0, row
            assert not any(row["sent_after_fault"].values()), row
    assert {r["kind"] for r in result["rows"]} == set(cell_faults.KINDS)
    assert s["early_silences"] == 0
