"""tools/feel.py, the transparency of the bilateral pair (issue 27): short CI versions.

- simulated time: 3 s of the paper's motion on the wall pair, with and without the OCC paper's
  double losses and 5 ms each way; the report's files and numbers (RMS error under 10 % of
  the peak, every loss counted);
- real daemons over the loss proxy (``slow``): both links through tools/loss_proxy.py with 2 %
  double losses each way, the return channel relayed back; the hand feels the tissue to 10 %
  RMS and both daemons keep running.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from .tooling import load_tool

feel = load_tool("feel")

pytestmark = pytest.mark.req("SR-FORCE-1")


def test_simulated_transparency_report(tmp_path: Path) -> None:
    code = feel.main(["--seconds", "3", "--delay-ms", "0", "5", "--loss", "0", "0.02",
                      "--out", str(tmp_path)])  # fmt: skip
    assert code == 0
    rows = json.loads((tmp_path / "feel.json").read_text())
    assert len(rows) == 4
    for r in rows:
        assert r["states"] == ["RUNNING", "RUNNING"]
        assert r["peak_n"] > 0.5
        assert r["rms_error_pct"] <= 10.0, r
    lossy = [r for r in rows if r["loss"] > 0]
    assert all(r["lost"]["forward"] > 0 and r["lost"]["return"] > 0 for r in lossy)
    assert (tmp_path / "feel.png").stat().st_size > 10_000
    assert "| tissue | 5 ms | 2 % |" in (tmp_path / "feel.md").read_text()


@pytest.mark.slow
def test_real_daemons_over_the_loss_proxy(tmp_path: Path) -> None:
    r = feel.run_real(loss=0.02, seconds=8.0, seed=3, out=tmp_path)
    if r["states"] != ["RUNNING", "RUNNING"] and _only_silence(r["last_alerts"]):
        # A stop for silence alone (no packet for the 100 ms limit: 2 % random loss cannot make
        # that; a stall of the shared machine or of this process's relay thread can) is the
        # safety rule working, not the pair failing: once more, and the second run must hold.
        print(f"stopped for silence, run again: {r['last_alerts']}")
        r = feel.run_real(loss=0.02, seconds=8.0, seed=3, out=tmp_path / "again")
    assert r["states"] == ["RUNNING", "RUNNING"], r["last_alerts"]
    assert r["proxy"]["dropped"] > 0 and r["proxy"]["return_dropped"] > 0, r["proxy"]
    assert r["proxy"]["returned"] > 2000  # the return channel came back through the relay
    assert r["polls"] > 50
    assert r["peak_n"] > 0.5  # the tool reached the wall within 8 s (one turn is 10 s)
    assert r["rms_error_pct"] <= 10.0, r
    assert r["slave_loss_monitor"]["trips"] == 0
    assert r["master_return_link"]["losses"] == 0


def _only_silence(alerts: list[str]) -> bool:
    """Every stop alert is the silence rule's (``no packet for ... ms``), none a sequence loss."""
    said = [a for a in alerts if a]
    return bool(said) and all("no packet for" in a for a in said)
