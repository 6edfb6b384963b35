"""CRTK as written: the daemon driven through CRTK's state table from a real ROS 2 node.

The rig (rig.py) runs the slave daemon, occ-ros2 and a real rclpy node (rmw_fastrtps_cpp) in
a private network namespace, plus a Cyclone participant (cyclone_agent.py) for what rclpy
cannot type here: crtk_msgs has no rclpy package on PyPI, so the node publishes the CRTK words
on ``/occ/slave/command`` (std_msgs/String, which the bridge reads like ``state_command``) and
``operating_state`` (crtk_msgs/OperatingState) is read by the Cyclone participant; one word
goes over ``state_command`` (crtk_msgs/StringStamped) itself.

:class:`CrtkClient` is the client-side logic of crtk_python_client (``crtk.utils``: enable,
disable, home, unhome, wait_for_operating_state, is_busy, wait_for_busy), re-implemented here
from its documented behaviour: a command whose target state already holds is sent and returns
True at once; otherwise the client waits for an ``operating_state`` *event* (a sample that comes
after the command) with the expected state; ``wait_for_busy(is_busy, start_time)`` returns at
once if the last sample is newer than ``start_time`` and already says so, else waits for events.
Before this issue ``is_busy`` was true whenever the slave was RUNNING, and ``wait_for_busy``
after a command to a running slave never returned.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from occ_testkit.netns import Netns
from occ_testkit.testing import wait_until

from .rig import Agent, Rig, clean_env

pytestmark = [pytest.mark.interop, pytest.mark.realtime]

LATCH = "latched until an operator's Reset"


class CrtkClient:
    """crtk_python_client's operating-state logic (module docstring), over the rig's agents."""

    def __init__(self, rig: Rig, cyclone: Agent) -> None:
        self.rig, self.cyclone = rig, cyclone
        self.replies_seen = 0

    # the subscriber side: operating_state samples [t, stamp, state, is_homed, is_busy]
    def samples(self) -> list[list[Any]]:
        return list(self.cyclone.ask("snapshot")["operating_state"])

    def last(self) -> list[Any]:
        s = self.samples()
        assert s, "no operating_state yet"
        return s[-1]

    def _wait_event(self, mark: int, pred: Callable[[list[Any]], bool], timeout: float) -> bool:
        """An operating_state event after ``mark`` samples that satisfies ``pred``."""
        return wait_until(lambda: any(pred(s) for s in self.samples()[mark:]), timeout)

    # the publisher side
    def state_command(self, word: str, via: str = "rclpy") -> float:
        """Publish a CRTK word; the rclpy node's time of sending (for its replies)."""
        if via == "rclpy":
            return float(self.rig.ask("publish", data=word)["t"])
        self.cyclone.ask("state_command", data=word)
        return float(self.rig.ask("snapshot")["t"])

    # crtk.utils' methods
    def _to_state(self, word: str, target: str, timeout: float, via: str = "rclpy") -> bool:
        if self.last()[2] == target:
            self.state_command(word, via)
            return True
        mark = len(self.samples())
        self.state_command(word, via)
        return self._wait_event(mark, lambda s: s[2] == target, timeout)

    def enable(self, timeout: float = 0.0, via: str = "rclpy") -> bool:
        return self._to_state("enable", "ENABLED", timeout, via)

    def disable(self, timeout: float = 0.0, via: str = "rclpy") -> bool:
        return self._to_state("disable", "DISABLED", timeout, via)

    def _homing(self, word: str, homed: bool, timeout: float) -> bool:
        if self.last()[3] == homed:
            self.state_command(word)
            return True
        mark = len(self.samples())
        self.state_command(word)
        return self._wait_event(mark, lambda s: s[3] == homed and not s[4], timeout)

    def home(self, timeout: float = 0.0) -> bool:
        return self._homing("home", True, timeout)

    def unhome(self, timeout: float = 0.0) -> bool:
        return self._homing("unhome", False, timeout)

    def wait_for_operating_state(self, state: str, timeout: float) -> bool:
        return self._wait_event(0, lambda s: s[2] == state, timeout) and self.last()[2] == state

    def is_busy(self, start_time: float = 0.0) -> bool:
        last = self.last()
        return bool(last[4]) if last[1] > start_time else True

    def wait_for_busy(
        self, is_busy: bool = False, start_time: float = 0.0, timeout: float = 30.0
    ) -> bool:
        # one look at the samples for both (two would miss an event that comes between them)
        seen = self.samples()
        assert seen, "no operating_state yet"
        last = seen[-1]
        if start_time > 0.0 and last[1] > start_time and last[4] == is_busy:
            return True
        return self._wait_event(len(seen), lambda s: s[4] == is_busy, timeout)

    # the replies (command_reply, as the rclpy node received them): one per command, in order
    def reply(self) -> str:
        """The next reply not yet looked at."""

        def replies() -> list[str]:
            return [r[1] for r in self.rig.ask("snapshot")["replies"]]

        assert wait_until(lambda: len(replies()) > self.replies_seen, timeout=5.0), (
            f"no command_reply (seen {self.replies_seen})"
        )
        self.replies_seen += 1
        return replies()[self.replies_seen - 1]


