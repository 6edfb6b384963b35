"""The gripper channel (issue 37, item 5; occ/haptics/gripper.py): the master's handle opens and
closes the slave's grippers, as the German Heart Center's handle switch did.

- The master's value from each source: a joint (mapped between its open and closed positions,
  limited to 0..1), the ``Grip`` command (open/close/a number; anything else refused with a
  reply), the simulated operator (a raised cosine while running); sent as ``gripper`` beside
  ``run`` and ``clutch`` on every sample.
- The slave's jaw (tests/occ/data/robots/occ_slave_jaw.urdf: configs/slave.yaml's arm with a jaw
  at the tip) follows it between its open and closed positions at no more than 0.9 times its
  velocity limit per tick, only while following: the clutch, ``run=0``, a late or lost stream
  and a stop hold it where it was told to be; a value that is no number from 0 to 1 is refused
  and counted.
- Configuration: an unknown joint, positions outside its limits or equal, a joint that moves
  the tip, a ``joint`` source without its joint: errors at load (or at build, naming why).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
import yaml

import igtl
from occ.core.loader import parse_config
from occ.core.safety import RobotState
from occ.errors import ConfigError
from occ.haptics.gripper import GripperFollower, GripperSource, parse_gripper
from occ_testkit.rigs import SlaveRig
from occ_testkit.testing import CONFIGS, SimPair, SimRobot

pytestmark = pytest.mark.req("SR-FORCE-23")

URDF = Path(__file__).resolve().parent / "data" / "robots" / "occ_slave_jaw.urdf"
JAW_VELOCITY = 3.0  # rad/s: the jaw's limit (configs below)
OPEN, CLOSED = 1.0, 0.1  # rad: the jaw wide open, nearly shut


# ------------------------------------------------------------------------------ units
def test_the_masters_value_from_a_joint_the_command_and_the_simulated_hand() -> None:
    j = GripperSource("joint", joint=1, open_pos=0.2, closed_pos=-0.3)
    assert j.update([9.0, 0.2, 9.0], 0.0) == 0.0
    assert j.update([9.0, -0.05, 9.0], 0.0) == pytest.approx(0.5)
    assert j.update([9.0, -0.4, 9.0], 0.0) == 1.0  # past closed: closed
    assert j.update([9.0, math.nan, 9.0], 0.0) == 1.0  # a NaN read keeps the last value
    with pytest.raises(ValueError, match="follows its joint, not the Grip command"):
        j.command("1")
    with pytest.raises(ValueError, match="needs a joint"):
        GripperSource("joint")
    c = GripperSource("command")
    assert c.update([], 0.0) == 0.0  # open until told
    assert c.command("close") == "gripper closed" and c.update([], 0.0) == 1.0
    assert c.command(" Open ") == "gripper open" and c.update([], 0.0) == 0.0
    assert c.command("0.25") == "gripper at 0.25" and c.update([], 0.0) == 0.25
    for bad in ("2", "-0.1", "nan", "shut"):
        with pytest.raises(ValueError, match="is not open, close or a number from 0 to 1"):
            c.command(bad)
    assert c.commanded == 0.25
    s = GripperSource("sim", period_s=4.0)
    assert [s.update([], t) for t in (0.0, 1.0, 2.0, 3.0)] == pytest.approx([0, 0.5, 1, 0.5])
    assert s.stats() == {"source": "sim", "value": 0.5}
    assert [parse_gripper(t) for t in ("0", "1", "0.5", "1.001", "-0", "x", "nan")] == [
        0.0, 1.0, 0.5, None, -0.0, None, None,
    ]  # fmt: skip


def test_the_jaw_steps_toward_the_value_only_while_following() -> None:
    g = GripperFollower(2, "jaw", OPEN, CLOSED, 0.1)
    q = g.apply([0.0, 0.0, 0.55], True)  # nothing from the master yet: held where it is
    assert q == [0.0, 0.0, 0.55] and g.setpoint == 0.55
    g.on_meta("1.000")  # closed: 0.1 rad, 0.45 away: five steps, the last one short
    path = [g.apply([0.0, 0.0, 9.0], True)[2] for _ in range(6)]
    assert path == pytest.approx([0.45, 0.35, 0.25, 0.15, 0.1, 0.1])
    g.on_meta("0")
    assert g.apply([0.0, 0.0, 9.0], False)[2] == pytest.approx(0.1)  # not following: held
    assert g.apply([0.0, 0.0, 9.0], True)[2] == pytest.approx(0.2)
    for bad in ("1.5", "x", "nan"):
        g.on_meta(bad)
    g.on_meta(None)  # a master that sends none: no change, nothing counted
    assert g.value == 0.0 and g.refused == 3 and g.samples == 2
    assert g.last_error == "gripper 'nan' is not a number from 0 to 1"
    g.restart()  # following again: from where the drives are told to be
    assert g.apply([0.0, 0.0, 0.7], False)[2] == 0.7
    assert g.stats() == {
        "joint": "jaw", "value": 0.0, "setpoint": 0.7, "samples": 2, "refused": 3,
        "last_error": "gripper 'nan' is not a number from 0 to 1",
    }  # fmt: skip


def test_the_sources_defaults_a_first_nan_read_and_the_stats_places() -> None:
    j = GripperSource("joint", joint=0)  # the defaults: 0 open, 1 closed
    assert j.stats() == {"source": "joint", "value": 0.0}  # open before any read
    assert j.update([math.nan], 0.0) == 0.0  # a first read of NaN: open, not closed, not None
    assert j.update([0.25], 0.0) == 0.25 and j.update([0.0], 0.0) == 0.0
    assert j.update([1.0], 0.0) == 1.0 and j.update([2.0], 0.0) == 1.0
    j.update([0.12345], 0.0)
    assert j.stats()["value"] == 0.123  # three places, as on the stream
    s = GripperSource("sim")  # the default period: 4 s
    assert [s.update([], t) for t in (1.0, 2.0, 4.0)] == pytest.approx([0.5, 1.0, 0.0], abs=1e-12)
    with pytest.raises(ValueError, match=r"^gripper source 'joint' needs a joint$"):
        GripperSource("joint")


def test_the_jaw_lands_on_its_goal_one_step_away_and_reports_before_its_first_tick() -> None:
    g = GripperFollower(0, "jaw", 0.0, 1.0, 0.35)
    assert g.stats() == {
        "joint": "jaw", "value": None, "setpoint": None, "samples": 0, "refused": 0,
        "last_error": "",
    }  # fmt: skip
    g.on_meta("0.45")
    # exactly one step away (0.45 - 0.1 == 0.35 in floats): the goal itself, not a step that
    # rounds to 0.44999999999999996
    assert g.apply([0.1], True)[0] == 0.45
    g2 = GripperFollower(0, "jaw", 0.0, 1.0, 0.5)
    g2.on_meta("0.1234567")
    g2.apply([0.0], True)
    assert g2.stats()["setpoint"] == 0.123457  # six places
    g2.on_meta("not-a-number-at-all-xyz")  # quoted to its first 20 characters
    assert g2.last_error == "gripper 'not-a-number-at-all-' is not a number from 0 to 1"


# ------------------------------------------------------------------------------ configs
def jaw_slave(**gripper: Any) -> dict[str, Any]:
    """configs/slave.yaml on the jaw model: the arm's joints and the jaw (0 to 1.2 rad,
    3 rad/s), all on the sim drive; the jaw follows the master's gripper value."""
    cfg = yaml.safe_load((CONFIGS / "slave.yaml").read_text())
    robot = cfg["robot"]
    robot["frame"] = {"urdf": str(URDF), "tip_link": "tool_tip"}
    robot["joints"].append(
        {"name": "jaw", "type": "revolute", "home": OPEN,
         "limits": {"min": 0.0, "max": 1.2, "velocity": JAW_VELOCITY, "effort": 1.0}}
    )  # fmt: skip
    robot["drivers"][0]["joints"].append("jaw")
    cfg["controller"]["params"]["gripper"] = {"joint": "jaw", "open": OPEN, "closed": CLOSED}
    cfg["controller"]["params"]["gripper"].update(gripper)
    return cfg


