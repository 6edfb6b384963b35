"""occ-ros2 against a REAL ROS 2 node: rclpy on rmw_fastrtps_cpp (ROS 2's default RMW).

Everything DDS runs in a private network namespace (netns.py): the slave daemon (``occd
configs/slave.yaml``, its shipped ports: the namespace has them to itself), the bridge
(``occ-ros2`` with its shipped DDS configuration) and the ROS 2 node (rclpy_agent.py, a
subprocess: ``ros-jazzy-rclpy[fastrtps]`` from PyPI, no ROS 2 installation). The node runs with
the settings the README gives a ROS 2 user on one machine (ROS_DOMAIN_ID, and
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST), and also with ROS 2's defaults (discovery range
SUBNET: multicast announcements). Start orders: node after the bridge (the reported bug: 0
messages), node before the bridge, bridge restarted under a running node, node restarted
under a running bridge. Each time the node must get ``measured_cp`` at the daemon's rate within
5 s, the latched state at once (no state change happens meanwhile: it can only come from the
transient-local history) and a reply to a command it publishes.

The CRTK-typed topics and /tf are checked with the project's Cyclone reader (crtk_msgs and
tf2_msgs have no rclpy packages on PyPI), also inside the namespace: cyclone_probe.py.

In CI (OCC_REQUIRE_INTEROP=1) a missing rclpy or a machine without namespaces fails the run.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest

from .netns import Netns, wait_until
from .rig import NS, Rig
from .rig import clean_env as _env

TIP_RATE_HZ = 10.0  # configs/slave.yaml: the viewer's Tip output

pytestmark = [pytest.mark.interop, pytest.mark.realtime]


def check_node_gets_everything(rig: Rig, since: float, *, command: str = "GetState") -> None:
    """The node's view from agent time ``since`` on: measured_cp within 5 s of ``since`` and
    at the daemon's rate, the latched state, and a reply to a command it publishes."""
    snap: dict[str, Any] = {}

    def cps() -> list[list[Any]]:
        nonlocal snap
        snap = rig.ask("snapshot")
        return [r for r in snap["poses"]["measured_cp"] if r[0] >= since]

    assert wait_until(lambda: len(cps()) >= 1, timeout=5.0), (
        f"no measured_cp within 5 s (agent time {since:.2f} .. {snap.get('t')})"
    )
    first = cps()[0][0]
    assert first - since <= 5.0
    # the rate: over 2 s of the daemon's own stamps, as configured (10 Hz) within 30 %
    assert wait_until(lambda: len(cps()) >= 22, timeout=6.0), len(cps())
    rows = cps()
    stamps = [r[1] for r in rows]
    span = stamps[-1] - stamps[0]
    rate = (len(stamps) - 1) / span
    assert 0.7 * TIP_RATE_HZ <= rate <= 1.3 * TIP_RATE_HZ, (rate, span, len(stamps))
    gaps = [b - a for a, b in zip(stamps, stamps[1:], strict=False)]
    assert max(gaps) < 3.0 / TIP_RATE_HZ, f"a hole in the stream: {max(gaps):.3f} s"
    assert rows[-1][2] == "world", rows[-1]  # measured_cp: with the base (the dVRK's)
    local = [r for r in snap["poses"]["local/measured_cp"] if r[0] >= since]
    assert local and local[-1][2] == "slave_base"
    # the latched state: here at once, with no state change to publish it again
    states = [s for s in snap["states"] if s[0] >= since]
    assert states and states[-1][1] == "READY", snap["states"]
    # a command from the node reaches the daemon, and its reply the node; the publisher
    # must have matched the bridge's subscription first (a volatile sample sent before
    # the match is lost, in any ROS 2)
    assert wait_until(lambda: rig.ask("matched")["matched"] >= 1, timeout=5.0)
    t_cmd = rig.ask("publish", data=command)["t"]

    def reply() -> list[str]:
        return [r[1] for r in rig.ask("snapshot")["replies"] if r[0] >= t_cmd]

    assert wait_until(lambda: reply(), timeout=5.0), "no command_reply"
    assert reply()[0] == "GetState SUCCESS: state=READY; reason=configured", reply()


