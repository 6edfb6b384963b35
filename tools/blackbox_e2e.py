#!/usr/bin/env python3
"""The black box end to end (issue 41, done-when): two real daemons over the loss relay.

The shipped slave and master run as ``occd`` processes on loopback (free ports), the master's
500 Hz stream through the loss proxy (tools/loss_proxy.py), which forwards every datagram for
``--warmup`` seconds and then drops exactly three consecutive ones. The slave latches its
stop and dumps its black box by itself; then this tool

1. checks the dump is there, with a trigger in the STOPPED tick;
2. replays it (``occ-record replay --deterministic``): every setpoint of the window, the
   state of every tick and the stop at the same tick, bit for bit;
3. asks ``occ-record why``: the three sequence numbers the proxy dropped must be named;
4. replays it again with the slave's motion scale changed by 1 %: the replay must diverge,
   at the first tick of the window that commands motion.

Prints one JSON object (also written to ``OUT/report.json``) and exits 0 when all four hold.
``--seconds`` is the black box's (30 by default, the shipped value); the run lasts
``--warmup`` (default: seconds + 5) plus a few seconds. CI runs a short version
(tests/tools/test_blackbox_e2e.py).

    python tools/blackbox_e2e.py --out /tmp/bb-e2e
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path[:0] = [str(HERE), str(ROOT)]

from loopback import wait_port  # noqa: E402
from loss_proxy import LossPattern, LossProxy  # noqa: E402
from soaklib.daemons import set_master_remote, start_occd, stop_proc, write_configs  # noqa: E402

RATE_HZ = 500.0  # the master's stream


def _occ_record(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "occ.recording.cli", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )


def _configs(out: Path, seconds: float) -> dict[str, Any]:
    ports = write_configs(out, ROOT / "configs" / "slave.yaml", ROOT / "configs" / "master.yaml")
    for key in ("_slave", "_master"):
        ports[key]["black_box"] = {"seconds": seconds, "dir": str(out / "bb")}
    return ports


def run(out: Path, seconds: float, warmup: float) -> dict[str, Any]:
    """The run and its checks (module docstring); the report."""
    out.mkdir(parents=True, exist_ok=True)
    ports = _configs(out, seconds)
    start_dg = int(warmup * RATE_HZ)
    pattern = LossPattern(drop_runs=[(3, 1)], warmup=start_dg, expected=start_dg + 3, min_gap=1)
    bound = warmup + 40.0
    proxy = LossProxy(("127.0.0.1", 0), ("127.0.0.1", ports["slave_udp"]), pattern, duration=bound)
    set_master_remote(ports, proxy.address[1])
    report: dict[str, Any] = {"seconds": seconds, "warmup_s": warmup}
    procs: list[subprocess.Popen[bytes]] = []
    try:
        slave = start_occd(ports["slave_yaml"], out / "slave-stats.json", out / "slave.log", bound)
        procs.append(slave)
        if not wait_port(ports["slave_op"], 30.0, slave):
            raise SystemExit(f"blackbox e2e: the slave did not start (see {out / 'slave.log'})")
        proxy.start()
        master = start_occd(
            ports["master_yaml"], out / "master-stats.json", out / "master.log", bound
        )
        procs.append(master)
        deadline = time.monotonic() + warmup + 30.0
        bb = out / "bb"
        while time.monotonic() < deadline and not list(bb.glob("slave-*-stopped/manifest.json")):
            time.sleep(0.1)
            if slave.poll() is not None:
                raise SystemExit(f"blackbox e2e: the slave exited (see {out / 'slave.log'})")
    finally:
        for proc in reversed(procs):
            stop_proc(proc)
        proxy.stop()
    proxy.write_csv(out / "drops.csv")
    dropped = [int(r["seq"]) for r in _drops(out / "drops.csv")]
    report["dropped_seq"] = dropped
    dumps = sorted(p.parent for p in (out / "bb").glob("slave-*-stopped/manifest.json"))
    report["dumps"] = [str(p) for p in dumps]
    if not dumps:
        report["ok"] = False
        report["why_not"] = "the slave wrote no dump of a stop"
        return report
    return _check(dumps[0], dropped, report, out)


def _drops(path: Path) -> list[dict[str, str]]:
    import csv

    with open(path, newline="") as f:
        return [r for r in csv.DictReader(f) if r.get("seq")]


def _check(dump: Path, dropped: list[int], report: dict[str, Any], out: Path) -> dict[str, Any]:
    manifest = json.loads((dump / "manifest.json").read_text())
    report["dump"] = str(dump)
    report["window"] = manifest["window"]
    report["trigger_tick"] = manifest["trigger"]["tick"]
    t0 = time.monotonic()
    r = _occ_record("replay", "--deterministic", str(dump), "--json")
    report["replay_s"] = round(time.monotonic() - t0, 2)
    rep = json.loads(r.stdout) if r.stdout.strip().startswith("{") else {"error": r.stderr}
    stops = [t for t in rep.get("transitions", []) if t["to"] == "STOPPED"]
    report["replay"] = {
        "exit": r.returncode,
        "exact": rep.get("exact"),
        "ticks": rep.get("ticks"),
        "first_tick": rep.get("first_tick"),
        "stop_tick": stops[-1]["tick"] if stops else None,
        "not_restored": rep.get("not_restored"),
        "divergence": rep.get("divergence"),
        "error": rep.get("error"),
    }
    why = _occ_record("why", str(dump), "--json")
    report["why_exit"] = why.returncode
    text = why.stdout
    report["why_names_dropped"] = bool(dropped) and all(str(s) in text for s in dropped)
    # what if: the slave's motion scale 1 % larger
    raw = yaml.safe_load((dump / "config.yaml").read_text())
    raw["controller"]["params"]["scale"] = float(raw["controller"]["params"]["scale"]) * 1.01
    changed = out / "slave-scale.yaml"
    changed.write_text(yaml.safe_dump(raw, sort_keys=False))
    w = _occ_record("replay", "--deterministic", str(dump), "--config", str(changed), "--json")
    wrep = json.loads(w.stdout) if w.stdout.strip().startswith("{") else {"error": w.stderr}
    report["what_if"] = {"exit": w.returncode, "divergence": wrep.get("divergence")}
    div = wrep.get("divergence") or {}
    report["ok"] = (
        r.returncode == 0
        and rep.get("exact") is True
        and report["replay"]["stop_tick"] == report["trigger_tick"]
        and rep.get("ticks") == manifest["window"]["ticks"]
        and report["why_names_dropped"]
        and w.returncode == 4
        and str(div.get("field", "")).startswith("sp.")
    )
    return report


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=None, help="directory (default: a temporary one)")
    p.add_argument("--seconds", type=float, default=30.0, help="the black box's seconds")
    p.add_argument("--warmup", type=float, default=None, help="seconds before the drop")
    args = p.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="occ-bb-e2e-"))
    warmup = args.warmup if args.warmup is not None else args.seconds + 5.0
    report = run(out, args.seconds, warmup)
    (out / "report.json").write_text(json.dumps(report, indent=1))
    print(json.dumps(report, indent=1))
    return 0 if report.get("ok") else 1


if __name__ == "__main__":
    sys.exit(main())
