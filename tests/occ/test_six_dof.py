"""Six degrees of freedom (issue 28, items 1-2): an arm from its URDF, teleoperated in position
and orientation.

- configs/ur5.yaml (a UR5 from example-robot-data) follows configs/master6.yaml (the paper's
  motion with a gimbal turning the handle) as a :class:`occ_testkit.testing.SimPair` in simulated
  time: the tool's orientation is the handle's rotation since the re-index applied to the
  tool's, to 1e-6 rad; its position the scaled displacement, to 1e-6 mm; the clutch re-indexes
  both without a jump; ``rotation_scale`` scales the angle; 3D Slicer's Tip carries the pose.
- A URDF that does not load, a tip link it does not have, joints that are not its own: errors
  at load, with the line.
- A hold and its re-entry (the master stalled 40 ms, a late stream without a gap): the pose
  solve goes on from the pose it told the arm, within 0.9 of the velocity limits, ahead of the
  setpoint re-joining it at half of them; through a laparoscopic port every told pose keeps
  the axis through the port and the tool's roll; the tool ends in the pose it is asked for.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
import yaml

from occ.errors import ConfigError, KinematicsError
from occ.core.loader import load_config, parse_config
from occ.core.safety import RobotState
from occ.samples import quaternion_to_rotation
from occ_testkit.testing import CONFIGS, SimPair

pytestmark = pytest.mark.req("SR-SIX-1")


def angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(pin.log3(a.T @ b)))


class Arm:
    def __init__(self, **slave_params: Any) -> None:
        self.pair = SimPair(
            CONFIGS / "master6.yaml", CONFIGS / "ur5.yaml", slave_params=slave_params or None
        )
        self.pair.start()
        self.slave = self.pair.slave.robot
        self.ctl: Any = self.slave.controller.controllers[0]
        self.master_ctl: Any = self.pair.master.robot.controller.controllers[0]

    def setpoint_pose(self) -> np.ndarray:
        return np.asarray(self.slave.frame.fk(self.slave.data.setpoint))

    def close(self) -> None:
        self.pair.close()


@pytest.fixture
def arm() -> Any:
    a = Arm()
    yield a
    a.close()


#: the master's axes seen in the slave's: a quarter turn about z, then a tilt about x
TURNED = (pin.rpy.rpyToMatrix(0.3, 0.0, 0.0) @ pin.rpy.rpyToMatrix(0.0, 0.0, math.pi / 2)).tolist()


def _ur5_home() -> np.ndarray:
    """The shipped UR5's tool pose at its home joints (world <- tip, metres)."""
    from occ.core.assembly import build_hardware

    joints, frame, _ = build_hardware(load_config(CONFIGS / "ur5.yaml").robot)
    return np.asarray(frame.fk([j.home for j in joints]))


@pytest.mark.parametrize("rotation", [None, TURNED], ids=["aligned", "turned"])
def test_the_tool_follows_the_handle_in_position_and_orientation(rotation: Any) -> None:
    """The handle's rotation since the re-index, seen in the slave's axes through ``rotation``
    (``A dR A^T``), applied to the tool's; its displacement through ``scale * A``."""
    arm = Arm() if rotation is None else Arm(rotation=rotation)
    try:
        _follows(arm, np.eye(3) if rotation is None else np.array(rotation))
    finally:
        arm.close()


def _follows(arm: Arm, a: np.ndarray) -> None:
    ctl = arm.ctl
    worst_r = worst_p = 0.0
    turned = 0.0
    for k in range(6000):
        arm.pair.step(1)
        if k < 100 or k % 50:
            continue
        pose = arm.setpoint_pose()
        # orientation: the handle's rotation since the re-index, applied to the tool's
        dm = quaternion_to_rotation(ctl.six.master_quat) @ ctl.six.rm_ref.T
        expect_r = a @ dm @ a.T @ ctl.six.rs_ref
        worst_r = max(worst_r, angle(expect_r, pose[:3, :3]))
        turned = max(turned, angle(ctl.six.rs_ref, pose[:3, :3]))
        # position: slave_ref + scale * A (master - master_ref)
        m, m0, s0 = (np.array(v) for v in (ctl.master_pos, ctl.master_ref, ctl.slave_ref))
        worst_p = max(worst_p, float(np.linalg.norm(s0 + 0.5 * a @ (m - m0) - pose[:3, 3])))
    assert arm.slave.state is RobotState.RUNNING
    assert ctl.ik_failures == 0 and ctl.reindexes == 1
    assert math.degrees(turned) > 15.0  # the gimbal's +-20 deg about z (and 10 about x, y)
    assert worst_r < 1e-6, worst_r
    assert worst_p < 1e-8, worst_p  # metres: 1e-5 mm (the DLS tolerance, 1e-8)


