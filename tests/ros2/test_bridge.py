"""occ-ros2 against a real slave daemon on loopback, read and driven from DDS as ROS 2 would.

A slave (``occd``, ports moved to free ones by tools/loopback.py) and the bridge (``occ-ros2``)
run as subprocesses; this process is the ROS 2 side: a DDS participant on the bridge's loopback
configuration, with the ROS 2 topic names, types and QoS. Its domain id is drawn per run and
its namespaces carry the pid (conftest.py). Checks behaviour, not timing.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from .conftest import UNICAST_CONFIG, poll, require_extra

require_extra()

from cyclonedds.pub import DataWriter  # noqa: E402
from cyclonedds.sub import DataReader  # noqa: E402
from cyclonedds.topic import Topic  # noqa: E402

from occ_ros2 import msgs  # noqa: E402
from occ_ros2.bridge import QOS_DEFAULT, QOS_LATCHED, topic_name  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))

from loopback import pair_configs, stop_processes, wait_port, write_yaml  # noqa: E402
from slicer_standin import SlicerStandIn  # noqa: E402

pytestmark = pytest.mark.realtime


class RosSide:
    """What a ROS 2 node would hold: readers and writers on the bridge's topics."""

    def __init__(self, participant: Any, ns: str) -> None:
        self.dp, self.ns = participant, ns
        self.readers: dict[str, DataReader[Any]] = {}
        self.seen: dict[str, list[Any]] = {}

    def reader(self, leaf: str, cls: type[Any], qos: Any = QOS_DEFAULT) -> None:
        dp = self.dp
        self.readers[leaf] = DataReader(dp, Topic(dp, topic_name(self.ns, leaf), cls), qos)
        self.seen[leaf] = []

    def take(self, leaf: str) -> list[Any]:
        self.seen[leaf].extend(self.readers[leaf].take(N=64))
        return self.seen[leaf]

    def writer(self, leaf: str, cls: type[Any]) -> DataWriter:
        dp = self.dp
        w = DataWriter(dp, Topic(dp, topic_name(self.ns, leaf), cls), QOS_DEFAULT)
        # a reliable sample written before the bridge's reader is matched would be lost
        assert poll(lambda: w.get_publication_matched_status().current_count >= 1), (
            f"{leaf}: the bridge's subscription was not discovered"
        )
        return w


@pytest.fixture
def slave_and_bridge(
    tmp_path: Path, dds: tuple[int, Any], namespace: str
) -> Iterator[tuple[dict[str, int], subprocess.Popen[bytes]]]:
    domain_id, _ = dds
    slave_cfg, _, ports = pair_configs()
    write_yaml(tmp_path / "slave.yaml", slave_cfg)
    procs: list[subprocess.Popen[bytes]] = []
    try:
        slave = subprocess.Popen(
            [sys.executable, "-m", "occ.cli", str(tmp_path / "slave.yaml"),
             "--log-level", "WARNING"],
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        )  # fmt: skip
        procs.append(slave)
        assert wait_port(ports["slave_tcp"], proc=slave), "the slave did not listen"
        assert wait_port(ports["slave_op"], proc=slave)
        bridge = subprocess.Popen(
            [sys.executable, "-m", "occ_ros2.cli",
             "--connect", f"127.0.0.1:{ports['slave_tcp']}={namespace}",
             "--operator", f"127.0.0.1:{ports['slave_op']}={namespace}",
             "--domain-id", str(domain_id), "--dds-config", str(UNICAST_CONFIG),
             "--log-level", "WARNING",
             "--stats", str(tmp_path / "bridge.json")],
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        )  # fmt: skip
        procs.append(bridge)
        yield ports, bridge
    finally:
        stop_processes(procs)


