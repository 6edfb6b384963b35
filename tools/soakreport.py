"""The report format of the loss soak and the OCC stability test: checks, numbers, runs,
stops, written as report.json and report.md (tools/soak.py and tools/stability.py both write
it; neither imports the other for it).
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any


@dataclass
class Check:
    name: str
    passed: bool
    detail: str
    severity: str = "fail"  # "fail" or "warn" (a warn never changes the exit code)

    @property
    def label(self) -> str:
        if self.passed:
            return "PASS"
        return "FAIL" if self.severity == "fail" else "WARN"


@dataclass
class RunOutcome:
    """One run of consecutive dropped packets and what the slave did about it."""

    t_s: float  # time of the first drop, seconds since the start of the stream
    length: int
    first_seq: int | None
    category: (
        str  # "stop", "no-stop", "masked", "bad-stop" (a <=2 run followed by a stop), "missed"
    )
    latency_ms: float | None = None  # last good packet -> latched stop
    note: str = ""
    hold_ms: float | None = None  # last good packet -> motion held (sim: exact)


@dataclass
class Report:
    mode: str
    checks: list[Check] = field(default_factory=list)
    numbers: dict[str, Any] = field(default_factory=dict)
    runs: list[RunOutcome] = field(default_factory=list)
    stops: list[dict[str, Any]] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)
    command: str = ""

    @property
    def passed(self) -> bool:
        return all(c.passed or c.severity != "fail" for c in self.checks)

    def check(self, name: str, passed: bool, detail: str, severity: str = "fail") -> None:
        self.checks.append(Check(name, bool(passed), detail, severity))


def histogram(values: list[int]) -> dict[str, int]:
    c = Counter(values)
    return {str(k): c[k] for k in sorted(c)}


def summarize(values: list[float]) -> dict[str, float] | None:
    if not values:
        return None
    v = sorted(values)
    n = len(v)

    def pct(p: float) -> float:
        return round(v[min(n - 1, max(0, int(math.ceil(p / 100.0 * n)) - 1))], 3)

    return {
        "n": n,
        "min": round(v[0], 3),
        "p50": pct(50),
        "p99": pct(99),
        "max": round(v[-1], 3),
        "mean": round(sum(v) / n, 3),
    }


def write_report(
    rep: Report,
    out: Path,
    *,
    title: str | None = None,
    plotter: Callable[[Report, Path], list[str]] | None = None,
) -> None:
    """report.json + report.md (+ the plots ``plotter`` draws) in ``out``: the same format for
    the loss soak (tools/soak.py) and the stability test (tools/stability.py)."""
    plots = plotter(rep, out) if plotter is not None else []
    data = {
        "mode": rep.mode,
        "passed": rep.passed,
        "command": rep.command,
        "checks": [asdict(c) | {"label": c.label} for c in rep.checks],
        "numbers": rep.numbers,
        "failures": rep.failures[:200],
        "stops": rep.stops[:5000],
        "plots": plots,
    }
    (out / "report.json").write_text(json.dumps(data, indent=2, default=str) + "\n")
    n = rep.numbers
    lines = [
        f"# {title or f'Loss soak ({rep.mode})'}: {'PASS' if rep.passed else 'FAIL'}",
        "",
        f"Command: `{rep.command}`",
        "",
        "## Checks",
        "",
        "| check | result | detail |",
        "|---|---|---|",
    ]
    for c in rep.checks:
        lines.append(f"| {c.name} | {c.label} | {c.detail.replace('|', '/')} |")
    lines += ["", "## Numbers", ""]
    for key, val in n.items():
        if isinstance(val, dict):
            val = json.dumps(val, default=str)
        lines.append(f"- **{key}**: {val}")
    if rep.failures:
        lines += ["", "## Failures (first 50)", ""] + [f"- {f}" for f in rep.failures[:50]]
    if plots:
        lines += ["", "## Plots", ""] + [f"![{p}]({p})" for p in plots]
    (out / "report.md").write_text("\n".join(lines) + "\n")
