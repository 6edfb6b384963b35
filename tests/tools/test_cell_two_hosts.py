"""The cell across a network: two members on two hosts (two network namespaces joined by a veth
pair, as the ROS 2 two-machine tests use), a fault of each kind in the one on the first host,
the other holding (tools/cell_faults.py, run on the first host)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from occ_testkit.netns import Netns, available

ROOT = Path(__file__).resolve().parents[2]

pytestmark = [pytest.mark.realtime, pytest.mark.req("SR-CELL-1", "SR-CELL-4")]


def test_a_cell_on_two_hosts_stops_as_one(tmp_path: Path) -> None:
    why = available()
    if why is not None:
        pytest.skip(why)
    with Netns() as a, Netns() as b:
        a.link(b, "10.211.9.1/24", "10.211.9.2/24", name="cell")
        out = tmp_path / "two.json"
        a.run(
            [sys.executable, str(ROOT / "tools" / "cell_faults.py"), "--count", "4",
             "--members", "2", "--host", "10.211.9.1", "--host", f"10.211.9.2@{b.pid}",
             "--out", str(out)],
            timeout=240.0,
        )  # fmt: skip
        result = json.loads(out.read_text())
    for row in result["rows"]:
        assert row["held"] == {"arm1": True} and row["named"] == {"arm1": True}, row
        assert row["early_runs"] == 0, row