def test_a_port_left_in_the_config_is_not_used_when_following() -> None:
    """``rcm_mm`` is the port of ``orientation: rcm`` only: a config switched to ``follow``
    with the port still in it follows the handle's orientation, as without it."""
    home = _ur5_home()
    port = (home[:3, 3] - 0.1 * home[:3, 2]) * 1e3
    arm = Arm(orientation="follow", rcm_mm=port.tolist())
    try:
        _follows(arm, np.eye(3))
    finally:
        arm.close()


def test_the_clutch_reindexes_orientation_without_a_jump(arm: Arm) -> None:
    arm.pair.step(1500)
    op = arm.pair.m_op
    before = arm.setpoint_pose()
    op.send_command("Clutch", '<Command Name="Clutch" Value="1"/>')
    arm.pair.step(2000)  # the handle turns and moves on while clutched: the tool holds
    held = arm.setpoint_pose()
    assert (
        angle(before[:3, :3], held[:3, :3]) < 0.02
        and np.linalg.norm(before[:3, 3] - held[:3, 3]) < 1e-3
    )
    op.send_command("Clutch", '<Command Name="Clutch" Value="0"/>')
    arm.pair.step(3)
    after = arm.setpoint_pose()
    assert angle(held[:3, :3], after[:3, :3]) < 0.005  # no jump on release: re-indexed
    assert arm.ctl.reindexes == 2


def test_rotation_scale_halves_the_angle() -> None:
    a = Arm(rotation_scale=0.5)
    try:
        a.pair.step(2600)  # a quarter turn of the gimbal: its largest angle
        ctl = a.ctl
        handle = angle(ctl.six.rm_ref, quaternion_to_rotation(ctl.six.master_quat))
        tool = angle(ctl.six.rs_ref, a.setpoint_pose()[:3, :3])
        assert handle > 0.3
        assert tool == pytest.approx(0.5 * handle, rel=1e-5)
    finally:
        a.close()


def test_slicer_sees_the_tools_full_pose(arm: Arm) -> None:
    slicer = arm.pair.slave.peer("slicer")
    arm.pair.step(2500)
    n = len(slicer.messages("TRANSFORM", "Tip"))
    while len(slicer.messages("TRANSFORM", "Tip")) == n:  # the tick that sends the next one
        arm.pair.step(1)
    tip = slicer.messages("TRANSFORM", "Tip")[-1]
    pose = np.asarray(arm.slave.data.world_tip())  # measured in that tick
    m = np.asarray(tip.matrix)
    assert m[:3, :3] == pytest.approx(pose[:3, :3], abs=1e-6)  # float32 on the wire
    assert m[:3, 3] == pytest.approx(pose[:3, 3] * 1e3, abs=1e-3)
    assert angle(np.eye(3), pose[:3, :3]) > 0.1  # not the identity: a real orientation


# ------------------------------------------------------------------ URDF errors, with lines
def ur5(tmp: Path, **frame: Any) -> Path:
    cfg = yaml.safe_load((CONFIGS / "ur5.yaml").read_text())
    cfg["robot"]["frame"].update(frame)
    path = tmp / "arm.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def test_the_ur5_config_loads_from_the_package() -> None:
    cfg = load_config(CONFIGS / "ur5.yaml")
    path = cfg.robot.frame.urdf_path()
    assert path is not None and path.name == "ur5_joint_limited_robot.urdf" and path.is_file()


@pytest.mark.parametrize(
    ("frame", "message"),
    [
        ({"tip_link": "gripper"}, "robot.frame.tip_link: no link 'gripper' in the URDF"),
        ({"package_urdf": "robots/nope.urdf"}, "no file 'robots/nope.urdf' in package"),
        ({"base_link": "nowhere"}, "robot.frame.base_link: no link 'nowhere'"),
    ],
)
def test_a_frame_the_urdf_does_not_have_is_an_error_with_its_line(
    tmp_path: Path, frame: dict[str, Any], message: str
) -> None:
    path = ur5(tmp_path, **frame)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    text = str(info.value)
    assert message in text, text
    assert f"{path}:" in text  # FILE:LINE


