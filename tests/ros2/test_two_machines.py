"""The console PC and the robot PC as two hosts (tools/two_machines.py; README, "Two machines").

Two network namespaces joined by a veth pair, addresses that exist only there. The shipped
configs changed only in ``host``, ``remote`` and ``allowed_peers``: the slave on the robot PC
follows the master on the console PC over the cable with nothing lost, the master gets the
slave's tip back, 3D Slicer on the console reads the Tip, a client from an address outside
``allowed_peers`` is refused. Then the ROS 2 bridge on the robot PC, with the DDS configuration
for a real interface (occ_ros2/cyclonedds-net.xml), and a real ROS 2 node (rclpy on
rmw_fastrtps_cpp, ROS 2's defaults) on the console PC: the node gets ``measured_cp`` and the
state, and its command reaches the daemon.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from occ_testkit.testing import wait_until

from .rig import HERE, NS, ROOT, Agent, clean_env, require

sys.path.insert(0, str(ROOT / "tools"))

import two_machines as tm  # noqa: E402

pytestmark = [pytest.mark.interop, pytest.mark.slow]


@pytest.fixture
def hosts(tmp_path: Path) -> Any:
    require()
    rig = tm.TwoMachines(tmp_path)
    try:
        yield rig
    finally:
        rig.close()


def test_the_shipped_configs_change_only_in_host_remote_and_allowed_peers(tmp_path: Path) -> None:
    paths = tm.two_machine_configs(tmp_path)
    changed = tm.changed_keys(paths)
    assert changed and all(c.rsplit(".", 1)[-1] in tm.CHANGED_KEYS for c in changed), changed
    from occ.core.loader import load_config

    for path in paths.values():
        load_config(path)  # valid as they are


def test_the_pair_slicer_operators_and_ros2_across_two_hosts(hosts: Any, tmp_path: Path) -> None:
    hosts.start_daemons()
    report = hosts.probe(3.0)
    assert tm.verdict(report) == [], report
    assert report["stranger"] == "refused: STATUS 'connection not allowed', closed"

    # the ROS 2 bridge on the robot PC, DDS on the cable
    bridge_env = clean_env(OCC_DDS_INTERFACE=hosts.robot_if, OCC_DDS_PEER=tm.CONSOLE)
    log = (tmp_path / "bridge.log").open("wb")
    hosts.robot.popen(
        [sys.executable, "-m", "occ_ros2.cli",
         "--connect", f"{tm.ROBOT}:18944={NS}", "--operator", f"{tm.ROBOT}:18947={NS}",
         "--dds-config", str(ROOT / "occ_ros2" / "cyclonedds-net.xml"), "--log-level", "WARNING"],
        cwd=ROOT, env=bridge_env, stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    time.sleep(2.0)  # the node comes after the bridge, the order that once lost everything
    node = Agent(hosts.console.popen(
        [sys.executable, str(HERE / "rclpy_agent.py"), NS],
        env=clean_env(), stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    ))  # fmt: skip
    try:
        def poses() -> list[Any]:
            return list(node.ask("snapshot")["poses"]["measured_cp"])

        assert wait_until(lambda: len(poses()) >= 5, timeout=10.0), (
            (tmp_path / "bridge.log").read_text()[-2000:]
        )
        assert poses()[-1][2] == "world"
        states = node.ask("snapshot")["states"]
        assert states and states[-1][1] == "RUNNING", states
        assert wait_until(lambda: node.ask("matched")["matched"] >= 1, timeout=10.0)
        t_cmd = node.ask("publish", data="GetState")["t"]

        def replies() -> list[str]:
            return [r[1] for r in node.ask("snapshot")["replies"] if r[0] >= t_cmd]

        assert wait_until(replies, timeout=10.0), "no command_reply across the hosts"
        assert replies()[0].startswith("GetState SUCCESS: state=RUNNING"), replies()
    finally:
        node.stop()
