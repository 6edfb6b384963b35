"""``soak.py real --runs N --hogs H``: repeated soaks beside CPU hogs, judged against a bar."""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

from soakreport import Report, summarize

from .common import MAX_TOLERATED
from .hogs import loadavg, start_hogs, stop_hogs
from .real import run_real
from .report import write_report


def summarize_real_run(index: int, rep: Report, bar_ms: float) -> dict[str, Any]:
    """What one soak says about the bar: its false stops (with the slave's words) and, for every
    run of >= 3 drops, whether the slave stopped with an alert and how soon (the stops slower
    than ``bar_ms`` with who was late)."""
    triples = [r for r in rep.runs if r.length > MAX_TOLERATED]
    false = [
        {k: s.get(k) for k in ("t_s", "kind", "reason", "diagnosis", "run_length") if k in s}
        for s in rep.stops
        if s.get("kind") != "run>=3"
    ]
    return {
        "run": index,
        "passed_soak_checks": rep.passed,
        "failed_checks": [c.name for c in rep.checks if c.label == "FAIL"],
        "drop_runs": rep.numbers.get("run_length_histogram"),
        "relay_scheduling": (rep.numbers.get("proxy") or {}).get("scheduling"),
        "relay_gaps": (rep.numbers.get("proxy") or {}).get("arrival_gaps_over_ms"),
        "runs_ge3": len(triples),
        "runs_ge3_stopped": sum(1 for r in triples if r.category == "stop"),
        "runs_ge3_missed": sum(1 for r in triples if r.category == "missed"),
        "runs_ge3_masked": sum(1 for r in triples if r.category == "masked"),
        "stop_latency_ms": [r.latency_ms for r in triples if r.category == "stop"],
        "false_stops": false,
        "slow_stops": [
            {k: s.get(k) for k in ("t_s", "latency_est_ms", "reason", "diagnosis")}
            for s in rep.stops
            if s.get("kind") == "run>=3" and (s.get("latency_est_ms") or 0.0) > bar_ms
        ],
        "holds": (rep.numbers.get("slave_loss_monitor") or {}).get("holds"),
        "resumes": (rep.numbers.get("slave_loss_monitor") or {}).get("resumes"),
        "refused_timestamps": {
            k: v
            for k, v in (rep.numbers.get("slave_loss_monitor") or {}).items()
            if k in ("stale", "future")
        },
        "slave_lateness_us": rep.numbers.get("slave_lateness_us"),
        "master_lateness_us": rep.numbers.get("master_lateness_us"),
    }