def test_a_urdf_that_does_not_load_says_why_with_its_line(tmp_path: Path) -> None:
    (tmp_path / "bad.urdf").write_text(
        '<robot name="x"><link name="a"/><joint name="j" type="revolute">'
        '<parent link="a"/><child link="b"/></joint><link name="b"/></robot>'
    )
    text = (
        "robot:\n  name: x\n  frame:\n    urdf: bad.urdf\n    tip_link: b\n"
        "  joints:\n    - {name: j, type: revolute, limits: {min: -1, max: 1, velocity: 1}}\n"
        "  drivers:\n    - {name: sim, plugin: sim, joints: [j]}\n"
    )
    (tmp_path / "x.yaml").write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(tmp_path / "x.yaml")
    msg = str(info.value)
    assert ":4 robot.frame.urdf: the URDF does not load" in msg, msg
    assert "does not specify limits" in msg  # urdfdom's own reason


def test_joints_that_are_not_the_urdfs_are_an_error(tmp_path: Path) -> None:
    cfg = yaml.safe_load((CONFIGS / "ur5.yaml").read_text())
    joints = cfg["robot"]["joints"]
    joints[0], joints[1] = joints[1], joints[0]  # the wrong order
    with pytest.raises(ConfigError, match="are not the URDF's"):
        parse_config(yaml.safe_dump(cfg, sort_keys=False))


# ------------------------------------------------------------------ keyframes with orientation
class Plan6:
    """configs/ur5-keyframe.yaml in simulated time, its operator (3D Slicer's port)."""

    def __init__(self, **params: Any) -> None:
        from occ_testkit.testing import SimRobot

        self.sim = SimRobot(CONFIGS / "ur5-keyframe.yaml", params=params or None)
        self.robot = self.sim.robot
        self.kf: Any = self.robot.controller.controllers[0]
        self.op = self.sim.peer("slicer")

    def cmd(self, name: str, text: str = "") -> Any:
        cid = self.op.send_command(name, text)
        self.sim.step(1)
        assert self.kf.wait_idle(60.0)
        reply = self.op.reply_to(cid)
        assert reply is not None, name
        return reply

    def ok(self, name: str, text: str = "") -> str:
        reply = self.cmd(name, text)
        assert reply.metadata["Status"] == "SUCCESS", (name, reply.metadata)
        return str(reply.metadata["Message"])

    def close(self) -> None:
        self.sim.close()


@pytest.mark.req("SR-SIX-2")
@pytest.mark.parametrize("interpolation", ["linear", "spline"])
def test_a_keyframe_plan_with_orientation_meets_every_keyframe(interpolation: str) -> None:
    """The shipped UR5 plan (configs/keyframes/ur5-demo.yaml): planned, checked every tick,
    acknowledged, run; at each keyframe's tick the tool's pose (FK of the setpoint) is the
    keyframe's to 1e-6 (metres, radians), the joints never past their velocity limits."""
    plan6 = Plan6(interpolation=interpolation)
    try:
        plan6.ok("Enable")
        plan6.ok("Run")
        text = plan6.ok("KeyframePlan")
        plan_id = int(text.split(":")[0].split()[1])
        plan6.sim.step(150)  # the preview goes out with the next 10 Hz output tick
        plan6.ok("KeyframeAck", f'<Command Name="KeyframeAck" Plan="{plan_id}"/>')
        keyframes = yaml.safe_load((CONFIGS / "keyframes" / "ur5-demo.yaml").read_text())
        setpoints = [list(plan6.robot.data.commanded())]
        for _ in range(7200):
            plan6.sim.step(1)
            setpoints.append(list(plan6.robot.data.commanded()))
        frame = plan6.robot.frame
        for k in keyframes["keyframes"][1:]:  # keyframe 0 is replaced by where the tool is
            j = round(k["t"] / 1e-3)
            pose = np.asarray(frame.fk(setpoints[j]))
            assert np.linalg.norm(pose[:3, 3] * 1e3 - np.array(k["pose"])) < 1e-3, k  # 1e-6 m
            assert angle(quaternion_to_rotation(k["rotation"]), pose[:3, :3]) < 1e-6, k
        v = np.abs(np.diff(np.array(setpoints), axis=0)) / 1e-3
        assert float(v.max()) <= 1.0 * (1 + 1e-9)  # the joints' 1 rad/s
        assert plan6.kf.stats()["runs_completed"] == 1
        assert plan6.robot.state is RobotState.RUNNING
    finally:
        plan6.close()