def commanded_master() -> dict[str, Any]:
    cfg = yaml.safe_load((CONFIGS / "master.yaml").read_text())
    cfg["controller"]["params"]["gripper"] = {"source": "command"}
    return cfg


def test_gripper_mistakes_are_errors_at_load() -> None:
    for gripper, error in (
        ({"joint": "claw"}, "gripper.joint: no joint 'claw'"),
        ({"closed": 1.5}, r"gripper.closed: 1.5 is outside joint 'jaw' \[0, 1.2\]"),
        ({"open": 0.1}, "gripper.closed: must differ from open"),
    ):
        with pytest.raises(ConfigError, match=error):
            parse_config(yaml.safe_dump(jaw_slave(**gripper)))
    with pytest.raises(ConfigError, match="gripper.open: missing required field"):
        cfg = jaw_slave()
        del cfg["controller"]["params"]["gripper"]["open"]
        parse_config(yaml.safe_dump(cfg))
    # the insertion moves the tip: the IK's joint, not a jaw (found when the robot is built)
    with pytest.raises(ConfigError, match="joint 'insertion' moves the tool's tip"):
        SimRobot(jaw_slave(joint="insertion", open=0.05, closed=0.1))
    cfg = yaml.safe_load((CONFIGS / "master.yaml").read_text())
    cfg["controller"]["params"]["gripper"] = {"source": "joint"}
    with pytest.raises(ConfigError, match="gripper.joint: required with source: joint"):
        parse_config(yaml.safe_dump(cfg))
    cfg["controller"]["params"]["gripper"] = {"source": "joint", "joint": "w"}
    with pytest.raises(ConfigError, match="gripper.joint: no joint 'w'"):
        parse_config(yaml.safe_dump(cfg))


