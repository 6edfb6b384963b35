"""The bridge's pieces without a daemon: pose conversion, names, command refusals."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from .conftest import poll, require_extra

require_extra()

from cyclonedds.sub import DataReader  # noqa: E402
from cyclonedds.topic import Topic  # noqa: E402

from occ_ros2 import msgs  # noqa: E402
from occ_ros2.bridge import (  # noqa: E402
    HELD,
    QOS_DEFAULT,
    QOS_LATCHED,
    Bridge,
    parse_endpoint,
    pose_stamped,
    quaternion,
    topic_name,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
from loopback import free_port  # noqa: E402


def rot(axis: tuple[float, float, float], angle: float) -> np.ndarray:
    x, y, z = np.array(axis) / np.linalg.norm(axis)
    k = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def from_quaternion(x: float, y: float, z: float, w: float) -> np.ndarray:
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


@pytest.mark.parametrize("angle", [0.0, 0.3, 1.5, math.pi - 1e-9, math.pi, -2.0])
@pytest.mark.parametrize("axis", [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, -2, 0.5)])
def test_quaternion_round_trips_every_branch(
    axis: tuple[float, float, float], angle: float
) -> None:
    r = rot(axis, angle)
    q = quaternion(r)
    assert q[3] >= 0.0
    assert math.isclose(sum(v * v for v in q), 1.0, rel_tol=1e-12)
    assert np.allclose(from_quaternion(*q), r, atol=1e-9)


def test_pose_stamped_takes_metres_and_the_frame() -> None:
    m = np.eye(4)
    m[:3, :3] = rot((0, 0, 1), 0.5)
    m[:3, 3] = (0.01, -0.02, 0.3)
    p = pose_stamped(m, msgs.Time(5, 6), "slave_base")
    assert (p.header.frame_id, p.header.stamp) == ("slave_base", msgs.Time(5, 6))
    assert (p.pose.position.x, p.pose.position.y, p.pose.position.z) == (0.01, -0.02, 0.3)
    assert math.isclose(p.pose.orientation.z, math.sin(0.25))


def test_time_from_seconds_never_overflows_nanoseconds() -> None:
    assert msgs.Time.from_seconds(1.5) == msgs.Time(1, 500_000_000)
    assert msgs.Time.from_seconds(2.9999999999).nanosec <= 999_999_999


def test_names() -> None:
    assert parse_endpoint("127.0.0.1:18944=/occ/slave") == ("127.0.0.1", 18944, "/occ/slave")
    assert parse_endpoint("::1:18944=occ/slave/") == ("::1", 18944, "/occ/slave")
    for bad in ("127.0.0.1:18944", "127.0.0.1=/x", "h:p=/x", "h:1=/", "h:1=/a-b"):
        with pytest.raises(ValueError):
            parse_endpoint(bad)
    assert topic_name("/occ/slave", "measured_cp") == "rt/occ/slave/measured_cp"
    assert topic_name("/occ/slave", "base/measured_cp") == "rt/occ/slave/base/measured_cp"


def test_commands_without_an_operator_port_are_refused_with_a_reply(
    dds: tuple[int, Any], namespace: str
) -> None:
    """A viewer-only bridge cannot move the robot, and says so on command_reply."""
    domain_id, dp = dds
    replies: DataReader[Any] = DataReader(
        dp, Topic(dp, topic_name(namespace, "command_reply"), msgs.String), QOS_DEFAULT
    )
    # nothing listens on the viewer port: the link just keeps trying to connect
    with Bridge([("127.0.0.1", free_port(), namespace)], domain_id=domain_id) as bridge:
        bridge.command(namespace, "enable")
        bridge.command(namespace, "rm -rf")
        got: list[Any] = []

        def two_replies() -> bool:
            got.extend(replies.take())
            return len(got) >= 2

        assert poll(two_replies)
    assert got[0].data.startswith("enable FAIL: no operator interface")
    assert got[1].data == "rm -rf FAIL: not a command name"
    assert bridge.stats()[namespace]["commands_refused"] == 2


#: every (word, daemon state) of CRTK's table and the answer the bridge gives itself, or
#: ``None`` where it forwards the daemon's command (then refused here: nothing listens on the
#: operator port, so the forward is visible as "<word> FAIL: <DaemonCommand>: ... not
#: connected"); ``("STOPPED", True)``: STOPPED by this bridge's own pause
CRTK_CASES: dict[tuple[str, str | tuple[str, bool]], str] = {
    ("enable", "READY"): "Enable",  # then Run: CRTK's ENABLED accepts motion commands
    ("enable", "ENABLED"): "Run",
    ("enable", "STOPPED"): "enable FAIL: the daemon is STOPPED (RUNNING -> STOPPED: a loss)",
    ("enable", ("STOPPED", True)): "Run",
    ("enable", "RUNNING"): "enable SUCCESS: already ENABLED",
    ("enable", "FAULT"): "enable FAIL: the daemon's FAULT is latched",
    ("enable", "ESTOP"): "enable FAIL: the daemon's ESTOP is latched",
    ("disable", "READY"): "disable SUCCESS: already DISABLED",
    ("disable", "ENABLED"): "Disable",
    ("disable", "RUNNING"): "Disable",
    ("disable", "STOPPED"): "Disable",
    ("disable", "FAULT"): "disable FAIL: the daemon's FAULT is latched",
    ("disable", "ESTOP"): "disable FAIL: the daemon's ESTOP is latched",
    ("pause", "READY"): "pause FAIL: not valid in DISABLED",
    ("pause", "ENABLED"): "pause SUCCESS: already PAUSED",
    ("pause", "RUNNING"): "Stop",
    ("pause", "STOPPED"): "pause SUCCESS: already PAUSED",
    ("pause", "ESTOP"): "pause FAIL: not valid in FAULT",
    ("resume", "READY"): "resume FAIL: not valid in DISABLED",
    ("resume", "ENABLED"): "Run",
    ("resume", "RUNNING"): "resume SUCCESS: already ENABLED",
    ("resume", "STOPPED"): "resume FAIL: the daemon is STOPPED (RUNNING -> STOPPED: a loss)",
    ("resume", ("STOPPED", True)): "Run",
    ("resume", "FAULT"): "resume FAIL: not valid in FAULT",
    ("home", "READY"): "home SUCCESS: homed",
    ("home", "RUNNING"): "home SUCCESS: homed",
    ("home", "FAULT"): "home SUCCESS: homed",
    ("unhome", "ENABLED"): "unhome FAIL: the joint sensors are absolute",
    ("enable", "INIT"): "enable FAIL: the daemon is in INIT",
    ("home", "SHUTDOWN"): "home FAIL: the daemon is in SHUTDOWN",
}


@pytest.mark.req("SR-REPLY-3")
def test_crtk_table_covers_every_word_in_every_powered_state() -> None:
    """Every CRTK word has a row for every daemon state but INIT and SHUTDOWN (which refuse
    all), and the mapping is CRTK's: ENABLED only where motion commands run (RUNNING)."""
    from occ_ros2.bridge import CRTK_STATE, CRTK_TABLE, CRTK_WORDS

    assert {s for s, meta in CRTK_STATE.items() if meta == "ENABLED"} == {"RUNNING"}
    assert {s for s, meta in CRTK_STATE.items() if meta == "PAUSED"} == {"ENABLED", "STOPPED"}
    powered = ("READY", "ENABLED", "STOPPED", "RUNNING", "FAULT", "ESTOP")
    missing = [(w, s) for w in CRTK_WORDS for s in powered if (w, s) not in CRTK_TABLE]
    # CRTK refuses these itself ("not valid in ..."): pause and resume need power, no fault
    assert sorted(missing) == sorted(
        [(w, s) for w in ("pause", "resume") for s in ("READY", "FAULT", "ESTOP")]
    )
    # each forward ends in the daemon state of the CRTK state the word asks for
    last = {"enable": "Run", "resume": "Run", "disable": "Disable", "pause": "Stop"}
    for (word, state), (action, what) in CRTK_TABLE.items():
        if action == "send":
            assert isinstance(what, tuple) and what[-1] == last[word], (word, state, what)