LOCALHOST = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
SETTINGS = {"readme": LOCALHOST, "ros_defaults": {}}


@pytest.mark.parametrize("settings", list(SETTINGS), ids=list(SETTINGS))
def test_node_started_after_the_bridge(netns: Netns, tmp_path: Path, settings: str) -> None:
    """The reported bug: a node that comes after the bridge got 0 messages."""
    rig = Rig(netns, tmp_path, _env(**SETTINGS[settings]))
    rig.start_daemon()
    rig.start_bridge()
    time.sleep(3.0)  # the bridge's start-up announcements are over: the node comes later
    rig.start_node()
    check_node_gets_everything(rig, 0.0)
    stats = rig.stop_bridge()[NS]
    assert stats["commands"] == 1 and stats["replies"] == 1 and stats["publish_errors"] == 0


@pytest.mark.parametrize("settings", list(SETTINGS), ids=list(SETTINGS))
def test_node_started_before_the_bridge(netns: Netns, tmp_path: Path, settings: str) -> None:
    rig = Rig(netns, tmp_path, _env(**SETTINGS[settings]))
    rig.start_daemon()
    rig.start_node()
    time.sleep(3.0)  # the node's start-up announcements are over: the bridge comes later
    since = rig.ask("snapshot")["t"]
    rig.start_bridge()
    check_node_gets_everything(rig, since)
    rig.stop_node()


def test_bridge_restarted_under_a_running_node(netns: Netns, tmp_path: Path) -> None:
    rig = Rig(netns, tmp_path, _env(**LOCALHOST))
    rig.start_daemon()
    rig.start_bridge()
    rig.start_node()
    check_node_gets_everything(rig, 0.0)
    rig.stop_bridge()
    time.sleep(2.0)  # the node notices the bridge gone (its readers' writers vanish)
    since = rig.ask("snapshot")["t"]
    rig.start_bridge()
    check_node_gets_everything(rig, since)
    rig.stop_node()


@pytest.mark.parametrize("settings", list(SETTINGS), ids=list(SETTINGS))
def test_node_restarted_under_a_running_bridge(netns: Netns, tmp_path: Path, settings: str) -> None:
    rig = Rig(netns, tmp_path, _env(**SETTINGS[settings]))
    rig.start_daemon()
    rig.start_bridge()
    rig.start_node()
    check_node_gets_everything(rig, 0.0)
    rig.stop_node()
    time.sleep(2.0)
    rig.start_node()
    check_node_gets_everything(rig, 0.0)
    stats = rig.stop_bridge()[NS]
    assert stats["commands"] == 2 and stats["replies"] == 2


def test_type_hashes_are_the_ones_rclpy_computes(netns: Netns, tmp_path: Path) -> None:
    """The bridge's endpoints carry ROS 2 Jazzy's type hash in USER_DATA: rclpy's graph shows
    the bridge's measured_cp publisher with the same hash as its own PoseStamped publisher
    (without it, the graph shows RIHS01_000...; a mismatch, and Jazzy would warn)."""
    rig = Rig(netns, tmp_path, _env(**LOCALHOST))
    rig.start_daemon()
    rig.start_bridge()
    rig.start_node()
    assert wait_until(lambda: rig.ask("graph")["bridge"], timeout=5.0)
    graph = rig.ask("graph")
    (bridge,), (own,) = graph["bridge"], graph["own"]
    assert bridge["type"] == own["type"] == "geometry_msgs/msg/PoseStamped"
    assert own["hash"].startswith("RIHS01_") and set(own["hash"][7:]) != {"0"}, own
    assert bridge["hash"] == own["hash"], graph
    rig.stop_node()