# ------------------------------------------------------------------------------ the pair
class Pair:
    """The shipped master with the ``Grip`` command and the jaw slave, in simulated time; the
    forward line can drop samples (``self.dropping``)."""

    def __init__(self) -> None:
        self.dropping = False
        self.p = SimPair(
            commanded_master(),
            jaw_slave(),
            drop=lambda way, m, i: way == "forward" and self.dropping,
        )
        self.p.start()
        self.ctl: Any = self.p.slave.robot.controller.controllers[0]
        self.p.run_for(0.2)

    def command(self, op: Any, name: str, value: str | None = None) -> Any:
        """``op`` sends the COMMAND; one tick of the pair; its reply."""
        text = "" if value is None else f'<Command Name="{name}" Value="{value}"/>'
        cid = op.send_command(name, text)
        self.p.step(1)
        reply = op.reply_to(cid)
        assert reply is not None
        return reply

    def grip(self, value: str) -> Any:
        return self.command(self.p.m_op, "Grip", value)

    def jaw(self) -> float:
        return float(self.p.slave.robot.data.setpoint[3])

    def track(self, seconds: float) -> list[float]:
        out = []
        for _ in range(round(seconds * 1000)):
            self.p.step(1)
            out.append(self.jaw())
        return out


def test_the_handles_switch_closes_and_opens_the_jaw_within_its_velocity_limit() -> None:
    pair = Pair()
    try:
        assert pair.jaw() == pytest.approx(OPEN)
        reply = pair.grip("close")
        assert reply.metadata["Status"] == "SUCCESS" and 'Message="gripper closed"' in reply.command
        path = [OPEN, pair.jaw(), *pair.track(0.6)]
        assert path[-1] == pytest.approx(CLOSED, abs=1e-12)
        steps = [abs(b - a) for a, b in zip(path, path[1:], strict=False)]
        assert max(steps) <= 0.9 * JAW_VELOCITY * 1e-3 + 1e-12
        # 0.9 rad at 2.7 rad/s: 333 ms, give or take the stream's 2 ms and a tick
        closed_at = next(i for i, v in enumerate(path) if abs(v - CLOSED) < 1e-12)
        assert 333 <= closed_at <= 340
        assert pair.p.master.robot.controller.controllers[0].stats()["gripper"] == {
            "source": "command", "value": 1.0,
        }  # fmt: skip
        # the drives follow the jaw's setpoint (a sim servo at 30 Hz)
        assert pair.p.slave.robot.data.q[3] == pytest.approx(CLOSED, abs=0.01)
        assert 'Message="gripper at 0.5"' in pair.grip("0.5").command
        assert pair.track(0.5)[-1] == pytest.approx(OPEN + 0.5 * (CLOSED - OPEN), abs=1e-12)
        bad = pair.grip("wide")
        assert bad.metadata["Status"] == "FAIL"
        assert "Grip: 'wide' is not open, close or a number from 0 to 1" in bad.metadata["Error"]
        st = pair.ctl.stats()["gripper"]
        assert st["value"] == 0.5 and st["refused"] == 0 and st["samples"] > 500
    finally:
        pair.p.close()


