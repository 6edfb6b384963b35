#!/usr/bin/env python3
"""Safety that trips on real faults only, measured on this machine with the real daemons.

Two measurements (each bounded in time, loopback only):

``pairs``
    Two master/slave pairs (four ``occd`` processes, SCHED_FIFO where permitted) streaming at
    500 Hz, each slave read by two Slicer-like clients (10 Hz TRANSFORMs) and asked for its
    statistics once a second, for ``--duration`` seconds. Reports latched stops (must be
    zero: nothing failed), holds and resumes, each loop's lateness p99.9 and max, the CPU
    of each daemon, each slave's master sample -> drive write latency p50/p99/max, the build
    each daemon ran (compiled or pure), and every daemon that left RUNNING with the cause from
    its log. ``--hogs N`` adds N ordinary CPU hogs (busy pure-Python processes at normal
    priority, as ``tools/soak.py real --hogs``: a workstation compiling beside Slicer).
    ``--pure B`` runs pair B with ``OCC_PURE=1`` (the pure Python hot path) and pair A as
    installed: the compiled and pure builds side by side in one run, same load. Beside it
    runs ``benchmarks/stall_probe.c`` (compiled with gcc into ``~/.cache/occ-bench``; skipped
    where there is no gcc): one SCHED_FIFO 99 thread per CPU that records every wake-up more
    than 1 ms late. A daemon stop at the moment every CPU was late is the machine's stall, not
    the daemon's. Each daemon's worst late ticks (its statistics keep the 20 worst over 1 ms,
    with the wall-clock time each started) are listed beside what the probe saw at the same
    moment (``late_ticks``: ``probe_late_ms``, the probe's worst late wake-up overlapping the
    tick's wait, and on how many CPUs), and ``lateness_max_outside_probe_us`` is the worst of
    them with no probe wake-up late at the same time (None: all of them were): the maxima that
    are the machine's, and the ones that are the daemon's own.

``sigstop``
    One pair. The master process is frozen with SIGSTOP for 30 ms and resumed with SIGCONT,
    ``--count`` times one second apart (a GC pause, a VM hiccup: the slave must hold and resume,
    never latch); then frozen for 1.5 s (a dead master: the slave must latch STOPPED and alert
    the operators, naming the cause).

Examples::

    python benchmarks/bench_safety.py pairs --duration 600
    python benchmarks/bench_safety.py pairs --duration 360 --hogs 1 --pure B
    python benchmarks/bench_safety.py sigstop --count 20

The result is printed as JSON and written to ``OUT/result.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

from loopback import pair_configs, stop_processes, wait_port, write_yaml  # noqa: E402
from slicer_standin import SlicerStandIn  # noqa: E402
from soaklib.hogs import start_hogs, stop_hogs  # noqa: E402


def start(
    out: Path, name: str, data: dict[str, Any], pure: bool = False
) -> subprocess.Popen[bytes]:
    data["stats"] = {"log_every_s": 3600.0}
    write_yaml(out / f"{name}.yaml", data)
    cmd = [
        sys.executable,
        "-m",
        "occ.cli",
        str(out / f"{name}.yaml"),
        "--start",
        "running",
        "--stats",
        str(out / f"{name}.json"),
        "--log-level",
        "WARNING",
    ]
    env = dict(os.environ)
    if pure:
        env["OCC_PURE"] = "1"
    return subprocess.Popen(cmd, cwd=ROOT, env=env, stderr=open(out / f"{name}.log", "wb"))  # noqa: SIM115


PROBE_SRC = ROOT / "benchmarks" / "stall_probe.c"
LATE_LINE = re.compile(r"^late cpu(\d+) (\d\d:\d\d:\d\d\.\d\d\d) ([\d.]+) ms$")
STATE_LINE = re.compile(r"^(\d\d:\d\d:\d\d\.\d+) \w+ +occ\.core\.robot: state (\w+) -> (\w+) (.*)$")


def start_probe(
    seconds: float, out: Path, period_us: float = 1000.0
) -> subprocess.Popen[bytes] | None:
    """The stall probe beside the run (waking every ``period_us`` on each CPU), or None where it
    cannot be built (no gcc) or ``period_us`` is 0 (no probe)."""
    gcc = shutil.which("gcc")
    if gcc is None or not period_us:
        return None
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "occ-bench"
    exe = cache / "stall_probe"
    if not exe.exists() or exe.stat().st_mtime < PROBE_SRC.stat().st_mtime:
        cache.mkdir(parents=True, exist_ok=True)
        built = subprocess.run(
            [gcc, "-O2", "-pthread", "-o", str(exe), str(PROBE_SRC)], capture_output=True
        )
        if built.returncode != 0:
            print(f"stall probe not built: {built.stderr.decode(errors='replace')}", flush=True)
            return None
    with open(out / "stall_probe.log", "wb") as log:  # the child keeps its own copy
        return subprocess.Popen(
            [str(exe), f"{seconds:.0f}", str(PROBE_THRESHOLD_US), f"{period_us:.0f}"], stdout=log
        )


PROBE_THRESHOLD_US = 1000


def probe_spans(out: Path) -> list[tuple[float, float, str]]:
    """The probe's late wake-ups as (start, end, cpu): ms of the (local) day, the interval the
    probe could not run (from its deadline to its wake-up)."""
    spans = []
    for line in (out / "stall_probe.log").read_text().splitlines():
        m = LATE_LINE.match(line)
        if m:
            end = _ms_of_day(m.group(2))
            spans.append((end - float(m.group(3)), end, m.group(1)))
    spans.sort()
    return spans


def probe_summary(proc: subprocess.Popen[bytes] | None, out: Path) -> dict[str, Any] | None:
    """The probe's late wake-ups merged into stalls.

    A wake-up ``late`` ms after its deadline means the probe could not run from the deadline to
    the wake-up; wake-ups (of any CPU) whose such intervals overlap or lie within 2 ms of each
    other are one stall, reported by its start, its span and the CPUs it held up. Stalls of
    10 ms or more are listed; ``machine_wide`` means every CPU was held up in it.
    """
    if proc is None:
        return None
    proc.terminate()
    proc.wait(5.0)
    spans = probe_spans(out)
    stalls: list[dict[str, Any]] = []
    for start, end, cpu in spans:
        if stalls and start <= stalls[-1]["_end"] + 2.0:
            st = stalls[-1]
            st["_end"] = max(st["_end"], end)
            st["_cpus"].add(cpu)
        else:
            stalls.append({"_start": start, "_end": end, "_cpus": {cpu}})
    ncpu = os.cpu_count() or 1
    listed = [
        {
            "at": _hms(st["_start"]),
            "span_ms": round(st["_end"] - st["_start"], 1),
            "cpus": sorted(st["_cpus"]),
            "machine_wide": len(st["_cpus"]) == ncpu,
        }
        for st in stalls
        if st["_end"] - st["_start"] >= 10.0
    ]
    return {
        "threshold_ms": PROBE_THRESHOLD_US / 1e3,
        "late_wakeups": len(spans),
        "stalls_over_10ms": len(listed),
        "stalls_over_20ms": sum(1 for st in listed if st["span_ms"] >= 20.0),
        "stalls": listed,
    }


def _hms(ms_of_day: float) -> str:
    s = ms_of_day / 1e3
    return f"{int(s // 3600):02d}:{int(s % 3600 // 60):02d}:{s % 60:06.3f}"


def _ms_of_day(hms: str) -> float:
    h, m, s = hms.split(":")
    return (int(h) * 3600 + int(m) * 60 + float(s)) * 1e3


def _local_ms_of_day(unix_s: float) -> float:
    """Unix time to ms of the local day, as the probe's log gives its times."""
    t = time.localtime(unix_s)
    return ((t.tm_hour * 60 + t.tm_min) * 60 + t.tm_sec + unix_s % 1.0) * 1e3


