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

import json
import time
from pathlib import Path
from typing import Any

import pytest

from occ_testkit.netns import Netns
from occ_testkit.testing import wait_until

from .rig import NS, ROOT, Rig
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
    assert states and states[-1][1] == "READY", (snap["states"], rig.daemon_log())
    # a command from the node reaches the daemon, and its reply the node; the publisher
    # must have matched the bridge's subscription first (a volatile sample sent before
    # the match is lost, in any ROS 2)
    assert wait_until(lambda: rig.ask("matched")["matched"] >= 1, timeout=5.0)
    # the reply goes back on a volatile topic: right after discovery the bridge's reply writer
    # may not have matched the node's reader yet, and the one reply is lost (any ROS 2): ask
    # again, once a second, for up to 5 s; one answer is the proof
    first = rig.ask("publish", data=command)["t"]

    def reply() -> list[str]:
        return [r[1] for r in rig.ask("snapshot")["replies"] if r[0] >= first]

    for _ in range(5):
        if wait_until(lambda: reply(), timeout=1.0):
            break
        rig.ask("publish", data=command)
    assert reply(), "no command_reply"
    # the state and its reason; a busy machine may add the daemon's last alert (a watchdog gap)
    assert reply()[0].startswith("GetState SUCCESS: state=READY;"), reply()
    assert "reason=configured" in reply()[0], reply()


LOCALHOST = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
#: the README's (Jazzy and later), ROS 2's defaults (discovery range SUBNET: the node announces
#: itself by multicast), and Humble's way of saying localhost (deprecated in Jazzy, still honored)
SETTINGS = {"readme": LOCALHOST, "ros_defaults": {}, "localhost_only": {"ROS_LOCALHOST_ONLY": "1"}}


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
    assert stats["commands"] >= 1 and stats["replies"] == stats["commands"]
    assert stats["publish_errors"] == 0


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
    assert stats["commands"] >= 2 and stats["replies"] == stats["commands"]


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


def _rate(rows: list[list[Any]]) -> float:
    stamps = [r[1] for r in rows]
    return (len(stamps) - 1) / (stamps[-1] - stamps[0])


def test_rate_option_and_setpoints(netns: Netns, tmp_path: Path) -> None:
    """A daemon whose viewer output sends at 100 Hz, with the setpoint sources: the node gets
    measured_cp at 100 Hz (the bridge's --rate at its maximum), then at 50 Hz with --rate 50;
    setpoint_js and setpoint_cp carry the held setpoints (the slave is READY, at home)."""
    import yaml

    cfg = yaml.safe_load((ROOT / "configs" / "slave.yaml").read_text())
    (viewer,) = [i for i in cfg["interfaces"] if i.get("role") == "viewer"]
    viewer["outputs"] = [
        {"type": "TRANSFORM", "device": "Tip", "source": "tip", "rate_hz": 100},
        {"type": "TRANSFORM", "device": "Base", "source": "base", "rate_hz": 100},
        {"type": "NDARRAY", "device": "Joints", "source": "joints", "rate_hz": 100},
        {"type": "NDARRAY", "device": "Setpoints", "source": "setpoint", "rate_hz": 100},
        {"type": "TRANSFORM", "device": "SetpointTip", "source": "setpoint_tip", "rate_hz": 100},
    ]
    config = tmp_path / "slave100.yaml"
    config.write_text(yaml.safe_dump(cfg, sort_keys=False))
    rig = Rig(netns, tmp_path, _env(**LOCALHOST))
    rig.start_daemon(config)
    rig.start_node()
    for rate, expected in (("100", 100.0), ("50", 50.0)):
        _check_rate_and_setpoints(rig, rate, expected)
    rig.stop_node()


def _check_rate_and_setpoints(rig: Rig, rate: str, expected: float) -> None:
    since = rig.ask("snapshot")["t"]
    rig.start_bridge("--rate", rate)
    snap: dict[str, Any] = {}

    def rows(t: float, leaf: str = "measured_cp") -> list[list[Any]]:
        return [r for r in snap["poses"][leaf] if r[0] >= t]

    def span(t: float) -> float:
        nonlocal snap
        snap = rig.ask("snapshot")
        got = rows(t)
        return got[-1][0] - t if got else -1.0

    assert wait_until(lambda: span(since) >= 0.0, timeout=5.0), "no measured_cp within 5 s"
    t1 = rows(since)[0][0] + 0.5  # past the start: 2 s of stream from there
    assert wait_until(lambda: span(t1) > 2.0, timeout=6.0)
    got = _rate(rows(t1))
    assert 0.8 * expected <= got <= 1.2 * expected, (rate, got)
    sp = rows(since, "setpoint_cp")
    assert sp and sp[-1][2] == "world"
    assert sp[-1][3:] == pytest.approx(rows(since)[-1][3:], abs=1e-4)  # holding: on target
    js = snap["joints"]["setpoint_js"][-1]
    assert js[1] == "slave" and js[2] == ["yaw", "pitch", "insertion"]
    assert js[3] == pytest.approx([0.0, 0.35, 0.05], abs=1e-4)  # the home pose, held
    stats = rig.stop_bridge()[NS]
    assert stats["publish_errors"] == 0
    if expected < 100.0:
        assert stats["rate_skipped"] > 0


#: a machine with a network interface besides lo: a veth pair standing in for eth0 (address in
#: a documentation range, existing only in the namespace), IPv6 off so the kernel itself sends
#: nothing on it (router solicitations); its transmit counter is then the DDS processes' alone
ETH0 = (
    "sysctl -qw net.ipv6.conf.all.disable_ipv6=1 && sysctl -qw net.ipv6.conf.default.disable_ipv6=1"
    " && ip link add v0 type veth peer name v1 && ip addr add 198.51.100.1/24 dev v0"
    " && ip link set v0 up && ip link set v1 up && ip route add default dev v0"
)


def test_nothing_leaves_on_the_machines_interface(tmp_path: Path) -> None:
    """On a machine with an eth0 (veth v0 here), the bridge and a node with the README's
    settings exchange everything on lo: v0 sends not one packet."""
    from .rig import require

    require()
    with Netns(ETH0) as ns:

        def sent() -> int:
            links = json.loads(ns.run(["ip", "-s", "-j", "link", "show", "v0"]))
            return int(links[0]["stats64"]["tx"]["packets"])

        assert sent() == 0
        rig = Rig(ns, tmp_path, _env(**LOCALHOST))
        rig.start_daemon()
        rig.start_bridge()
        time.sleep(3.0)
        assert sent() == 0, "the bridge sent on the machine's interface"
        rig.start_node()
        check_node_gets_everything(rig, 0.0)
        assert sent() == 0, "DDS traffic left on the machine's interface"
        rig.stop_node()