def test_measured_cp_is_the_slaves_tip_in_metres(
    slave_and_bridge: Any, dds: tuple[int, Any], namespace: str
) -> None:
    ports, bridge = slave_and_bridge
    ros = RosSide(dds[1], namespace)
    ros.reader("measured_cp", msgs.PoseStamped)
    ros.reader("local/measured_cp", msgs.PoseStamped)
    ros.reader("base/measured_cp", msgs.PoseStamped)
    ros.reader("measured_js", msgs.JointState)
    assert poll(lambda: len(ros.take("measured_cp")) >= 3), "no measured_cp from the bridge"
    assert poll(lambda: ros.take("local/measured_cp")), "no local/measured_cp"
    assert poll(lambda: ros.take("measured_js")), "no measured_js from the bridge"
    js = ros.seen["measured_js"][-1]
    assert list(js.name) == ["yaw", "pitch", "insertion"] and len(js.position) == 3
    assert js.header.frame_id == "slave"
    assert js.position[1] == pytest.approx(0.35, abs=0.01)  # the slave's home pitch
    assert poll(lambda: ros.take("base/measured_cp"))
    tip = ros.seen["local/measured_cp"][-1]
    assert tip.header.frame_id == "slave_base"
    world = ros.seen["measured_cp"][-1]
    assert world.header.frame_id == "world"  # the dVRK's measured_cp: with the base
    assert tip.header.stamp.sec > 0  # the daemon's timestamp, not zero
    base = ros.seen["base/measured_cp"][-1]
    assert base.header.frame_id == "world"
    q = tip.pose.orientation
    assert math.isclose(q.x**2 + q.y**2 + q.z**2 + q.w**2, 1.0, rel_tol=1e-9) and q.w >= 0.0
    # the same pose as 3D Slicer gets (the slave holds still: READY), mm -> m; the shipped base
    # is the identity, so the base frame is the world frame here
    with SlicerStandIn(port=ports["slave_tcp"]) as viewer:
        assert poll(lambda: viewer.last.get("Tip")), "the viewer got no Tip"
        ref = viewer.last["Tip"]
    expected = np.array(ref.translation) * 1e-3
    for pose in (tip, world):
        got = np.array([pose.pose.position.x, pose.pose.position.y, pose.pose.position.z])
        assert np.allclose(got, expected, atol=1e-6), (got, expected)  # float32 on the wire
    assert 0.0 < float(np.linalg.norm(got)) < 1.0  # metres, not millimetres
    assert bridge.poll() is None


def test_commands_round_trip_and_state_is_latched(
    slave_and_bridge: Any, dds: tuple[int, Any], namespace: str
) -> None:
    _, bridge = slave_and_bridge
    ros = RosSide(dds[1], namespace)
    ros.reader("command_reply", msgs.String)
    ros.reader("operating_state", msgs.OperatingState, QOS_LATCHED)
    ros.reader("state", msgs.String, QOS_LATCHED)

    def state() -> str | None:
        seen = ros.take("state")
        return seen[-1].data if seen else None

    # transient local: the state published before this reader existed arrives all the same
    assert poll(lambda: state() == "READY"), ros.seen["state"]
    # operating_state follows once the bridge knows whether a plan runs (its GetStats on
    # connecting, docs/ROS2.md): a moment after the state
    assert poll(lambda: ros.take("operating_state")), "no operating_state"
    assert ros.seen["operating_state"][-1].state == "DISABLED"

    # CRTK's word on CRTK's topic: enable is ENABLED, accepting motion: the daemon RUNNING
    crtk = ros.writer("state_command", msgs.StringStamped)
    crtk.write(msgs.StringStamped(header=msgs.Header(frame_id=""), string="enable"))
    assert poll(lambda: ros.take("command_reply")), "no reply to enable"
    assert ros.seen["command_reply"][0].data == (
        "enable SUCCESS: Enable: READY -> ENABLED; Run: ENABLED -> RUNNING"
    )
    assert poll(lambda: state() == "RUNNING")
    # CRTK: following the master is not a move: RUNNING is ENABLED and not busy
    assert poll(lambda: ros.take("operating_state")[-1].state == "ENABLED")
    op = ros.seen["operating_state"][-1]
    assert (op.state, op.is_busy, op.is_homed) == ("ENABLED", False, True)

    # the daemon's own command names on the plain String topic, with a request id or without
    plain = ros.writer("command", msgs.String)
    plain.write(msgs.String(data="[h1] Hold"))
    assert poll(lambda: state() == "ENABLED")
    plain.write(msgs.String(data="NoSuchCommand"))
    assert poll(lambda: len(ros.take("command_reply")) >= 3)
    replies = [r.data for r in ros.seen["command_reply"]]
    assert replies[1] == "[h1] Hold SUCCESS: RUNNING -> ENABLED"
    assert replies[2].startswith("NoSuchCommand FAIL:"), replies
    # the daemon ENABLED (holding) is CRTK's PAUSED; enable Runs it
    assert poll(lambda: ros.take("operating_state")[-1].state == "PAUSED")
    crtk.write(msgs.StringStamped(string="enable"))
    assert poll(lambda: len(ros.take("command_reply")) >= 4)
    assert ros.seen["command_reply"][3].data == "enable SUCCESS: Run: ENABLED -> RUNNING"
    crtk.write(msgs.StringStamped(string="pause"))
    assert poll(lambda: state() == "STOPPED")
    assert poll(lambda: ros.take("operating_state")[-1].state == "PAUSED")
    crtk.write(msgs.StringStamped(string="resume"))  # out of its own pause: Run again
    assert poll(lambda: state() == "RUNNING")
    assert bridge.poll() is None