def beside_probe(
    late_ticks: list[dict[str, float]], spans: list[tuple[float, float, str]] | None
) -> tuple[list[dict[str, Any]], float | None]:
    """Each of a daemon's worst late ticks (``at``: Unix time the tick started, ``late_us``)
    with the probe's late wake-ups at the same moment: those whose interval overlaps the tick's
    wait (from its deadline to its start, 0.5 ms of slack for the two clocks' readings). Returns
    the listed ticks and the worst one no probe wake-up overlaps (None: every one had one)."""
    listed: list[dict[str, Any]] = []
    outside: float | None = None
    for tick in late_ticks:
        end = _local_ms_of_day(tick["at"])
        start = end - tick["late_us"] / 1e3
        row: dict[str, Any] = {"at": _hms(end), "late_ms": round(tick["late_us"] / 1e3, 2)}
        if spans is not None:
            hits = [sp for sp in spans if sp[0] <= end + 0.5 and sp[1] >= start - 0.5]
            row["probe_late_ms"] = round(max(sp[1] - sp[0] for sp in hits), 1) if hits else None
            row["probe_cpus"] = len({sp[2] for sp in hits})
            if not hits and (outside is None or tick["late_us"] > outside):
                outside = tick["late_us"]
        listed.append(row)
    return listed, outside


def state_changes(log: Path) -> list[str]:
    """Each ``state A -> B (why)`` line of a daemon's log: what left RUNNING, and why."""
    found = []
    for line in log.read_text(errors="replace").splitlines():
        m = STATE_LINE.match(line)
        if m:
            found.append(f"{m.group(1)} {m.group(2)} -> {m.group(3)} {m.group(4)}")
    return found