@pytest.mark.req("SR-SIX-2")
def test_an_unreachable_orientation_is_refused_before_acknowledgement(tmp_path: Path) -> None:
    """The wrist's joints limited to 0.3 rad around home: a keyframe turning the tool 1.2 rad
    about its own axis is refused when planned, naming the keyframe and a joint at its limit;
    the robot does not move."""
    from occ_testkit.testing import SimRobot

    cfg = yaml.safe_load((CONFIGS / "ur5-keyframe.yaml").read_text())
    for j in cfg["robot"]["joints"][3:]:
        j["limits"].update(min=j["home"] - 0.3, max=j["home"] + 0.3)
    home_q = [j["home"] for j in cfg["robot"]["joints"]]
    frame_cfg = load_config(CONFIGS / "ur5.yaml")
    from occ.core.assembly import build_hardware
    from occ.samples import rotation_to_quaternion

    _, frame, _ = build_hardware(frame_cfg.robot)
    home = np.asarray(frame.fk(home_q))
    turned = home[:3, :3] @ pin.utils.rpyToMatrix(0.0, 0.0, 1.2)
    start = {"t": 0.0, "pose": (home[:3, 3] * 1e3).tolist(),
             "rotation": list(rotation_to_quaternion(home[:3, :3]))}  # fmt: skip
    end = {"t": 3.0, "pose": (home[:3, 3] * 1e3).tolist(),
           "rotation": list(rotation_to_quaternion(turned)), "name": "twist"}  # fmt: skip
    (tmp_path / "twist.yaml").write_text(
        yaml.safe_dump({"space": "cartesian", "keyframes": [start, end]})
    )
    cfg["controller"]["params"].update(file=None, keyframe_dir=str(tmp_path))
    sim = SimRobot(cfg)
    try:
        op = sim.peer("slicer")
        kf: Any = sim.robot.controller.controllers[0]
        for c in ("Enable", "Run"):
            assert sim.command(op, c).metadata["Status"] == "SUCCESS"

        def cmd(name: str, text: str) -> Any:
            cid = op.send_command(name, text)
            sim.step(1)
            assert kf.wait_idle(60.0)
            sim.step(1)
            return op.reply_to(cid)

        r = cmd("KeyframeLoad", '<Command Name="KeyframeLoad" File="twist.yaml"/>')
        assert r.metadata["Status"] == "SUCCESS", r.metadata
        before = list(sim.robot.data.commanded())
        r = cmd("KeyframePlan", "")
        assert r.metadata["Status"] == "FAIL", r.metadata
        assert "twist" in r.metadata["Error"] and "wrist_" in r.metadata["Error"], r.metadata
        # held at the joint limits by the IK (clamped), not an IK that gave up
        assert "the tip leaves the workspace at t=" in r.metadata["Error"], r.metadata
        assert "beyond its limits" in r.metadata["Error"], r.metadata
        sim.step(100)
        assert list(sim.robot.data.commanded()) == before
    finally:
        sim.close()