def _first(reader: DataReader[Any], what: object) -> Any:
    got: list[Any] = []

    def some() -> bool:
        got.extend(reader.take())
        return bool(got)

    assert poll(some), what
    return got[0]


@pytest.mark.req("SR-REPLY-3")
def test_crtk_state_table_every_cell_answered(dds: tuple[int, Any], namespace: str) -> None:
    """CRTK's words in each daemon state: the bridge's own answers (no-ops, refusals, the
    latch) word for word, and the forwards by the daemon command they become. The daemon side
    of the table is tests/ros2/test_crtk.py."""
    domain_id, dp = dds
    replies: DataReader[Any] = DataReader(
        dp, Topic(dp, topic_name(namespace, "command_reply"), msgs.String), QOS_DEFAULT
    )
    ops: DataReader[Any] = DataReader(
        dp, Topic(dp, topic_name(namespace, "operating_state"), msgs.OperatingState), QOS_LATCHED
    )
    endpoint = [("127.0.0.1", free_port(), namespace)]
    with Bridge(endpoint, endpoint, domain_id=domain_id) as bridge:
        robot = bridge.robots[namespace]
        for (word, where), expected in CRTK_CASES.items():
            state, ours = where if isinstance(where, tuple) else (where, False)
            robot.state, robot.paused_by_bridge = state, ours
            robot.state_text = "RUNNING -> STOPPED: a loss"
            ops.take()
            bridge.command(namespace, word)
            text = _first(replies, (word, state)).data
            if " " not in expected:  # forwarded as this daemon command
                assert text == f"{word} FAIL: {expected}: operator interface not connected"
                continue
            assert text.startswith(expected), (word, state, text)
            if "latched" in expected:
                assert "until an operator's Reset" in text and "CRTK retry" in text
            if "STOPPED" in expected:
                assert "not by this bridge's pause" in text and "daemon's Run" in text
            # and operating_state again, with a fresh stamp, for the CRTK client's wait
            if state not in ("INIT", "SHUTDOWN"):
                fresh = _first(ops, (word, state))
                assert fresh.is_busy is False and fresh.is_homed is True


