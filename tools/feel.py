#!/usr/bin/env python3
"""Feel the tissue: how faithfully the master's hand feels what the slave's instrument touches.

Transparency of the bilateral pair (issue 27): the shipped master (configs/master.yaml, the
simulated hand on a haptic device) and the wall slave (configs/wall.yaml, its tool pressing on a
simulated tissue wall) as an :class:`occ.testing.SimPair` in simulated time, the hand making
the OCC paper's motion (50 mm circle at 0.1 Hz; the slave's 5 mm circle presses up to 3 mm into
the wall, 0.5 N/mm). For each condition (added delay each way, the OCC paper's double losses on
both links) it measures, every 1 ms tick over ``--seconds`` after a 2 s settle:

- the force at the instrument (the simulated tissue's contact force, mapped into the master's
  axes) and the force the hand feels (the master's displayed force);
- RMS error between them, and as a share of the peak force;
- lag: the shift of the hand's force that fits the instrument's best (least squares);
- the handle's velocity RMS (an oscillating loop shakes the handle: compare with no loss);
- the passivity controller's dissipated energy.

Writes ``feel.json``, ``feel.md`` and ``feel.png`` (the two forces over one turn, and the error)
to ``--out``. Everything is simulated and seeded: the same arguments give the same numbers.

    python tools/feel.py --out /tmp/feel
    python tools/feel.py --delay-ms 0 5 20 --loss 0 0.02 --sources tissue effort --out /tmp/feel
"""

from __future__ import annotations

import argparse
import json
import random
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from occ.testing import CONFIGS, SimPair  # noqa: E402


def double_loss(rate: float, seed: int) -> Callable[[str, Any, int], bool] | None:
    """Runs of exactly two lost messages, ``rate`` of them lost, each way on its own seeded
    stream (the OCC paper's pattern; tools/stability.py uses the same on the forward link)."""
    if rate <= 0.0:
        return None
    rngs = {d: random.Random(f"{seed}-{d}") for d in ("forward", "return")}
    left = dict.fromkeys(rngs, 0)
    gap = dict.fromkeys(rngs, 1)

    def drop(direction: str, msg: Any, index: int) -> bool:
        if left[direction] > 0:
            left[direction] -= 1
            gap[direction] = 0
            return True
        gap[direction] += 1
        if gap[direction] > 1 and rngs[direction].random() < rate / 2:
            left[direction] = 1
            return True
        return False

    return drop


def run_condition(
    *, delay_ms: float, loss: float, source: str, seconds: float, seed: int, passivity: bool
) -> dict[str, Any]:
    cfg = yaml.safe_load((CONFIGS / "wall.yaml").read_text())
    cfg["controller"]["params"]["force"]["sources"] = [source]
    pair = SimPair(
        CONFIGS / "master.yaml", cfg, delay_ms=delay_ms, drop=double_loss(loss, seed),
        master_params={"passivity": passivity},
    )  # fmt: skip
    try:
        pair.start()
        env = pair.slave.robot.hardware.environment
        ctl: Any = pair.master.robot.controller.controllers[0]
        pair.run_for(2.0)
        n = round(seconds * 1000)
        tip = np.empty((n, 3))
        hand = np.empty((n, 3))
        handle = np.empty((n, 3))
        for k in range(n):
            pair.step(1)
            tip[k] = ctl.fixtures.mapping.force(env.force_n)
            hand[k] = ctl.displayed_n
            handle[k] = pair.master.robot.frame.tip_position(pair.master.robot.data.q)
        states = (pair.master.robot.state.value, pair.slave.robot.state.value)
        passive = ctl.passivity.stats()
        counts = dict(pair.counts)
    finally:
        pair.close()
    err = hand - tip
    rms = float(np.sqrt((err**2).sum(axis=1).mean()))
    peak = float(np.linalg.norm(tip, axis=1).max())
    # lag: the shift (ms) of the hand's force that best fits the instrument's
    best, lag = np.inf, 0
    for shift in range(0, 200):
        e = hand[shift:] - tip[: n - shift]
        r = float((e**2).sum(axis=1).mean())
        if r < best:
            best, lag = r, shift
    vel = np.diff(handle, axis=0) * 1000.0
    return {
        "delay_ms": delay_ms,
        "loss": loss,
        "source": source,
        "passivity": passivity,
        "peak_n": round(peak, 4),
        "rms_error_n": round(rms, 4),
        "rms_error_pct": round(100.0 * rms / peak, 2) if peak > 0 else None,
        "max_error_n": round(float(np.linalg.norm(err, axis=1).max()), 4),
        "lag_ms": lag,
        "rms_error_at_lag_n": round(float(np.sqrt(best)), 4),
        "handle_velocity_rms_mm_s": round(float(np.sqrt((vel**2).sum(axis=1).mean())) * 1e3, 2),
        "dissipated_mj": passive["dissipated_mj"],
        "states": states,
        "lost": {"forward": counts["forward_lost"], "return": counts["return_lost"]},
        "trace": {"tip_x": tip[:, 0].tolist(), "hand_x": hand[:, 0].tolist()},
    }