def test_grip_takes_value_in_either_case_closes_without_one_and_leaves_other_commands() -> None:
    pair = Pair()
    try:
        op = pair.p.m_op

        def said(text: str) -> str:
            cid = op.send_command("Grip", text)
            pair.p.step(1)
            reply = op.reply_to(cid)
            assert reply is not None and reply.metadata["Status"] == "SUCCESS", text
            return str(reply.command)

        assert 'Message="gripper at 0.25"' in said('<Command Name="Grip" value="0.25"/>')
        assert 'Message="gripper open"' in said('<Command Name="Grip" value="open"/>')
        assert 'Message="gripper closed"' in said("")  # no value: close it
        assert pair.p.master.robot.controller.controllers[0].stats()["gripper"]["value"] == 1.0
        # the master's other commands are not the gripper's
        cleared = pair.command(op, "ClearFixtures")
        assert 'Message="fixtures cleared"' in cleared.command
        assert pair.p.master.robot.controller.controllers[0].stats()["gripper"]["value"] == 1.0
    finally:
        pair.p.close()


def test_the_jaw_holds_through_the_clutch_a_late_stream_and_a_stop() -> None:
    pair = Pair()
    try:
        pair.command(pair.p.m_op, "Clutch", "1")
        pair.grip("close")
        held = pair.track(0.2)
        assert held == [pytest.approx(OPEN)] * len(held)  # the clutch: not following
        pair.command(pair.p.m_op, "Clutch", "0")
        moving = pair.track(0.1)
        assert moving[-1] < OPEN - 0.2  # released: it follows
        # the stream late (a master stalled 40 ms: no sample, no number skipped): the robot
        # holds, the jaw with it, and re-joins when it comes back (at half the velocity limits)
        at = pair.jaw()
        pair.p.stall_master(40)  # the slave holds at its deadline (7 ms): 6 steps before it
        held = pair.jaw()
        assert 0.0 < at - held <= 7 * 0.9 * JAW_VELOCITY * 1e-3
        assert pair.p.slave.robot.motion.reentry  # it was held (re-joins from the setpoint)
        back = [held, *pair.track(1.0)]
        assert back[-1] == pytest.approx(CLOSED, abs=1e-12)
        assert max(abs(b - a) for a, b in zip(back, back[1:], strict=False)) <= 2.7e-3 + 1e-12
        # the stream lost (25 samples dropped): a latched stop; the jaw stays where it was told
        # to be, whatever the switch says
        pair.grip("open")
        pair.p.step(50)
        pair.dropping = True
        pair.p.step(50)
        pair.dropping = False
        at = pair.jaw()
        stopped = pair.track(0.2)
        assert pair.p.slave.robot.data.state is RobotState.STOPPED
        assert CLOSED < at < OPEN and pair.p.slave.robot.data.hold_setpoint[3] == at
        assert pair.ctl.stats()["gripper"]["value"] == 0.0  # the switch says open
        assert stopped == [at] * len(stopped)
    finally:
        pair.p.close()


def test_the_simulated_hand_closes_and_opens_it_on_the_stream() -> None:
    cfg = yaml.safe_load((CONFIGS / "master.yaml").read_text())
    cfg["controller"]["params"]["gripper"] = {"source": "sim", "period_s": 1.0}
    p = SimPair(cfg, jaw_slave())
    try:
        p.start()
        values = []
        for _ in range(1000):
            p.step(1)
            values.append(p.slave.robot.controller.controllers[0].gripper.value)
        # the slave received the whole cycle (3 decimals on the wire)
        assert min(values) <= 0.001 and max(values) >= 0.999
        jaw = [p.slave.robot.data.setpoint[3]]
        p.run_for(0.25)
        jaw.append(p.slave.robot.data.setpoint[3])
        assert jaw[0] != jaw[1]
    finally:
        p.close()