def test_move_time_rule() -> None:
    """Distance over the speed, up to the millisecond, at least MOVE_MIN_S (1 s)."""
    from occ_ros2.bridge import MOVE_MIN_S, move_time

    assert MOVE_MIN_S == 1.0
    assert move_time(0.0, 0.05) == 1.0
    assert move_time(0.04, 0.05) == 1.0
    assert move_time(0.1, 0.05) == 2.0
    assert move_time(0.10001, 0.05) == 2.001  # rounded up: never faster than the speed
    assert move_time(0.005, 0.01) == 1.0


def test_plan_running_reads_the_keyframe_controllers_statistics() -> None:
    """The probe of a bridge that connects mid-run: the daemon's GetStats (the operator
    desk's report, as GetStats sends it) says a plan runs only while it does; the STATUS names
    the bridge follows are the controller's."""
    import json

    import yaml

    from occ.controllers import keyframe
    from occ_ros2 import bridge as b
    from occ_testkit.testing import SimRobot

    assert (b.KEYFRAME_RUNNING, b.KEYFRAME_ENDED) == (
        keyframe.STATUS_RUNNING,
        keyframe.STATUS_ENDED,
    )
    root = Path(__file__).resolve().parents[2]
    cfg = yaml.safe_load((root / "configs" / "keyframe.yaml").read_text())
    cfg["controller"]["params"]["file"] = str(root / "configs" / "keyframes" / "demo.yaml")
    cfg["controller"]["params"]["keyframe_dir"] = str(root / "configs" / "keyframes")
    with SimRobot(cfg) as sim:
        peer = sim.peer("slicer")

        def stats() -> str:
            return json.dumps(sim.robot.operators.report(), default=str)

        assert not b.plan_running(stats())
        for name in ("Enable", "Run"):
            assert sim.command(peer, name).metadata["Status"] == "SUCCESS"
        cid = peer.send_command("KeyframePlan")
        sim.step(1)
        (ctrl,) = sim.robot.controller.controllers
        assert ctrl.wait_idle(30.0)  # type: ignore[attr-defined]
        sim.step(200)  # the plan's answer, and its preview
        reply = peer.reply_to(cid)
        assert reply is not None and reply.metadata["Status"] == "SUCCESS"
        plan = ctrl.plan.id  # type: ignore[attr-defined]
        reply = sim.command(peer, "KeyframeAck", f'<Command Name="KeyframeAck" Plan="{plan}"/>')
        assert reply.metadata["Status"] == "SUCCESS", reply.metadata
        sim.step(10)
        assert b.plan_running(stats())
        sim.run_for(ctrl.active.traj.duration + 0.1)  # type: ignore[attr-defined]
        assert not b.plan_running(stats())
    # several controllers: the keyframe one's; and anything else is not a running plan
    assert b.plan_running('{"controller": {"keyframe": {"running": 3, "runs_completed": 0}}}')
    assert not b.plan_running('{"controller": {"running": 3}}')  # not a keyframe controller
    assert not b.plan_running("not json") and not b.plan_running("[1]")