def write(results: list[dict[str, Any]], out: Path, command: str) -> None:
    out.mkdir(parents=True, exist_ok=True)
    lines = [
        "# Feel the tissue: transparency of the bilateral pair (simulated time)",
        "",
        f"    {command}",
        "",
        "| source | delay each way | double loss | passivity | peak at the tip | RMS error "
        "| RMS / peak | max error | lag | handle velocity RMS | dissipated | lost fwd/ret |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {r['source']} | {r['delay_ms']:g} ms | {100 * r['loss']:g} % | "
            f"{'on' if r['passivity'] else 'off'} | {r['peak_n']:.3f} N | "
            f"{r['rms_error_n']:.4f} N | {r['rms_error_pct']:.1f} % | {r['max_error_n']:.3f} N | "
            f"{r['lag_ms']} ms | {r['handle_velocity_rms_mm_s']:.1f} mm/s | "
            f"{r['dissipated_mj']:.2f} mJ | {r['lost']['forward']}/{r['lost']['return']} |"
        )
    (out / "feel.md").write_text("\n".join(lines) + "\n")
    slim = [{k: v for k, v in r.items() if k != "trace"} for r in results]
    (out / "feel.json").write_text(json.dumps(slim, indent=2) + "\n")
    plot(results, out / "feel.png")


def plot(results: list[dict[str, Any]], path: Path) -> None:
    """One panel per force source: the instrument's force and the hand's in each condition;
    below, the hand's error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sources = list(dict.fromkeys(r["source"] for r in results))
    fig, axes = plt.subplots(len(sources) + 1, 1, figsize=(9, 3 + 2.4 * len(sources)), sharex=True)
    t = np.arange(len(results[0]["trace"]["tip_x"])) * 1e-3
    named = {"tissue": "sensor at the instrument", "effort": "estimated from the drives' efforts"}
    for ax, source in zip(axes, sources, strict=False):
        runs = [r for r in results if r["source"] == source]
        ax.plot(t, runs[0]["trace"]["tip_x"], label="at the instrument", lw=3, color="0.75")
        for r in runs:
            label = (
                f"hand: {r['delay_ms']:g} ms each way, {100 * r['loss']:g} % double loss"
                f"{'' if r['passivity'] else ', passivity off'}"
            )
            ax.plot(t, r["trace"]["hand_x"], label=label, lw=0.8)
            err = np.array(r["trace"]["hand_x"]) - np.array(r["trace"]["tip_x"])
            axes[-1].plot(t, err, lw=0.8, label=f"{source}: {label}")
        ax.set_ylabel("force x (N)")
        ax.set_title(f"The wall pushes the hand back (slave force: {named.get(source, source)})")
        ax.legend(fontsize=7, loc="lower left")
    axes[-1].set_ylabel("hand - instrument (N)")
    axes[-1].set_xlabel("time (s) after a 2 s settle: one turn of the paper's motion")
    axes[-1].legend(fontsize=6, loc="upper right")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=10.0, help="measured (after a 2 s settle)")
    p.add_argument("--delay-ms", type=float, nargs="+", default=[0.0, 5.0])
    p.add_argument("--loss", type=float, nargs="+", default=[0.0, 0.02])
    p.add_argument("--sources", nargs="+", default=["tissue"], choices=("tissue", "effort"))
    p.add_argument("--no-passivity", action="store_true", help="also run with passivity off")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--out", type=Path, default=Path("feel"))
    args = p.parse_args(argv)
    if not 0.0 < args.seconds <= 600.0:
        raise SystemExit("--seconds must be in (0, 600]")
    results = []
    for source in args.sources:
        for delay in args.delay_ms:
            for loss in args.loss:
                for passivity in (True, False) if args.no_passivity else (True,):
                    r = run_condition(
                        delay_ms=delay, loss=loss, source=source, seconds=args.seconds,
                        seed=args.seed, passivity=passivity,
                    )  # fmt: skip
                    results.append(r)
                    print(
                        f"{source:7s} delay {delay:4g} ms loss {100 * loss:3g} % "
                        f"passivity {'on ' if passivity else 'off'}: peak {r['peak_n']:.3f} N, "
                        f"RMS error {r['rms_error_n']:.4f} N ({r['rms_error_pct']:.1f} %), "
                        f"lag {r['lag_ms']} ms, handle {r['handle_velocity_rms_mm_s']} mm/s"
                    )
    command = "python tools/feel.py " + " ".join(argv if argv is not None else sys.argv[1:])
    write(results, args.out, command.strip())
    print(f"wrote {args.out}/feel.md, feel.json, feel.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
