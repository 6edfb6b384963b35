"""The report folder of a soak: runs.csv, the plots, report.json and report.md."""

from __future__ import annotations

import csv
import sys
from collections import Counter
from pathlib import Path

import soakreport
from soakreport import Report

from .common import MAX_TOLERATED, STOP_WITHIN_MS


def write_runs_csv(rep: Report, path: Path) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t_s", "length", "first_seq", "category", "latency_ms"])
        for r in rep.runs:
            w.writerow(
                [
                    r.t_s,
                    r.length,
                    "" if r.first_seq is None else r.first_seq,
                    r.category,
                    "" if r.latency_ms is None else r.latency_ms,
                ]
            )


COLORS = {
    "stop": "tab:red",
    "no-stop": "tab:green",
    "masked": "tab:gray",
    "bad-stop": "black",
    "missed": "tab:purple",
    "deadline-stop": "tab:orange",
}


def plot(rep: Report, out: Path) -> list[str]:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("soak: matplotlib missing, no plots (pip install matplotlib)", file=sys.stderr)
        return []
    files = []
    # 1. drops over time, stops marked
    fig, ax = plt.subplots(figsize=(11, 4))
    for cat in sorted({r.category for r in rep.runs}):
        pts = [r for r in rep.runs if r.category == cat]
        ax.scatter(
            [r.t_s for r in pts],
            [r.length for r in pts],
            s=8,
            color=COLORS.get(cat, "tab:blue"),
            label=f"{cat} ({len(pts)})",
            zorder=3,
        )
    stop_t = [s["t_s"] for s in rep.stops]
    if stop_t:
        ymax = max([r.length for r in rep.runs] + [3])
        ax.vlines(
            stop_t,
            0,
            ymax + 0.5,
            colors="tab:red",
            alpha=0.25 if len(stop_t) > 50 else 0.6,
            linewidth=0.8,
            label=f"robot stopped ({len(stop_t)})",
            zorder=1,
        )
    ax.axhline(
        MAX_TOLERATED + 0.5, color="k", linestyle="--", linewidth=0.8, label="stop threshold (3)"
    )
    ax.set_xlabel("time since the stream started (s)")
    ax.set_ylabel("consecutive packets dropped")
    ax.set_title(f"{rep.mode}: runs of dropped POSITION packets and robot stops")
    ax.yaxis.get_major_locator().set_params(integer=True)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "drops_over_time.png", dpi=110)
    plt.close(fig)
    files.append("drops_over_time.png")
    # 2. run-length histogram by outcome
    fig, ax = plt.subplots(figsize=(7, 4))
    lengths = sorted({r.length for r in rep.runs})
    bottom = {n: 0 for n in lengths}
    for cat in ("no-stop", "stop", "masked", "deadline-stop", "bad-stop", "missed"):
        counts = Counter(r.length for r in rep.runs if r.category == cat)
        if not counts:
            continue
        vals = [counts.get(n, 0) for n in lengths]
        ax.bar(lengths, vals, bottom=[bottom[n] for n in lengths], color=COLORS[cat], label=cat)
        for n, v in zip(lengths, vals, strict=True):
            bottom[n] += v
    if max(bottom.values() or [1]) > 100:
        ax.set_yscale("log")
        ax.set_ylim(bottom=0.5)
    ax.set_xlabel("run length (consecutive drops)")
    ax.set_ylabel("runs")
    ax.set_title(f"{rep.mode}: run-length histogram by outcome")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "run_lengths.png", dpi=110)
    plt.close(fig)
    files.append("run_lengths.png")
    # 3. stop latency histogram
    lat = [s.get("latency_ms", s.get("latency_est_ms")) for s in rep.stops]
    lat = [v for v in lat if v is not None]
    fig, ax = plt.subplots(figsize=(7, 4))
    if lat:
        if rep.mode == "sim":
            c = Counter(lat)
            ax.bar(list(c), list(c.values()), width=0.6, color="tab:red")
        else:
            ax.hist(lat, bins=30, color="tab:red")
    ax.axvline(STOP_WITHIN_MS, color="k", linestyle="--", label="7 ms requirement")
    ax.set_xlabel(
        "last good packet -> robot stopped (ms)"
        + (" [estimated: proxy arrival -> STATUS time]" if rep.mode == "real" else "")
    )
    ax.set_ylabel("stops")
    ax.set_title(f"{rep.mode}: stop latency ({len(lat)} stops)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "stop_latency.png", dpi=110)
    plt.close(fig)
    files.append("stop_latency.png")
    return files


def write_report(rep: Report, out: Path, *, title: str | None = None) -> None:
    """The soak's report (soakreport.write_report) with its runs.csv and three plots."""

    def soak_plots(rep: Report, out: Path) -> list[str]:
        write_runs_csv(rep, out / "runs.csv")
        return plot(rep, out)

    soakreport.write_report(rep, out, title=title, plotter=soak_plots)