def test_moves_refused_by_the_bridge_say_why(dds: tuple[int, Any], namespace: str) -> None:
    """What the bridge refuses itself, before the daemon is asked: no operator port; the joint
    positions or the tip not known yet; a joint or a frame it does not know; and what it sends
    when it does ask (here nothing listens: 'not connected')."""
    domain_id, dp = dds
    replies: DataReader[Any] = DataReader(
        dp, Topic(dp, topic_name(namespace, "command_reply"), msgs.String), QOS_DEFAULT
    )
    jp = msgs.JointState(name=["yaw"], position=[0.1])
    cp = msgs.PoseStamped(header=msgs.Header(frame_id="world"))
    with Bridge([("127.0.0.1", free_port(), namespace)], domain_id=domain_id) as bridge:
        bridge.move(namespace, "move_jp", jp)
        assert _first(replies, "no operator").data == (
            f"move_jp FAIL: no operator interface for {namespace} (occ-ros2 --operator)"
        )
    endpoint = [("127.0.0.1", free_port(), namespace)]
    with Bridge(endpoint, endpoint, domain_id=domain_id) as bridge:
        robot = bridge.robots[namespace]

        def answer(kind: str, goal: Any) -> str:
            bridge.move(namespace, kind, goal)
            return str(_first(replies, kind).data)

        assert answer("move_jp", jp) == (
            "move_jp FAIL: the daemon's joint positions are not known yet (its NDARRAY Joints)"
        )
        assert answer("move_cp", cp) == (
            "move_cp FAIL: the tip is not known yet (the daemon's TRANSFORM Tip)"
        )
        robot.joints = (["yaw", "pitch", "insertion"], [0.0, 0.35, 0.05])
        robot.tip_m = np.eye(4)
        assert answer("move_jp", msgs.JointState(position=[0.1])) == (
            "move_jp FAIL: 1 positions for 3 joints (yaw, pitch, insertion); give all, or name them"
        )
        nan = msgs.JointState(name=["yaw"], position=[float("nan")])
        assert answer("move_jp", nan) == "move_jp FAIL: a position is not a finite number"
        base = msgs.PoseStamped(header=msgs.Header(frame_id=robot.base_frame))
        assert answer("move_cp", base).startswith("move_cp FAIL: the base is not known yet")
        # accepted: the daemon's commands go out (nothing listens here)
        assert answer("move_jp", jp) == "move_jp FAIL: operator interface not connected"
        assert robot.move is None
        assert bridge.stats()[namespace]["commands_refused"] == 6


