"""A laparoscopic tool's keyframe plans keep its port (issue 40, item 5).

- The geometry (occ/kinematics/port.py): the shaft's distance from the port, the port in the
  base frame, the shortest turn; a :class:`PortTrajectory`'s axis passes through the port at
  every time, its tip path is the plan's without the port, every keyframe's pose is met, the
  roll is kept when none is given and interpolated between those given.
- The geometry's edges (no robot): a tip 1 um from the port and at it, a turn past a right
  angle and one that turns the tool over, the first of equally bad samples named, the first
  keyframe's orientation taken as the tool's, a turn exactly at the tolerance, rolls that go
  the short way across 180 deg, and what port_plan refuses.
- The plan (configs/ur5-keyframe.yaml's UR5 with ``rcm_mm``, the keyframes of the shipped
  configs/keyframes/ur5-port.yaml, in simulated time): checked, acknowledged and run; at every
  tick the shaft of the commanded pose (and of the measured one) is within 0.05 mm of the port.
- Refusals: a keyframe whose orientation contradicts the port (named, with the angle), a tool
  not through the port where the plan starts, a tip drawn back to the port, a port for an arm
  that cannot turn the tool; a sample off the port (a fault injected into the orientation)
  refused naming the worst sample; at run time a tick off the port stops the run.
- A joint set with a port is planned through the port as the tool's poses and reaches the
  keyframes' joints; the same set planned in joint space without the port sweeps the shaft
  across it (what the port prevents).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from occ.controllers.keyframe.plan import PlanRefused, PlanRequest, build_plan
from occ.controllers.keyframe.sets import make_set
from occ.core.assembly import build_hardware
from occ.core.loader import load_config, parse_config
from occ.core.safety import RobotState
from occ.errors import ConfigError
from occ.kinematics.port import (
    SHAFT_BOUND_M,
    PortMismatch,
    PortTrajectory,
    ShaftWatch,
    axis,
    keyframes_through_port,
    port_in_base,
    port_plan,
    shaft_offset,
    swing,
)
from occ.kinematics.trajectory import Keyframe, plan
from occ.samples import quaternion_to_rotation, rotation_to_quaternion
from occ_testkit.testing import CONFIGS, SimRobot

PORT_SET = CONFIGS / "keyframes" / "ur5-port.yaml"
#: the shipped example's port (configs/ur5-port.yaml), the same UR5 as configs/ur5-keyframe.yaml
PORT_MM = yaml.safe_load((CONFIGS / "ur5-port.yaml").read_text())["controller"]["params"]["rcm_mm"]


def _ur5() -> tuple[Any, list[float]]:
    cfg = load_config(CONFIGS / "ur5-keyframe.yaml")
    _, frame, _ = build_hardware(cfg.robot)
    return frame, [j.home for j in cfg.robot.joints]


def _pose(r: np.ndarray, p: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = r, p
    return out


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    c = (float(np.trace(a.T @ b)) - 1.0) / 2.0
    return math.acos(max(-1.0, min(1.0, c)))


# ------------------------------------------------------------------ geometry
@pytest.mark.req("SR-PORTPLAN-1")
def test_the_shafts_distance_from_the_port_and_the_port_in_the_base_frame() -> None:
    """The shaft runs back from the tip along -z: a port behind the tip is as far as it is
    from that line, one ahead of the tip as far as from the tip; the port in mm (world) is
    turned into the base frame; the shortest turn takes one axis onto another and refuses to
    turn one over."""
    pose = _pose(np.eye(3), np.array([0.1, 0.0, 0.2]))
    assert shaft_offset(pose, np.array([0.1, 0.0, 0.1])) == pytest.approx((0.0, 0.1))
    dist, depth = shaft_offset(pose, np.array([0.1003, 0.0004, 0.15]))
    assert dist == pytest.approx(0.0005) and depth == pytest.approx(0.05)
    dist, depth = shaft_offset(pose, np.array([0.1, 0.0, 0.23]))
    assert dist == pytest.approx(0.03) and depth == pytest.approx(-0.03)
    base = _pose(quaternion_to_rotation([0.0, 0.0, math.sin(0.4), math.cos(0.4)]), [0.2, 0.1, 0])
    p = port_in_base([300.0, 100.0, 50.0], base)
    assert np.allclose(base[:3, :3] @ p + base[:3, 3], [0.3, 0.1, 0.05])
    with pytest.raises(ValueError, match="x y z in mm"):
        port_in_base([1.0, 2.0], base)
    a, b = np.array([0.0, 0.0, 1.0]), np.array([0.6, 0.0, 0.8])
    assert np.allclose(swing(a, b) @ a, b) and np.allclose(swing(a, a), np.eye(3))
    with pytest.raises(ValueError, match="turn over"):
        swing(a, -a)


# ------------------------------------------------------------------ the geometry's edges
_UP = np.array([0.0, 0.0, 1.0])


def _at(tip: Any, rotation: Any = (0.0, 0.0, 0.0, 1.0), t: float = 0.0) -> Keyframe:
    return Keyframe(t, tuple(float(v) for v in tip), tuple(rotation))


@pytest.mark.req("SR-PORTPLAN-1")
def test_the_axis_is_defined_from_one_micrometre_off_the_port_and_not_at_it() -> None:
    """A tip 1 um from the port (exactly the limit) has an axis, the unit vector from the
    port to it; a tip at the port has none, and a plan with a keyframe there is refused
    saying so; a keyframe 1 um from the port is planned with its axis through it."""
    port = np.array([0.1, 0.2, 0.3])
    um = np.array([1e-6, 0.0, 0.0])
    assert np.array_equal(axis(um, np.zeros(3)), [1.0, 0.0, 0.0])
    with pytest.raises(
        ValueError, match="^the tip is at the port: the tool's axis is not defined$"
    ):
        axis(port, port)
    with pytest.raises(
        ValueError, match="^the tip is at the port: the tool's axis is not defined$"
    ):
        port_plan([_at(port + 0.05 * _UP), _at(port, t=1.0)], port)
    traj = port_plan([_at(um), _at(um + [0.0, 0.0, 0.05], t=1.0)], np.zeros(3))
    assert np.allclose(traj.rotation(0.0)[:, 2], [1.0, 0.0, 0.0], atol=1e-12)


@pytest.mark.req("SR-PORTPLAN-1")
def test_the_shortest_turn_goes_past_a_right_angle_and_never_turns_the_tool_over() -> None:
    """The shortest turn takes an axis 120 deg away (past a right angle: any turn short of
    turning over is a turn); a plan whose keyframe is across the port from the start (its axis
    turned over) is refused, whatever orientation it is given."""
    a = _UP
    b = np.array([math.sin(math.radians(120.0)), 0.0, math.cos(math.radians(120.0))])
    r = swing(a, b)
    assert np.allclose(r @ a, b, atol=1e-12) and np.allclose(r.T @ r, np.eye(3), atol=1e-12)
    port = np.zeros(3)
    over = r"^the tool's axis would turn over \(180 deg about the port\)$"
    with pytest.raises(ValueError, match=over):
        swing(a, -a)
    with pytest.raises(ValueError, match=over):
        port_plan([_at(0.05 * _UP), _at(-0.05 * _UP, (1.0, 0.0, 0.0, 0.0), t=1.0)], port)
    # 120 deg from the start's axis is planned, and its axis passes through the port
    traj = port_plan([_at(0.05 * _UP), _at(0.05 * b, t=1.0)], port)
    assert np.allclose(traj.rotation(1.0)[:, 2], b, atol=1e-12)


@pytest.mark.req("SR-PORTPLAN-3")
def test_the_shaft_watch_names_the_first_of_the_worst_samples() -> None:
    """The worst shaft offset of a plan's samples and where: the first sample is the worst
    until another is farther; of equally far samples the first is named; every sample is
    counted."""
    port = np.zeros(3)
    watch = ShaftWatch(port)

    def pose(dx: float) -> np.ndarray:
        return _pose(np.eye(3), np.array([dx, 0.0, 0.1]))

    watch.see(0, pose(0.0))  # on the port
    assert (watch.worst, watch.worst_at, watch.seen) == (0.0, 0, 1)
    watch.see(1, pose(0.0))
    assert watch.worst_at == 0
    watch.see(2, pose(2e-5))
    watch.see(3, pose(1e-5))
    watch.see(4, pose(2e-5))
    assert (watch.worst, watch.worst_at, watch.seen) == (pytest.approx(2e-5), 2, 5)
    first = ShaftWatch(port)
    first.see(7, pose(3e-5))
    first.see(8, pose(1e-5))
    assert (first.worst, first.worst_at) == (pytest.approx(3e-5), 7)


@pytest.mark.req("SR-PORTPLAN-2")
def test_the_keyframes_turned_onto_the_port_start_from_the_tools_orientation() -> None:
    """The keyframes' orientations through the port: the first must be the tool's (none given:
    refused, as is no keyframe at all), and it is never refused for being off the port's axis
    (it is where the tool is; the start check bounds it); a later one exactly at the tolerance
    is turned onto the axis, one past it refused with its index and angle."""
    port = np.zeros(3)
    with pytest.raises(ValueError, match="^the first keyframe needs the tool's orientation$"):
        keyframes_through_port([], port, 0.01)
    with pytest.raises(ValueError, match="^the first keyframe needs the tool's orientation$"):
        keyframes_through_port([Keyframe(0.0, (0.0, 0.0, 0.05))], port, 0.01)
    c, s = math.cos(0.1), math.sin(0.1)
    tilt = rotation_to_quaternion(np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]))
    frames, turns = keyframes_through_port([_at(0.05 * _UP, tilt)], port, 0.01)
    assert turns[0] == pytest.approx(0.1, abs=1e-12)
    z = quaternion_to_rotation(frames[0].rotation)[:, 2]
    assert np.allclose(z, _UP, atol=1e-12)
    keys = [_at(0.05 * _UP), _at(0.06 * _UP, tilt, t=1.0)]
    exact = keyframes_through_port(keys, port, 1.0)[1][1]
    frames, turns = keyframes_through_port(keys, port, exact)
    assert turns[1] == exact and np.allclose(quaternion_to_rotation(frames[1].rotation)[:, 2], _UP)
    with pytest.raises(PortMismatch) as err:
        keyframes_through_port(keys, port, math.nextafter(exact, 0.0))
    assert err.value.index == 1 and err.value.angle == exact


@pytest.mark.req("SR-PORTPLAN-1")
def test_the_roll_goes_the_short_way_between_keyframes() -> None:
    """Keyframes whose rolls about the axis are 0, 2, -2, 2 and 0 rad: from 2 to -2 the roll
    goes the short way, through 180 deg (to 2 pi - 2 rad), not back through 0; the tool's
    orientation halfway between them is rolled by 180 deg; each keyframe's orientation is met.
    The plan's orientation as a quaternion is its rotation's; the plan says it keeps a port."""
    port = np.zeros(3)
    rolls = [0.0, 2.0, -2.0, 2.0, 0.0]
    tips = [0.05 * _UP + [0.01 * i, 0.0, 0.0] for i in range(5)]
    frames = []
    for i, (tip, roll) in enumerate(zip(tips, rolls, strict=True)):
        c, s = math.cos(roll), math.sin(roll)
        turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        r = swing(_UP, axis(tip, port)) @ turn
        frames.append(_at(tip, rotation_to_quaternion(r), t=float(i)))
    traj = port_plan(frames, port, "linear", "stop")
    assert traj.rolls == pytest.approx([0.0, 2.0, 2.0 * math.pi - 2.0, 2.0, 0.0], abs=1e-9)
    for k in frames:
        assert np.allclose(traj.rotation(k.t), quaternion_to_rotation(k.rotation), atol=1e-12)
    mid = traj.rotation(1.5)
    x_ref = swing(_UP, mid[:, 2]) @ np.array([1.0, 0.0, 0.0])
    assert float(mid[:, 0] @ x_ref) == pytest.approx(-1.0, abs=1e-9)  # rolled by pi
    for t in (0.0, 0.7, 2.5, 4.0):
        q = traj.orientation(t)
        assert q.dtype == np.float64 and q.shape == (4,)
        assert np.allclose(quaternion_to_rotation(q), traj.rotation(t), atol=1e-12)
    assert repr(traj).startswith("PortTrajectory(5 keyframes, linear, stop")


@pytest.mark.req("SR-PORTPLAN-1")
def test_a_port_plan_needs_a_tip_and_a_turn_at_every_keyframe_and_a_port_of_three_numbers() -> None:
    """port_plan refuses keyframes of six values (joints, not a tip), keyframes without an
    orientation, and a port that is not three finite numbers, each saying what it needs."""
    port = np.zeros(3)
    first = _at(0.05 * _UP)
    joints = [
        Keyframe(float(t), (0.0, 0.0, 0.05, 0.0, 0.0, t), (0.0, 0.0, 0.0, 1.0)) for t in (0, 1)
    ]
    with pytest.raises(ValueError, match="keyframe 0: a plan through a port needs a tip"):
        port_plan(joints, port)
    bare = [Keyframe(0.0, (0.0, 0.0, 0.05)), Keyframe(1.0, (0.0, 0.0, 0.06))]
    with pytest.raises(ValueError, match="keyframe 0: a plan through a port needs a tip"):
        port_plan(bare, port)
    for bad in ([0.0, 0.0], [0.0, math.nan, 0.0], [0.0, 0.0, math.inf]):
        with pytest.raises(ValueError, match="the port must be x y z"):
            port_plan([first, _at(0.06 * _UP, t=1.0)], np.array(bad))


def _square(home: np.ndarray, port: np.ndarray, rolls: list[float] | None) -> list[Keyframe]:
    """Keyframes around the tip at ``home`` (a 30 mm square, 15 mm deeper at one corner):
    positions only (``rolls`` None) or each with its orientation through the port turned by
    its roll about the axis."""
    tip = home[:3, 3]
    offsets = ([0, 0, 0], [0.03, 0, 0], [0.03, 0.03, -0.015], [0, 0.03, -0.005], [0, 0, 0])
    out = []
    for i, d in enumerate(offsets):
        p = tip + np.array(d)
        if rolls is None and i > 0:
            out.append(Keyframe(2.0 * i, p))
            continue
        z = (p - port) / np.linalg.norm(p - port)
        r = swing(home[:3, 2], z) @ home[:3, :3]
        roll = 0.0 if rolls is None else rolls[i]
        c, s = math.cos(roll), math.sin(roll)
        r = r @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        out.append(Keyframe(2.0 * i, p, rotation_to_quaternion(r)))
    return out


@pytest.mark.req("SR-PORTPLAN-1")
@pytest.mark.parametrize("interpolation", ["linear", "spline"])
@pytest.mark.parametrize("mode", ["stop", "continuous"])
def test_a_port_plan_turns_the_tool_about_the_port_along_the_planned_tip_path(
    interpolation: Any, mode: Any
) -> None:
    """Every ms of the plan: the tool's axis passes through the port (1e-12 m), the tip is
    where the plan without the port puts it (exactly), the orientation is continuous; each
    keyframe's pose is met at its time (1e-9 rad) with its roll (given: 0.4, -0.3, 0.6 rad);
    a rotation is a function of the time alone (asked out of order, the same)."""
    frame, home_q = _ur5()
    home = np.asarray(frame.fk(home_q))
    port = home[:3, 3] - 0.1 * home[:3, 2]
    frames = _square(home, port, [0.0, 0.4, -0.3, 0.6, 0.0])
    traj = port_plan(frames, port, interpolation, mode)
    plain = plan([Keyframe(k.t, k.pose) for k in frames], interpolation, mode)
    worst_axis = worst_step = 0.0
    prev = traj.rotation(0.0)
    for t in np.arange(0.0, traj.end + 5e-4, 1e-3).tolist():
        r = traj.rotation(t)
        tip = traj.position(t)
        assert np.array_equal(tip, plain.position(t))
        worst_axis = max(worst_axis, shaft_offset(_pose(r, tip), port)[0])
        worst_step = max(worst_step, _angle(prev, r))
        prev = r
    assert worst_axis < 1e-12, worst_axis
    assert worst_step < 2e-3, worst_step  # no jump: at most a few mrad a ms
    for k in frames:
        assert _angle(traj.rotation(k.t), quaternion_to_rotation(k.rotation)) < 1e-9, k.t
    assert np.array_equal(traj.rotation(3.3), PortTrajectory.rotation(traj, 3.3))
    later = traj.rotation(7.1)
    traj.rotation(1.2)
    assert np.array_equal(traj.rotation(7.1), later)


@pytest.mark.req("SR-PORTPLAN-1")
def test_without_given_orientations_the_roll_is_kept_and_the_way_back_restores_the_pose() -> None:
    """Positions only: each keyframe's orientation is the start's turned the shortest way onto
    its axis (no roll added), and a plan whose tip comes back to the start ends in the start's
    orientation exactly (no roll gathered on the way round); a given orientation within the
    tolerance is turned onto the port's axis, one beyond it is refused with its index and
    angle."""
    frame, home_q = _ur5()
    home = np.asarray(frame.fk(home_q))
    port = home[:3, 3] - 0.1 * home[:3, 2]
    frames, turns = keyframes_through_port(_square(home, port, None), port, math.radians(0.5))
    assert turns == [0.0] * 5
    for k in frames:
        r = quaternion_to_rotation(k.rotation)
        z = r[:, 2]
        assert np.allclose(r, swing(home[:3, 2], z) @ home[:3, :3], atol=1e-12)
    traj = port_plan(frames, port, "spline", "stop")
    assert _angle(traj.rotation(traj.end), home[:3, :3]) < 1e-12
    assert max(abs(v) for v in traj.rolls) < 1e-12
    tilted = list(_square(home, port, [0.0] * 5))
    c, s = math.cos(0.003), math.sin(0.003)
    off = quaternion_to_rotation(tilted[2].rotation) @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    tilted[2] = Keyframe(tilted[2].t, tilted[2].pose, rotation_to_quaternion(off))
    fixed, turns = keyframes_through_port(tilted, port, math.radians(0.5))
    assert turns[2] == pytest.approx(0.003, abs=1e-9)
    z = quaternion_to_rotation(fixed[2].rotation)[:, 2]
    assert shaft_offset(_pose(quaternion_to_rotation(fixed[2].rotation), fixed[2].pose), port)[
        0
    ] < 1e-12 and np.linalg.norm(z) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="keyframe 2: the tool's axis is 0.172 deg"):
        keyframes_through_port(tilted, port, math.radians(0.1))


# ------------------------------------------------------------------ the UR5 in simulated time
class Ur5Port:
    """configs/ur5-keyframe.yaml with the port of configs/ur5-port.yaml and its keyframes (or
    ``params``), in simulated time; its operator (3D Slicer's port)."""

    def __init__(self, **params: Any) -> None:
        merged = {"rcm_mm": PORT_MM, "file": str(PORT_SET), **params}
        self.sim = SimRobot(CONFIGS / "ur5-keyframe.yaml", params=merged)
        self.robot = self.sim.robot
        self.kf: Any = self.robot.controller.controllers[0]
        self.op = self.sim.peer("slicer")
        self.port = port_in_base(PORT_MM, np.asarray(self.robot.data.base))

    def cmd(self, name: str, **args: str) -> Any:
        attrs = "".join(f' {k}="{v}"' for k, v in args.items())
        cid = self.op.send_command(name, f'<Command Name="{name}"{attrs}/>' if args else "")
        self.sim.step(1)
        assert self.kf.wait_idle(60.0)
        self.sim.step(1)
        reply = self.op.reply_to(cid)
        assert reply is not None, name
        return reply

    def ok(self, name: str, **args: str) -> str:
        reply = self.cmd(name, **args)
        assert reply.metadata["Status"] == "SUCCESS", (name, reply.metadata)
        return str(reply.metadata["Message"])

    def refused(self, name: str, **args: str) -> str:
        reply = self.cmd(name, **args)
        assert reply.metadata["Status"] == "FAIL", (name, reply.metadata)
        return str(reply.metadata["Error"])

    def offset(self, q: Any) -> float:
        return shaft_offset(np.asarray(self.robot.frame.fk(list(q))), self.port)[0]

    def run(self, seconds: float) -> tuple[list[list[float]], float]:
        """Acknowledge the previewed plan and run ``seconds``: (every tick's setpoint, index j
        the plan at j ms; the worst shaft offset of the measured joints)."""
        plan_id = self.kf.plan.id
        self.sim.step(150)  # the preview goes out with the next 10 Hz output tick
        cid = self.op.send_command("KeyframeAck", f'<Command Name="KeyframeAck" Plan="{plan_id}"/>')
        self.sim.step(1)  # acknowledged in this tick, whose update is the plan at t = 0
        assert self.op.reply_to(cid).metadata["Status"] == "SUCCESS"
        setpoints = [list(self.robot.data.commanded())]
        worst_measured = 0.0
        for _ in range(round(seconds / 1e-3)):
            self.sim.step(1)
            setpoints.append(list(self.robot.data.commanded()))
            worst_measured = max(worst_measured, self.offset(self.robot.data.q))
        return setpoints, worst_measured

    def close(self) -> None:
        self.sim.close()


def test_the_shipped_port_example_is_the_keyframe_ur5_with_a_port() -> None:
    """configs/ur5-port.yaml is configs/ur5-keyframe.yaml's robot and interfaces with the port
    and its keyframes (what the simulated-time tests here run), and passes ``occd --check``."""
    port_cfg = yaml.safe_load((CONFIGS / "ur5-port.yaml").read_text())
    kf_cfg = yaml.safe_load((CONFIGS / "ur5-keyframe.yaml").read_text())
    for section in ("robot", "interfaces", "safety"):
        assert port_cfg[section] == kf_cfg[section], section
    params = dict(port_cfg["controller"]["params"])
    assert params.pop("rcm_mm") == PORT_MM and params.pop("file") == "keyframes/ur5-port.yaml"
    assert params == {k: v for k, v in kf_cfg["controller"]["params"].items() if k != "file"}
    load_config(CONFIGS / "ur5-port.yaml")


@pytest.mark.req("SR-PORTPLAN-3")
@pytest.mark.parametrize("interpolation", ["linear", "spline"])
def test_a_plan_through_the_port_keeps_it_at_every_tick_of_its_run(interpolation: str) -> None:
    """The UR5 in simulated time, the shipped keyframes (tip positions only) with the port:
    the plan is checked and run; at every tick the shaft of the commanded pose is within 0.05
    mm of the port (in fact 1e-5 mm) and that of the measured joints (the simulated drives'
    lag) within 0.05 mm; each keyframe's tip is met to 1e-6 m; the joints within their 1 rad/s;
    the tool ends in the pose it started in."""
    arm = Ur5Port(interpolation=interpolation)
    try:
        arm.ok("Enable")
        arm.ok("Run")
        home = np.asarray(arm.robot.frame.fk(list(arm.robot.data.commanded())))
        text = arm.ok("KeyframePlan")
        assert "shaft within" in text and "of the port at every sample" in text, text
        setpoints, worst_measured = arm.run(7.2)
        worst = max(arm.offset(q) for q in setpoints)
        assert worst < 1e-8, worst  # 1e-5 mm: the pose IK's tolerance
        assert worst_measured < SHAFT_BOUND_M, worst_measured
        keys = yaml.safe_load(PORT_SET.read_text())["keyframes"]
        for k in keys[1:]:
            tip = arm.robot.frame.fk(setpoints[round(k["t"] / 1e-3)])[:3, 3]
            assert np.linalg.norm(tip * 1e3 - np.array(k["pose"])) < 1e-3, k
        v = np.abs(np.diff(np.array(setpoints), axis=0)) / 1e-3
        assert float(v.max()) <= 1.0 * (1 + 1e-9)
        # the roll kept: the end is the start turned the shortest way onto the end's axis (the
        # last keyframe is 0.06 mm from where the tool started; the start 5e-6 rad off the
        # port's axis through it: the rounding of rcm_mm)
        end = np.asarray(arm.robot.frame.fk(setpoints[-1]))
        kept = swing(home[:3, 2], end[:3, 2]) @ home[:3, :3]
        assert _angle(end[:3, :3], kept) < 1e-5
        assert arm.kf.stats()["runs_completed"] == 1 and arm.kf.stats()["port_stops"] == 0
        assert arm.robot.state is RobotState.RUNNING
    finally:
        arm.close()


@pytest.mark.req("SR-PORTPLAN-2")
def test_a_keyframe_whose_orientation_contradicts_the_port_is_refused_with_its_angle(
    tmp_path: Path,
) -> None:
    """The shipped configs/keyframes/ur5-demo.yaml (orientations tilting the tool freely) with
    the port: refused when planned, naming the keyframe whose axis is off the port's and by
    how many degrees; the robot does not move. The same set with its orientations turned onto
    the port within 0.3 deg is planned (its summary says how far they were turned)."""
    arm = Ur5Port(file=str(CONFIGS / "keyframes" / "ur5-demo.yaml"))
    try:
        arm.ok("Enable")
        arm.ok("Run")
        before = list(arm.robot.data.commanded())
        error = arm.refused("KeyframePlan")
        assert "keyframe 1 'turn-z' (t=2 s) contradicts the port" in error, error
        assert "deg from the axis through the port and its tip (rcm_tolerance_deg 0.5)" in error
        degrees = float(error.split("tool axis is ")[1].split(" deg")[0])
        assert 5.0 < degrees < 30.0, error
        arm.sim.step(100)
        assert list(arm.robot.data.commanded()) == before
    finally:
        arm.close()
    frame, home_q = _ur5()
    home = np.asarray(frame.fk(home_q))
    base_port = port_in_base(PORT_MM, np.eye(4))
    keys = []
    for i, k in enumerate(_square(home, base_port, [0.0, 0.4, -0.3, 0.6, 0.0])):
        r = quaternion_to_rotation(k.rotation)
        tilt = 0.3 * (i % 2)  # every other keyframe 0.3 deg off the port's axis
        c, s = math.cos(math.radians(tilt)), math.sin(math.radians(tilt))
        r = r @ np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
        pose = (np.asarray(k.pose) * 1e3).tolist()
        keys.append({"t": k.t, "pose": pose, "rotation": list(rotation_to_quaternion(r))})
    (tmp_path / "rolls.yaml").write_text(yaml.safe_dump({"space": "cartesian", "keyframes": keys}))
    arm = Ur5Port(file=str(tmp_path / "rolls.yaml"))
    try:
        arm.ok("Enable")
        arm.ok("Run")
        text = arm.ok("KeyframePlan")
        assert "turned onto the port's axis (at most 0.3 deg)" in text, text
        # the summary's notes, one after the other
        assert "(at most 0.3 deg); the tool's shaft within " in text, text
        setpoints, _ = arm.run(8.2)
        assert max(arm.offset(q) for q in setpoints) < 1e-8
        for k in _square(home, base_port, [0.0, 0.4, -0.3, 0.6, 0.0])[1:]:
            pose = np.asarray(arm.robot.frame.fk(setpoints[round(k.t / 1e-3)]))
            # the roll given is met (the keyframe's own turn, 0.3 deg off the port's, is not)
            assert _angle(pose[:3, :3], quaternion_to_rotation(k.rotation)) < 1e-6, k.t
        assert arm.kf.stats()["runs_completed"] == 1
    finally:
        arm.close()


@pytest.mark.req("SR-PORTPLAN-2")
def test_a_tool_off_its_port_a_tip_drawn_to_the_port_and_a_short_arm_are_refused() -> None:
    """Refused with why before anything moves: the tool's shaft 0.2 mm from the port where the
    plan starts ("bring the tool through the port first"); a keyframe whose tip is 5 mm from
    the port (``rcm_min_depth_mm`` 10); a path that passes within it between two keyframes,
    named with the time; a port for a 3-joint arm (``occd --check``)."""
    home_port = np.array(PORT_MM)
    arm = Ur5Port(rcm_mm=(home_port + [0.2, 0.0, 0.0]).tolist())
    try:
        arm.ok("Enable")
        arm.ok("Run")
        error = arm.refused("KeyframePlan")
        assert "the tool's shaft is 0.2" in error, error  # 0.2 mm and the port's rounding
        assert "mm from the port (rcm_mm) where the plan starts" in error
        assert "bring the tool through the port first" in error
    finally:
        arm.close()
    frame, home_q = _ur5()
    home_mm = np.asarray(frame.fk(home_q))[:3, 3] * 1e3
    axis = (home_mm - home_port) / np.linalg.norm(home_mm - home_port)
    shallow = home_port + 5.0 * axis
    side = np.cross(axis, [0.0, 1.0, 0.0])  # across the axis: 10.1 mm deep on either side
    near, far = home_port + 9.5 * axis + 3.5 * side, home_port + 9.5 * axis - 3.5 * side
    arm = Ur5Port()
    try:
        arm.ok("Enable")
        arm.ok("Run")
        arm.ok("KeyframeClear")
        arm.ok("KeyframeAdd", T="3", Pose=" ".join(f"{v:.4f}" for v in shallow), Label="out")
        error = arm.refused("KeyframePlan")
        assert "keyframe 0 'out' (t=3 s): the tip is 5 mm beyond the port" in error, error
        assert "less than rcm_min_depth_mm (10)" in error
        arm.ok("KeyframeClear")
        arm.ok("KeyframeAdd", T="10", Pose=" ".join(f"{v:.4f}" for v in near), Label="near")
        arm.ok("KeyframeAdd", T="20", Pose=" ".join(f"{v:.4f}" for v in far), Label="far")
        error = arm.refused("KeyframePlan")
        assert "the tip comes 9.99" in error and "mm from the port at t=1" in error, error
        assert "between keyframe 0 'near' (t=10 s) and keyframe 1 'far' (t=20 s)" in error, error
    finally:
        arm.close()
    cfg = yaml.safe_load((CONFIGS / "keyframe.yaml").read_text())
    cfg["controller"]["params"]["rcm_mm"] = [0.0, 0.0, 300.0]
    with pytest.raises(ConfigError, match="rcm_mm: a port needs a 6-DOF arm"):
        parse_config(yaml.safe_dump(cfg, sort_keys=False), base_dir=CONFIGS)


def _side_set(dx_mm: float, t: float) -> tuple[Any, list[float], np.ndarray, np.ndarray, Any]:
    """The UR5 at home, its port 100 mm up the tool's axis from the tip, and a set of one
    Cartesian keyframe ``dx_mm`` to the side at ``t``: (frame, home_q, home, port, kset)."""
    frame, home_q = _ur5()
    home = np.asarray(frame.fk(home_q))
    port = home[:3, 3] - 0.1 * home[:3, 2]
    tip_mm = (home[:3, 3] * 1e3).tolist()
    side = [tip_mm[0] + dx_mm, tip_mm[1], tip_mm[2]]
    kset = make_set("cartesian", [(t, side, "side")], "test", joints=6, max_keyframes=10)
    return frame, home_q, home, port, kset


def _request(frame: Any, home_q: list[float], kset: Any, port: np.ndarray) -> PlanRequest:
    from occ.joint import JointLimits

    return PlanRequest(
        id=1,
        kset=kset,
        q_start=tuple(home_q),
        base=np.eye(4),
        interpolation="linear",
        mode="stop",
        steepness=6.0,
        ramp=0.25,
        period=1e-3,
        joint_names=tuple(frame.joint_names),
        limits=tuple(
            JointLimits(lo, hi, 1.0) for lo, hi in zip(frame.lower, frame.upper, strict=True)
        ),
        velocity_scale=1.0,
        start_tolerance=1e-3,
        start_tolerance_mm=0.5,
        workspace=None,
        forbidden=(),
        max_duration_s=300.0,
        preview_points=64,
        port=port,
    )


@pytest.mark.req("SR-PORTPLAN-3")
def test_a_sample_off_the_port_refuses_the_plan_naming_the_worst(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A fault injected into the port's orientation (the tool tilted up to 1 mrad, most at
    t = 1 s, about 0.1 mm off the port at the tip's 100 mm): the plan check, which looks at the
    shaft of every sample's joints (FK), refuses it naming the worst sample (where the tilt
    times the tip's depth is largest), its time and distance; a fifth of the tilt (within the
    bound) passes."""
    frame, home_q, home, port, kset = _side_set(30.0, 2.0)
    real = PortTrajectory.rotation

    def tilted(amplitude: float) -> Any:
        def rotation(self: PortTrajectory, t: float) -> np.ndarray:
            e = amplitude * math.sin(math.pi * min(max(t, 0.0), 2.0) / 2.0)
            c, s = math.cos(e), math.sin(e)
            return np.asarray(real(self, t) @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]]))

        return rotation

    monkeypatch.setattr(PortTrajectory, "rotation", tilted(1e-3))
    with pytest.raises(PlanRefused) as err:
        build_plan(_request(frame, home_q, kset, port), frame.copy())
    text = str(err.value)
    # the worst: the tilt times the tip's depth below the port along the planned tip path
    tip_path = plan([Keyframe(0.0, home[:3, 3]), Keyframe(2.0, home[:3, 3] + [0.03, 0, 0])])
    offsets = [
        float(np.linalg.norm(tip_path.position(j * 1e-3) - port))
        * math.sin(1e-3 * math.sin(j * math.pi / 2000))
        for j in range(2001)
    ]
    worst = max(range(2001), key=offsets.__getitem__)
    assert 1000 < worst < 1100
    assert f"the tool's shaft passes {offsets[worst] * 1e3:.4g} mm from the port" in text, text
    assert f"at t={worst * 1e-3:.3f} s, between the start (the robot's pose) and keyframe 0" in text
    assert f"(sample {worst}, the worst of 2001; bound 0.05 mm)" in text, text
    monkeypatch.setattr(PortTrajectory, "rotation", tilted(2e-4))
    checked = build_plan(_request(frame, home_q, kset, port), frame.copy())
    assert "shaft within 0.02 mm of the port at every sample" in checked.summary, checked.summary


@pytest.mark.req("SR-PORTPLAN-3")
def test_a_tick_off_the_port_at_run_time_stops_the_run_and_the_robot_holds() -> None:
    """The run checks the shaft of every tick's joints too: a fault injected into the running
    plan's orientation after 1 s (a tilt growing 2 mrad a second) stops the run at the first
    tick past 0.05 mm (the run's STATUS ended, ``port_stops`` counted, the error naming the
    distance); every tick commanded was within the bound; the robot holds there, RUNNING."""
    arm = Ur5Port()
    try:
        arm.ok("Enable")
        arm.ok("Run")
        arm.ok("KeyframePlan")
        plan_id = arm.kf.plan.id
        arm.sim.step(150)
        arm.ok("KeyframeAck", Plan=str(plan_id))
        traj = arm.kf.active.traj
        real = traj.rotation

        def tilted(t: float) -> np.ndarray:
            e = 2e-3 * max(0.0, t - 1.0)
            c, s = math.cos(e), math.sin(e)
            return np.asarray(real(t) @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]]))

        traj.rotation = tilted
        setpoints = []
        for _ in range(2000):
            arm.sim.step(1)
            setpoints.append(list(arm.robot.data.commanded()))
        stats = arm.kf.stats()
        assert stats["port_stops"] == 1 and stats["runs_completed"] == 0, stats
        assert "mm from the port (bound 0.05 mm)" in stats["last_error"], stats
        assert stats["status"].startswith(f"plan {plan_id} stopped at t=1.2"), stats
        assert max(arm.offset(q) for q in setpoints) <= SHAFT_BOUND_M
        assert setpoints[-1] == setpoints[-300]  # held
        assert arm.robot.state is RobotState.RUNNING
    finally:
        arm.close()


@pytest.mark.req("SR-PORTPLAN-4")
def test_a_joint_set_is_planned_through_the_port_and_reaches_its_joints() -> None:
    """Joint keyframes with a port: each is the tool's pose through the port (three taken
    from a Cartesian port plan's run), planned through the port as those poses; at every tick
    the shaft is within 1e-5 mm of the port, and the arm reaches each keyframe's joints
    (1e-6 rad). Planned in joint space without the port, the same keyframes sweep the shaft
    more than 1 mm across the port (what the port prevents). A joint keyframe whose tool is
    not through the port (a wrist turned 0.1 rad) is refused with the angle, one whose pose
    the arm reaches through the port in another configuration is refused naming the joint."""
    arm = Ur5Port()
    try:
        arm.ok("Enable")
        arm.ok("Run")
        arm.ok("KeyframePlan")
        setpoints, _ = arm.run(7.2)
        picks = [setpoints[round(t / 1e-3)] for t in (2.0, 4.0, 5.5)]
        arm.ok("KeyframeClear")
        for i, q in enumerate(picks):
            pose = " ".join(f"{v:.12f}" for v in q)
            arm.ok("KeyframeAdd", T=str(2.0 * (i + 1)), Pose=pose, Space="joint")
        text = arm.ok("KeyframePlan", Interpolation="linear")
        assert "joint keyframes planned through the port as the tool's poses" in text, text
        assert arm.kf.plan.space == "cartesian"
        run, _ = arm.run(6.2)
        assert max(arm.offset(q) for q in run) < 1e-8
        for i, q in enumerate(picks):
            got = run[round(2.0 * (i + 1) / 1e-3)]
            assert max(abs(a - b) for a, b in zip(got, q, strict=True)) < 1e-6, i
        frame, _ = _ur5()
        joint = plan(
            [Keyframe(0.0, run[-1])] + [Keyframe(2.0 * (i + 1), q) for i, q in enumerate(picks)],
            "linear",
        )
        swept = max(
            shaft_offset(np.asarray(frame.fk(joint.position(t))), arm.port)[0]
            for t in np.arange(0.0, 6.0, 0.01).tolist()
        )
        assert swept > 1e-3, swept
        arm.ok("KeyframeClear")
        bent = list(picks[0])
        bent[4] += 0.1
        arm.ok("KeyframeAdd", T="2", Pose=" ".join(f"{v:.12f}" for v in bent), Space="joint")
        error = arm.refused("KeyframePlan")
        assert "keyframe 0 (t=2 s) contradicts the port: its tool axis is" in error, error
        degrees = float(error.split("tool axis is ")[1].split(" deg")[0])
        assert 1.0 < degrees < 2.0, error  # the wrist's 5.7 deg, less the tip's own move
        # the first keyframe rolled 1 rad (the same axis) but in the arm's other configuration
        # that reaches the same pose (elbow and wrist flipped): planned through the port from
        # where the arm is, the IK stays in its own; refused, naming the furthest joint
        rolled = list(picks[0])
        rolled[5] += 1.0
        target = np.asarray(frame.fk(rolled))
        seed = np.add(rolled, [0.0, 0.5, -0.84, 3.47, 3.14, -3.14])
        other = frame.solve_ik(target, list(np.clip(seed, frame.lower, frame.upper)), clamp=True)
        assert other.error < 1e-9 and max(abs(np.subtract(other.q, rolled))) > 3.0
        arm.ok("KeyframeClear")
        pose = " ".join(f"{v:.12f}" for v in other.q)
        arm.ok("KeyframeAdd", T="2", Pose=pose, Space="joint")
        error = arm.refused("KeyframePlan")
        assert (
            "keyframe 0 (t=2 s): through the port the arm reaches its tool pose in another "
            in error
        )
        assert "configuration (joint 'wrist_1_joint' 3." in error, error
        assert "give these keyframes in Cartesian space" in error, error
    finally:
        arm.close()
