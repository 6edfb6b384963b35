#!/usr/bin/env python3
"""Feel the tissue: how faithfully the master's hand feels what the slave's instrument touches.

Transparency of the bilateral pair (issue 27): the shipped master (configs/master.yaml, the
simulated hand on a haptic device) and the wall slave (configs/wall.yaml, its tool pressing on a
simulated tissue wall) as an :class:`occ_testkit.testing.SimPair` in simulated time, the hand making
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
    python tools/feel.py --real --seconds 30 --loss 0 0.02 --out /tmp/feel   # real daemons

With ``--real`` the same pair runs as two ``occd`` processes over real UDP, both links through
tools/loss_proxy.py (the return channel relayed back through its own drops), and the forces
are read from both daemons' ``GetStats`` (``feel-real.json``).
"""

from __future__ import annotations

import argparse
import json
import random
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from occ_testkit.testing import CONFIGS, SimPair  # noqa: E402


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
            hand[k] = ctl.display.displayed_n
            handle[k] = pair.master.robot.frame.tip_position(pair.master.robot.data.q)
        states = (pair.master.robot.state.value, pair.slave.robot.state.value)
        passive = ctl.display.passivity.stats()
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


def run_real(
    *, loss: float, seconds: float, seed: int, out: Path, poll_hz: float = 20.0
) -> dict[str, Any]:
    """The same over real sockets: ``occd`` on copies of configs/master.yaml and
    configs/wall.yaml moved to free ports on 127.0.0.1, the master's stream and the slave's
    return channel through tools/loss_proxy.py (runs of exactly 2 lost, ``loss`` of the
    packets, each way), both daemons' ``GetStats`` polled at ``poll_hz``: the master's
    displayed force against the slave's tissue force (interpolated to the master's poll time;
    the force changes by at most ~0.5 N/s, so the polls' skew costs under 1 %)."""
    import socket
    import time

    sys.path.insert(0, str(ROOT / "tools"))
    from fixture_e2e import Client
    from loopback import free_port, pair_configs, stop_processes, wait_port, write_yaml
    from loss_proxy import LossPattern, LossProxy

    out.mkdir(parents=True, exist_ok=True)
    slave, master, ports = pair_configs(slave_cfg=CONFIGS / "wall.yaml")
    proxy_port = free_port(socket.SOCK_DGRAM)
    for iface in master["interfaces"]:
        if iface.get("transport") == "udp":
            iface["remote"] = f"127.0.0.1:{proxy_port}"
    packets = round((seconds + 30.0) * 500)
    runs = round(loss * packets / 2)

    def pattern(way: str) -> LossPattern | None:
        if runs <= 0:
            return None
        return LossPattern(
            seed=hash((seed, way)) & 0xFFFF, drop_runs=[(2, runs)], expected=packets,
            warmup=2500, min_gap=10,
        )  # fmt: skip

    proxy = LossProxy(
        ("127.0.0.1", proxy_port), ("127.0.0.1", ports["slave_udp"]), pattern("forward"),
        duration=seconds + 60.0, return_pattern=pattern("return"),
        fifo_priority=50,  # the relay is the network, not a process competing with the pair
    )  # fmt: skip
    procs: list[subprocess.Popen[bytes]] = []
    rows: list[tuple[float, list[float], list[float] | None, dict[str, Any]]] = []
    truth: list[tuple[float, list[float]]] = []
    clients: list[Any] = []

    def start(cfg: dict[str, Any], name: str) -> subprocess.Popen[bytes]:
        path = write_yaml(out / f"{name}.yaml", cfg)
        log = (out / f"{name}.log").open("wb")
        cmd = [sys.executable, "-m", "occ.cli", str(path), "--start", "running",
               "--log-level", "WARNING"]  # fmt: skip
        return subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)

    try:
        proxy.start()
        procs.append(start(slave, "slave"))
        assert wait_port(ports["slave_op"], 30.0, procs[0]), "the slave did not listen"
        procs.append(start(master, "master"))
        assert wait_port(ports["master_tcp"], 30.0, procs[1]), "the master did not listen"
        s_cli, m_cli = Client(ports["slave_op"]), Client(ports["master_tcp"])
        clients = [s_cli, m_cli]
        for c in clients:
            c.client.start()
            assert c.connected.wait(10.0)
        end = time.monotonic() + 20.0
        while time.monotonic() < end:  # the pair following, the tool's force fully shown
            m = m_cli.stats()["controller"]
            if m.get("fixture_gain") == 1 and (m.get("slave_tip") or {}).get("status") == "fresh":
                break
            time.sleep(0.1)
        t0 = time.monotonic()
        period = 1.0 / poll_hz
        while time.monotonic() - t0 < seconds:
            ts = time.monotonic()
            env = s_cli.stats()["hardware"].get("environment") or {}
            truth.append((ts - t0, list(env.get("force_n", [0.0, 0.0, 0.0]))))
            tm = time.monotonic()
            mc = m_cli.stats()["controller"]
            tip = mc.get("slave_tip") or {}
            rows.append((tm - t0, mc["force_n"], tip.get("force_n"), mc.get("passivity", {})))
            time.sleep(max(0.0, period - (time.monotonic() - ts)))
        states = [m_cli.stats()["state"], s_cli.stats()["state"]]
        last_alerts = [m_cli.stats().get("last_alert"), s_cli.stats().get("last_alert")]
        slave_loss = s_cli.stats().get("loss", {})
        master_tip = m_cli.stats()["controller"].get("slave_tip") or {}
    finally:
        for c in clients:
            c.client.stop()
        stop_processes(procs)
        proxy.stop()
    tt = np.array([t for t, _ in truth])
    tf = np.array([f for _, f in truth])
    hand = np.array([r[1] for r in rows])
    tm = np.array([r[0] for r in rows])
    tip = np.column_stack([np.interp(tm, tt, tf[:, i]) for i in range(3)])
    err = hand - tip
    peak = float(np.linalg.norm(tip, axis=1).max()) if len(tip) else 0.0
    rms = float(np.sqrt((err**2).sum(axis=1).mean())) if len(err) else float("nan")
    c = proxy.counters
    return {
        "mode": "real",
        "loss": loss,
        "seconds": seconds,
        "polls": len(rows),
        "peak_n": round(peak, 4),
        "rms_error_n": round(rms, 4),
        "rms_error_pct": round(100.0 * rms / peak, 2) if peak > 0 else None,
        "max_error_n": round(float(np.linalg.norm(err, axis=1).max()), 4) if len(err) else None,
        "states": states,
        "last_alerts": last_alerts,
        "proxy": {
            "forwarded": c.forwarded,
            "dropped": c.dropped,
            "returned": c.returned,
            "return_dropped": c.return_dropped,
        },  # fmt: skip
        "slave_loss_monitor": {k: slave_loss.get(k) for k in ("holds", "lost_total", "trips")},
        "master_return_link": {k: master_tip.get(k) for k in ("late", "lost_total", "losses")},
        "trace": {"t": tm.tolist(), "tip_x": tip[:, 0].tolist(), "hand_x": hand[:, 0].tolist()},
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=10.0, help="measured (after a 2 s settle)")
    p.add_argument("--delay-ms", type=float, nargs="+", default=[0.0, 5.0])
    p.add_argument("--loss", type=float, nargs="+", default=[0.0, 0.02])
    p.add_argument("--sources", nargs="+", default=["tissue"], choices=("tissue", "effort"))
    p.add_argument("--no-passivity", action="store_true", help="also run with passivity off")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--out", type=Path, default=Path("feel"))
    p.add_argument(
        "--real",
        action="store_true",
        help="real daemons over the loss proxy (each --loss; --seconds each), not simulated",
    )
    args = p.parse_args(argv)
    if not 0.0 < args.seconds <= 600.0:
        raise SystemExit("--seconds must be in (0, 600]")
    if args.real:
        real = []
        for loss in args.loss:
            r = run_real(
                loss=loss, seconds=args.seconds, seed=args.seed, out=args.out / f"real-{loss:g}"
            )
            real.append(r)
            print(
                f"real    loss {100 * loss:3g} %: peak {r['peak_n']:.3f} N, RMS error "
                f"{r['rms_error_n']:.4f} N ({r['rms_error_pct']} %), max {r['max_error_n']} N, "
                f"polls {r['polls']}, proxy {r['proxy']}, states {r['states']} {r['last_alerts']}"
            )
        args.out.mkdir(parents=True, exist_ok=True)
        slim = [{k: v for k, v in r.items() if k != "trace"} for r in real]
        (args.out / "feel-real.json").write_text(json.dumps(slim, indent=2) + "\n")
        return 0
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