def test_a_move_becomes_the_daemons_keyframe_commands() -> None:
    """The goals as the daemon's KeyframeAdd gets them: joints in its order (named ones
    replaced), Cartesian goals in its world frame in mm (a goal in the base frame through the
    base pose), and the time from the distance."""
    from occ_ros2.bridge import Robot

    bridge = Bridge.__new__(Bridge)  # the conversions only: no DDS, no links
    bridge.world_frame, bridge.move_joint_speed, bridge.move_tip_speed = "world", 0.05, 0.01
    robot = Robot(ns="/occ/kf", leaf="kf")
    robot.joints = (["yaw", "pitch", "insertion"], [0.0, 0.35, 0.05])
    goal = msgs.JointState(name=["insertion", "yaw"], position=[0.08, -0.1])
    assert bridge._joint_goal(robot, goal) == ("joint", "-0.1 0.35 0.08", 2.0)
    base = np.eye(4)
    base[:3, :3] = rot((0, 0, 1), math.pi / 2)
    base[:3, 3] = (0.1, 0.0, 0.0)
    robot.base_m = base
    robot.tip_m = np.eye(4)
    robot.tip_m[:3, 3] = (0.1, 0.02, 0.0)
    local = msgs.PoseStamped(header=msgs.Header(frame_id="kf_base"))
    local.pose.position = msgs.Point(0.03, 0.0, 0.0)  # base x is world y
    space, pose, t = bridge._tip_goal(robot, local)
    assert (space, pose) == ("cartesian", "100.000000 30.000000 0.000000")
    assert t == 1.0  # 10 mm at 10 mm/s
    robot.joints = ([], [])  # a daemon without joints: nothing to move, in the shortest time
    assert bridge._joint_goal(robot, msgs.JointState()) == ("joint", "", 1.0)
    world = msgs.PoseStamped(header=msgs.Header(frame_id=""))  # empty: the world frame
    world.pose.position = msgs.Point(0.1, 0.07, 0.0)
    assert bridge._tip_goal(robot, world) == ("cartesian", "100.000000 70.000000 0.000000", 5.0)


def test_a_slaves_tip_force_becomes_measured_cf_in_the_world(
    dds: tuple[int, Any], namespace: str
) -> None:
    """TRANSFORM ``TipForce`` (occ/haptics/forceviz.py) -> WrenchStamped from its metadata
    ``force_n``, frame_id the world frame; one in header version 1 (no metadata: before the
    daemon reads the bridge's v2 greeting) is counted apart, one without a readable
    ``force_n`` or in another frame is refused and counted; neither is published."""
    import dataclasses

    import igtl
    from occ.haptics.forceviz import force_matrix

    domain_id, dp = dds
    wrenches: DataReader[Any] = DataReader(
        dp, Topic(dp, topic_name(namespace, "measured_cf"), msgs.WrenchStamped), QOS_DEFAULT
    )
    with Bridge([("127.0.0.1", free_port(), namespace)], domain_id=domain_id) as bridge:
        robot = bridge.robots[namespace]
        f = (-1.25, 0.5, 0.0625)

        def tip_force(meta: dict[str, str]) -> igtl.TransformMessage:
            return igtl.TransformMessage.from_matrix(
                force_matrix((1.0, 2.0, 3.0), f, 10.0), device_name="TipForce",
                timestamp=1_700_000_000.5, header_version=2, metadata=meta,
            )  # fmt: skip

        # v1, no metadata: what a daemon sends before it reads the greeting
        bridge._on_igtl(robot, dataclasses.replace(tip_force({}), header_version=1))
        bridge._on_igtl(robot, tip_force({}))  # v2 without force_n
        bridge._on_igtl(robot, tip_force({"force_n": "1,2", "frame": "patient"}))
        bridge._on_igtl(robot, tip_force({"force_n": "1,2,3", "frame": "tip"}))
        bridge._on_igtl(robot, tip_force({"force_n": ",".join(map(str, f)), "frame": "patient"}))
        w = _first(wrenches, "measured_cf")
    assert w.header.frame_id == "world"
    assert (w.header.stamp.sec, w.header.stamp.nanosec) == (1_700_000_000, 500_000_000)
    force, torque = w.wrench.force, w.wrench.torque
    assert (force.x, force.y, force.z) == f and (torque.x, torque.y, torque.z) == (0, 0, 0)
    st = bridge.stats()[namespace]
    assert st["forces"] == 1 and st["forces_refused"] == 3 and st["forces_v1"] == 1