@pytest.mark.req("SR-SIX-1")
@pytest.mark.parametrize("base_mm", [None, [40.0, -25.0, 60.0]], ids=["at-origin", "moved-base"])
def test_a_laparoscopic_tool_keeps_its_axis_through_the_port(base_mm: list[float] | None) -> None:
    """``orientation: rcm``: the port 100 mm up the tool's axis from its tip at home (given in
    the patient frame: the base's position added when it is moved); while the tip follows the
    master (the paper's circle, 25 mm), the tool's axis passes through the port to 1e-6 m every
    tick, the tip is where the position mapping puts it, and the tool keeps its roll (its x
    axis turns only as much as its axis does, tick by tick)."""
    home = _ur5_home()
    port = (home[:3, 3] - 0.1 * home[:3, 2]) * 1e3
    if base_mm is None:
        a = Arm(orientation="rcm", rcm_mm=port.tolist())
    else:
        a = Arm(orientation="rcm", rcm_mm=(port + base_mm).tolist(), base_mm=base_mm)
    try:
        worst_axis = worst_p = worst_roll = 0.0
        prev = a.setpoint_pose()
        for k in range(5000):
            a.pair.step(1)
            pose = a.setpoint_pose()
            if k >= 50:
                # the new x axis is the previous one projected off the new tool axis
                x0, z1 = prev[:3, 0], pose[:3, 2]
                kept = x0 - float(x0 @ z1) * z1
                roll = float(np.linalg.norm(kept / np.linalg.norm(kept) - pose[:3, 0]))
                worst_roll = max(worst_roll, roll)
            prev = pose
            if k < 50 or k % 25:
                continue
            z, tip = pose[:3, 2], pose[:3, 3]
            r = port * 1e-3 - tip
            worst_axis = max(worst_axis, float(np.linalg.norm(r - float(r @ z) * z)))
            ctl = a.ctl
            m, m0, s0 = (np.array(v) for v in (ctl.master_pos, ctl.master_ref, ctl.slave_ref))
            worst_p = max(worst_p, float(np.linalg.norm(s0 + 0.5 * (m - m0) - tip)))
        assert a.slave.state is RobotState.RUNNING and a.ctl.ik_failures == 0
        assert worst_axis < 1e-6, worst_axis
        assert worst_p < 1e-6, worst_p
        assert worst_roll < 1e-5, worst_roll
        travel = np.linalg.norm(a.setpoint_pose()[:3, 3] - home[:3, 3])
        assert travel > 0.005  # the tip really moved (and the axis turned about the port)
    finally:
        a.close()


@pytest.mark.req("SR-SIX-1")
def test_a_tool_off_its_port_is_brought_through_it_without_a_pause() -> None:
    """``orientation: rcm`` with the port 10 mm off the tool's axis when following starts: the
    tool turns until its axis passes through the port, moving on every master sample from the
    first one it follows (never two ticks in a row without coming closer: at 500 Hz every
    other tick brings a sample), then stays through it; the robot still RUNNING (the steps
    within the velocity limits the drives check)."""
    home = _ur5_home()
    port = home[:3, 3] - 0.1 * home[:3, 2] + 0.01 * home[:3, 0]
    a = Arm(orientation="rcm", rcm_mm=(port * 1e3).tolist())

    def off_axis() -> float:
        pose = a.setpoint_pose()
        z, r = pose[:3, 2], port - pose[:3, 3]
        return float(np.linalg.norm(r - float(r @ z) * z))

    try:
        dist = [off_axis()]
        assert dist[0] > 0.009  # 10 mm off, less the little the master moved it
        while dist[-1] > 1e-6:
            assert len(dist) < 400, dist[-1]
            a.pair.step(1)
            dist.append(off_axis())
            if len(dist) > 2:
                assert dist[-1] < dist[-2] or dist[-2] < dist[-3], (len(dist), dist[-3:])
        for _ in range(100):
            a.pair.step(1)
            assert off_axis() < 1e-6
        assert a.slave.state is RobotState.RUNNING and a.ctl.ik_failures == 0
    finally:
        a.close()


def test_rcm_needs_its_port() -> None:
    cfg = yaml.safe_load((CONFIGS / "ur5.yaml").read_text())
    cfg["controller"]["params"]["orientation"] = "rcm"
    with pytest.raises(ConfigError, match="rcm_mm: required with orientation: rcm"):
        parse_config(yaml.safe_dump(cfg, sort_keys=False))


