"""The bridge against a daemon's operator port: what a ROS 2 client gets for what it sends.

The daemon side here is a real OpenIGTLink TCP server on 127.0.0.1 (:class:`DaemonPort`) that
records every message the bridge sends and answers each COMMAND as the test says, in the
daemon's reply format (RTS_COMMAND, metadata ``Status`` and ``Message``); it sends STATUS
messages as the daemon does on a state change. The ROS 2 side is a DDS participant in this
process on loopback without multicast (conftest.py). Master mode's stream is read from a real
UDP socket on 127.0.0.1. Every wait is on an event, bounded (``poll``), never on a clock.

The daemon's own side of these exchanges (its state machine, its keyframe controller) is
tests/ros2/test_crtk.py and test_moves.py, with real daemons and real ROS 2 nodes; these tests
are fast and deterministic, so that the mutation run (scripts/mutate bridge) can use them.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path
from typing import Any

import pytest

from .conftest import poll, require_extra

require_extra()

from cyclonedds.pub import DataWriter  # noqa: E402
from cyclonedds.qos import Policy, Qos  # noqa: E402
from cyclonedds.sub import DataReader  # noqa: E402
from cyclonedds.topic import Topic  # noqa: E402
from cyclonedds.util import duration  # noqa: E402

import igtl  # noqa: E402
from igtl.auth import verify  # noqa: E402
from igtl.transport import TCPServer, UDPEndpoint  # noqa: E402
from occ_ros2 import bridge as bridge_module  # noqa: E402
from occ_ros2 import msgs  # noqa: E402
from occ_ros2.bridge import (  # noqa: E402
    CRTK_STATE,
    QOS_DEFAULT,
    Bridge,
    topic_name,
    typed_qos,
)
from occ_ros2.master import MasterStream, parse_master  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
from loopback import free_port  # noqa: E402

#: a reader of a latched topic that keeps every sample (the bridge's writer keeps the last)
QOS_ALL_LATCHED = Qos(
    Policy.Reliability.Reliable(duration(milliseconds=100)),
    Policy.Durability.TransientLocal,
    Policy.History.KeepLast(1000),
)

Answer = Callable[[str, str], "tuple[str, str] | None"]


def ok(name: str, text: str) -> tuple[str, str] | None:
    """The default daemon: GetState says READY, GetStats says no plan runs, the rest succeed."""
    if name == "GetState":
        return "SUCCESS", "state=READY; alert=none"
    if name == "GetStats":
        return "SUCCESS", '{"controller": {"running": null, "runs_completed": 0}}'
    return "SUCCESS", f"{name} done"


#: the time stamp of the daemon's replies here
REPLY_STAMP = 1_700_000_500.75


class DaemonPort:
    """A daemon's operator port as the bridge sees it (module docstring). ``answer(name,
    text)`` gives (Status, Message) for a COMMAND, or None to leave it unanswered (then
    :meth:`reply` answers it later)."""

    def __init__(self, answer: Answer = ok) -> None:
        self.answer = answer
        self.port = free_port()
        self.received: list[igtl.Message] = []
        self.lock = threading.Lock()
        self.server = TCPServer("127.0.0.1", self.port, on_message=self._on_message,
                                name="test-daemon-port")  # fmt: skip

    def _on_message(self, peer: Any, msg: igtl.Message) -> None:
        with self.lock:
            self.received.append(msg)
        if msg.message_type == "COMMAND":
            got = self.answer(msg.command_name, msg.command)  # type: ignore[attr-defined]
            if got is not None:
                self.reply(msg, *got)

    def reply(self, cmd: igtl.Message, status: str, text: str) -> None:
        """The daemon's answer (occ/net/commands.py), stamped :data:`REPLY_STAMP`."""
        self.server.send(
            igtl.RTSCommandMessage(
                command_id=cmd.command_id,  # type: ignore[attr-defined]
                command_name=cmd.command_name,  # type: ignore[attr-defined]
                device_name="occd",
                header_version=2,
                metadata={"Status": status, "Message": text},
                timestamp=REPLY_STAMP,
            )
        )

    def status(self, name: str, text: str = "", timestamp: float = 0.0) -> None:
        self.server.send(
            igtl.StatusMessage(
                error_name=name, status_message=text or name, header_version=2,
                timestamp=timestamp,
            )
        )  # fmt: skip

    def commands(self, name: str | None = None) -> list[Any]:
        with self.lock:
            return [
                m for m in self.received
                if m.message_type == "COMMAND" and name in (None, m.command_name)  # type: ignore[attr-defined]
            ]  # fmt: skip

    def wait_command(self, name: str, n: int = 1) -> Any:
        assert poll(lambda: len(self.commands(name)) >= n), (name, self.names())
        return self.commands(name)[n - 1]

    def names(self) -> list[str]:
        return [m.command_name for m in self.commands()]


class RosSide:
    """What a ROS 2 node of the robot's namespace reads: every sample of each topic, in order."""

    def __init__(self, dp: Any, ns: str) -> None:
        def reader(leaf: str, cls: type[Any], qos: Qos) -> DataReader[Any]:
            return DataReader(dp, Topic(dp, topic_name(ns, leaf), cls), qos)

        self.readers = {
            "command_reply": reader("command_reply", msgs.String, QOS_DEFAULT),
            "status": reader("status", msgs.String, QOS_DEFAULT),
            "state": reader("state", msgs.String, QOS_ALL_LATCHED),
            "operating_state": reader("operating_state", msgs.OperatingState, QOS_ALL_LATCHED),
        }
        self.seen: dict[str, list[Any]] = {leaf: [] for leaf in self.readers}

    def take(self, leaf: str) -> list[Any]:
        self.seen[leaf].extend(self.readers[leaf].take(N=256))
        return self.seen[leaf]

    def wait(self, leaf: str, n: int) -> list[Any]:
        """The first ``n`` samples of ``leaf`` (waits for them)."""
        assert poll(lambda: len(self.take(leaf)) >= n), (leaf, n, self.take(leaf))
        return self.seen[leaf][:n]

    def replies(self, n: int) -> list[str]:
        return [s.data for s in self.wait("command_reply", n)]

    def ops(self) -> list[tuple[str, bool, bool]]:
        return [(s.state, s.is_homed, s.is_busy) for s in self.take("operating_state")]


@pytest.fixture
def rig(
    dds: tuple[int, Any], namespace: str
) -> Iterator[Callable[..., tuple[Bridge, DaemonPort, RosSide]]]:
    """``rig(answer=ok, **bridge options)``: a daemon port, the ROS side, and a bridge whose
    operator link is connected to it (the ROS side's readers exist before the bridge)."""
    domain_id, dp = dds
    opened: list[Any] = []

    def make(answer: Answer = ok, **options: Any) -> tuple[Bridge, DaemonPort, RosSide]:
        daemon = DaemonPort(answer)
        daemon.server.start()
        opened.append(daemon.server)
        ros = RosSide(dp, namespace)
        endpoint = [("127.0.0.1", daemon.port, namespace)]
        bridge = Bridge((), endpoint, domain_id=domain_id, tf=False, **options)
        opened.append(bridge)
        bridge.start()
        assert bridge.wait_connected()
        return bridge, daemon, ros

    yield make
    for thing in reversed(opened):
        thing.stop()


def connected(bridge: Bridge, daemon: DaemonPort, ros: RosSide, state: str) -> None:
    """Wait for the bridge's look on connecting (GetStats, GetState), then put the daemon in
    ``state`` by its STATUS and wait until the bridge has published it."""
    daemon.wait_command("GetState")
    robot = bridge.robots[ros_ns(bridge)]
    seen = robot.counters.statuses
    daemon.status(state)
    assert poll(lambda: robot.counters.statuses > seen)  # the STATUS has been handled
    assert poll(lambda: bool(ros.take("state")) and ros.seen["state"][-1].data == state)
    assert poll(lambda: bool(ros.ops()) and ros.ops()[-1][0] == CRTK_STATE[state])


# ---------------------------------------------------------------------------- the state mapping


def test_every_daemon_state_as_crtk_operating_state(rig: Callable[..., Any]) -> None:
    """Each state the daemon announces (its STATUS) is published on ``state`` as it is and on
    ``operating_state`` as CRTK's meta-state, homed past INIT, never busy without a plan; the
    stamp is the daemon's (the STATUS's timestamp); a repeated state is not published again."""
    bridge, daemon, ros = rig()
    daemon.wait_command("GetState")
    assert poll(lambda: bool(ros.ops()))  # READY, from the GetState reply
    assert ros.take("state")[0].data == "READY"
    assert ros.ops()[0] == ("DISABLED", True, False)
    expected = {
        "INIT": ("DISABLED", False),
        "ENABLED": ("PAUSED", True),  # powered, holding: motion commands wait for Run
        "RUNNING": ("ENABLED", True),  # CRTK's ENABLED: motion commands are executed
        "STOPPED": ("PAUSED", True),
        "FAULT": ("FAULT", True),
        "ESTOP": ("FAULT", True),
        "READY": ("DISABLED", True),
        "SHUTDOWN": ("DISABLED", False),
    }
    for i, (state, (meta, homed)) in enumerate(expected.items()):
        daemon.status(state, timestamp=1_700_000_000.25 + i)
        daemon.status(state, timestamp=1_700_000_100.0 + i)  # the same again: nothing new
        states = ros.wait("state", i + 2)
        assert states[-1].data == state
        got = ros.wait("operating_state", i + 2)[-1]
        assert (got.state, got.is_homed, got.is_busy) == (meta, homed, False), state
        assert (got.header.stamp.sec, got.header.stamp.nanosec) == (1_700_000_000 + i, 250_000_000)
    daemon.status("ESTOP")  # a change after the repeats: the repeats made no sample
    assert ros.wait("state", len(expected) + 2)[-1].data == "ESTOP"
    assert len(ros.take("operating_state")) == len(expected) + 2


