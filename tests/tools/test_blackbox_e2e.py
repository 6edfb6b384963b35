"""The CI version of tools/blackbox_e2e.py (issue 41, done-when): the shipped slave and
master as real ``occd`` processes on loopback, the master's stream through the loss proxy,
three consecutive datagrams dropped after 3 s. The slave dumps its black box by itself; the
dump replays bit for bit with the stop at the same tick; ``occ-record why`` names the three
sequence numbers the proxy dropped; a 1 % larger motion scale makes the replay diverge at a
setpoint. The long version (30 s of black box, the shipped value) is the tool's default run.

Timing tolerance (a loaded 2-core machine): a stop for silence before the drop (the master not
scheduled for 100 ms) would be a different dump; the tool then finds no ``stopped`` dump after
the drop or one whose ``why`` does not name the drop, and the test says so (the report is in
the failure message)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from .tooling import load_tool


@pytest.mark.realtime
@pytest.mark.req("SR-BOX-6")
def test_two_real_daemons_a_triple_loss_a_dump_that_replays_and_explains(tmp_path: Path) -> None:
    e2e = load_tool("blackbox_e2e")
    report = e2e.run(tmp_path, seconds=2.0, warmup=3.0)
    text = json.dumps(report, indent=1)
    assert report["ok"], text
    assert len(report["dropped_seq"]) == 3
    assert (
        report["replay"]["exact"] is True
        and report["replay"]["stop_tick"] == report["trigger_tick"]
    )
    assert report["replay"]["ticks"] == report["window"]["ticks"] >= 2000
    assert report["replay"]["not_restored"] == [], text
    assert report["what_if"]["exit"] == 4