def loop_summary(stats: dict[str, Any]) -> dict[str, Any]:
    late = stats["lateness_us"]
    return {
        "build": stats.get("build"),
        "final_state": stats.get("final_state"),
        "ticks": stats["ticks"],
        "lateness_p99_9_us": late["p99_9"],
        "lateness_max_us": late["max"],
        "late_over_1ms": stats["late_over_1ms"],
        "cpu_percent": stats["cpu_percent"],
    }


def tolerate(cfg: dict[str, Any], ms: float) -> None:
    """Let the daemon ride out a stall of the whole machine shorter than ``ms``: the
    supervisor's timeout, the watchdog's hard gap and every drive's heartbeat set to ``ms``
    (defaults 20, 50, 50). For a VM whose CPUs are taken away for tens of milliseconds."""
    safety = cfg.setdefault("safety", {})
    safety.setdefault("supervisor", {})["timeout_ms"] = ms
    safety.setdefault("watchdog", {})["hard_gap_ms"] = ms
    for drv in cfg["robot"]["drivers"]:
        drv.setdefault("params", {})["heartbeat_ms"] = ms


def start_pair(
    out: Path,
    tag: str,
    spin_us: float | None,
    tolerance_ms: float | None = None,
    phase_lock_us: float | None = None,
    pure: bool = False,
) -> tuple[list[subprocess.Popen[bytes]], dict[str, int]]:
    slave, master, ports = pair_configs()
    for cfg in (slave, master):
        if spin_us is not None:
            cfg["robot"]["realtime"]["spin_us"] = spin_us
        if tolerance_ms is not None:
            tolerate(cfg, tolerance_ms)
    if phase_lock_us is not None:  # negative: off
        lock = None if phase_lock_us < 0 else phase_lock_us
        slave["controller"]["params"]["phase_lock_us"] = lock
    procs = [start(out, f"slave{tag}", slave, pure)]
    if not wait_port(ports["slave_tcp"], 30.0, procs[0]):
        raise SystemExit(f"slave{tag} did not start; see {out}/slave{tag}.log")
    procs.append(start(out, f"master{tag}", master, pure))
    if not wait_port(ports["master_tcp"], 30.0, procs[1]):
        raise SystemExit(f"master{tag} did not start; see {out}/master{tag}.log")
    return procs, ports


def stops_seen(client: SlicerStandIn) -> list[str]:
    with client._lock:
        return [s.status_message for s in client.statuses if s.error_name == "STOPPED"]


def run_pairs(args: argparse.Namespace, out: Path) -> dict[str, Any]:
    procs: list[subprocess.Popen[bytes]] = []
    clients: list[SlicerStandIn] = []
    probe = start_probe(args.duration + 120.0, out, args.probe_period_us)
    hogs: list[subprocess.Popen[bytes]] = []
    hog_shares: list[float | None] = []
    try:
        for tag in ("A", "B"):
            p, ports = start_pair(
                out, tag, args.spin_us, args.tolerate_ms, args.phase_lock_us, tag in args.pure
            )
            procs += p
            clients += [SlicerStandIn("127.0.0.1", ports["slave_tcp"]).start() for _ in range(2)]
        for c in clients:
            c.connected.wait(10.0)
        t_hogs = time.monotonic()
        hogs = start_hogs(args.hogs, args.duration + 90.0)
        print(
            f"pairs: 4 daemons, 4 clients, {args.hogs} CPU hog(s), {args.duration:.0f} s; "
            f"files in {out}",
            flush=True,
        )
        end = time.monotonic() + args.duration
        while time.monotonic() < end:
            time.sleep(1.0)
            for c in clients[::2]:  # an operator console asks each slave once a second
                c.send_command("GetStats")
            if any(p.poll() is not None for p in procs):
                raise SystemExit("pairs: a daemon exited early")
        latched = {f"slave{t}": stops_seen(c) for t, c in zip("AB", clients[::2], strict=True)}
    finally:
        if hogs:
            hog_shares = stop_hogs(hogs, t_hogs)
        for c in clients:
            c.stop()
        stop_processes(procs)
        machine = probe_summary(probe, out)
    spans = probe_spans(out) if machine is not None else None
    daemons = {}
    for name in ("slaveA", "masterA", "slaveB", "masterB"):
        d = json.loads((out / f"{name}.json").read_text())
        daemons[name] = loop_summary(d)
        listed, outside = beside_probe(d.get("late_ticks", []), spans)
        daemons[name]["late_ticks"] = listed
        daemons[name]["lateness_max_outside_probe_us"] = outside
        daemons[name]["state_changes"] = state_changes(out / f"{name}.log")
        lat = d.get("controller", {}).get("sample_to_write_us")
        if lat is not None:
            daemons[name]["sample_to_write_us"] = lat
            daemons[name]["sample_to_rx_us"] = d["controller"].get("sample_to_rx_us")
            daemons[name]["phase_shifts"] = d["controller"].get("phase_shifts")
            daemons[name]["phase_error_us"] = d["controller"].get("phase_error_us")
        if "loss" in d:
            daemons[name]["loss"] = {
                k: d["loss"][k] for k in ("received", "lost_total", "holds", "resumes", "trips")
            }
    return {
        "mode": "pairs",
        "duration_s": args.duration,
        "tolerate_ms": args.tolerate_ms,
        "hogs": args.hogs,
        "hog_cpu_percent": hog_shares,
        "pure_pairs": sorted(args.pure),
        "load_after": " ".join(Path("/proc/loadavg").read_text().split()[:3]),
        "latched_stops": sum(len(v) for v in latched.values()),
        "stop_alerts": latched,
        "left_running": sorted(n for n, d in daemons.items() if d["final_state"] != "RUNNING"),
        "machine_stalls": machine,
        "daemons": daemons,
    }