def test_is_busy_while_a_plan_runs_and_never_out_of_running(rig: Callable[..., Any]) -> None:
    """CRTK's is_busy follows the keyframe controller's STATUS KEYFRAME_RUNNING ..
    KEYFRAME_ENDED, and is false as soon as the daemon leaves RUNNING (the daemon drops the
    plan then) even without KEYFRAME_ENDED."""
    bridge, daemon, ros = rig()
    connected(bridge, daemon, ros, "RUNNING")
    n = len(ros.ops())
    daemon.status("KEYFRAME_RUNNING", "plan 3 running", timestamp=1_700_000_001.5)
    assert poll(lambda: len(ros.ops()) == n + 1)
    busy = ros.take("operating_state")[-1]
    assert (busy.state, busy.is_homed, busy.is_busy) == ("ENABLED", True, True)
    assert (busy.header.stamp.sec, busy.header.stamp.nanosec) == (1_700_000_001, 500_000_000)
    daemon.status("KEYFRAME_RUNNING", "plan 3 running")  # no change: no sample
    daemon.status("KEYFRAME_ENDED", "plan 3 completed")
    assert poll(lambda: len(ros.ops()) == n + 2)
    assert ros.ops()[-1] == ("ENABLED", True, False)
    daemon.status("KEYFRAME_RUNNING", "plan 4 running")
    daemon.status("STOPPED")  # the plan is dropped with the state
    assert poll(lambda: len(ros.ops()) == n + 4)
    assert ros.ops()[-2:] == [("ENABLED", True, True), ("PAUSED", True, False)]
    assert bridge.robots[ros_ns(bridge)].busy is False
    daemon.status("RUNNING")
    assert poll(lambda: len(ros.ops()) == n + 5)
    assert ros.ops()[-1] == ("ENABLED", True, False)  # back in RUNNING: no plan runs


def ros_ns(bridge: Bridge) -> str:
    (ns,) = bridge.robots
    return ns


def test_get_state_answers_set_the_state_whoever_asked(rig: Callable[..., Any]) -> None:
    """The daemon's answer to GetState ("state=X; alert=...") sets the state: the bridge's own
    on connecting (not published as a reply) and a client's (published as one); a refused
    GetState or an unknown state changes nothing."""
    answers = {"n": 0}

    def daemon_answer(name: str, text: str) -> tuple[str, str] | None:
        if name == "GetState":
            answers["n"] += 1
            return {
                1: ("SUCCESS", "alert=none; state=STOPPED"),
                2: ("SUCCESS", "state=ESTOP;alert=estop pressed"),
                3: ("FAIL", "state=READY"),
                4: ("SUCCESS", "state=BOGUS"),
            }[answers["n"]]
        return ok(name, text)

    bridge, daemon, ros = rig(daemon_answer)
    assert poll(lambda: bool(ros.take("state")))
    assert ros.seen["state"][0].data == "STOPPED"
    assert poll(lambda: bool(ros.ops()))
    assert ros.ops()[0] == ("PAUSED", True, False)
    stamp = ros.take("operating_state")[0].header.stamp  # the daemon's, of its answer
    assert (stamp.sec, stamp.nanosec) == (1_700_000_500, 750_000_000)
    for _ in range(3):
        bridge.command(ros_ns(bridge), "GetState")
    assert ros.replies(3) == [
        "GetState SUCCESS: state=ESTOP;alert=estop pressed",
        "GetState FAIL: state=READY",
        "GetState SUCCESS: state=BOGUS",
    ]
    assert [s.data for s in ros.take("state")] == ["STOPPED", "ESTOP"]
    assert bridge.robots[ros_ns(bridge)].state == "ESTOP"


def test_a_bridge_started_during_a_plan_says_busy_at_once(rig: Callable[..., Any]) -> None:
    """The daemon answers in order: GetStats (a plan runs), then GetState (RUNNING): the first
    operating_state says ENABLED and busy."""

    def daemon_answer(name: str, text: str) -> tuple[str, str] | None:
        if name == "GetStats":
            return "SUCCESS", '{"controller": {"running": 4, "runs_completed": 0}}'
        if name == "GetState":
            return "SUCCESS", "state=RUNNING"
        return ok(name, text)

    bridge, daemon, ros = rig(daemon_answer)
    assert poll(lambda: bool(ros.ops()))
    assert ros.ops()[0] == ("ENABLED", True, True)
    assert [s.data for s in ros.take("state")] == ["RUNNING"]


def test_a_bridge_started_during_a_plan_never_says_not_busy(rig: Callable[..., Any]) -> None:
    """On connecting the bridge asks GetStats before it publishes operating_state: the first
    operating_state a client sees during a run says busy. Until the answer comes, a state
    change is published on ``state`` but not on ``operating_state``."""
    held: list[Any] = []

    def daemon_answer(name: str, text: str) -> tuple[str, str] | None:
        if name == "GetStats":
            return None  # answered below, after GetState
        if name == "GetState":
            return "SUCCESS", "state=RUNNING"
        return ok(name, text)

    bridge, daemon, ros = rig(daemon_answer)
    stats = daemon.wait_command("GetStats")
    daemon.wait_command("GetState")
    assert daemon.names()[:2] == ["GetStats", "GetState"]
    assert poll(lambda: bool(ros.take("state")))
    daemon.reply(
        stats, "SUCCESS", '{"controller": {"keyframe": {"running": 7, "runs_completed": 2}}}'
    )
    assert poll(lambda: bool(ros.ops()))
    assert ros.ops()[0] == ("ENABLED", True, True)
    assert not ros.take("command_reply")  # the bridge's own questions are not replies
    held.append(stats)
    # the same with a failed GetStats: not busy, published at once
    ns = ros_ns(bridge)
    robot = bridge.robots[ns]
    robot.probing_until = math.inf
    bridge._send_command(robot, robot.operator, "GetStats", probe=True)  # type: ignore[arg-type]
    again = daemon.wait_command("GetStats", 2)
    n = len(ros.ops())
    daemon.reply(again, "FAIL", '{"controller": {"running": 1, "runs_completed": 0}}')
    assert poll(lambda: len(ros.ops()) == n + 1)
    assert ros.ops()[-1] == ("ENABLED", True, False)
    assert robot.probing_until == 0.0