class _Recorder:
    """A DDS writer's stand-in: what the bridge publishes on one leaf."""

    def __init__(self, leaf: str, out: list[tuple[str, Any]]) -> None:
        self.leaf, self.out = leaf, out

    def write(self, sample: Any) -> None:
        self.out.append((self.leaf, sample))


class _Writers(dict[str, _Recorder]):
    def __init__(self) -> None:
        super().__init__()
        self.out: list[tuple[str, Any]] = []

    def __missing__(self, leaf: str) -> _Recorder:
        self[leaf] = _Recorder(leaf, self.out)
        return self[leaf]


class _Link:
    """An operator link's stand-in: each command it is given, sent (1) or not (0)."""

    def __init__(self) -> None:
        self.up = 1
        self.sent: list[Any] = []

    def send(self, msg: Any) -> int:
        self.sent.append(msg)
        return self.up


def _offline_bridge(ack_moves: bool) -> tuple[Bridge, Any, _Link, _Writers]:
    """A bridge without DDS or sockets: its robot's writers record, its operator link is a
    stand-in; the daemon's answers are given to ``_on_reply`` by the test."""
    import threading
    from collections import OrderedDict

    from occ_ros2.bridge import Robot

    bridge = Bridge.__new__(Bridge)
    bridge.world_frame, bridge.move_joint_speed, bridge.move_tip_speed = "world", 0.05, 0.01
    bridge.ack_moves = ack_moves
    bridge._lock, bridge._cmd_id, bridge._pending = threading.Lock(), 0, OrderedDict()
    robot = Robot(ns="/occ/rid", leaf="rid")
    writers = _Writers()
    robot.writers = writers
    link = _Link()
    robot.operator = link
    robot.joints = (["yaw"], [0.0])
    bridge.robots = {robot.ns: robot}
    return bridge, robot, link, writers


def _answer(bridge: Bridge, robot: Any, link: _Link, status: str, text: str) -> None:
    import igtl

    cmd = link.sent[-1]
    reply = igtl.RTSCommandMessage(
        command_id=cmd.command_id,
        command_name=cmd.command_name,
        header_version=2,
        metadata={"Status": status, "Message": text},
    )
    bridge._on_reply(robot, reply, msgs.Time.from_seconds(1.0))


def _replies(writers: _Writers) -> list[str]:
    found = [str(s.data) for leaf, s in writers.out if leaf == "command_reply"]
    writers.out.clear()
    return found


