"""``soak.py real``: occd slave and master on loopback through the loss proxy."""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import time
from pathlib import Path
from typing import Any

from loopback import wait_port
from loss_proxy import LossProxy, pattern_from_args
from soakreport import Report

from .daemons import set_master_remote, start_occd, stop_proc, write_configs
from .realcheck import analyse_real


def run_real(args: argparse.Namespace, out: Path) -> Report:
    from slicer_standin import SlicerStandIn

    rep = Report("real")
    duration = float(args.duration)
    rate = float(args.rate_hz)
    if not (args.loss or args.burst or args.drop_runs or args.drop_cycle):
        n = max(1, int(duration // 6))
        args.drop_runs = [f"1:{4 * n}", f"2:{2 * n}", f"3:{n}", f"5:{max(1, n // 2)}"]
    # runs at least 0.6 s apart (stop + pause + Run round trip fits in between)
    min_gap_default = int(math.ceil(max(0.6, args.pause_ms / 1000.0 + 0.4) * rate))
    try:
        pattern = pattern_from_args(args, duration, min_gap_default=min_gap_default)
    except ValueError as err:
        raise SystemExit(f"soak real: {err}") from None
    ports = write_configs(out, Path(args.config), Path(args.master_config))
    # a silence stop latches only past the grace (a dead master); shorter silences hold and resume
    loss_cfg = (ports["_slave"].get("safety") or {}).get("loss") or {}
    deadline_ms = float(loss_cfg.get("grace_ms", 100.0))
    bound = duration + 30.0  # hard bound of every process, whatever happens here
    proxy = LossProxy(
        ("127.0.0.1", 0),
        ("127.0.0.1", ports["slave_udp"]),
        pattern,
        delay_ms=args.delay_ms,
        jitter_ms=args.jitter_ms,
        duration=bound,
        seed=args.seed,
        fifo_priority=args.relay_fifo,
    )
    set_master_remote(ports, proxy.address[1])
    rep.numbers["ports"] = {k: v for k, v in ports.items() if not k.startswith("_")}
    rep.numbers["proxy_listen"] = list(proxy.address)
    procs: list[subprocess.Popen[bytes]] = []
    names: list[str] = []
    standin = None
    runs_sent: list[dict[str, Any]] = []
    t_end_wall = t_start_wall = time.time()
    codes: dict[str, int | None] = {}
    try:
        slave = start_occd(ports["slave_yaml"], out / "slave-stats.json", out / "slave.log", bound)
        procs.append(slave)
        names.append("slave")
        if not wait_port(ports["slave_op"], 30.0, slave):
            raise SystemExit(f"soak real: the slave did not start (see {out / 'slave.log'})")
        standin = SlicerStandIn("127.0.0.1", ports["slave_op"]).start()
        if not standin.connected.wait(10.0):
            raise SystemExit("soak real: the operator client could not connect to the slave")
        proxy.start()
        master = start_occd(
            ports["master_yaml"], out / "master-stats.json", out / "master.log", bound
        )
        procs.append(master)
        names.append("master")
        if not wait_port(ports["master_tcp"], 30.0, master):
            raise SystemExit(f"soak real: the master did not start (see {out / 'master.log'})")
        # the soak window starts with the stream
        t0 = time.monotonic()
        while proxy.counters.received == 0 and time.monotonic() - t0 < 10.0:
            time.sleep(0.01)
        t_start_wall = time.time()
        end = time.monotonic() + duration
        seen = 0
        resume_due: float | None = None
        while time.monotonic() < end:
            time.sleep(0.01)
            for proc in procs:
                if proc.poll() is not None:
                    raise SystemExit(f"soak real: a daemon exited early with {proc.returncode}")
            with standin._lock:
                new = standin.statuses[seen:]
                seen += len(new)
            for st in new:
                if st.error_name == "STOPPED" and resume_due is None:
                    resume_due = time.monotonic() + args.pause_ms / 1000.0
            if resume_due is not None and time.monotonic() >= resume_due:
                resume_due = None
                t_send = time.time()
                cid = standin.send_command("Run")
                r = standin.wait_reply(cid, timeout=2.0)
                runs_sent.append(
                    {
                        "t_wall": t_send,
                        "status": r.metadata.get("Status") if r else "no reply",
                        "text": getattr(r, "command", "") if r else "",
                    }
                )
        t_end_wall = time.time()
    finally:
        # the master first: the slave will then trip its deadline, after the window (ignored)
        for name, proc in reversed(list(zip(names, procs, strict=True))):
            codes[name] = stop_proc(proc)
        proxy.stop()
        if standin is not None:
            standin.stop()
    proxy.write_csv(out / "drops.csv")
    proxy.write_runs_csv(out / "proxy_runs.csv")
    proxy.write_gaps_csv(out / "proxy_gaps.csv")
    statuses = list(standin.statuses) if standin is not None else []
    stats: dict[str, Any] = {}
    for name in ("slave", "master"):
        f = out / f"{name}-stats.json"
        try:
            stats[name] = json.loads(f.read_text())
        except (OSError, ValueError):
            stats[name] = None
    analyse_real(
        rep, proxy, statuses, runs_sent, stats, codes, t_start_wall, t_end_wall, deadline_ms, args
    )
    return rep