@pytest.mark.parametrize("signed", [False, True], ids=["plain", "hmac"])
def test_master_mode_a_ros2_pose_stream_drives_the_slave(
    tmp_path: Path, dds: tuple[int, Any], namespace: str, signed: bool
) -> None:
    """servo_cp published from DDS becomes the slave's 500 Hz master stream: the slave
    (RUNNING) follows it, scaled 10:1, and is not stopped by the stream; with the slave's
    shared key (auth_key_file) the bridge signs every POSITION and the slave still follows."""
    domain_id, dp = dds
    slave_cfg, _, ports = pair_configs()
    auth: list[str] = []
    if signed:
        key = tmp_path / "link.key"
        key.write_text("a shared key for the master link\n")
        for itf in slave_cfg["interfaces"]:
            if itf["transport"] == "udp":
                itf["auth_key_file"] = str(key)
        auth = ["--auth-key-file", str(key)]
    write_yaml(tmp_path / "slave.yaml", slave_cfg)
    master_ns = namespace.rsplit("/", 1)[0] + "/master"
    procs: list[subprocess.Popen[bytes]] = []
    try:
        slave = subprocess.Popen(
            [sys.executable, "-m", "occ.cli", str(tmp_path / "slave.yaml"),
             "--log-level", "WARNING", "--start", "running"],
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        )  # fmt: skip
        procs.append(slave)
        assert wait_port(ports["slave_tcp"], proc=slave), "the slave did not listen"
        bridge = subprocess.Popen(
            [sys.executable, "-m", "occ_ros2.cli",
             "--connect", f"127.0.0.1:{ports['slave_tcp']}={namespace}",
             "--master", f"{master_ns}=127.0.0.1:{ports['slave_udp']}", *auth,
             "--domain-id", str(domain_id), "--dds-config", str(UNICAST_CONFIG),
             "--log-level", "WARNING",
             "--stats", str(tmp_path / "bridge.json")],
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        )  # fmt: skip
        procs.append(bridge)
        ros = RosSide(dp, namespace)
        ros.reader("measured_cp", msgs.PoseStamped)
        ros.reader("state", msgs.String, QOS_LATCHED)
        assert poll(lambda: ros.take("measured_cp")), "no measured_cp"
        start = ros.seen["measured_cp"][-1].pose.position
        servo = RosSide(dp, master_ns).writer("servo_cp", msgs.PoseStamped)

        # the operator's hand: +20 mm along x in 1 mm steps, then held there; poll's period
        # (10 ms) paces it like a 100 Hz device, and it keeps publishing so run stays 1
        step = [0]

        def moved() -> bool:
            x_mm = float(min(step[0], 20))
            step[0] += 1
            servo.write(msgs.PoseStamped(pose=msgs.Pose(msgs.Point(x_mm * 1e-3, 0.0, 0.02))))
            p = ros.take("measured_cp")[-1].pose.position
            return bool(p.x - start.x > 1.5e-3)  # 20 mm at 10:1 is 2 mm

        assert poll(moved, timeout=15.0), (start, ros.seen["measured_cp"][-1])
        states = [s.data for s in ros.take("state")]
        assert states[-1] == "RUNNING", states
        assert bridge.poll() is None and slave.poll() is None
    finally:
        stop_processes(procs[1:])  # the bridge first: the slave then sees its master die
        stop_processes(procs)
    stats = json.loads((tmp_path / "bridge.json").read_text())[f"master {master_ns}"]
    assert stats["sent"] > 0 and stats["poses"] > 0