@pytest.mark.req("SR-REPLY-2")
def test_every_refusal_and_answer_carries_the_clients_request_id() -> None:
    """Issue 41's promise on each of the bridge's own paths, without DDS: a command's
    refusal (not a name, no operator port, the link down, the state not known), a CRTK
    refusal out of a stop not its own, and a move's refusals and answers (no operator port,
    the link down, the daemon's FAIL, a plan without a number, the Ack's SUCCESS) each begin
    with the request id the client gave."""
    bridge, robot, link, writers = _offline_bridge(ack_moves=True)
    ns = robot.ns

    bridge.command(ns, "[c1] _")  # underscores alone are no command name
    assert _replies(writers) == ["[c1] _ FAIL: not a command name"] and not link.sent
    link.up = 0
    bridge.command(ns, "[c2] GetState")
    assert _replies(writers) == ["[c2] GetState FAIL: operator interface not connected"]
    bridge.command(ns, "[c3] enable")  # a CRTK word before the daemon's state is known
    assert _replies(writers) == [
        "[c3] enable FAIL: the daemon's state is not known yet (not connected)"
    ]
    link.up = 1
    robot.state, robot.state_text, robot.paused_by_bridge = "STOPPED", "", False
    refused = robot.counters.commands_refused
    bridge.command(ns, "[c4] resume")  # a stop without words: still named
    why = "a stop"
    assert _replies(writers)[0] == f"[c4] resume FAIL: {HELD.format(why=why, word='resume')}"
    assert robot.counters.commands_refused == refused + 1

    goal = msgs.JointState(name=["yaw"], position=[0.1])
    goal.header.stamp = msgs.Time(sec=5, nanosec=7)
    rid = "[5.000000007]"
    link.up = 0
    bridge.move(ns, "move_jp", goal)
    assert _replies(writers) == [f"{rid} move_jp FAIL: operator interface not connected"]
    link.up = 1
    bridge.move(ns, "move_jp", goal)  # KeyframeClear sent; the daemon refuses it
    _answer(bridge, robot, link, "FAIL", "KeyframeClear: busy")
    assert _replies(writers) == [f"{rid} move_jp FAIL: KeyframeClear: busy"]
    bridge.move(ns, "move_jp", goal)
    _answer(bridge, robot, link, "SUCCESS", "cleared")
    _answer(bridge, robot, link, "SUCCESS", "added")
    _answer(bridge, robot, link, "SUCCESS", "planned")  # KeyframePlan: no plan number
    assert _replies(writers) == [
        f"{rid} move_jp FAIL: KeyframePlan answered 'planned': no plan number"
    ]
    bridge.move(ns, "move_jp", goal)
    for text in ("cleared", "added", "plan 3: 1 keyframe"):
        _answer(bridge, robot, link, "SUCCESS", text)
    assert link.sent[-1].command_name == "KeyframeAck"
    _answer(bridge, robot, link, "SUCCESS", "plan 3 runs")
    assert _replies(writers) == [f"{rid} move_jp SUCCESS: plan 3 runs"]

    robot.operator = None
    bridge.command(ns, "[c5] enable")
    assert _replies(writers) == [
        f"[c5] enable FAIL: no operator interface for {ns} (occ-ros2 --operator)"
    ]
    bridge.move(ns, "move_jp", goal)
    assert _replies(writers) == [
        f"{rid} move_jp FAIL: no operator interface for {ns} (occ-ros2 --operator)"
    ]


def test_operating_state_follows_the_answer_to_each_state_command() -> None:
    """A CRTK client waits for an operating_state after a command that may change the state:
    the daemon's answer to Enable, Disable, Stop, Run or Hold, forwarded as the daemon's own
    command, is followed by one (changed or not); the answer to any other command is not."""
    bridge, robot, link, writers = _offline_bridge(ack_moves=False)
    robot.state = "ENABLED"
    for n, name in enumerate(("Enable", "Disable", "Stop", "Run", "Hold", "GetStats", "enable_")):
        bridge.command(robot.ns, f"[s{n}] {name}")
        assert link.sent[-1].command_name == name
        _answer(bridge, robot, link, "SUCCESS", "done")
        leaves = [leaf for leaf, _ in writers.out]
        assert _replies(writers) == [f"[s{n}] {name} SUCCESS: done"]
        state_command = name[0].isupper() and name != "GetStats"
        assert leaves == (
            ["command_reply", "operating_state"] if state_command else ["command_reply"]
        ), name