def freeze(proc: subprocess.Popen[bytes], seconds: float) -> float:
    t0 = time.monotonic()
    os.kill(proc.pid, signal.SIGSTOP)
    time.sleep(seconds)
    os.kill(proc.pid, signal.SIGCONT)
    return time.monotonic() - t0


def run_sigstop(args: argparse.Namespace, out: Path) -> dict[str, Any]:
    procs, ports = start_pair(out, "", args.spin_us, args.tolerate_ms, args.phase_lock_us)
    client = SlicerStandIn("127.0.0.1", ports["slave_tcp"]).start()
    try:
        client.connected.wait(10.0)
        time.sleep(2.0)  # the stream flows
        frozen = []
        for _ in range(args.count):
            frozen.append(freeze(procs[1], 0.030))
            time.sleep(1.0)
        short_stops = stops_seen(client)
        with client._lock:
            warnings = [s.status_message for s in client.statuses if s.error_name == "STREAM"]
        long_frozen = freeze(procs[1], 1.5)
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline and len(stops_seen(client)) == len(short_stops):
            time.sleep(0.05)
        long_stops = stops_seen(client)[len(short_stops) :]
    finally:
        client.stop()
        stop_processes(procs)
    slave = json.loads((out / "slave.json").read_text())
    return {
        "mode": "sigstop",
        "short_freezes": len(frozen),
        "short_frozen_ms": [round(f * 1e3, 1) for f in frozen],
        "latched_after_short_freezes": len(short_stops),
        "resume_warnings": len(warnings),
        "long_freeze_ms": round(long_frozen * 1e3, 1),
        "latched_after_long_freeze": len(long_stops),
        "long_freeze_alert": long_stops[:1],
        "slave_loss": {
            k: slave["loss"][k] for k in ("received", "lost_total", "holds", "resumes", "trips")
        },
        "slave_final_state": slave.get("final_state"),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("mode", choices=["pairs", "sigstop"])
    p.add_argument("--duration", type=float, default=60.0, help="pairs: seconds (default 60)")
    p.add_argument("--count", type=int, default=20, help="sigstop: 30 ms freezes (default 20)")
    p.add_argument("--spin-us", type=float, default=None, help="override robot.realtime.spin_us")
    p.add_argument(
        "--tolerate-ms",
        type=float,
        default=None,
        help="supervisor timeout, watchdog hard gap and drive heartbeats (default: as shipped)",
    )
    p.add_argument(
        "--phase-lock-us",
        type=float,
        default=None,
        help="override the slaves' teleop phase_lock_us (negative = off; default: as shipped)",
    )
    p.add_argument("--hogs", type=int, default=0, help="pairs: ordinary CPU hogs (default 0)")
    p.add_argument(
        "--pure",
        default="",
        help="pairs: the pairs (A, B or AB) run with OCC_PURE=1, the pure Python build",
    )
    p.add_argument(
        "--probe-period-us",
        type=float,
        default=1000.0,
        help="pairs: the stall probe's period (default 1000; 0 = no probe): it preempts the "
        "daemons on every CPU at each wake-up",
    )
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    if args.hogs < 0 or set(args.pure) - {"A", "B"}:
        p.error("--hogs must be >= 0; --pure takes A, B or AB")
    out = args.out or Path(tempfile.mkdtemp(prefix=f"occ-safety-{args.mode}-"))
    out.mkdir(parents=True, exist_ok=True)
    result = run_pairs(args, out) if args.mode == "pairs" else run_sigstop(args, out)
    (out / "result.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