@pytest.mark.parametrize(
    ("frequency_hz", "amplitude_deg", "velocity"),
    [(2.0, 40.0, 1.0), (0.25, 20.0, 0.8)],
    ids=["2Hz-1rad/s", "0.25Hz-0.8rad/s"],
)
def test_a_fast_turn_is_slowed_to_the_velocity_limits_all_joints_alike(
    frequency_hz: float, amplitude_deg: float, velocity: float, tmp_path: Path
) -> None:
    """The gimbal at 2 Hz (20 times the demo's), or at 0.25 Hz and 20 degrees on an arm limited
    to 0.8 rad/s (where a step asks between one and two times the limit), asks the wrist faster
    than its limits: every tick's joint step stays within 0.9 times them and reaches them, no
    drive clamps on its own, the robot keeps running, and every step turns the tool toward the
    orientation it is asked for."""
    slave_cfg = CONFIGS / "ur5.yaml"
    if velocity != 1.0:
        cfg = yaml.safe_load(slave_cfg.read_text())
        for j in cfg["robot"]["joints"]:
            j["limits"]["velocity"] = velocity
        slave_cfg = tmp_path / "ur5_slow.yaml"
        slave_cfg.write_text(yaml.safe_dump(cfg, sort_keys=False))
    pair = SimPair(
        CONFIGS / "master6.yaml", slave_cfg,
        master_params={
            "frequency_hz": frequency_hz, "orientation_amplitude_deg": [0.0, 0.0, amplitude_deg]
        },
    )  # fmt: skip
    try:
        pair.start()
        slave = pair.slave.robot
        ctl: Any = slave.controller.controllers[0]
        prev = list(slave.data.setpoint)
        worst = turned = 0.0
        moves = closer = at_limit = 0
        for _ in range(3000):
            pair.step(1)
            sp = list(slave.data.setpoint)
            step = max(abs(x - y) for x, y in zip(sp, prev, strict=True))
            worst = max(worst, step / 1e-3)
            at_limit += step >= 0.9 * velocity * 1e-3 * (1 - 1e-9)
            if step > 0.0 and ctl.six.rs_ref is not None:
                # each step turns the tool toward the orientation it is asked for
                want = ctl.six.target_rotation()
                before = angle(want, np.asarray(slave.frame.fk(prev))[:3, :3])
                after = angle(want, np.asarray(slave.frame.fk(sp))[:3, :3])
                moves += 1
                closer += after < before
                turned = max(turned, angle(ctl.six.rs_ref, np.asarray(slave.frame.fk(sp))[:3, :3]))
            prev = sp
        assert worst <= 0.9 * velocity + 1e-9, worst  # rad/s: 0.9 x the limits
        assert worst >= 0.9 * velocity * (1 - 1e-6), worst  # and the limit is what it reached
        # GetStats' rate_limited: the ticks slowed, each one at the limit
        assert ctl.stats()["rate_limited"] == at_limit > 0
        assert turned > 0.05  # rad: it turned, slowed
        assert closer == moves > 500, (closer, moves)
        assert sum(d.stats()["limit_events"] for d in slave.hardware.drivers) == 0
        assert slave.state is RobotState.RUNNING
    finally:
        pair.close()


@pytest.mark.req("SR-SIX-1")
def test_a_port_along_the_tools_roll_axis_still_gives_an_orientation() -> None:
    """``orientation: rcm`` with the port straight along the tool's x axis from the target: the
    roll to keep is not defined (the x axis is the new tool axis), so any perpendicular serves,
    a proper rotation with its z axis from the port to the tip; a target at the port itself
    has no axis at all: an error the loop counts, never a NaN pose."""
    home = _ur5_home()
    port = home[:3, 3] - 0.1 * home[:3, 2]
    a = Arm(orientation="rcm", rcm_mm=(port * 1e3).tolist())
    try:
        a.pair.step(100)
        ctl = a.ctl
        x = np.asarray(a.slave.frame.fk(ctl._q_last))[:3, 0]
        for sign in (1.0, -1.0):
            r = ctl.six.rcm_rotation(tuple((port + sign * 0.05 * x).tolist()))
            assert np.all(np.isfinite(r))
            np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
            assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)
            np.testing.assert_allclose(r[:, 2], sign * x, atol=1e-12)
        with pytest.raises(KinematicsError, match="^the tip is at the port: the tool's axis is"):
            ctl.six.rcm_rotation(tuple(port.tolist()))
    finally:
        a.close()


