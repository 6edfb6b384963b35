#!/usr/bin/env python3
"""occ-ros2's latency: a slave's TRANSFORM out (its IGTL timestamp) to the ROS 2 subscriber.

Starts a slave (free ports) whose viewer outputs run at ``--rate`` Hz instead of 10, the bridge
(``occ-ros2``, a subprocess) and, in this process, a DDS subscriber to ``measured_cp`` on the
bridge's loopback configuration. Reports two numbers (µs, same machine, same wall clock):

- ``end_to_end``: the PoseStamped's header stamp (the daemon's TRANSFORM timestamp, taken when
  the output was built) to its arrival in this process's reader (a WaitSet wake-up): daemon send
  queue, TCP, the bridge's decode + conversion + DDS write, DDS over loopback, our wake-up;
- ``bridge``: inside the bridge, the decoded TRANSFORM in the IGTL client's callback to the DDS
  write having returned (its ``--stats``, ``igtl_to_dds_us``).

    .venv/bin/python benchmarks/bench_ros2.py --duration 30 --rate 100
"""

from __future__ import annotations

import argparse
import json
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from cyclonedds.core import ReadCondition, SampleState, WaitSet
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from occ.core.stats import Histogram
from occ_ros2 import msgs
from occ_ros2.bridge import QOS_DEFAULT, topic_name

ROOT = Path(__file__).resolve().parents[1]
#: loopback, unicast only: nothing but unicast to 127.0.0.1 from a benchmark on the host
UNICAST = ROOT / "tests" / "ros2" / "cyclonedds-unicast.xml"
sys.path.insert(0, str(ROOT / "tools"))
from loopback import pair_configs, stop_processes, wait_port, write_yaml  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=20.0)
    p.add_argument("--rate", type=int, default=100, help="viewer output rate, Hz (<= 1000)")
    args = p.parse_args()
    domain_id = random.SystemRandom().randint(100, 232)
    ns = f"/occbench{domain_id}/slave"
    tmp = Path(tempfile.mkdtemp(prefix="bench-ros2-"))
    slave, _, ports = pair_configs()
    for itf in slave["interfaces"]:
        for out in itf.get("outputs", []):
            out["rate_hz"] = args.rate
    write_yaml(tmp / "slave.yaml", slave)
    py = sys.executable
    slave_cmd = [py, "-m", "occ.cli", str(tmp / "slave.yaml"), "--log-level", "WARNING"]
    procs = [subprocess.Popen(slave_cmd, cwd=ROOT)]
    try:
        if not wait_port(ports["slave_tcp"], proc=procs[0]):
            print("the slave did not start", file=sys.stderr)
            return 1
        domain = Domain(domain_id, UNICAST.read_text())
        dp = DomainParticipant(domain_id)
        reader: DataReader[msgs.PoseStamped] = DataReader(
            dp, Topic(dp, topic_name(ns, "measured_cp"), msgs.PoseStamped), QOS_DEFAULT
        )
        ws = WaitSet(dp)
        ws.attach(ReadCondition(reader, SampleState.NotRead))
        procs.append(subprocess.Popen(
            [py, "-m", "occ_ros2.cli", "--connect", f"127.0.0.1:{ports['slave_tcp']}={ns}",
             "--domain-id", str(domain_id), "--dds-config", str(UNICAST),
             "--log-level", "WARNING", "--stats", str(tmp / "bridge.json")],
            cwd=ROOT,
        ))  # fmt: skip
        e2e = Histogram()
        end = time.monotonic() + args.duration
        warm = time.monotonic() + 2.0  # discovery and the first connections are not measured
        while time.monotonic() < end:
            ws.wait(duration(milliseconds=200))
            now = time.time()
            for s in reader.take(N=64):
                if time.monotonic() > warm:
                    e2e.add((now - s.header.stamp.to_seconds()) * 1e6)
        stop_processes(procs[1:])
        bridge = json.loads((tmp / "bridge.json").read_text())
        s = e2e.summary() if e2e.count else {}
        summary = {k: round(s[k], 1) for k in ("p50", "p99", "max") if k in s}
        print(json.dumps({
            "rate_hz": args.rate,
            "end_to_end_us": {"n": e2e.count, **summary},
            "bridge_us": bridge.get("igtl_to_dds_us"),
        }, indent=2))  # fmt: skip
        del domain
    finally:
        stop_processes(procs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
