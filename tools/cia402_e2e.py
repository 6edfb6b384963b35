"""The OCC slave on CiA 402 drives, end to end: ``occd configs/slave-cia402.yaml`` against the
CiA 402 drive emulator in another process, on python-can's ``udp_multicast`` bus.

1. start ``python -m occ.drivers.cia402_sim`` (nodes 1, 2, 3 on 239.74.163.2, SCHED_FIFO 60
   where permitted, as the daemons' loops) and
   ``occd configs/slave-cia402.yaml``, which configures the three nodes over SDO;
2. start ``occd configs/master.yaml --start running`` (its simulated hand streams the OCC
   paper's motion to the slave) and, on the slave's operator port (18947), Enable and Run;
3. watch the slave's ``Tip`` on its 3D Slicer port (18944) move, and ``GetStats``: the state,
   every node OPERATION ENABLED, the bus load, the loop's lateness;
4. with ``--fault`` (e.g. ``"emcy 2 0x2310"``), type that on the emulator's standard input
   and wait for the slave to latch FAULT naming the node and the cause.

The report's ``cycle`` is the slave's cycle as the emulated drives received it over the watched
seconds (the emulator's ``timing`` command; occ/drivers/cia402_sim.py, ``CycleTimes``): per
SYNC, the time from the cycle's first RPDO to the SYNC (``rpdo_to_sync_us``), from its last
RPDO to the SYNC (``setpoints_ready_us``: how long before the SYNC every setpoint was there),
and from the SYNC's arrival to the drives' last TPDO answering it (``sync_to_tpdo_us``), each
as count, min, p50, p99, p99.9 and max in µs. With ``--profile`` the slave runs under
tools/profiled.py and the report's ``profile`` is its loop thread's time over the watched
seconds, per owner (python-can's ``udp_multicast``, canopen, the driver, the rest).

The report also has each process's CPU over the watched seconds (``cpu_percent``, from
/proc/PID/stat) and the slave's loop lateness (GetStats): ``--slave configs/slave.yaml`` runs
the same with the simulated drives (no emulator), the benchmark's other half
(docs/BENCHMARKS.md, "CiA 402 drives").

It prints one JSON report (``--json``) and exits 0; the checks are the test's
(tests/occ/test_cia402_e2e.py). Multicast needs a route on a host without a default route:
``--lo-up`` brings the loopback up and adds ``239.0.0.0/8 dev lo`` (a fresh network namespace,
where nothing leaves the host)::

    unshare -n python tools/cia402_e2e.py --lo-up --seconds 5 --fault "emcy 2 0x2310"
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

from fixture_e2e import Client, loopback_up  # noqa: E402
from loopback import stop_processes, wait_port  # noqa: E402
from profiled import summary  # noqa: E402

SLAVE = ROOT / "configs" / "slave-cia402.yaml"
MASTER = ROOT / "configs" / "master.yaml"
OPERATOR, SLICER = 18947, 18944
#: the emulated drives' SCHED_FIFO priority (where permitted), the daemons' loops' own (their
#: configs' realtime): drives are hardware of their own, and a drive emulator starved by the
#: host's other work answered its SYNCs 20-90 ms late under load, which the slave rightly
#: faulted (docs/VERIFICATION.md, the cia402 section)
EMULATOR_FIFO = 60


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far, s (/proc/PID/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def emulator_says(proc: subprocess.Popen[bytes], log: Path, line: str, prefix: str) -> str:
    """``line`` typed on the emulator's standard input, and the first line of its output
    after that which starts with ``prefix`` (within 10 s)."""
    assert proc.stdin is not None
    seen = len(log.read_bytes())
    proc.stdin.write((line + "\n").encode())
    proc.stdin.flush()
    end = time.monotonic() + 10.0
    while time.monotonic() < end:
        for out in log.read_bytes()[seen:].decode(errors="replace").splitlines():
            if out.startswith(prefix):
                return out
        time.sleep(0.05)
    raise AssertionError(f"the emulator did not answer {line!r}")


def run(
    seconds: float,
    fault: str | None,
    out_dir: Path,
    slave_cfg: Path = SLAVE,
    profile: bool = False,
) -> dict[str, Any]:
    report: dict[str, Any] = {"slave_config": str(slave_cfg)}
    drivers = yaml.safe_load(slave_cfg.read_text())["robot"]["drivers"]
    emulated = any(d["plugin"] == "cia402" for d in drivers)
    drive = drivers[0]["name"]
    procs: list[subprocess.Popen[bytes]] = []
    logs: dict[str, Path] = {}

    def start(name: str, cmd: list[str], **kw: Any) -> subprocess.Popen[bytes]:
        logs[name] = out_dir / f"{name}.log"
        proc = subprocess.Popen(
            cmd, cwd=ROOT, stdout=logs[name].open("wb"), stderr=subprocess.STDOUT, **kw
        )
        procs.append(proc)
        return proc

    slicer, operator = Client(SLICER), Client(OPERATOR)
    emulator: subprocess.Popen[bytes] | None = None
    try:
        if emulated:
            emulator = start(
                "emulator",
                [sys.executable, "-m", "occ.drivers.cia402_sim", "--interface",
                 "udp_multicast", "--channel", "239.74.163.2", "--nodes", "1,2,3",
                 "--fifo-priority", str(EMULATOR_FIFO)],
                stdin=subprocess.PIPE,
            )  # fmt: skip
            end = time.monotonic() + 30.0
            while "cia402 emulator: nodes" not in logs["emulator"].read_text():
                assert emulator.poll() is None and time.monotonic() < end, "no emulator"
                time.sleep(0.05)
        prof = out_dir / "slave.prof"
        wrap = [str(ROOT / "tools" / "profiled.py"), str(prof)] if profile else []
        slave = start(
            "slave",
            [sys.executable, *wrap, "-m", "occ.cli", str(slave_cfg), "--log-level", "WARNING"],
        )
        assert wait_port(OPERATOR, 30.0, slave), "the slave did not listen"
        master = start(
            "master",
            [sys.executable, "-m", "occ.cli", str(MASTER), "--start", "running",
             "--log-level", "WARNING"],
        )  # fmt: skip
        slicer.client.start()
        operator.client.start()
        assert slicer.connected.wait(10.0) and operator.connected.wait(10.0)
        before = operator.stats()
        report["before"] = {
            "state": before["state"],
            "drivers": before["drivers"],
            "hardware": before.get("hardware", {}).get("states"),
        }
        report["enable"] = operator.command("Enable")
        report["run"] = operator.command("Run")
        first = None
        end = time.monotonic() + 20.0
        while time.monotonic() < end and first is None:
            got = slicer.tip()
            first = got[1] if got else None
            time.sleep(0.05)
        samples = []
        pids = {"slave": slave.pid, "master": master.pid}
        if emulator is not None:
            pids["emulator"] = emulator.pid
        if emulator is not None:  # the master's cycle as the drives receive it, from here
            emulator_says(emulator, logs["emulator"], "timing reset", "ok: timing reset")
        cpu0 = {name: cpu_seconds(pid) for name, pid in pids.items()}
        if profile:
            prof.with_name(prof.name + ".json").unlink(missing_ok=True)
            slave.send_signal(signal.SIGUSR1)  # the profiler on (tools/profiled.py)
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            time.sleep(0.5)
            snap = operator.stats()
            got = slicer.tip()
            arm = snap["drivers"][drive]
            samples.append(
                {
                    "t": round(time.monotonic() - t0, 2),
                    "state": snap["state"],
                    "tip_mm": got[1] if got else None,
                    "nodes": {j: n["cia402"] for j, n in arm.get("nodes", {}).items()},
                    "sync_frames": arm.get("sync_frames"),
                    "tpdo_frames": arm.get("tpdo_frames"),
                }
            )
            if snap["state"] == "STOPPED":
                operator.command("Run")  # a late master on a loaded machine: go on
        window = time.monotonic() - t0
        if profile:
            slave.send_signal(signal.SIGUSR1)  # and off: the statistics written
            done = prof.with_name(prof.name + ".json")
            end = time.monotonic() + 30.0
            while not done.exists() and time.monotonic() < end:
                time.sleep(0.1)
            report["profile"] = summary(prof)
        report["cpu_percent"] = {
            name: round(100.0 * (cpu_seconds(pid) - cpu0[name]) / window, 1)
            for name, pid in pids.items()
        }
        if emulator is not None:
            said = emulator_says(emulator, logs["emulator"], "timing", "cia402 emulator timing: ")
            report["cycle"] = json.loads(said.split(": ", 1)[1])
        last = operator.stats()
        report["samples"] = samples
        report["first_tip_mm"] = first
        report["arm"] = last["drivers"][drive]
        report["lateness"] = {k: v for k, v in last.items() if "late" in k}
        report["state"] = last["state"]
        if fault is not None and emulator is not None and emulator.stdin is not None:
            emulator.stdin.write((fault + "\n").encode())
            emulator.stdin.flush()
            end = time.monotonic() + 10.0
            snap = last
            while time.monotonic() < end:
                snap = operator.stats()
                if snap["state"] == "FAULT":
                    time.sleep(0.2)  # the nodes' TPDOs after the quick stop
                    snap = operator.stats()
                    break
                time.sleep(0.1)
            report["fault"] = {
                "state": snap["state"],
                "last_alert": snap.get("last_alert"),
                "arm": snap["drivers"][drive],
                "statuses": operator.statuses[-5:],
            }
    finally:
        slicer.client.stop()
        operator.client.stop()
        stop_processes(procs)
        report["logs"] = {name: path.read_text()[-2000:] for name, path in logs.items()}
    return report


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=5.0, help="the motion watched")
    p.add_argument("--fault", default=None, help="an emulator command at the end")
    p.add_argument("--slave", type=Path, default=SLAVE, help="the slave's config")
    p.add_argument("--lo-up", action="store_true", help="loopback up, multicast routed to it")
    p.add_argument("--out-dir", type=Path, default=Path("."), help="the processes' logs")
    p.add_argument("--json", type=Path, default=None, help="write the report here")
    p.add_argument(
        "--profile",
        action="store_true",
        help="cProfile the slave's loop thread over the watched seconds (tools/profiled.py)",
    )
    args = p.parse_args(argv)
    if args.lo_up:
        loopback_up()
        subprocess.run(["ip", "route", "add", "239.0.0.0/8", "dev", "lo"], check=True)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    report = run(args.seconds, args.fault, args.out_dir, args.slave, args.profile)
    text = json.dumps(report, indent=1)
    if args.json is not None:
        args.json.write_text(text)
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