def run_real_series(args: argparse.Namespace, out: Path, command: str) -> Report:
    rep = Report("real-series")
    rows: list[dict[str, Any]] = []
    bound = float(args.duration) + 90.0  # a hog outlives no run by more than this
    for i in range(1, args.runs + 1):
        sub = out / f"run-{i:02d}"
        sub.mkdir(parents=True, exist_ok=True)
        load_before = loadavg()
        t_hogs = time.monotonic()
        hogs = start_hogs(args.hogs, bound)
        try:
            one = run_real(argparse.Namespace(**vars(args)), sub)
        finally:
            shares = stop_hogs(hogs, t_hogs)
        one.command = f"{command} (run {i} of {args.runs})"
        write_report(one, sub)
        row = summarize_real_run(i, one, float(args.stop_within_ms))
        row.update(
            load_before=load_before,
            load_after=loadavg(),
            hog_cpu_percent=shares,
            hog_pids=[h.pid for h in hogs],
        )
        rows.append(row)
        lat = [v for v in row["stop_latency_ms"] if v is not None]
        print(
            f"soak real run {i}/{args.runs}: {row['runs_ge3_stopped']}/{row['runs_ge3']} runs "
            f">= 3 stopped (max {max(lat, default=float('nan')):.1f} ms), "
            f"{len(row['false_stops'])} false stops, load {row['load_before']} -> "
            f"{row['load_after']}, hogs {shares} % CPU",
            flush=True,
        )
    bar = float(args.stop_within_ms)
    lat = [v for r in rows for v in r["stop_latency_ms"] if v is not None]
    false = [dict(f, run=r["run"]) for r in rows for f in r["false_stops"]]
    triples = sum(r["runs_ge3"] for r in rows)
    stopped = sum(r["runs_ge3_stopped"] for r in rows)
    missed = sum(r["runs_ge3_missed"] for r in rows)
    masked = sum(r["runs_ge3_masked"] for r in rows)
    slow = [v for v in lat if v > bar]
    rep.stops = false
    rep.numbers = {
        "runs": args.runs,
        "duration_s": args.duration,
        "hogs": args.hogs,
        "relay_scheduling": rows[0]["relay_scheduling"] if rows else None,
        "pattern": rows[0]["drop_runs"] if rows else None,
        "runs_ge3": triples,
        "runs_ge3_stopped": stopped,
        "runs_ge3_missed": missed,
        "runs_ge3_masked": masked,
        "stop_latency_ms": summarize(lat),
        "stops_slower_than_bar": len(slow),
        "false_stops": len(false),
        "false_stop_causes": [
            f"run {f['run']} at {f['t_s']} s: {f['reason']}; {f.get('diagnosis')}" for f in false
        ],
        "slow_stops": [
            f"run {r['run']} at {f['t_s']} s: {f['latency_est_ms']} ms; {f.get('diagnosis')}"
            for r in rows
            for f in r["slow_stops"]
        ],
        "per_run": rows,
    }
    rep.check(
        "no false latched stop",
        not false,
        f"{len(false)} stops not caused by a run of >= 3 drops in {args.runs} runs of "
        f"{args.duration:g} s" + (f": {rep.numbers['false_stop_causes'][:5]}" if false else ""),
    )
    rep.check(
        f"every run >= 3 stopped the slave with an alert within {bar:g} ms",
        triples > 0 and missed == 0 and not slow and stopped == len(lat),
        f"{triples} runs >= 3: {stopped} stopped, {missed} missed, {masked} masked (the slave "
        f"was already stopped); last good packet -> STOPPED alert {summarize(lat)} ms, "
        f"{len(slow)} over {bar:g} ms" + (f": {rep.numbers['slow_stops'][:5]}" if slow else ""),
    )
    rep.check(
        "no run >= 3 masked",
        masked == 0,
        f"{masked} runs >= 3 started while the slave was stopped (not judged)",
        severity="warn",
    )
    return rep


def write_series_report(rep: Report, out: Path) -> None:
    """report.json + report.md of ``--runs``: the bar, then one row per run."""
    data = {
        "mode": rep.mode,
        "passed": rep.passed,
        "command": rep.command,
        "checks": [asdict(c) | {"label": c.label} for c in rep.checks],
        "numbers": rep.numbers,
    }
    (out / "report.json").write_text(json.dumps(data, indent=2, default=str) + "\n")
    n = rep.numbers
    lines = [
        f"# Loss soak, {n['runs']} runs beside {n['hogs']} CPU hogs: "
        f"{'PASS' if rep.passed else 'FAIL'}",
        "",
        f"Command: `{rep.command}`; the relay's thread: {n['relay_scheduling']}",
        "",
        "| check | result | detail |",
        "|---|---|---|",
        *(f"| {c.name} | {c.label} | {c.detail.replace('|', '/')} |" for c in rep.checks),
        "",
        "| run | load before -> after | hogs % CPU | runs >= 3 stopped / missed / masked "
        "| stop latency max (ms) | holds / resumes | arrival gaps > 5 ms at the relay "
        "| false stops |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in n["per_run"]:
        lat = [v for v in r["stop_latency_ms"] if v is not None]
        causes = (
            "; ".join(
                f"{f['t_s']} s: {f['reason']} ({f.get('diagnosis')})" for f in r["false_stops"]
            )
            or "0"
        )
        lines.append(
            f"| {r['run']} | {r['load_before']} -> {r['load_after']} | {r['hog_cpu_percent']} "
            f"| {r['runs_ge3_stopped']}/{r['runs_ge3']} / {r['runs_ge3_missed']} / "
            f"{r['runs_ge3_masked']} | {max(lat, default=float('nan')):.2f} "
            f"| {r['holds']} / {r['resumes']} | {(r['relay_gaps'] or {}).get('by_cause')} "
            f"| {causes.replace('|', '/')} |"
        )
    (out / "report.md").write_text("\n".join(lines) + "\n")
