#!/usr/bin/env python3
"""Stop propagation in a cell, measured on real daemons (issue 40, docs/BENCHMARKS.md).

Starts ``--members`` daemons (default 3) of one cell on loopback, each a 3-DOF slave on simulated
drives holding where it is (``hold``: no stream to lose), ``--start running``, its cell link on
UDP (5 ms heartbeats, 100 ms grace). Then, ``--count`` times (default 100), one fault in member
``arm0``, cycling through the kinds:

``drive``  SIGUSR1: its drive's next write fails (tools/cellmember.py), the robot FAULTs
``estop``  an operator's ``EStop`` (COMMAND over its operator port)
``kill``   SIGKILL (silence: the others notice after the grace), then started again
``stop``   SIGSTOP for 1 s (silence as well), then SIGCONT

and for each: the time from the fault (this tool's wall clock just before it acts) to each other
member's hold (its GetStats ``cell.last_stop.wall``: the same host's clock), whether it held
and named the origin, and the origin's silence at the hold (the hold's wall time minus the send
time of the origin's last heartbeat that member took, ``cell.last_stop.origin_sent_wall``): for
the silent kinds at least the grace, though the time from the fault may be up to a heartbeat
period and the origin's last lateness less. Then the origin is brought back (Reset, Enable, Run;
a killed one restarted) and the others ``Run`` again, which they may only once the origin runs:
each of their Runs before that is refused (checked, counted). Prints p50/p99/max per kind and
writes ``--out`` JSON. Exit 1 when any fault did not stop every other member, a Run was taken
too early, a silent origin was held for before its grace (``early_silences``), or a hold was
later than its bound (20 ms; the silent kinds grace + 10 ms).

    python tools/cell_faults.py --count 100 --out /tmp/cell_faults.json
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

import yaml  # noqa: E402
from fixture_e2e import Client  # noqa: E402
from loopback import free_port, stop_processes, wait_port  # noqa: E402

KINDS = ("drive", "estop", "kill", "stop")
GRACE_MS = 100.0
BOUND_MS = {"drive": 20.0, "estop": 20.0, "kill": GRACE_MS + 10.0, "stop": GRACE_MS + 10.0}


def member_yaml(
    name: str, op_port: int, members: list[dict[str, str]], host: str = "127.0.0.1"
) -> dict[str, Any]:
    """A member on ``host``: its operators may come from any member's host (this tool runs on
    the first one)."""
    peers = sorted({m["address"].rsplit(":", 1)[0] + "/32" for m in members} | {"127.0.0.1/32"})
    limits = {"min": -1.0, "max": 1.0, "velocity": 1.5, "effort": 20.0}
    return {
        "robot": {
            "name": name,
            "rate_hz": 1000,
            "frame": {"model": "occ_slave"},
            "joints": [
                {"name": "yaw", "type": "revolute", "limits": limits, "home": 0.0},
                {"name": "pitch", "type": "revolute", "limits": limits, "home": 0.35},
                {"name": "insertion", "type": "prismatic", "home": 0.05,
                 "limits": {"min": 0.0, "max": 0.15, "velocity": 0.1, "effort": 50.0}},
            ],
            "drivers": [{"name": "sim", "plugin": "sim-signal",
                         "joints": ["yaw", "pitch", "insertion"]}],
            "realtime": {"fifo_priority": 60, "gc": "freeze", "switch_interval_us": 500},
        },
        "interfaces": [
            {"name": "operator", "transport": "tcp-server", "host": host,
             "port": op_port, "role": "operator", "allowed_peers": peers},
        ],
        "safety": {"loss": {"enabled": False}},
        "cell": {"name": "bench", "members": members, "grace_ms": GRACE_MS},
    }  # fmt: skip


class Member:
    def __init__(
        self, name: str, cfg: Path, op_port: int, log: Path, host: str = "127.0.0.1",
        enter: str = "",
    ) -> None:  # fmt: skip
        self.name, self.cfg, self.op_port, self.log = name, cfg, op_port, log
        self.host = host
        #: the pid whose network namespace the daemon runs in ('' = this one's): another host
        self.enter = enter
        self.proc: subprocess.Popen[bytes] | None = None
        self.client: Client | None = None

    def start(self) -> None:
        with self.log.open("ab") as log:
            prefix = ["nsenter", "-n", "-t", self.enter] if self.enter else []
            self.proc = subprocess.Popen(
                [*prefix, sys.executable, str(ROOT / "tools" / "cellmember.py"), str(self.cfg),
                 "--start", "running", "--log-level", "WARNING"],
                cwd=ROOT, stdout=log, stderr=log,
            )  # fmt: skip
        if not wait_port(self.op_port, 30.0, self.proc, host=self.host):
            raise RuntimeError(f"{self.name} did not start: see {self.log}")
        if self.client is None:
            self.client = Client(self.op_port, host=self.host)
            self.client.client.start()
        assert self.client.connected.wait(10.0), f"{self.name}: no operator connection"

    @property
    def op(self) -> Client:
        assert self.client is not None
        return self.client

    def stats(self) -> dict[str, Any]:
        return self.op.stats()

    def state(self) -> str:
        return str(self.stats()["state"])


def wait(cond: Any, timeout: float, step: float = 0.02) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(step)
    return False


def inject(kind: str, origin: Member) -> tuple[float, float]:
    """The fault; the wall times just before and just after it."""
    assert origin.proc is not None
    t = time.time()
    if kind == "drive":
        origin.proc.send_signal(signal.SIGUSR1)
    elif kind == "estop":
        origin.op._ask("EStop", "")
    elif kind == "kill":
        origin.op.connected.clear()  # set again when the restarted daemon takes the client
        origin.proc.kill()
        origin.proc.wait(5.0)
    elif kind == "stop":
        origin.proc.send_signal(signal.SIGSTOP)
    return t, time.time()


def recover(kind: str, origin: Member) -> None:
    assert origin.proc is not None
    if kind == "stop":
        time.sleep(max(0.0, 1.0 - 0.3))  # 1 s stopped in all (the holds took ~0.3 s to read)
        origin.proc.send_signal(signal.SIGCONT)
    if kind == "kill":
        origin.start()  # --start running
    else:
        time.sleep(0.05)
        for cmd in ("Reset", "Enable", "Run"):
            origin.op.command(cmd)
    if not wait(lambda: origin.state() == "RUNNING", 10.0, 0.05):
        raise RuntimeError(f"{origin.name} did not run again: {origin.stats().get('last_alert')}")


def one_fault(kind: str, origin: Member, others: list[Member]) -> dict[str, Any]:
    before = {m.name: (m.stats()["cell"]["last_stop"] or {}).get("wall") for m in others}
    t0, t1 = inject(kind, origin)
    row: dict[str, Any] = {"kind": kind, "held": {}, "ms": {}, "named": {}, "early_runs": 0,
                           "silence_ms": {}, "sent_after_fault": {}}  # fmt: skip
    for m in others:

        def held(m: Member = m) -> bool:
            s = m.stats()
            last = s["cell"]["last_stop"]
            return s["state"] == "STOPPED" and last is not None and last["wall"] != before[m.name]

        ok = wait(held, 5.0)
        row["held"][m.name] = ok
        if ok:
            last = m.stats()["cell"]["last_stop"]
            row["ms"][m.name] = (last["wall"] - t0) * 1e3
            row["named"][m.name] = last["origin"] == origin.name
            sent = last.get("origin_sent_wall")
            if sent is not None:
                # how long the origin had been silent when this member held, from the send time
                # of its last heartbeat taken here; one sent after the fault was over would be
                # a heartbeat the fault should have silenced (or a clock that lies)
                row["silence_ms"][m.name] = (last["wall"] - sent) * 1e3
                row["sent_after_fault"][m.name] = sent > t1
    # the others may not run before the origin does
    for m in others:
        reply = m.op.command("Run")
        if reply.get("Status") == "SUCCESS":
            row["early_runs"] += 1
    recover(kind, origin)
    for m in others:
        if not wait(lambda m=m: m.op.command("Run").get("Status") == "SUCCESS"
                    or m.state() == "RUNNING", 5.0, 0.05):  # fmt: skip
            raise RuntimeError(f"{m.name} could not run again after {origin.name} did")
    return row


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for kind in KINDS:
        ms = sorted(v for r in rows if r["kind"] == kind for v in r["ms"].values())
        n = sum(1 for r in rows if r["kind"] == kind)
        if not n:
            continue
        missed = sum(1 for r in rows if r["kind"] == kind for v in r["held"].values() if not v)
        out[kind] = {
            "faults": n,
            "holds": len(ms),
            "missed": missed,
            "p50_ms": ms[len(ms) // 2] if ms else None,
            "p99_ms": ms[min(len(ms) - 1, int(0.99 * len(ms)))] if ms else None,
            "max_ms": ms[-1] if ms else None,
            "over_bound": sum(1 for v in ms if v > BOUND_MS[kind]),
            "bound_ms": BOUND_MS[kind],
        }
    out["early_runs"] = sum(r["early_runs"] for r in rows)
    out["unnamed"] = sum(1 for r in rows for v in r["named"].values() if not v)
    silent = [r for r in rows if r["kind"] in ("kill", "stop")]
    out["early_silences"] = sum(
        1 for r in silent for v in r["silence_ms"].values() if v < GRACE_MS - 1.0
    ) + sum(1 for r in silent for v in r["sent_after_fault"].values() if v)
    return out


def run(
    count: int,
    members_n: int = 3,
    kinds: list[str] | None = None,
    *,
    verbose: bool = False,
    hosts: list[tuple[str, str]] | None = None,
) -> dict[str, Any]:
    """``count`` faults in ``arm0`` of a cell of ``members_n`` daemons (module docstring);
    ``hosts``: (address, namespace pid or '') each member runs on, in turn (default: all on
    127.0.0.1 here)."""
    kinds = kinds or list(KINDS)
    hosts = hosts or [("127.0.0.1", "")]
    tmp = Path(tempfile.mkdtemp(prefix="cell-faults-"))
    names = [f"arm{i}" for i in range(members_n)]
    cell_ports = [free_port(2) for _ in names]  # SOCK_DGRAM
    where = [hosts[i % len(hosts)] for i in range(members_n)]
    members = [
        {"name": n, "address": f"{host}:{port}"}
        for n, port, (host, _) in zip(names, cell_ports, where, strict=True)
    ]
    daemons = []
    for n, (host, enter) in zip(names, where, strict=True):
        op_port = free_port()
        cfg = tmp / f"{n}.yaml"
        cfg.write_text(yaml.safe_dump(member_yaml(n, op_port, members, host)))
        daemons.append(Member(n, cfg, op_port, tmp / f"{n}.log", host, enter))
    rows: list[dict[str, Any]] = []
    try:
        for d in daemons:
            d.start()
        if not wait(lambda: all(d.state() == "RUNNING" for d in daemons), 15.0, 0.1):
            raise RuntimeError({d.name: d.stats().get("last_alert") for d in daemons})
        origin, others = daemons[0], daemons[1:]
        for i in range(count):
            kind = kinds[i % len(kinds)]
            row = one_fault(kind, origin, others)
            rows.append(row)
            worst = max(row["ms"].values(), default=float("nan"))
            if verbose:
                print(f"{i + 1:3d} {kind:5s} held {sum(row['held'].values())}/{len(others)}"
                      f" worst {worst:6.1f} ms", flush=True)  # fmt: skip
    finally:
        for d in daemons:
            if d.proc is not None and d.proc.poll() is None:
                os.kill(d.proc.pid, signal.SIGCONT)
            if d.client is not None:
                d.client.client.stop()
        stop_processes([d.proc for d in daemons if d.proc is not None])
    result = {"members": members_n, "count": len(rows), "summary": summary(rows), "rows": rows}
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--count", type=int, default=100, help="faults (cycling through the kinds)")
    p.add_argument("--members", type=int, default=3)
    p.add_argument(
        "--kinds", default=",".join(KINDS), help="comma-separated subset of " + ",".join(KINDS)
    )
    p.add_argument("--out", type=Path, default=None)
    p.add_argument(
        "--host",
        action="append",
        default=[],
        metavar="ADDR[@PID]",
        help="a host the members run on, in turn: its address and the pid whose network "
        "namespace it is (nsenter; none = this one). Default: 127.0.0.1 here",
    )
    args = p.parse_args(argv)
    kinds = [k for k in args.kinds.split(",") if k]
    bad = [k for k in kinds if k not in KINDS]
    if bad or not kinds:
        p.error(f"unknown kinds {bad}; known: {', '.join(KINDS)}")
    hosts = [(h.partition("@")[0], h.partition("@")[2]) for h in args.host] or None
    result = run(args.count, args.members, kinds, verbose=True, hosts=hosts)
    print(json.dumps(result["summary"], indent=2))
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=1))
    s = result["summary"]
    failed = (
        s["early_runs"]
        or s["unnamed"]
        or s["early_silences"]
        or any(v["missed"] or v["over_bound"] for k, v in s.items() if isinstance(v, dict))
    )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