def test_a_daemon_that_never_answers_get_stats_does_not_silence_operating_state(
    rig: Callable[..., Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The wait for GetStats's answer on connecting is bounded (PROBE_WAIT_S): past it, the
    next state change is published on operating_state, not busy."""
    monkeypatch.setattr(bridge_module, "PROBE_WAIT_S", 0.2)

    def daemon_answer(name: str, text: str) -> tuple[str, str] | None:
        return None if name == "GetStats" else ok(name, text)

    bridge, daemon, ros = rig(daemon_answer)
    robot = bridge.robots[ros_ns(bridge)]
    assert poll(lambda: bool(ros.take("state")))  # READY, not on operating_state yet
    assert not ros.ops()
    assert poll(lambda: time.monotonic() > robot.probing_until)
    daemon.status("ENABLED")
    assert poll(lambda: bool(ros.ops()))
    assert ros.ops() == [("PAUSED", True, False)]


# ---------------------------------------------------------------------------- command forwarding


def test_crtk_words_become_the_daemons_commands_and_its_answers_come_back(
    rig: Callable[..., Any],
) -> None:
    """``enable`` in READY is the daemon's Enable, then its Run once Enable is answered (CRTK's
    ENABLED accepts motion commands: the daemon's RUNNING), sent as 3D Slicer sends commands
    (COMMAND, header version 2, device occ-ros2, a new id each); one reply names the word and
    each answer, then operating_state again (a fresh stamp, for crtk_python_client)."""
    bridge, daemon, ros = rig()
    connected(bridge, daemon, ros, "READY")
    ns = ros_ns(bridge)
    n = len(ros.ops())
    bridge.command(ns, "  enable \n")
    cmd = daemon.wait_command("Enable")
    assert (cmd.header_version, cmd.device_name, cmd.command) == (2, "occ-ros2", "")
    daemon.wait_command("Run")
    assert ros.replies(1) == ["enable SUCCESS: Enable: Enable done; Run: Run done"]
    assert poll(lambda: len(ros.ops()) == n + 1)  # unchanged, published again
    fresh = ros.take("operating_state")[-1]
    assert (
        fresh.state == "DISABLED" and fresh.header.stamp.sec > REPLY_STAMP
    )  # now, not the reply's
    daemon.status("RUNNING")
    assert poll(lambda: len(ros.ops()) == n + 2)
    bridge.command(ns, "pause")
    assert daemon.wait_command("Stop").command_name == "Stop"
    bridge.command(ns, "disable")
    daemon.wait_command("Disable")
    assert ros.replies(3)[1:] == [
        "pause SUCCESS: Stop: Stop done",
        "disable SUCCESS: Disable: Disable done",
    ]
    assert poll(lambda: len(ros.ops()) == n + 4)
    # the daemon's words that change its state are followed by operating_state too, the others
    # not (Sync's reply comes after the last of them)
    for word in ("Run", "Reset", "Stop", "Sync"):
        bridge.command(ns, word)
    assert ros.replies(7)[3:] == [
        f"{w} SUCCESS: {w} done" for w in ("Run", "Reset", "Stop", "Sync")
    ]
    assert poll(lambda: len(ros.ops()) >= n + 6)
    assert len(ros.ops()) == n + 6
    ids = [m.command_id for m in daemon.commands()]
    assert len(set(ids)) == len(ids) and ids == sorted(ids), ids
    st = bridge.stats()[ns]
    assert (st["commands"], st["replies"], st["commands_refused"]) == (7, 7, 0)


@pytest.mark.req("SR-REPLY-3")
def test_enable_stops_at_the_first_refusal_and_says_where(rig: Callable[..., Any]) -> None:
    """An Enable refused: no Run is sent; a Run refused after the Enable: the reply says the
    robot is enabled (CRTK's PAUSED) and why it does not run."""

    def daemon_answer(name: str, text: str) -> tuple[str, str] | None:
        if name == "Run":
            return "FAIL", "no master connected"
        return ok(name, text)

    bridge, daemon, ros = rig(daemon_answer)
    connected(bridge, daemon, ros, "READY")
    ns = ros_ns(bridge)
    bridge.command(ns, "enable")
    assert ros.replies(1) == ["enable FAIL: Enable: Enable done; Run: no master connected"]
    daemon.status("ENABLED")
    assert poll(lambda: bridge.robots[ns].state == "ENABLED")
    bridge.command(ns, "[r2] enable")  # out of PAUSED (the daemon's ENABLED): Run alone
    assert ros.replies(2)[1] == "[r2] enable FAIL: Run: no master connected"
    assert daemon.names()[2:] == ["Enable", "Run", "Run"]


def transitions(name: str, text: str) -> tuple[str, str] | None:
    """The daemon's answers to its state commands (occ/core/transitions.py's text)."""
    moves = {"Stop": "RUNNING -> STOPPED", "Run": "STOPPED -> RUNNING", "Enable": "x -> ENABLED"}
    return ("SUCCESS", moves[name]) if name in moves else ok(name, text)


@pytest.mark.req("SR-REPLY-3")
def test_resume_runs_again_only_out_of_this_bridges_own_pause(rig: Callable[..., Any]) -> None:
    """pause from RUNNING is the daemon's Stop; resume (or enable) Runs again out of that
    stop. A stop the bridge did not cause (a safety stop, an operator's), or an alarm during
    the pause, is the daemon's Run's to resume: CRTK's resume and enable are refused, saying
    so; the daemon's own Run still goes."""
    bridge, daemon, ros = rig(transitions)
    ns = ros_ns(bridge)
    robot = bridge.robots[ns]
    connected(bridge, daemon, ros, "RUNNING")

    def to(state: str, text: str) -> None:
        daemon.status(state, f"RUNNING -> {state}{text}", timestamp=time.time())
        assert poll(lambda: robot.state == state and robot.state_text.endswith(text))

    bridge.command(ns, "pause")
    daemon.wait_command("Stop")
    to("STOPPED", ": operator Stop")
    assert ros.replies(1) == ["pause SUCCESS: Stop: RUNNING -> STOPPED"]
    bridge.command(ns, "resume")
    daemon.wait_command("Run")
    assert ros.replies(2)[1] == "resume SUCCESS: Run: STOPPED -> RUNNING"
    to("RUNNING", "")
    # the daemon's own stop (a loss of the master): not the bridge's to resume
    to("STOPPED", ": master lost: 3 consecutive samples")
    for word in ("resume", "enable"):
        bridge.command(ns, word)
    for reply, word in zip(ros.replies(4)[2:], ("resume", "enable"), strict=True):
        assert reply.startswith(
            f"{word} FAIL: the daemon is STOPPED (RUNNING -> STOPPED: master lost: 3 consecutive "
            "samples) and not by this bridge's pause: a stop is resumed by the daemon's Run"
        ), reply
    # paused by the bridge, then an alarm while paused: no longer the bridge's to resume
    to("RUNNING", "")
    bridge.command(ns, "pause")
    daemon.wait_command("Stop", 2)
    to("STOPPED", ": operator Stop")
    assert ros.replies(5)[4] == "pause SUCCESS: Stop: RUNNING -> STOPPED"
    daemon.status("COLLISION", "link 'insertion' 1.2 mm from 'table'", timestamp=time.time())
    assert poll(lambda: not robot.paused_by_bridge)
    bridge.command(ns, "resume")
    assert ros.replies(6)[5].startswith("resume FAIL: the daemon is STOPPED"), ros.replies(6)
    bridge.command(ns, "Run")  # the daemon's word, deliberate: goes as it is
    assert ros.replies(7)[6] == "Run SUCCESS: STOPPED -> RUNNING"
    assert daemon.names()[2:] == ["Stop", "Run", "Stop", "Run"]


def test_the_daemons_own_words_go_as_they_are_and_bad_names_are_refused(
    rig: Callable[..., Any],
) -> None:
    """Any other word is the daemon's command (Reset, EStop, Clutch, names with ``_``); a name
    that is not one (spaces, punctuation, empty) is refused by the bridge and never sent; a
    refusal by the daemon comes back as it is; CRTK's own answers need no daemon."""

    def daemon_answer(name: str, text: str) -> tuple[str, str] | None:
        if name == "EStop":
            return "FAIL", "EStop is an operator's"
        return ok(name, text)

    bridge, daemon, ros = rig(daemon_answer)
    connected(bridge, daemon, ros, "FAULT")
    ns = ros_ns(bridge)
    for word in ("Reset", "EStop", "Get_Stats2", "rm -rf", "", "Run;Stop", "Enable\x00", "home"):
        bridge.command(ns, word)
    # the bridge's own answers come at once, the daemon's when it answers
    assert sorted(ros.replies(8)) == sorted(
        [
            "Reset SUCCESS: Reset done",
            "EStop FAIL: EStop is an operator's",
            "Get_Stats2 SUCCESS: Get_Stats2 done",
            "rm -rf FAIL: not a command name",
            "(empty) FAIL: not a command name",
            "Run;Stop FAIL: not a command name",
            "Enable\x00 FAIL: not a command name",
            "home SUCCESS: homed: the joint sensors are absolute",
        ]
    )
    assert daemon.names()[2:] == ["Reset", "EStop", "Get_Stats2"]
    st = bridge.stats()[ns]
    assert (st["commands"], st["replies"], st["commands_refused"]) == (8, 4, 4)


def test_crtk_refusals_in_fault_keep_the_latch(rig: Callable[..., Any]) -> None:
    """enable and disable in FAULT or ESTOP are refused by the bridge (the daemon's latch holds
    until an operator's Reset), counted, answered, and operating_state is published again;
    nothing reaches the daemon."""
    bridge, daemon, ros = rig()
    connected(bridge, daemon, ros, "ESTOP")
    ns = ros_ns(bridge)
    n = len(ros.ops())
    bridge.command(ns, "enable")
    bridge.command(ns, "disable")
    bridge.command(ns, "unhome")
    bridge.command(ns, "pause")  # not in CRTK's table for FAULT: refused all the same
    assert [r.split(":")[0] for r in ros.replies(4)] == [
        "enable FAIL",
        "disable FAIL",
        "unhome FAIL",
        "pause FAIL",
    ]
    assert ros.replies(4)[3] == "pause FAIL: not valid in FAULT"
    assert ros.replies(1)[0] == (
        "enable FAIL: the daemon's ESTOP is latched until an operator's Reset (command Reset, "
        "after the cause is found); a CRTK retry does not clear it"
    )
    assert poll(lambda: len(ros.ops()) == n + 4)
    assert ros.ops()[-1] == ("FAULT", True, False)
    assert ros.take("operating_state")[-1].header.frame_id == ""
    assert daemon.names() == ["GetStats", "GetState"]
    st = bridge.stats()[ns]
    assert (st["commands"], st["replies"], st["commands_refused"]) == (4, 4, 4)
    # INIT and SHUTDOWN: no word is valid (not homed either)
    daemon.status("SHUTDOWN")
    assert poll(lambda: bridge.robots[ns].state == "SHUTDOWN")
    m = len(ros.ops())
    bridge.command(ns, "disable")
    assert ros.replies(5)[4] == "disable FAIL: the daemon is in SHUTDOWN"
    assert daemon.names() == ["GetStats", "GetState"]
    assert bridge.robots[ns].counters.commands_refused == 5
    assert poll(lambda: len(ros.ops()) == m + 1)  # published again, as after every CRTK word
    assert ros.ops()[-1] == ("DISABLED", False, False)


def test_crtk_word_before_the_state_is_known(dds: tuple[int, Any], namespace: str) -> None:
    """A CRTK word before the daemon's state is known (its link not connected) is refused and
    says why; nothing is sent."""
    domain_id, dp = dds
    ros = RosSide(dp, namespace)
    endpoint = [("127.0.0.1", free_port(), namespace)]
    with Bridge((), endpoint, domain_id=domain_id, tf=False) as bridge:
        bridge.command(namespace, "enable")
        bridge.command(namespace, "Reset")
        assert ros.replies(2) == [
            "enable FAIL: the daemon's state is not known yet (not connected)",
            "Reset FAIL: operator interface not connected",
        ]
        st = bridge.stats()[namespace]
        assert (st["commands"], st["replies"], st["commands_refused"]) == (2, 0, 2)
        # a command that could not be sent waits for no answer (it would crowd real ones out
        # of the bounded list of commands waiting for theirs)
        assert not bridge._pending


def test_replies_are_matched_by_command_id_and_the_wait_list_is_bounded(
    rig: Callable[..., Any],
) -> None:
    """Answers that come in another order go to their own commands (by COMMAND_ID); a daemon
    that never answers cannot grow the bridge's list of commands waiting for an answer past
    256: the oldest are forgotten (their late answers are not published), the newest kept."""
    bridge, daemon, ros = rig(lambda name, text: ok(name, text) if name.startswith("Get") else None)
    ns = ros_ns(bridge)
    connected(bridge, daemon, ros, "READY")
    for i in range(300):
        bridge.command(ns, f"Cmd{i}")
        if i % 50 == 49:  # within the link's send queue
            assert poll(partial(received, daemon, 2 + i + 1))
    sent = daemon.commands()[2:]
    assert [m.command_name for m in sent] == [f"Cmd{i}" for i in range(300)]
    # kept: the last 256, Cmd44..Cmd299; forgotten: Cmd0..Cmd43
    for i in (299, 44, 43, 0, 100):
        daemon.reply(sent[i], "SUCCESS", f"answer {i}")
    assert ros.replies(3) == [
        "Cmd299 SUCCESS: answer 299",
        "Cmd44 SUCCESS: answer 44",
        "Cmd100 SUCCESS: answer 100",
    ]
    daemon.reply(sent[299], "SUCCESS", "again")  # answered once: the second is nobody's
    bridge.command(ns, "Last")
    daemon.reply(daemon.wait_command("Last"), "FAIL", "no")
    assert ros.replies(4)[3] == "Last FAIL: no"
    assert len(bridge._pending) == 256 - 3  # three answered


def received(daemon: DaemonPort, n: int) -> bool:
    return len(daemon.commands()) == n


def test_the_command_id_wraps_at_32_bits(rig: Callable[..., Any]) -> None:
    bridge, daemon, ros = rig()
    connected(bridge, daemon, ros, "READY")
    bridge._cmd_id = 0xFFFFFFFE
    for word in ("A", "B"):
        bridge.command(ros_ns(bridge), word)
    assert [daemon.wait_command(w).command_id for w in ("A", "B")] == [0xFFFFFFFF, 0]
    assert ros.replies(2) == ["A SUCCESS: A done", "B SUCCESS: B done"]


# ---------------------------------------------------------------------------- servo_cf


def wrench(frame: str, x: float, y: float, z: float) -> msgs.WrenchStamped:
    w = msgs.WrenchStamped(header=msgs.Header(frame_id=frame))
    w.wrench.force = msgs.Vector3(x, y, z)
    w.wrench.torque = msgs.Vector3(9.0, 9.0, 9.0)
    return w


def test_servo_cf_is_sent_in_newtons_in_the_base_frame_only(rig: Callable[..., Any]) -> None:
    """A servo_cf wrench in ``<leaf>_base`` (or without a frame) becomes SENSOR ServoCF with its
    three force values in N (torque is not sent); one in another frame or not finite is
    refused and counted, never sent."""
    bridge, daemon, ros = rig()
    connected(bridge, daemon, ros, "RUNNING")
    ns = ros_ns(bridge)
    base = bridge.robots[ns].base_frame
    for w in (
        wrench(base, 1.5, -2.0, 0.25),
        wrench("world", 1.0, 0.0, 0.0),
        wrench("", 0.0, 3.0, 0.0),
        wrench(base, math.nan, 0.0, 0.0),
        wrench(base, 0.0, math.inf, 0.0),
        wrench("slave_tip", 0.0, 0.0, 1.0),
    ):
        bridge.servo_cf(ns, w)

    def sensors() -> list[Any]:
        with daemon.lock:
            return [m for m in daemon.received if m.message_type == "SENSOR"]

    assert poll(lambda: len(sensors()) >= 2)
    got = sensors()
    assert [m.device_name for m in got] == ["ServoCF", "ServoCF"]
    assert [tuple(m.data) for m in got] == [(1.5, -2.0, 0.25), (0.0, 3.0, 0.0)]
    assert all(m.unit == igtl.messages.sensor.NEWTON and m.header_version == 2 for m in got)
    assert all(m.timestamp > 1_000_000_000 for m in got)
    st = bridge.stats()[ns]
    assert (st["servo_cf"], st["servo_cf_refused"]) == (2, 4)
    bridge.command(ns, "Sync")  # after the wrenches on the same link: none is still coming
    daemon.wait_command("Sync")
    assert len(sensors()) == 2


def test_servo_cf_without_an_operator_link_is_refused(
    dds: tuple[int, Any], namespace: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Without an operator link (a viewer-only bridge) or with one not connected, a wrench is
    refused, counted, and the log says which."""
    domain_id, _ = dds
    viewer = [("127.0.0.1", free_port(), namespace)]
    with caplog.at_level("WARNING", logger="occ_ros2"):
        with Bridge(viewer, (), domain_id=domain_id, tf=False) as bridge:
            bridge.servo_cf(namespace, wrench("", 1.0, 0.0, 0.0))
            assert bridge.stats()[namespace]["servo_cf_refused"] == 1
        with Bridge((), viewer, domain_id=domain_id, tf=False) as bridge:  # not connected
            bridge.servo_cf(namespace, wrench("", 1.0, 0.0, 0.0))
            st = bridge.stats()[namespace]
            assert (st["servo_cf"], st["servo_cf_refused"]) == (0, 1)
    lines = [r.getMessage() for r in caplog.records if "servo_cf refused" in r.getMessage()]
    assert lines == [
        f"{namespace}/servo_cf refused (1 so far): no operator interface for {namespace} "
        "(occ-ros2 --operator)",
        f"{namespace}/servo_cf refused (1 so far): operator interface not connected",
    ]


# ---------------------------------------------------------------------------- moves


def keyframe_daemon(plan: str = "plan 7: 3 keyframes, 2.000 s", ack: list[str] | None = None
                    ) -> Answer:  # fmt: skip
    """A keyframe daemon's answers: Clear and Add succeed, Plan says ``plan``, KeyframeAck
    answers from ``ack`` in turn (then SUCCESS)."""
    acks = list(ack or [])

    def answer(name: str, text: str) -> tuple[str, str] | None:
        if name == "KeyframePlan":
            return ("SUCCESS", plan) if plan else ("FAIL", "KeyframePlan: no keyframes")
        if name == "KeyframeAck":
            return ("FAIL", acks.pop(0)) if acks else ("SUCCESS", "plan 7 running: 2.000 s")
        return ok(name, text)

    return answer


def joints(bridge: Bridge) -> None:
    robot = bridge.robots[ros_ns(bridge)]
    robot.joints = (["yaw", "pitch", "insertion"], [0.0, 0.35, 0.05])


def test_move_jp_waits_for_an_operators_ack_by_default(rig: Callable[..., Any]) -> None:
    """move_jp is KeyframeClear, KeyframeAdd (the goal, its time, joint space), KeyframePlan
    (linear, stop), each sent when the last is answered; without --ack-moves the reply says the
    plan waits for an operator's KeyframeAck, and so does ``status``; no KeyframeAck is sent."""
    bridge, daemon, ros = rig(keyframe_daemon())
    connected(bridge, daemon, ros, "RUNNING")
    joints(bridge)
    ns = ros_ns(bridge)
    bridge.move(ns, "move_jp", msgs.JointState(name=["yaw"], position=[0.1]))
    waits = "plan 7 waits for an operator's KeyframeAck Plan=7 (occ-ros2 runs without --ack-moves)"
    assert ros.replies(1) == [f"move_jp WAITING: {waits}: plan 7: 3 keyframes, 2.000 s"]
    assert poll(lambda: any(s.data == f"KEYFRAME_WAITING: {waits}" for s in ros.take("status")))
    clear, add, plan = (
        daemon.commands(n)[0] for n in ("KeyframeClear", "KeyframeAdd", "KeyframePlan")
    )
    assert daemon.names()[2:] == ["KeyframeClear", "KeyframeAdd", "KeyframePlan"]
    assert clear.command == ""
    assert add.command == (
        '<Command Name="KeyframeAdd" T="2.000" Pose="0.1 0.35 0.05" Space="joint" Label="move_jp"/>'
    )
    assert plan.command == '<Command Name="KeyframePlan" Interpolation="linear" Mode="stop"/>'
    robot = bridge.robots[ns]
    assert robot.move is None
    bridge.move(ns, "move_jp", msgs.JointState(position=[0.0, 0.35, 0.1]))  # and another
    assert ros.replies(2)[1].startswith("move_jp WAITING: plan 7 waits")
    assert daemon.commands("KeyframeAdd")[1].command == (
        '<Command Name="KeyframeAdd" T="1.000" Pose="0 0.35 0.1" Space="joint" Label="move_jp"/>'
    )  # 0.05 m at 0.05 m/s: 1 s
    c = robot.counters
    assert (c.moves, c.moves_waiting, c.moves_running, c.replies, c.commands_refused) == (
        2,
        2,
        0,
        2,
        0,
    )
    assert not daemon.commands("KeyframeAck")


def test_move_cp_with_ack_moves_acknowledges_once_the_plan_is_previewed(
    rig: Callable[..., Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """With --ack-moves the bridge sends KeyframeAck Plan=N; refused while the preview has not
    gone out, it asks again (ACK_RETRY_S later) and the move's reply is the daemon's SUCCESS."""
    monkeypatch.setattr(bridge_module, "ACK_RETRY_S", 0.001)
    early = "KeyframeAck: plan 7 has not been previewed yet"
    bridge, daemon, ros = rig(keyframe_daemon(ack=[early, early]), ack_moves=True)
    connected(bridge, daemon, ros, "RUNNING")
    ns = ros_ns(bridge)
    robot = bridge.robots[ns]
    import numpy as np

    robot.tip_m = np.eye(4)
    goal = msgs.PoseStamped(header=msgs.Header(frame_id="world"))
    goal.pose.position = msgs.Point(0.03, -0.04, 0.0)  # 50 mm at 10 mm/s
    bridge.move(ns, "move_cp", goal)
    assert ros.replies(1) == ["move_cp SUCCESS: plan 7 running: 2.000 s"]
    acks = daemon.commands("KeyframeAck")
    assert len(acks) == 3
    assert {a.command for a in acks} == {'<Command Name="KeyframeAck" Plan="7"/>'}
    add = daemon.commands("KeyframeAdd")[0]
    assert add.command == (
        '<Command Name="KeyframeAdd" T="5.000" Pose="30.000000 -40.000000 0.000000" '
        'Space="cartesian" Label="move_cp"/>'
    )
    assert robot.move is None
    bridge.move(ns, "move_cp", goal)  # again: acknowledged at once this time
    assert ros.replies(2)[1] == "move_cp SUCCESS: plan 7 running: 2.000 s"
    c = robot.counters
    assert (c.moves, c.moves_running, c.moves_waiting, c.replies) == (2, 2, 0, 2)
    assert not [s for s in ros.take("status") if s.data.startswith("KEYFRAME_WAITING")]


def test_an_ack_never_accepted_is_given_up_after_its_retries(
    rig: Callable[..., Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """ACK_RETRIES (50) asks again, then the daemon's refusal is the move's reply; another
    refusal of KeyframeAck is not asked again."""
    monkeypatch.setattr(bridge_module, "ACK_RETRY_S", 0.0005)
    early = "KeyframeAck: plan 7 has not been previewed yet"
    bridge, daemon, ros = rig(keyframe_daemon(ack=[early] * 60 + ["plan 7: the robot moved"]),
                              ack_moves=True)  # fmt: skip
    connected(bridge, daemon, ros, "RUNNING")
    joints(bridge)
    ns = ros_ns(bridge)
    bridge.move(ns, "move_jp", msgs.JointState(position=[0.0, 0.35, 0.05]))
    assert ros.replies(1) == [f"move_jp FAIL: {early}"]
    assert len(daemon.commands("KeyframeAck")) == 51
    assert bridge.robots[ns].move is None
    # the next move's tries start again: the 9 early refusals left, then another refusal,
    # which is not asked again (the command's name added to the daemon's text)
    bridge.move(ns, "move_jp", msgs.JointState(name=["pitch"], position=[0.45]))
    assert ros.replies(2)[1] == "move_jp FAIL: KeyframeAck: plan 7: the robot moved"
    assert len(daemon.commands("KeyframeAck")) == 51 + 10


def test_move_refusals_by_the_daemon_are_the_moves_reply(rig: Callable[..., Any]) -> None:
    """A step the daemon refuses ends the move with its reason, the step named once; a plan
    answer without a plan number is refused; the next move may then start."""
    answers: dict[str, tuple[str, str]] = {}

    def daemon_answer(name: str, text: str) -> tuple[str, str] | None:
        return answers.get(name) or keyframe_daemon()(name, text)

    bridge, daemon, ros = rig(daemon_answer)
    connected(bridge, daemon, ros, "RUNNING")
    joints(bridge)
    ns = ros_ns(bridge)
    goal = msgs.JointState(name=["yaw"], position=[0.1])
    answers["KeyframeClear"] = ("FAIL", "plan 3 is running; Stop first")
    bridge.move(ns, "move_jp", goal)
    assert ros.replies(1) == ["move_jp FAIL: KeyframeClear: plan 3 is running; Stop first"]
    del answers["KeyframeClear"]
    answers["KeyframeAdd"] = ("FAIL", "KeyframeAdd: T must be > 0")
    bridge.move(ns, "move_jp", goal)
    assert ros.replies(2)[1] == "move_jp FAIL: KeyframeAdd: T must be > 0"
    del answers["KeyframeAdd"]
    answers["KeyframePlan"] = ("SUCCESS", "planned, no number")
    bridge.move(ns, "move_jp", goal)
    assert ros.replies(3)[2] == (
        "move_jp FAIL: KeyframePlan answered 'planned, no number': no plan number"
    )
    del answers["KeyframePlan"]
    bridge.move(ns, "move_jp", goal)
    assert ros.replies(4)[3].startswith("move_jp WAITING: plan 7 waits")
    assert daemon.names()[2:] == [
        "KeyframeClear",
        "KeyframeClear", "KeyframeAdd",
        "KeyframeClear", "KeyframeAdd", "KeyframePlan",
        "KeyframeClear", "KeyframeAdd", "KeyframePlan",
    ]  # fmt: skip
    c = bridge.robots[ns].counters
    assert (c.moves, c.commands_refused, c.moves_waiting) == (4, 3, 1)


def test_one_move_at_a_time_until_its_answer_or_its_timeout(rig: Callable[..., Any]) -> None:
    """A second move while the first is still being answered is refused; a move left without
    an answer for MOVE_TIMEOUT_S no longer blocks the next, and its late answers are ignored."""
    held: list[Any] = []

    def daemon_answer(name: str, text: str) -> tuple[str, str] | None:
        if name == "KeyframeClear" and not held:
            held.append(name)
            return None  # the first move's first step is never answered
        return keyframe_daemon()(name, text)

    bridge, daemon, ros = rig(daemon_answer)
    connected(bridge, daemon, ros, "RUNNING")
    joints(bridge)
    ns = ros_ns(bridge)
    robot = bridge.robots[ns]
    goal = msgs.JointState(name=["yaw"], position=[0.1])
    bridge.move(ns, "move_jp", goal)
    first = daemon.wait_command("KeyframeClear")
    first_move = robot.move
    bridge.move(ns, "move_cp", msgs.PoseStamped())
    assert ros.replies(1) == [
        "move_cp FAIL: the last move_jp is still being planned; wait for its reply"
    ]
    assert robot.move is first_move
    first_move.started -= bridge_module.MOVE_TIMEOUT_S - 1.0  # not yet
    bridge.move(ns, "move_jp", goal)
    assert ros.replies(2)[1].startswith("move_jp FAIL: the last move_jp is still")
    first_move.started -= 1.001  # now it is
    bridge.move(ns, "move_jp", goal)
    assert ros.replies(3)[2].startswith("move_jp WAITING: plan 7")
    daemon.reply(first, "FAIL", "late")  # the given-up move's answer: nothing
    bridge.command(ns, "Sync")
    assert ros.replies(4)[3] == "Sync SUCCESS: Sync done"
    assert len(ros.take("command_reply")) == 4
    assert daemon.names()[2:] == [
        "KeyframeClear",
        "KeyframeClear",
        "KeyframeAdd",
        "KeyframePlan",
        "Sync",
    ]
    # a given-up move sends nothing more
    bridge._move_send(robot, first_move, "KeyframeAdd", {})
    bridge.command(ns, "Sync")
    daemon.wait_command("Sync", 2)
    assert daemon.names()[-2:] == ["Sync", "Sync"]


def test_move_goals_the_bridge_refuses_itself(rig: Callable[..., Any]) -> None:
    """Named joints that are not the daemon's, names and positions that do not pair, a goal
    frame that is neither the world nor the base, a position that is not finite: refused,
    said why, nothing sent."""
    bridge, daemon, ros = rig()
    connected(bridge, daemon, ros, "RUNNING")
    joints(bridge)
    ns = ros_ns(bridge)
    robot = bridge.robots[ns]
    import numpy as np

    robot.tip_m = np.eye(4)
    cases: list[tuple[str, Any, str]] = [
        ("move_jp", msgs.JointState(name=["yaw", "roll"], position=[0.1, 0.2]),
         "no joint 'roll' (the daemon's: yaw, pitch, insertion)"),
        ("move_jp", msgs.JointState(name=["yaw", "pitch"], position=[0.1]),
         "2 names but 1 positions"),
        ("move_jp", msgs.JointState(position=[0.1, 0.2, 0.3, 0.4]),
         "4 positions for 3 joints (yaw, pitch, insertion); give all, or name them"),
        ("move_jp", msgs.JointState(position=[0.1, math.inf, 0.3]),
         "a position is not a finite number"),
        ("move_cp", msgs.PoseStamped(header=msgs.Header(frame_id="slave_tip")),
         f"frame_id 'slave_tip': a goal is in 'world' (as measured_cp) or "
         f"'{robot.base_frame}' (as local/measured_cp)"),
    ]  # fmt: skip
    nan_goal = msgs.PoseStamped(header=msgs.Header(frame_id="world"))
    nan_goal.pose.position = msgs.Point(0.0, math.nan, 0.0)
    cases.append(("move_cp", nan_goal, "the position is not finite"))
    for kind, goal, _ in cases:
        bridge.move(ns, kind, goal)
    assert ros.replies(len(cases)) == [f"{k} FAIL: {why}" for k, _, why in cases]
    assert daemon.names() == ["GetStats", "GetState"]
    assert robot.move is None


# ---------------------------------------------------------------------------- master mode


def test_parse_master() -> None:
    assert parse_master("/occ/master=127.0.0.1:18946") == ("/occ/master", "127.0.0.1", 18946)
    assert parse_master("occ/master/=::1:5") == ("/occ/master", "::1", 5)
    assert parse_master("/Xarm/X=h:1") == ("/Xarm/X", "h", 1)  # only slashes are stripped
    assert parse_master("/X1/occ=h:1") == ("/X1/occ", "h", 1)  # and checked: X1 is a name
    assert parse_master("/a=my-host_2.lab:7") == ("/a", "my-host_2.lab", 7)
    # a host holding "=" (or a space, a slash) is refused here, not by the resolver later
    for bad in ("/occ/master", "/occ/master=127.0.0.1", "/occ/master=:1", "/occ/ma-ster=h:1",
                "/occ/master=h:x1", "=h:1", "/ns=a=b:1", "/ns=a b:1", "/ns=a/b:1"):  # fmt: skip
        with pytest.raises(ValueError, match="expected /NAMESPACE=HOST:PORT"):
            parse_master(bad)


class Slave:
    """The slave's side of master mode: a UDP endpoint on 127.0.0.1 that keeps what comes."""

    def __init__(self) -> None:
        self.udp = UDPEndpoint("127.0.0.1", 0, name="test-slave").start()

    def take(self, n: int) -> list[Any]:
        got: list[Any] = []

        def some() -> bool:
            item = self.udp.receive(0.05)
            if item is not None:
                got.append(item[1])
            return len(got) >= n

        assert poll(some)
        return got


@pytest.fixture
def master(dds: tuple[int, Any], namespace: str) -> Iterator[Callable[..., Any]]:
    """``master(**options)``: (stream, slave, pose writer, clutch writer); the stream's
    period is driven by the test (``_read_topics``, ``_send``), not by its thread."""
    _, dp = dds
    opened: list[Any] = []

    def make(**options: Any) -> tuple[MasterStream, Slave, DataWriter, DataWriter]:
        slave = Slave()
        opened.append(slave.udp)
        stream = MasterStream(dp, namespace, slave.udp.address, **options)
        stream.udp.start()
        opened.append(stream)  # its stop() stops its link (its thread was never started)
        poses = DataWriter(dp, Topic(dp, topic_name(namespace, "servo_cp"), msgs.PoseStamped),
                           QOS_DEFAULT)  # fmt: skip
        clutch = DataWriter(dp, Topic(dp, topic_name(namespace, "clutch"), msgs.String),
                            QOS_DEFAULT)  # fmt: skip
        for w in (poses, clutch):
            assert poll(partial(matched, w))
        return stream, slave, poses, clutch

    yield make
    for thing in reversed(opened):
        thing.stop()


def pose(x: float, y: float, z: float, q: tuple[float, float, float, float],
         frame: str = "world") -> msgs.PoseStamped:  # fmt: skip
    return msgs.PoseStamped(header=msgs.Header(frame_id=frame),
                            pose=msgs.Pose(msgs.Point(x, y, z), msgs.Quaternion(*q)))  # fmt: skip


def matched(writer: DataWriter) -> bool:
    return bool(writer.get_publication_matched_status().current_count >= 1)


def deliver(stream: MasterStream, now: float, until: Callable[[], bool]) -> None:
    """Let the stream read its topics (at time ``now``) until ``until()``."""

    def read() -> bool:
        stream._read_topics(now)
        return until()

    assert poll(read)


def clutch_is(stream: MasterStream, pressed: bool) -> bool:
    return stream.clutch is pressed


def test_master_stream_sends_the_latest_pose_in_mm_with_run_and_clutch(
    master: Callable[..., Any],
) -> None:
    """servo_cp (metres) becomes POSITION ``Master`` in mm, the quaternion with w >= 0 (the
    24-byte variant drops w), the message ID +1 per packet, header version 2, ``run`` 1 while
    the latest pose is at most ``stale_s`` (0.1 s) old, then 0; ``clutch`` follows the clutch
    topic's words; nothing is sent before the first pose."""
    stream, slave, poses, clutch = master(first_seq=41)
    assert stream.period == pytest.approx(0.002)  # 500 Hz, as the master daemon's stream
    stream._send(0.0)
    assert stream.sent == 0 and stream.seq == 41
    s = math.sqrt(0.5)
    poses.write(pose(0.01, -0.02, 0.3, (0.0, 0.0, s, -s)))
    deliver(stream, 10.0, lambda: stream.poses == 1)
    stream._send(10.0)
    stream._send(10.1)
    stream._send(10.1001)
    got = slave.take(3)
    assert [m.message_id for m in got] == [42, 43, 44]
    first = got[0]
    assert (first.message_type, first.device_name, first.header_version) == (
        "POSITION",
        "Master",
        2,
    )
    assert first.position == pytest.approx((10.0, -20.0, 300.0), abs=1e-4)
    assert first.quaternion == pytest.approx((0.0, 0.0, -s, s), abs=1e-6)
    assert first.timestamp > 1_000_000_000
    assert first.layout == 24  # position + 3-element quaternion, as the master daemon's
    assert verify(first, b"any key") == "no HMAC"  # no key: not signed
    assert [m.metadata["run"] for m in got] == ["1", "1", "0"]
    assert [m.metadata["clutch"] for m in got] == ["0", "0", "0"]
    for word, pressed in (("pressed", True), (" 1 ", True), ("TRUE", True), ("On", True),
                          ("0", False), ("released", False), ("yes", False)):  # fmt: skip
        clutch.write(msgs.String(data=word))
        deliver(stream, 10.0, partial(clutch_is, stream, pressed))
        stream._send(10.0)
        (m,) = slave.take(1)
        assert (m.metadata["clutch"], m.metadata["run"]) == ("1" if pressed else "0", "1"), word
    st = stream.stats()
    assert (st["sent"], st["poses"], st["late_periods"], st["refused_frames"]) == (10, 1, 0, 0)


def test_master_stream_keeps_a_positive_w_and_the_sequence_wraps(
    master: Callable[..., Any],
) -> None:
    stream, slave, poses, _ = master(first_seq=0xFFFFFFFF + 2, stale_s=0.5, device="ServoCP")
    assert stream.seq == 1
    poses.write(pose(0.0, 0.0, 0.0, (0.5, 0.5, 0.5, 0.5)))
    deliver(stream, 1.0, lambda: stream.poses == 1)
    stream._send(1.5)
    stream._send(1.5001)
    a, b = slave.take(2)
    assert (a.device_name, a.message_id, a.metadata["run"]) == ("ServoCP", 2, "1")
    assert b.metadata["run"] == "0"
    assert a.quaternion == pytest.approx((0.5, 0.5, 0.5, 0.5))
    stream.seq = 0xFFFFFFFF
    stream._send(1.0)
    (c,) = slave.take(1)
    assert c.message_id == 0
    # the latest pose is the one sent; every pose counted
    poses.write(pose(0.0, 0.0, 0.004, (0.0, 0.0, 0.0, 1.0)))
    deliver(stream, 2.0, lambda: stream.poses == 2)
    stream._send(2.0)
    (d,) = slave.take(1)
    assert d.position == pytest.approx((0.0, 0.0, 4.0), abs=1e-4) and d.message_id == 1


def test_servo_mode_refuses_a_pose_in_another_frame(master: Callable[..., Any]) -> None:
    """With ``frames`` (servo mode: the world frame of measured_cp) a pose stamped in another
    frame is refused and counted; the last accepted pose stays the one sent."""
    stream, slave, poses, _ = master(frames=("world",), device="ServoCP")
    poses.write(pose(0.001, 0.0, 0.0, (0.0, 0.0, 0.0, 1.0)))
    deliver(stream, 1.0, lambda: stream.poses == 1)
    poses.write(pose(0.5, 0.5, 0.5, (0.0, 0.0, 0.0, 1.0), frame="slave_base"))
    poses.write(pose(0.5, 0.5, 0.5, (0.0, 0.0, 0.0, 1.0), frame=""))
    deliver(stream, 2.0, lambda: stream.refused_frames == 2)
    assert stream.poses == 1 and stream.pose_t == 1.0
    stream._send(1.05)
    (m,) = slave.take(1)
    assert m.position == pytest.approx((1.0, 0.0, 0.0), abs=1e-4)
    assert m.metadata["run"] == "1"
    assert stream.stats()["refused_frames"] == 2


def test_master_mode_takes_any_frame_and_signs_with_the_slaves_key(
    master: Callable[..., Any],
) -> None:
    key = b"a shared key for the master link"
    stream, slave, poses, _ = master(auth_key=key)
    poses.write(pose(0.0, 0.002, 0.0, (0.0, 0.0, 0.0, 1.0), frame="anything"))
    deliver(stream, 1.0, lambda: stream.poses == 1)
    stream._send(1.0)
    (m,) = slave.take(1)
    assert verify(m, key) == "" and verify(m, b"another key") == "wrong HMAC"
    assert m.position == pytest.approx((0.0, 2.0, 0.0), abs=1e-4)


def test_master_stream_binds_to_loopback_for_a_slave_on_loopback(dds: tuple[int, Any]) -> None:
    """A slave on 127.0.0.1: the stream's socket is bound to 127.0.0.1 too, so nothing off the
    machine can reach it; another slave address needs the machine's interfaces (not started
    here: nothing is sent)."""
    _, dp = dds
    local = MasterStream(dp, "/occtest_bind/a", ("127.0.0.1", 9))
    remote = MasterStream(dp, "/occtest_bind/b", ("192.0.2.1", 9))
    assert (local.udp.host, remote.udp.host) == ("127.0.0.1", "0.0.0.0")
    assert (local.device, local.stale_s, local.frames, local.auth_key) == (
        "Master",
        0.1,
        None,
        None,
    )
    assert (local.pose, local.clutch, local.sent, local.seq) == (None, False, 0, 0)


def test_two_streams_each_have_their_own_port(dds: tuple[int, Any]) -> None:
    """A bridge with --master and --servo runs two streams: each binds a port of its own (the
    kernel's choice), so both start."""
    _, dp = dds
    streams = [MasterStream(dp, f"/occtest_ports/{n}", ("127.0.0.1", 9)) for n in "ab"]
    try:
        for stream in streams:
            stream.udp.start()
        ports = {stream.udp.address[1] for stream in streams}
        assert len(ports) == 2 and min(ports) >= 1024, ports
    finally:
        for stream in streams:
            stream.stop()


def test_master_streams_subscriptions_as_ros2_nodes_discover_them(
    dds: tuple[int, Any], namespace: str
) -> None:
    """What a ROS 2 node learns of the stream's subscriptions on discovery (DDS's built-in
    subscription topic): servo_cp best effort (it matches reliable and best-effort publishers
    alike), clutch reliable (a press is not lost), each with its type's ROS 2 Jazzy type hash
    in USER_DATA, which Jazzy nodes compare."""
    from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsSubscription

    _, dp = dds
    seen = BuiltinDataReader(dp, BuiltinTopicDcpsSubscription)
    stream = MasterStream(dp, namespace, ("127.0.0.1", 9))
    found: dict[str, Any] = {}

    def both() -> bool:
        for s in seen.take(N=256):
            found[s.topic_name] = s.qos
        return all(topic_name(namespace, leaf) in found for leaf in ("servo_cp", "clutch"))

    try:
        assert poll(both), sorted(found)
        for leaf, cls, reliability in (
            ("servo_cp", msgs.PoseStamped, "Policy.Reliability.BestEffort"),
            ("clutch", msgs.String, "Policy.Reliability.Reliable("),
        ):
            qos = found[topic_name(namespace, leaf)]
            assert str(qos[Policy.Reliability]).startswith(reliability), (leaf, qos)
            assert qos[Policy.Userdata].data == msgs.user_data(cls), leaf
    finally:
        stream.stop()


def test_servo_cf_refusals_are_logged_first_and_every_thousandth(
    dds: tuple[int, Any], namespace: str, caplog: pytest.LogCaptureFixture
) -> None:
    """A client streaming wrenches in a wrong frame (hundreds a second) is reported in the log
    at its first refusal and every 1000th, with the count and the reason, not once per wrench."""
    domain_id, _ = dds
    endpoint = [("127.0.0.1", free_port(), namespace)]
    with Bridge((), endpoint, domain_id=domain_id, tf=False) as bridge:
        with caplog.at_level("WARNING", logger="occ_ros2"):
            for _ in range(2001):
                bridge.servo_cf(namespace, wrench("world", 1.0, 0.0, 0.0))
    lines = [r.getMessage() for r in caplog.records if "servo_cf refused" in r.getMessage()]
    why = "frame 'world' (takes 'slave_base')"
    assert lines == [f"{namespace}/servo_cf refused ({n} so far): {why}" for n in (1, 1000, 2000)]
    assert bridge.stats()[namespace]["servo_cf_refused"] == 2001


def test_a_reply_as_the_reference_peer_sends_it(rig: Callable[..., Any]) -> None:
    """A reply without the v2 metadata, an error string in its command name (the reference
    OpenIGTLink's way): published under the command's own name, its status unknown ("?")."""
    bridge, daemon, ros = rig(lambda name, text: ok(name, text) if name.startswith("Get") else None)
    connected(bridge, daemon, ros, "READY")
    bridge.command(ros_ns(bridge), "Foo")
    cmd = daemon.wait_command("Foo")
    daemon.server.send(
        igtl.RTSCommandMessage(command_id=cmd.command_id, command_name="Error: unknown command")
    )
    assert ros.replies(1) == ["Foo ?: "]


# ---------------------------------------------------------------------------- the DDS side


def test_commands_come_from_the_ros2_topics_and_the_state_is_latched(
    rig: Callable[..., Any], dds: tuple[int, Any]
) -> None:
    """What a ROS 2 node publishes reaches the daemon: CRTK's state_command
    (crtk_msgs/StringStamped), command (std_msgs/String), move_jp, move_cp and servo_cf, each
    with the ROS 2 type hash its node checks; a node that subscribes later gets the current
    state and operating_state at once (transient local), and only the current one."""
    _, dp = dds
    bridge, daemon, ros = rig(keyframe_daemon())
    ns = ros_ns(bridge)
    connected(bridge, daemon, ros, "STOPPED")
    daemon.status("RUNNING")
    assert poll(lambda: bridge.robots[ns].state == "RUNNING")
    joints(bridge)
    import numpy as np

    bridge.robots[ns].tip_m = np.eye(4)

    def writer(leaf: str, cls: type[Any]) -> DataWriter:
        w = DataWriter(dp, Topic(dp, topic_name(ns, leaf), cls), typed_qos(QOS_DEFAULT, cls))
        assert poll(partial(matched, w)), leaf
        return w

    writer("state_command", msgs.StringStamped).write(msgs.StringStamped(string="pause"))
    daemon.wait_command("Stop")
    writer("command", msgs.String).write(msgs.String(data="Reset"))
    daemon.wait_command("Reset")
    writer("move_jp", msgs.JointState).write(msgs.JointState(name=["yaw"], position=[0.1]))
    daemon.wait_command("KeyframePlan")
    assert poll(
        lambda: any(r.data.startswith("move_jp WAITING") for r in ros.take("command_reply"))
    )
    goal = msgs.PoseStamped(header=msgs.Header(frame_id="world"))
    goal.pose.position = msgs.Point(0.0, 0.0, 0.01)
    writer("move_cp", msgs.PoseStamped).write(goal)
    daemon.wait_command("KeyframePlan", 2)
    assert daemon.commands("KeyframeAdd")[1].command == (
        '<Command Name="KeyframeAdd" T="1.000" Pose="0.000000 0.000000 10.000000" '
        'Space="cartesian" Label="move_cp"/>'
    )
    writer("servo_cf", msgs.WrenchStamped).write(wrench("", 0.5, 0.0, 0.0))
    assert poll(lambda: bridge.robots[ns].counters.servo_cf == 1)
    late = RosSide(dp, ns)
    assert poll(lambda: bool(late.take("state")) and bool(late.take("operating_state")))
    assert [s.data for s in late.take("state")] == ["RUNNING"]
    assert late.ops() == [("ENABLED", True, False)]


def test_a_ros2_node_that_goes_away_does_not_end_the_forwarding(
    rig: Callable[..., Any], dds: tuple[int, Any]
) -> None:
    """When a ROS 2 node's publisher goes away (the node exits: its writer is deleted), DDS
    tells the bridge's reader so with a sample that carries no data; the bridge goes on taking
    commands from the next node."""
    import gc

    _, dp = dds
    bridge, daemon, ros = rig()
    ns = ros_ns(bridge)
    connected(bridge, daemon, ros, "READY")
    sends: tuple[tuple[str, type[Any], Any, str], ...] = (
        ("command", msgs.String, msgs.String(data="Reset"), "Reset"),
        ("state_command", msgs.StringStamped, msgs.StringStamped(string="Sync"), "Sync"),
        ("command", msgs.String, msgs.String(data="Reset"), "Reset"),
    )
    for n, (leaf, cls, sample, name) in enumerate(sends):
        w: DataWriter = DataWriter(
            dp, Topic(dp, topic_name(ns, leaf), cls), typed_qos(QOS_DEFAULT, cls)
        )
        assert poll(partial(matched, w)), leaf
        w.write(sample)
        daemon.wait_command(name, 1 + n // 2)
        del w  # the node exits
        gc.collect()
    assert daemon.names()[2:] == ["Reset", "Sync", "Reset"]
    assert bridge._thread is not None and bridge._thread.is_alive()


def test_master_stream_outlives_a_node_that_goes_away(master: Callable[..., Any]) -> None:
    """servo_cp's and clutch's publishers going away (the node exits) leave the stream
    running on the last pose; the next node's poses are followed."""
    import gc

    stream, slave, poses, clutch = master()
    poses.write(pose(0.001, 0.0, 0.0, (0.0, 0.0, 0.0, 1.0)))
    clutch.write(msgs.String(data="pressed"))
    deliver(stream, 1.0, lambda: stream.poses == 1 and stream.clutch)
    del poses, clutch  # the node exits
    gc.collect()
    for t in (1.01, 1.02, 1.03):
        stream._read_topics(t)  # no error: the "gone" notifications carry no pose
    assert stream.poses == 1 and stream.clutch is True
    stream._send(1.05)
    (m,) = slave.take(1)
    assert m.position == pytest.approx((1.0, 0.0, 0.0), abs=1e-4)


def test_every_status_is_on_the_status_topic_but_keep_alives(rig: Callable[..., Any]) -> None:
    """Each STATUS the daemon sends is published on ``status`` as ``NAME: message`` (alerts
    included, a name or a message alone too); an empty one (a keep-alive, a greeting) is
    counted only. A state's STATUS sets the state with or without a message, stamped with its
    time stamp when it has one (any positive time), else when it came."""
    bridge, daemon, ros = rig()
    connected(bridge, daemon, ros, "READY")
    ns = ros_ns(bridge)
    before = bridge.stats()[ns]["statuses"]
    n = len(ros.ops())

    def send(name: str, text: str, timestamp: float = 0.0) -> None:
        daemon.server.send(
            igtl.StatusMessage(
                error_name=name, status_message=text, header_version=2, timestamp=timestamp
            )
        )

    send("", "")  # a keep-alive
    send("ALERT_LOSS", "master silent for 120 ms")
    send("ENABLED", "", timestamp=0.5)  # a state without a message; a stamp near the epoch
    send("", "a note")
    send("ESTOP", "estop pressed")  # no time stamp
    assert poll(lambda: len(ros.take("status")) >= 5)
    assert [s.data for s in ros.take("status")] == [
        "READY: READY",  # connected()'s
        "ALERT_LOSS: master silent for 120 ms",
        "ENABLED: ",
        ": a note",
        "ESTOP: estop pressed",
    ]
    assert bridge.stats()[ns]["statuses"] == before + 5
    assert poll(lambda: len(ros.ops()) == n + 2)
    enabled, estop = ros.take("operating_state")[-2:]
    assert enabled.state == "PAUSED"
    assert (enabled.header.stamp.sec, enabled.header.stamp.nanosec) == (0, 500_000_000)
    assert estop.state == "FAULT" and estop.header.stamp.sec > REPLY_STAMP
    assert bridge.robots[ns].state == "ESTOP"


def test_master_stream_takes_the_next_nodes_pose_behind_a_gone_one(
    master: Callable[..., Any], dds: tuple[int, Any], namespace: str
) -> None:
    """One node's pose and clutch, the node gone, the next node's pose and clutch, all waiting
    in one period: the stream follows the next node's."""
    import gc

    _, dp = dds
    stream, slave, poses, clutch = master()

    def node(leaf: str, cls: type[Any]) -> DataWriter:
        w: DataWriter = DataWriter(dp, Topic(dp, topic_name(namespace, leaf), cls), QOS_DEFAULT)
        assert poll(partial(matched, w)), leaf
        return w

    del poses, clutch  # the fixture's node: gone before anything is sent
    gc.collect()
    first_pose, first_clutch = node("servo_cp", msgs.PoseStamped), node("clutch", msgs.String)
    first_pose.write(pose(0.001, 0.0, 0.0, (0.0, 0.0, 0.0, 1.0)))
    first_clutch.write(msgs.String(data="pressed"))
    del first_pose, first_clutch  # the first node exits
    gc.collect()
    next_pose, next_clutch = node("servo_cp", msgs.PoseStamped), node("clutch", msgs.String)
    next_pose.write(pose(0.0, 0.003, 0.0, (0.0, 0.0, 0.0, 1.0)))
    next_clutch.write(msgs.String(data="released"))

    def waiting(reader: DataReader[Any]) -> list[str]:  # looked at, not taken
        return [type(x).__name__ for x in reader.read(N=64)]

    # both nodes' samples wait; the notice of the first one's exit is not among them (Cyclone
    # drops an unread "gone" notice when the next sample comes)
    assert poll(lambda: len(waiting(stream._poses)) == len(waiting(stream._clutch)) == 2)
    assert (waiting(stream._poses), waiting(stream._clutch)) == (
        ["PoseStamped"] * 2,
        ["String"] * 2,
    )
    stream._read_topics(1.0)
    assert (stream.poses, stream.clutch) == (2, False)
    stream._send(1.0)
    (m,) = slave.take(1)
    assert m.position == pytest.approx((0.0, 3.0, 0.0), abs=1e-4)
    assert m.metadata["clutch"] == "0"


# ---------------------------------------------------------------------------- each STATUS once


@pytest.mark.req("SR-REPLY-1")
def test_a_daemon_on_two_links_has_each_status_published_once(
    dds: tuple[int, Any], namespace: str
) -> None:
    """``--connect`` and ``--operator`` to one daemon: it sends every STATUS to both links
    (occ/core/alarms.py ``broadcast``) and greets each new link with its state
    (occ/net/operators.py ``greet``). Each is published once on ``status``; the state and
    operating_state change once. Unstamped STATUS cannot be told apart and is published as it
    comes."""
    domain_id, dp = dds
    daemon = DaemonPort()
    stamp = [1_700_000_000.0]

    def greet(peer: Any) -> None:
        stamp[0] += 1.0
        msg = igtl.StatusMessage(error_name="READY", status_message="occd is READY",
                                 header_version=2, timestamp=stamp[0])  # fmt: skip
        daemon.server.send(msg, peer)

    daemon.server.on_connect = greet
    daemon.server.start()
    ros = RosSide(dp, namespace)
    link = [("127.0.0.1", daemon.port, namespace)]
    with Bridge(link, link, domain_id=domain_id, tf=False) as bridge:
        assert bridge.wait_connected()
        robot = bridge.robots[namespace]
        assert poll(lambda: robot.counters.statuses == 2)  # both greetings handled
        # operating_state waits for the answer to the bridge's GetStats probe (is a plan
        # running?): the changes below are each published once it has come
        assert poll(lambda: robot.probing_until == 0.0)
        for i, (state, text) in enumerate(
            [("ENABLED", "READY -> ENABLED"), ("RUNNING", "ENABLED -> RUNNING"),
             ("ALERT", "master late by 4.1 ms"), ("STOPPED", "RUNNING -> STOPPED: loss")]
        ):  # fmt: skip
            daemon.status(state, text, timestamp=1_700_000_100.0 + i)
        assert poll(lambda: robot.counters.statuses == 2 + 8)
        daemon.status("RUNNING", "unstamped")  # no time stamp: each copy is news
        assert poll(lambda: robot.counters.statuses == 2 + 8 + 2)
        assert poll(lambda: len(ros.take("status")) >= 7)
        assert [s.data for s in ros.take("status")] == [
            "READY: occd is READY",
            "ENABLED: READY -> ENABLED",
            "RUNNING: ENABLED -> RUNNING",
            "ALERT: master late by 4.1 ms",
            "STOPPED: RUNNING -> STOPPED: loss",
            "RUNNING: unstamped",
            "RUNNING: unstamped",
        ]
        assert [s.data for s in ros.take("state")] == ["READY", "ENABLED", "RUNNING", "STOPPED",
                                                       "RUNNING"]  # fmt: skip
        # operating_state may say the same state twice (the answer to the bridge's GetStats
        # probe on connecting republishes it, whenever it comes): its changes, once each
        ops = [o[0] for o in ros.ops()]
        changes = [s for i, s in enumerate(ops) if i == 0 or ops[i - 1] != s]
        assert changes == ["DISABLED", "PAUSED", "ENABLED", "PAUSED", "ENABLED"], ops
        assert bridge.stats()[namespace]["statuses_repeated"] == 5
    daemon.server.stop()


def test_a_late_copy_never_sets_an_old_state_again(dds: tuple[int, Any], namespace: str) -> None:
    """The copies of a daemon's STATUS reach the bridge's two links in any order: a state the
    first link has already moved past, arriving on the second, is a copy, not a change."""
    domain_id, _ = dds
    with Bridge((), [("127.0.0.1", free_port(), namespace)], domain_id=domain_id, tf=False
                ) as bridge:  # fmt: skip
        robot = bridge.robots[namespace]
        robot.viewer = robot.operator  # a second link (neither connected: no greeting rule)

        def status(name: str, t: float, link: str) -> None:
            msg = igtl.StatusMessage(error_name=name, status_message=name, timestamp=t)
            bridge._on_igtl(robot, msg, link)

        status("STOPPED", 5.0, "viewer")
        status("RUNNING", 6.0, "viewer")
        status("STOPPED", 5.0, "operator")  # the slow link's copy of the first
        status("RUNNING", 6.0, "operator")
        assert robot.state == "RUNNING"
        status("STOPPED", 5.0, "viewer")  # the same link twice: a new STATUS
        assert robot.state == "STOPPED"
        assert robot.counters.statuses_repeated == 2


# ---------------------------------------------------------------------------- request ids


@pytest.mark.req("SR-REPLY-2")
def test_a_reply_names_the_request_it_answers(rig: Callable[..., Any]) -> None:
    """``[ID] word`` (a daemon command, a CRTK word, a word the bridge refuses) is answered
    ``[ID] ...``; a move is named by its goal's stamp; a word without an id is answered as
    before; a malformed id is refused, saying how to write one, and nothing is sent."""
    bridge, daemon, ros = rig(keyframe_daemon())
    connected(bridge, daemon, ros, "RUNNING")
    joints(bridge)
    ns = ros_ns(bridge)
    bridge.command(ns, "[a-1] GetRecordingStatus")
    bridge.command(ns, " [node_7:2.x]   enable")
    bridge.command(ns, "[a-2] rm -rf")
    bridge.command(ns, "Sync")
    goal = msgs.JointState(header=msgs.Header(stamp=msgs.Time(1_700_000_123, 45)),
                           name=["yaw"], position=[0.1])  # fmt: skip
    bridge.move(ns, "move_jp", goal)
    assert poll(lambda: len(ros.take("command_reply")) == 5)
    bridge.move(ns, "move_jp", msgs.JointState(name=["roll"], position=[0.1]))  # unstamped
    replies = ros.replies(6)
    assert sorted(replies[:4]) == [  # the bridge's own answers may overtake the daemon's
        "Sync SUCCESS: Sync done",
        "[a-1] GetRecordingStatus SUCCESS: GetRecordingStatus done",
        "[a-2] rm -rf FAIL: not a command name",
        "[node_7:2.x] enable SUCCESS: already ENABLED",
    ]
    assert replies[4].startswith("[1700000123.000000045] move_jp WAITING: plan 7 waits")
    assert replies[5].startswith("move_jp FAIL: no joint 'roll'")
    sent = len(daemon.commands())
    for bad in ("[] enable", "[a b] enable", "[x" + "y" * 64 + "] Run", "[unclosed Run"):
        bridge.command(ns, bad)
    for reply in ros.replies(10)[6:]:
        assert reply.startswith("(request) FAIL: ") and "a request id is 1..64" in reply, reply
    assert len(daemon.commands()) == sent  # refused: nothing went to the daemon


@pytest.mark.req("SR-REPLY-2")
def test_a_client_takes_only_its_own_reply_when_a_gone_clients_comes_first(
    rig: Callable[..., Any], dds: tuple[int, Any]
) -> None:
    """Client A asks, and goes before the answer; client B subscribes, asks, and A's answer is
    published first (the daemon answers in its own time): on the shared reply topic B tells
    its own by its id, as a ROS 2 service client tells its response by its request's id."""
    bridge, daemon, _ = rig(lambda name, text: None if name == "Slow" else ok(name, text))
    ns = ros_ns(bridge)
    bridge.command(ns, "[A-1] Slow")  # answered later
    a_cmd = daemon.wait_command("Slow")
    _, dp = dds
    b_side = RosSide(dp, ns)  # client B comes after A's request
    bridge.command(ns, "[B-1] Slow")
    b_cmd = daemon.wait_command("Slow", 2)
    daemon.reply(a_cmd, "SUCCESS", "for A")  # A's answer, late: before B's
    daemon.reply(b_cmd, "SUCCESS", "for B")
    got = [s.data for s in b_side.wait("command_reply", 2)]
    assert got == ["[A-1] Slow SUCCESS: for A", "[B-1] Slow SUCCESS: for B"]
    assert [r for r in got if r.startswith("[B-1] ")] == ["[B-1] Slow SUCCESS: for B"]


@pytest.mark.req("SR-REPLY-1")
def test_an_answer_to_getstate_on_connect_never_undoes_a_newer_status(
    dds: tuple[int, Any], namespace: str
) -> None:
    """The bridge asks GetState as each link connects (a late joiner learns the state); on two
    links that answer may be handled after a STATUS of a newer state (another link's thread):
    it is then older news and must not set the state back. Without a STATUS since the
    question, the answer is taken (a daemon that does not greet)."""
    domain_id, dp = dds
    daemon = DaemonPort(answer=lambda n, t: None if n == "GetState" else ok(n, t))
    daemon.server.start()
    ros = RosSide(dp, namespace)
    link = [("127.0.0.1", daemon.port, namespace)]
    with Bridge(link, link, domain_id=domain_id, tf=False) as bridge:
        assert bridge.wait_connected()
        robot = bridge.robots[namespace]
        asked = [daemon.wait_command("GetState", 1), daemon.wait_command("GetState", 2)]
        daemon.reply(asked[0], "SUCCESS", "state=READY; alert=none")  # no STATUS yet: taken
        assert poll(lambda: robot.state == "READY")
        daemon.status("ENABLED", "READY -> ENABLED", timestamp=1_700_000_100.0)
        assert poll(lambda: robot.counters.statuses == 2)  # both links' copies handled
        daemon.reply(asked[1], "SUCCESS", "state=READY; alert=none")  # the late answer
        daemon.status("ALERT", "after the answer", timestamp=1_700_000_101.0)
        assert poll(lambda: robot.counters.statuses == 4)  # each link handled the answer first
        assert robot.state == "ENABLED"
        assert [s.data for s in ros.take("state")] == ["READY", "ENABLED"]
    daemon.server.stop()