def test_a_turn_past_a_joints_limit_holds_that_joint_at_its_limit(tmp_path: Path) -> None:
    """The last wrist joint limited to +-0.1 rad while the handle turns +-20 degrees about z:
    the pose is solved with that joint held at its limit (counted as clamped), never refused
    as unreachable (the arm would freeze where it is), and the robot keeps running."""
    cfg = yaml.safe_load((CONFIGS / "ur5.yaml").read_text())
    cfg["robot"]["joints"][5]["limits"].update({"min": -0.1, "max": 0.1})
    slave_cfg = tmp_path / "ur5_narrow_wrist.yaml"
    slave_cfg.write_text(yaml.safe_dump(cfg, sort_keys=False))
    pair = SimPair(CONFIGS / "master6.yaml", slave_cfg)
    try:
        pair.start()
        slave = pair.slave.robot
        ctl: Any = slave.controller.controllers[0]
        wrist = []
        for _ in range(3000):
            pair.step(1)
            wrist.append(slave.data.setpoint[5])
        assert min(wrist) == -0.1 and max(wrist) <= 0.1  # at the limit, never past it
        assert ctl.stats()["ik_clamped"] > 0 and ctl.stats()["ik_failures"] == 0
        assert slave.state is RobotState.RUNNING
    finally:
        pair.close()


# ------------------------------------------------------------------ a hold and its re-entry


def _rejoin_pair(**slave_params: Any) -> SimPair:
    """master6 at 0.25 Hz (the gimbal up to 0.55 rad/s) streaming at the loop's rate, 1 kHz (the
    slave's loss monitor told so), to the UR5: a new sample every tick, so that after a hold the
    pose solve runs ahead of the setpoint re-joining it at half the velocity limits (at the
    shipped 500 Hz the tick without a sample lets the setpoint catch up every other tick)."""
    master = yaml.safe_load((CONFIGS / "master6.yaml").read_text())
    for i in master["interfaces"]:
        for o in i.get("outputs", []):
            if o["source"] == "teleop":
                o["rate_hz"] = 1000
    slave = yaml.safe_load((CONFIGS / "ur5.yaml").read_text())
    slave["safety"]["loss"]["period_ms"] = 1.0
    pair = SimPair(
        master, slave, master_params={"frequency_hz": 0.25}, slave_params=slave_params or None
    )
    pair.start()
    return pair


class Rejoin:
    """A pair followed for 500 ms, its master stalled 40 ms (a late stream without a sequence
    gap: the slave holds), then followed 300 ms more, tick by tick: ``told``, what the
    controller told the motion layer (its pose solution), from the held setpoint (the last
    solution before the hold) on; ``sp``, the setpoints written; ``ticks``, how long the
    motion layer re-joined; ``rate_limited``, GetStats' count over those 300 ms."""

    def __init__(self, pair: SimPair) -> None:
        slave = self.slave = pair.slave.robot
        self.ctl: Any = slave.controller.controllers[0]
        told: list[list[float]] = []
        update = slave.controller.update

        def tell(now: float, current: Any) -> Any:
            target = update(now, current)
            told.append(list(target) if target is not None else told[-1])
            return target

        pair.step(500)
        monitor = slave.streams.monitor
        assert monitor is not None
        holds = monitor.counters()["holds"]
        pair.stall_master(40)
        assert monitor.counters()["holds"] == holds + 1  # held, not stopped
        told.append(list(slave.data.setpoint))
        sp = [list(slave.data.setpoint)]
        rejoining = []
        limited = self.ctl.stats()["rate_limited"]
        slave.controller.update = tell  # type: ignore[method-assign]
        try:
            for _ in range(300):
                pair.step(1)
                sp.append(list(slave.data.setpoint))
                rejoining.append(slave.motion.reentry)
        finally:
            del slave.controller.update
        c = monitor.counters()
        assert c["lost_total"] == 0 and c["resumes"] >= 1 and slave.state is RobotState.RUNNING
        self.rate_limited = self.ctl.stats()["rate_limited"] - limited
        self.told, self.sp = np.array(told), np.array(sp)
        self.ticks = rejoining.index(False)
        assert not any(rejoining[self.ticks :])

    def pose(self, q: Any) -> np.ndarray:
        return np.asarray(self.slave.frame.fk(list(q)))

    def check_limits(self) -> None:
        """The setpoint re-joins at half the velocity limits, then is what the controller
        says; the controller's own steps stay within 0.9 of them, all joints scaled alike
        from where it told the arm to be (GetStats' ``rate_limited``: the ticks slowed, each
        one with its largest step at 0.9 of the limit)."""
        limit = np.array([j.limits.velocity * 1e-3 for j in self.slave.joints])
        ticks, told, sp = self.ticks, self.told, self.sp
        assert ticks > 20  # a real re-entry
        assert (np.abs(np.diff(sp, axis=0))[:ticks] <= 0.5 * limit * (1 + 1e-9)).all()
        lead = max(
            float(np.linalg.norm(self.pose(q)[:3, 3] - self.pose(s)[:3, 3]))
            for q, s in zip(told[1 : ticks + 1], sp[1 : ticks + 1], strict=True)
        )
        assert lead > 0.5e-3, lead  # metres: the setpoint trailed the solution by a millimetre
        np.testing.assert_array_equal(sp[ticks + 1 :], told[ticks + 1 :])
        steps = (np.abs(np.diff(told, axis=0)) / limit).max(axis=1)
        assert steps.max() <= 0.9 * (1 + 1e-9)
        assert self.rate_limited == int((steps >= 0.9 * (1 - 1e-9)).sum()) > 10