def test_the_simulated_hands_value_holds_while_the_master_is_stopped_without_energy() -> None:
    """The simulated hand's value on a master that sends no energy (``passivity`` off: no
    ``energy_j`` on its stream) reaches the slave all the same; while the master is stopped its
    hand's time stands still, so the value the slave gets holds (it ran on to 1.0 before),
    and Run resumes it from there."""
    cfg = yaml.safe_load((CONFIGS / "master.yaml").read_text())
    cfg["controller"]["params"]["gripper"] = {"source": "sim", "period_s": 1.0}
    cfg["controller"]["params"]["passivity"] = False
    p = SimPair(cfg, jaw_slave())
    try:
        p.start()
        assert p.master.robot.controller.controllers[0].display.energy_out() is None
        follower = p.slave.robot.controller.controllers[0].gripper
        p.run_for(0.3)
        assert follower.value is not None and 0.0 < follower.value < 1.0
        stop = p.m_op.send_command("Stop", "")
        p.step(1)
        assert p.m_op.reply_to(stop).metadata["Status"] == "SUCCESS"
        held = follower.value
        values = []
        for _ in range(300):
            p.step(1)
            values.append(follower.value)
        assert values == [held] * 300
        run = p.m_op.send_command("Run", "")
        p.step(2)
        assert p.m_op.reply_to(run).metadata["Status"] == "SUCCESS"
        assert p.master.robot.data.state is RobotState.RUNNING
        assert abs(follower.value - held) < 0.01  # on from where it held, no jump
    finally:
        p.close()


def test_a_masters_joint_gives_the_value_on_the_stream() -> None:
    """A ``joint`` source on the master (here its handle's z axis, open at -0.1 m, closed at
    0.1 m, as the simulated hand moves it): the slave gets the joint's measured position mapped
    to 0..1 with every sample (0.6 at its 20 mm), to the stream's three decimals."""
    cfg = yaml.safe_load((CONFIGS / "master.yaml").read_text())
    cfg["controller"]["params"]["gripper"] = {
        "source": "joint", "joint": "z", "open": -0.1, "closed": 0.1,
    }  # fmt: skip
    p = SimPair(cfg, jaw_slave())
    try:
        p.start()
        follower = p.slave.robot.controller.controllers[0].gripper
        master = p.master.robot.data
        values, wanted = [], []
        for _ in range(500):
            p.step(1)
            values.append(follower.value)
            wanted.append((master.q[2] + 0.1) / 0.2)
        assert values[-1] == pytest.approx(wanted[-1], abs=2e-3)
        assert 0.0 < values[-1] < 1.0  # mapped, not at an end
        assert p.master.robot.data.state is RobotState.RUNNING
    finally:
        p.close()


def test_a_refused_servo_target_holds_the_jaw_with_the_arm() -> None:
    """An external source (``mapping: absolute``) closing the jaw, then sending a target 15 mm
    away (beyond ``max_jump_mm``) with the jaw's value open: the arm holds where it was told
    to be and the jaw with it, where the close had taken it."""
    rig = SlaveRig(
        jaw_slave(), params={"mapping": "absolute", "max_jump_mm": 10.0, "phase_lock_us": None}
    )
    value = ["0.000"]

    def send() -> None:  # the rig's sample with the gripper value beside run and clutch
        rig.seq += 1
        x, y, z = rig.target
        meta = {"run": "1", "clutch": "0", "gripper": value[0]}
        rig.source.send(
            igtl.PositionMessage((x, y, z), (0.0, 0.0, 0.0, 1.0), 24, device_name="Master",
                                 header_version=2, message_id=rig.seq, metadata=meta)
        )  # fmt: skip

    rig.send = send  # type: ignore[method-assign]
    try:
        rig.running()
        value[0] = "1.000"
        rig.step(100)
        closing = rig.robot.data.setpoint[3]
        assert CLOSED < closing < OPEN - 0.2  # on its way to closed
        arm = rig.robot.data.setpoint[:3]
        rig.target = (rig.world_tip_mm() + [0.0, 0.0, 15.0]).tolist()
        value[0] = "0.000"
        rig.step(100)
        assert rig.ctl.stats()["servo_refused"] == 50
        assert rig.robot.data.setpoint[:3] == arm and rig.robot.data.setpoint[3] == closing
        assert rig.robot.state is RobotState.RUNNING
    finally:
        rig.close()