def daemon_state(rig: Rig) -> str:
    return str(rig.ask("snapshot")["states"][-1][1])


@pytest.mark.req("SR-REPLY-3")
def test_crtk_state_table_from_a_real_ros2_node(netns: Netns, tmp_path: Path) -> None:
    rig = Rig(netns, tmp_path, clean_env(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    rig.start_daemon()
    rig.start_bridge()
    rig.start_node()
    cyc = rig.start_cyclone()
    crtk = CrtkClient(rig, cyc)
    # the latched operating_state, and the node's command publisher matched to the bridge
    assert wait_until(lambda: crtk.samples(), timeout=5.0), "no operating_state"
    assert wait_until(lambda: rig.ask("snapshot")["states"], timeout=5.0), "no state"
    assert wait_until(
        lambda: min(rig.ask("matched")[k] for k in ("matched", "reply_publishers")) >= 1,
        timeout=5.0,
    )
    assert wait_until(lambda: cyc.ask("matched")["matched"] >= 1, timeout=5.0)
    assert crtk.last()[2:] == ["DISABLED", True, False]

    # the reply path: DDS matches each direction on its own, and a volatile reply sent before
    # the bridge's writer has matched the node's reader is lost (in any ROS 2): ask until one
    # comes back, as a ROS 2 client would, then count the replies from there
    def answered() -> bool:
        rig.ask("publish", data="GetState")
        return wait_until(lambda: rig.ask("snapshot")["replies"], timeout=0.5)

    assert wait_until(answered, timeout=10.0), "no reply to GetState"
    time.sleep(0.5)  # a second GetState's reply may still be on its way
    crtk.replies_seen = len(rig.ask("snapshot")["replies"])

    def word(w: str) -> str:
        crtk.state_command(w)
        return crtk.reply()

    # DISABLED: home is a no-op (absolute joint sensors); pause and resume are not valid
    assert crtk.home(timeout=1.0) is True  # is_homed: sent, True at once
    assert crtk.reply() == "home SUCCESS: homed: the joint sensors are absolute"
    assert word("pause") == "pause FAIL: not valid in DISABLED"
    assert word("resume") == "resume FAIL: not valid in DISABLED"
    assert crtk.disable() is True  # already DISABLED: sent, True at once
    assert crtk.reply() == "disable SUCCESS: already DISABLED"
    # enable: DISABLED -> ENABLED, CRTK's "accepts motion commands": the daemon's Enable and
    # Run (the client sees PAUSED on the way and waits on); then a no-op that succeeds
    assert crtk.enable(timeout=5.0)
    assert crtk.reply() == "enable SUCCESS: Enable: READY -> ENABLED; Run: ENABLED -> RUNNING"
    assert crtk.enable() is True
    assert crtk.reply() == "enable SUCCESS: already ENABLED"
    assert daemon_state(rig) == "RUNNING"
    # following the master (RUNNING) is ENABLED and not busy: wait_for_busy returns
    start = time.time()
    assert crtk.wait_for_busy(is_busy=False, start_time=start - 5.0, timeout=5.0)
    assert not crtk.is_busy(start_time=start - 5.0)
    assert word("resume") == "resume SUCCESS: already ENABLED"
    # pause and resume: the daemon's Stop, and Run out of that stop
    assert word("pause") == "pause SUCCESS: Stop: RUNNING -> STOPPED"
    assert crtk.wait_for_operating_state("PAUSED", timeout=5.0)
    assert word("pause") == "pause SUCCESS: already PAUSED"
    assert word("resume") == "resume SUCCESS: Run: STOPPED -> RUNNING"
    assert crtk.wait_for_operating_state("ENABLED", timeout=5.0)
    assert wait_until(lambda: daemon_state(rig) == "RUNNING", timeout=5.0)
    # a stop this bridge's pause did not cause (the daemon's own Stop, here sent as a word of
    # the daemon's: a safety stop is the same to the bridge) is not CRTK's to resume
    assert word("Stop") == "Stop SUCCESS: RUNNING -> STOPPED"
    for w in ("resume", "enable"):
        reply = word(w)
        assert reply.startswith(
            f"{w} FAIL: the daemon is STOPPED (RUNNING -> STOPPED: operator Stop) and not by "
            "this bridge's pause"
        ), reply
    assert word("Run") == "Run SUCCESS: STOPPED -> RUNNING"
    # the daemon's ENABLED (holding: an operator's Hold or Enable) is PAUSED; resume Runs
    assert word("Hold") == "Hold SUCCESS: RUNNING -> ENABLED"
    assert crtk.wait_for_operating_state("PAUSED", timeout=5.0)
    assert word("resume") == "resume SUCCESS: Run: ENABLED -> RUNNING"
    assert wait_until(lambda: daemon_state(rig) == "RUNNING", timeout=5.0)
    # disable, and unhome: refused (the sensors are absolute), the client's unhome times out
    assert crtk.disable(timeout=5.0)
    assert crtk.reply() == "disable SUCCESS: Disable: RUNNING -> READY"
    assert crtk.unhome(timeout=1.0) is False
    assert crtk.reply() == "unhome FAIL: the joint sensors are absolute: always homed"
    assert crtk.last()[3] is True
    # FAULT (here the e-stop, latched like a fault): CRTK would retry enable and disable; the
    # daemon's latch wins, the reply says why, and the client's enable times out
    assert word("Enable").startswith("Enable SUCCESS")
    assert word("EStop").startswith("EStop SUCCESS")
    assert crtk.wait_for_operating_state("FAULT", timeout=5.0)
    assert crtk.enable(timeout=1.0) is False
    reply = crtk.reply()
    assert reply.startswith("enable FAIL: the daemon's ESTOP is") and LATCH in reply, reply
    reply = word("disable")
    assert reply.startswith("disable FAIL: the daemon's ESTOP is") and LATCH in reply, reply
    assert word("pause") == "pause FAIL: not valid in FAULT"
    assert word("resume") == "resume FAIL: not valid in FAULT"
    assert word("home") == "home SUCCESS: homed: the joint sensors are absolute"
    assert daemon_state(rig) == "ESTOP"
    # the operator's Reset (the daemon's command, deliberate) clears it; then CRTK works again,
    # on CRTK's own topic too (crtk_msgs/StringStamped on state_command)
    assert word("Reset").startswith("Reset SUCCESS")
    assert crtk.wait_for_operating_state("DISABLED", timeout=5.0)
    assert crtk.enable(timeout=5.0, via="state_command")
    assert crtk.reply().startswith("enable SUCCESS: Enable: READY -> ENABLED; Run:")
    assert crtk.disable(timeout=5.0, via="state_command")
    assert crtk.reply() == "disable SUCCESS: Disable: RUNNING -> READY"
    assert wait_until(lambda: daemon_state(rig) == "READY", timeout=5.0)
    stats = rig.stop_bridge()["/occ/slave"]
    assert stats["publish_errors"] == 0 and stats["commands_refused"] == 9


@pytest.mark.req("SR-REPLY-1")
def test_each_status_once_on_the_status_topic(netns: Netns, tmp_path: Path) -> None:
    """The documented bridge (``--connect`` the viewer port and ``--operator`` the operator
    port of one slave): the daemon sends each STATUS to both links and greets each; a real
    rclpy node gets each once on ``status``."""
    rig = Rig(netns, tmp_path, clean_env(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    rig.start_daemon()
    rig.start_bridge()
    rig.start_node()
    ready(rig)
    for w, change in (("Enable", "READY -> ENABLED"), ("Run", "ENABLED -> RUNNING"),
                      ("Stop", "RUNNING -> STOPPED"), ("Disable", "STOPPED -> READY")):  # fmt: skip
        rig.ask("publish", data=w)
        target = change.split()[-1]
        assert wait_until(lambda: daemon_state(rig) == target, timeout=5.0)  # noqa: B023
    time.sleep(0.5)  # a copy would come within milliseconds of the first
    statuses = [s[1] for s in rig.ask("snapshot")["statuses"]]
    states = [s for s in statuses if s.split(":")[0] in ("READY", "ENABLED", "RUNNING", "STOPPED")]
    # (the greetings went out before the node's subscription matched: tests/ros2/
    # test_bridge_commands.py shows the two links' greetings published once)
    assert states == [
        "ENABLED: READY -> ENABLED: operator Enable",
        "RUNNING: ENABLED -> RUNNING: operator Run",
        "STOPPED: RUNNING -> STOPPED: operator Stop",
        "READY: STOPPED -> READY: operator Disable",
    ], statuses
    assert len(set(statuses)) == len(statuses), statuses
    stats = rig.stop_bridge()["/occ/slave"]
    assert stats["statuses_repeated"] >= 5  # each copy on the second link, and its greeting


@pytest.mark.req("SR-REPLY-2")
def test_a_node_after_one_killed_takes_only_its_own_replies(netns: Netns, tmp_path: Path) -> None:
    """A node asks and is killed (SIGKILL: no clean exit) right after; the next node asks
    with its own id: every reply it reads names its request, and it takes only its own."""
    rig = Rig(netns, tmp_path, clean_env(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    rig.start_daemon()
    rig.start_bridge()
    rig.start_node()
    ready(rig)
    for i in range(20):
        rig.ask("publish", data=f"[A-{i}] GetStats")
    assert rig.node is not None
    rig.node.proc.kill()  # unclean: its DDS participant is not deleted
    rig.node.proc.wait(10.0)
    rig.node = None
    rig.start_node()

    def own() -> list[str]:
        return [r[1] for r in rig.ask("snapshot")["replies"] if r[1].startswith("[B-1] ")]

    def answered() -> bool:
        rig.ask("publish", data="[B-1] GetState")
        return bool(wait_until(own, timeout=0.5))

    assert wait_until(answered, timeout=10.0), rig.ask("snapshot")["replies"]
    assert own()[0].startswith("[B-1] GetState SUCCESS: state=READY"), own()
    replies = [r[1] for r in rig.ask("snapshot")["replies"]]
    assert all(r.startswith(("[A-", "[B-1] ")) for r in replies), replies


def ready(rig: Rig) -> None:
    """The node's command publisher and reply subscription matched, the state in, and the
    command path proven by an answer: rclpy's subscription count comes from the ROS graph,
    which can know the bridge's reader before the DDS writer has matched it, and a volatile
    command published in between is lost (a CI run lost the first Enable so): ask GetState
    until one comes back, as a ROS 2 client would."""
    assert wait_until(lambda: rig.ask("snapshot")["states"], timeout=5.0), "no state"
    assert wait_until(
        lambda: min(rig.ask("matched")[k] for k in ("matched", "reply_publishers")) >= 1,
        timeout=5.0,
    )

    def answered() -> bool:
        rig.ask("publish", data="GetState")
        return bool(wait_until(lambda: rig.ask("snapshot")["replies"], timeout=0.5))

    assert wait_until(answered, timeout=10.0), "no reply to GetState"
    time.sleep(0.3)  # a second GetState's reply may still be on its way


def test_tf_frames_and_a_late_cyclone_participant(netns: Netns, tmp_path: Path) -> None:
    """tf2: /tf_static (latched) holds world -> slave_base, /tf slave_base -> slave_tip at
    the pose rate, equal to local/measured_cp; a Cyclone participant that comes 3 s after the
    bridge (Cyclone to Cyclone, the shipped configuration) gets both, and operating_state."""
    rig = Rig(netns, tmp_path, clean_env())
    rig.start_daemon()
    rig.start_bridge()
    time.sleep(3.0)
    cyc = rig.start_cyclone()
    snap: dict[str, Any] = {}

    def seen() -> bool:
        nonlocal snap
        snap = cyc.ask("snapshot")
        return bool(snap["tf_static"] and snap["tf_count"] >= 5 and snap["operating_state"])

    assert wait_until(seen, timeout=5.0), snap
    (static,) = snap["tf_static"]
    assert static[:2] == ["world", "slave_base"]
    assert static[2:] == pytest.approx([0, 0, 0, 0, 0, 0, 1])  # the shipped base: identity
    (moving,) = snap["tf"]
    assert moving[:2] == ["slave_base", "slave_tip"]
    cp = snap["measured_cp"][-1]
    assert cp[2] == "world"
    # the slave holds still (READY): the transform is the tip, as measured_cp says (float32
    # on the IGTL wire, so to a micrometre)
    assert moving[2:5] == pytest.approx(cp[3:6], abs=1e-6)
    assert snap["operating_state"][-1][2] == "DISABLED"
