#!/usr/bin/env python3
"""The console PC and the robot PC as two hosts: the shipped pair across a network.

Two private network namespaces stand for the two machines, joined by a veth pair (a cable):
the console at 10.211.7.1 (the master daemon, 3D Slicer, the operators, a ROS 2 user) and the
robot at 10.211.7.2 (the slave daemon and, with ``--ros2``, the ROS 2 bridge). The addresses
exist only inside those namespaces. The shipped configs are changed only in ``host``,
``remote`` and ``allowed_peers`` (``two_machine_configs``; README, "Two machines"):

- slave (robot PC): every interface listens on the robot's address and takes only the console
  and the robot PC itself (``allowed_peers: [10.211.7.1/32, 10.211.7.2/32]``: the ROS 2 bridge
  runs beside the slave);
- master (console PC): its operator port on the console's address (local operators and Slicer
  connect there, so ``allowed_peers`` is the console itself), its stream sent to
  ``10.211.7.2:18946`` and taken back (the slave's tip) only from the robot.

Then both daemons run (``--start running``) and, from the console, a Slicer-like client reads
the slave's ``Tip`` on 10.211.7.2:18944, an operator asks both daemons for their statistics,
and the report says whether the slave follows its master across the cable with nothing lost,
whether the master gets the slave's tip back (the return channel), and what a client from
another address gets (refused: it is not in ``allowed_peers``). Needs root (network
namespaces). ``--ros2`` adds the ROS 2 bridge on the robot PC with the DDS configuration for a
real interface (``occ_ros2/cyclonedds-net.xml``); its test (tests/test_two_machines.py) adds a
real rclpy node on the console PC::

    python tools/two_machines.py --seconds 5
    python tools/two_machines.py --json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

from occ_testkit.netns import Netns  # noqa: E402

CONSOLE = "10.211.7.1"
ROBOT = "10.211.7.2"
PREFIX = 24
#: the keys the shipped configs are changed in, and nothing else
CHANGED_KEYS = ("host", "remote", "allowed_peers")


def two_machine_configs(out: Path) -> dict[str, Path]:
    """The shipped slave and master for two hosts, written to ``out``."""
    slave = yaml.safe_load((ROOT / "configs" / "slave.yaml").read_text())
    master = yaml.safe_load((ROOT / "configs" / "master.yaml").read_text())
    for iface in slave["interfaces"]:
        iface["host"] = ROBOT
        # the console PC, and the robot PC itself (the ROS 2 bridge and tools beside the slave)
        iface["allowed_peers"] = [f"{CONSOLE}/32", f"{ROBOT}/32"]
    for iface in master["interfaces"]:
        iface["host"] = CONSOLE
        if iface.get("remote"):
            port = str(iface["remote"]).rpartition(":")[2]
            iface["remote"] = f"{ROBOT}:{port}"
            iface["allowed_peers"] = [f"{ROBOT}/32"]  # the slave's tip comes back from there
        else:
            iface["allowed_peers"] = [f"{CONSOLE}/32"]
    paths = {"slave": out / "slave.yaml", "master": out / "master.yaml"}
    for name, data in (("slave", slave), ("master", master)):
        paths[name].write_text(yaml.safe_dump(data, sort_keys=False))
    return paths


def _diff(a: Any, b: Any, path: str = "") -> list[str]:
    """Where two YAML documents differ, as key paths."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b), key=str):
            out += _diff(a.get(k), b.get(k), f"{path}.{k}" if path else str(k))
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        pairs = enumerate(zip(a, b, strict=True))
        return [d for i, (x, y) in pairs for d in _diff(x, y, f"{path}[{i}]")]
    return [] if a == b else [path]


def changed_keys(paths: dict[str, Path]) -> list[str]:
    """Every key path where the two-machine configs differ from the shipped ones."""
    out = []
    for name, path in paths.items():
        shipped = yaml.safe_load((ROOT / "configs" / f"{name}.yaml").read_text())
        out += [f"{name}: {d}" for d in _diff(shipped, yaml.safe_load(path.read_text()))]
    return out


PROBE = r"""
import json, socket, sys, time
sys.path.insert(0, sys.argv[1] + "/tools")
from fixture_e2e import Client
robot, console, seconds = sys.argv[2], sys.argv[3], float(sys.argv[4])
report = {}
slicer = Client(18944, robot)
slave_op = Client(18947, robot)
master_op = Client(18945, console)
for c in (slicer, slave_op, master_op):
    c.client.start()
try:
    for c in (slicer, slave_op, master_op):
        assert c.connected.wait(15.0), "no connection"
    # the pair is up when the master has a fresh tip from a slave that follows it
    end = time.monotonic() + 20.0
    while time.monotonic() < end:
        tip = master_op.stats().get("controller", {}).get("slave_tip") or {}
        if tip.get("status") == "fresh" and tip.get("following"):
            break
        time.sleep(0.2)
    first = slave_op.stats()
    tips = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        got = slicer.tip()
        if got is not None and (not tips or got[0] != tips[-1][0]):
            tips.append(got)
        time.sleep(0.05)
    last = slave_op.stats()
    mstats = master_op.stats()
    loss = last.get("loss") or {}
    axes = [[p[1][i] for p in tips] for i in range(3)] if tips else []
    span = [max(a) - min(a) for a in axes]
    report.update(
        slave_state=last.get("state"), master_state=mstats.get("state"),
        slave_received=loss.get("accepted", 0) - (first.get("loss") or {}).get("accepted", 0),
        lost=loss.get("lost_total"), trips=loss.get("trips"), holds=loss.get("holds"),
        tips=len(tips), tip_span_mm=[round(v, 3) for v in span],
        return_channel=(mstats.get("controller") or {}).get("slave_tip"),
    )
    # a client from another address than the console's is refused by the robot
    s = socket.socket()
    s.settimeout(3.0)
    s.bind((sys.argv[5], 0))
    try:
        s.connect((robot, 18947))
        s.settimeout(2.0)
        data = b""
        while len(data) < 4096:  # what it is told before the robot closes the connection
            chunk = s.recv(4096)
            if not chunk:
                break
            data += chunk
        if not data:
            report["stranger"] = "closed"
        else:
            import igtl
            msg = igtl.unpack(data)
            report["stranger"] = (
                f"refused: {msg.message_type} {getattr(msg, 'status_message', '')!r}, closed"
            )
    except OSError as err:
        report["stranger"] = f"refused ({type(err).__name__})"
    finally:
        s.close()
finally:
    for c in (slicer, slave_op, master_op):
        c.client.stop()
print(json.dumps(report))
"""