def test_after_a_hold_the_tool_rejoins_its_pose_within_the_velocity_limits() -> None:
    """A master that goes quiet for 40 ms while the handle turns: the slave holds, then the
    setpoint re-joins at half the velocity limits the pose solve that went on at 0.9 of them
    from where it told the arm to be (never from the setpoint trailing it), and the tool ends
    in the pose it is asked for: the handle's rotation and displacement since the re-index."""
    pair = _rejoin_pair()
    try:
        r = Rejoin(pair)
        r.check_limits()
        ctl = r.ctl
        pose = r.pose(r.sp[-1])
        assert angle(ctl.six.target_rotation(), pose[:3, :3]) < 1e-6
        m, m0, s0 = (np.array(v) for v in (ctl.master_pos, ctl.master_ref, ctl.slave_ref))
        assert float(np.linalg.norm(s0 + 0.5 * (m - m0) - pose[:3, 3])) < 1e-8
        assert ctl.reindexes == 1 and ctl.ik_failures == 0
    finally:
        pair.close()


@pytest.mark.req("SR-SIX-1")
def test_after_a_hold_the_laparoscopic_tool_rejoins_through_its_port_with_its_roll() -> None:
    """``orientation: rcm`` through a hold and its re-entry: every pose the controller tells
    the arm keeps the tool's axis through the port (1e-6 m) and its roll from the pose it told
    before (its x axis turns only as much as its axis does), not a roll re-derived from the
    setpoint trailing it; the setpoint re-joins them within the limits and ends on them, the
    tip where the position mapping puts it."""
    home = _ur5_home()
    port = home[:3, 3] - 0.1 * home[:3, 2]
    pair = _rejoin_pair(orientation="rcm", rcm_mm=(port * 1e3).tolist())
    try:
        r = Rejoin(pair)
        r.check_limits()
        worst_axis = worst_roll = 0.0
        for a, b in zip(r.told[:-1], r.told[1:], strict=True):
            before, after = r.pose(a), r.pose(b)
            z, tip = after[:3, 2], after[:3, 3]
            d = port - tip
            worst_axis = max(worst_axis, float(np.linalg.norm(d - float(d @ z) * z)))
            x0 = before[:3, 0]
            kept = x0 - float(x0 @ z) * z
            roll = float(np.linalg.norm(kept / np.linalg.norm(kept) - after[:3, 0]))
            worst_roll = max(worst_roll, roll)
        assert worst_axis < 1e-6, worst_axis
        assert worst_roll < 1e-6, worst_roll
        # what the drives are told while re-joining: every joint together along the straight
        # line, so the axis leaves the port only to second order (2.8 um here; one joint
        # arriving before the others took it 0.17 mm off)
        off = 0.0
        for q in r.sp[: r.ticks + 2]:
            p = r.pose(q)
            z, d = p[:3, 2], port - p[:3, 3]
            off = max(off, float(np.linalg.norm(d - float(d @ z) * z)))
        assert off < 1e-5, off
        ctl = r.ctl
        tip = r.pose(r.sp[-1])[:3, 3]
        m, m0, s0 = (np.array(v) for v in (ctl.master_pos, ctl.master_ref, ctl.slave_ref))
        assert float(np.linalg.norm(s0 + 0.5 * (m - m0) - tip)) < 1e-8
        assert ctl.reindexes == 1 and ctl.ik_failures == 0
    finally:
        pair.close()