#: a second address on the console's cable, not in the slave's ``allowed_peers``
STRANGER = "10.211.7.9"


class TwoMachines:
    """The two hosts and their daemons (module docstring); a context manager."""

    def __init__(self, out: Path) -> None:
        self.out = out
        self.console = Netns()
        self.robot = Netns()
        self.console_if, self.robot_if = self.console.link(
            self.robot, f"{CONSOLE}/{PREFIX}", f"{ROBOT}/{PREFIX}", name="occ2m"
        )
        self.console.run(["ip", "addr", "add", f"{STRANGER}/{PREFIX}", "dev", self.console_if])
        self.paths = two_machine_configs(out)

    def env(self) -> dict[str, str]:
        return {k: v for k, v in os.environ.items() if not k.startswith(("ROS_", "RMW_"))}

    def start_daemons(self) -> None:
        for ns, name in ((self.robot, "slave"), (self.console, "master")):
            log = (self.out / f"{name}.log").open("wb")
            ns.popen(
                [sys.executable, "-m", "occ.cli", str(self.paths[name]), "--start", "running",
                 "--log-level", "WARNING"],
                cwd=ROOT, env=self.env(), stdout=log, stderr=subprocess.STDOUT,
            )  # fmt: skip
            wait = (
                "import socket,sys,time\n"
                "end=time.monotonic()+30\n"
                "while time.monotonic()<end:\n"
                "    s=socket.socket(); s.settimeout(0.2)\n"
                "    ok=s.connect_ex((sys.argv[1],int(sys.argv[2])))==0; s.close()\n"
                "    if ok: sys.exit(0)\n"
                "    time.sleep(0.05)\n"
                "sys.exit(1)\n"
            )
            host, port = (ROBOT, "18947") if name == "slave" else (CONSOLE, "18945")
            ns.run([sys.executable, "-c", wait, host, port], timeout=35.0)

    def probe(self, seconds: float) -> dict[str, Any]:
        """The console's view (module docstring), as one JSON report."""
        out = self.console.run(
            [sys.executable, "-c", PROBE, str(ROOT), ROBOT, CONSOLE, str(seconds), STRANGER],
            timeout=seconds + 90.0,
        )
        return dict(json.loads(out.strip().splitlines()[-1]))

    def close(self) -> None:
        self.console.close()
        self.robot.close()

    def __enter__(self) -> TwoMachines:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def verdict(report: dict[str, Any]) -> list[str]:
    """What is wrong with a report ([] when the pair works across the two hosts)."""
    problems = []
    if report.get("slave_state") != "RUNNING" or report.get("master_state") != "RUNNING":
        problems.append(f"states {report.get('master_state')}, {report.get('slave_state')}")
    if not report.get("slave_received"):
        problems.append("the slave received nothing from its master")
    if report.get("lost") or report.get("trips"):
        problems.append(f"lost {report.get('lost')}, trips {report.get('trips')}")
    if report.get("tips", 0) < 3 or not any(v > 0.1 for v in report.get("tip_span_mm", [])):
        problems.append(f"Slicer's Tip did not follow the master: {report.get('tip_span_mm')}")
    tip = report.get("return_channel") or {}
    if tip.get("status") != "fresh":
        problems.append(f"no fresh tip back at the master: {tip}")
    if not str(report.get("stranger", "")).startswith(("closed", "refused")):
        problems.append(f"a stranger was answered: {report.get('stranger')}")
    return problems


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0, help="how long Slicer watches")
    ap.add_argument("--json", action="store_true", help="print the report as JSON")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="occ-2m-") as tmp, TwoMachines(Path(tmp)) as rig:
        print(f"console {CONSOLE} ({rig.console_if}), robot {ROBOT} ({rig.robot_if})")
        print("configs changed only in:", ", ".join(changed_keys(rig.paths)))
        rig.start_daemons()
        report = rig.probe(args.seconds)
    problems = verdict(report)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        for k, v in report.items():
            print(f"{k}: {v}")
    print("PASS" if not problems else "FAIL: " + "; ".join(problems))
    return 0 if not problems else 1


if __name__ == "__main__":
    sys.exit(main())
