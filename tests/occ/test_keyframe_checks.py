"""The keyframe controller's plan checks and acknowledgement: what mutation testing found
unchecked (issue 29; docs/VERIFICATION.md, "occ/controllers/keyframe.py").

Through the daemon's own command path in simulated time (test_keyframe's Session: a keyframe
robot with an ideal driver, an operator peer), except the refusal's wording of a time
(``_where``), checked at its half-period boundaries directly.
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import math
import threading
import time
from collections.abc import Iterator
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from occ.controllers.keyframe import KeyframeController, KeyframeParams
from occ.controllers.keyframe.pacer import Pacer
from occ.controllers.keyframe.plan import (
    PlanRefused,
    _join_start,
    _TickChecks,
    _Timeline,
    _where,
    ack_ready,
    build_plan,
    plan_request,
    pose_ik,
    run_tick,
)
from occ.controllers.keyframe.preview import Preview
from occ.controllers.keyframe.sets import PlanSettings, make_set
from occ.core.safety import RobotState
from occ.errors import CommandError, KinematicsError
from occ.joint import JointLimits
from occ.kinematics.port import SHAFT_BOUND_M, PortTrajectory, port_in_base, port_plan
from occ.kinematics.trajectory import Keyframe

from .test_keyframe import HOME, Session, xml

# --------------------------------------------------------------------------- acknowledgement


def _logged(caplog: pytest.LogCaptureFixture, level: int) -> list[str]:
    return [
        r.getMessage()
        for r in caplog.records
        if r.name == "occ.controllers.keyframe" and r.levelno == level
    ]


def test_every_refused_acknowledgement_says_why(
    session: Session, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="occ.controllers.keyframe")
    s = session
    s.ok("KeyframeAdd", T=1.0, Pose="0.2 0.35 0.05")
    s.ok("KeyframePlan")
    assert s.refused("KeyframeAck") == "KeyframeAck needs Plan (the number of the previewed plan)"
    assert s.refused("KeyframeAck", Plan="one") == "KeyframeAck: Plan must be a number, got 'one'"
    assert s.refused("KeyframeAck", Plan=1) == (
        "KeyframeAck: plan 1 has not been previewed yet (its preview goes out with the next "
        "keyframe-path output); look at it, then acknowledge"
    )
    s.step(20)
    assert s.refused("KeyframeAck", Plan=2) == (
        "KeyframeAck: plan 2 is not the previewed plan (plan 1 is previewed)"
    )
    assert s.refused("KeyframeAck", Plan=1) == (
        "KeyframeAck: the robot is READY; send Run first (it holds until a plan is acknowledged)"
    )
    s.start()
    assert s.kf.stats()["runs"] == 0
    assert s.ok("KeyframeAck", Plan=1) == "plan 1 running: 1.000 s"
    assert s.kf.stats()["runs"] == 1
    assert "keyframes: plan 1 acknowledged, running 1.000 s" in _logged(caplog, logging.INFO)
    assert s.refused("KeyframeAck", Plan=1) == "plan 1 is running already"
    s.step(1100)
    assert "keyframes: plan 1 completed (1.000 s)" in _logged(caplog, logging.INFO)
    assert s.refused("KeyframeAck", Plan=1) == (
        "KeyframeAck: plan 1 is not the previewed plan (no plan is previewed)"
    )
    s.ok("KeyframeAdd", T=2.0, Pose="0.0 0.35 0.05")
    s.plan_and_ack()
    assert s.kf.stats()["runs"] == 2
    s.step(2100)
    assert s.kf.stats()["runs_completed"] == 2


@pytest.fixture
def session() -> Iterator[Session]:
    s = Session()
    try:
        yield s
    finally:
        s.close()


def _move_by_hand(s: Session, yaw: float) -> None:
    """The arm pushed by `yaw` rad while the servos are off, in 20 ticks (a hand, not a jump
    the driver would take for a sensor fault)."""
    (driver,) = s.robot.hardware.drivers
    for k in range(1, 21):
        driver.last = [HOME[0] + yaw * k / 20, HOME[1], HOME[2]]  # type: ignore[attr-defined]
        s.step(1)


@pytest.mark.parametrize("moved", [0.05, 2e-9])
def test_a_plan_is_not_run_once_the_robot_has_moved_since_it_was_checked(moved: float) -> None:
    """Planned while enabled; the servos off, the arm is moved by hand (the ideal driver
    reports where it was put); enabled and running again, the robot holds there, not where
    the plan starts: the acknowledgement is refused with the distance."""
    s = Session({"keyframes": [{"t": 1.0, "pose": [0.2, 0.35, 0.05]}]})
    try:
        s.ok("Enable")
        s.ok("KeyframePlan")
        s.step(20)
        s.ok("Disable")
        _move_by_hand(s, moved)
        s.ok("Enable")
        s.ok("Run")
        assert s.robot.data.setpoint[0] == HOME[0] + moved
        error = s.refused("KeyframeAck", Plan=1)
        assert error == (
            f"KeyframeAck: the robot moved since plan 1 was checked ({moved:.3g} rad/m); plan again"
        )
        s.step(100)
        assert all(sp == [HOME[0] + moved, HOME[1], HOME[2]] for sp in s.setpoints[-100:])
        # planned again from where it is, it runs
        s.plan_and_ack()
        s.step(1100)
        assert s.setpoints[-1] == [0.2, 0.35, 0.05]
    finally:
        s.close()


def test_a_plan_is_run_when_the_robot_is_where_it_was_checked() -> None:
    """The same servo cycle without moving the arm: the plan still starts where the robot is
    and is acknowledged."""
    s = Session({"keyframes": [{"t": 1.0, "pose": [0.2, 0.35, 0.05]}]})
    try:
        s.ok("Enable")
        s.ok("KeyframePlan")
        s.step(20)
        s.ok("Disable")
        s.step(2)
        s.start()
        assert s.ok("KeyframeAck", Plan=1) == "plan 1 running: 1.000 s"
    finally:
        s.close()


# --------------------------------------------------------------------------- the world changes


def _hold_planner(s: Session) -> tuple[threading.Event, threading.Event]:
    """A forbidden-region check that blocks the planner thread until released."""
    gate, entered = threading.Event(), threading.Event()

    def held(p: tuple[float, float, float]) -> None:
        entered.set()
        gate.wait(30.0)

    s.kf.add_forbidden_check(held)
    return gate, entered


def _plan_held(s: Session, text: str = "") -> tuple[int, threading.Event]:
    """KeyframePlan sent and the planner thread held inside its checks: (the command's id,
    the gate that releases it)."""
    gate, entered = _hold_planner(s)
    cid = s.slicer.send_command("KeyframePlan", text)
    s.step(1)
    assert entered.wait(30.0)
    return cid, gate


def _add_keyframe_meanwhile(s: Session) -> None:
    added = s.slicer.send_command("KeyframeAdd", xml("KeyframeAdd", T=2.0, Pose="0 0.35 0.05"))
    s.step(1)
    assert s.slicer.reply_to(added).metadata["Status"] == "SUCCESS"  # type: ignore[union-attr]


def _reply_after(s: Session, cid: int, gate: threading.Event) -> Any:
    gate.set()
    assert s.kf.wait_idle(30.0)
    s.step(1)
    reply = s.slicer.reply_to(cid)
    assert reply is not None
    return reply


def test_a_plan_checked_while_the_regions_changed_is_dropped(session: Session) -> None:
    """invalidate_plan while the planner is checking: the plan it finishes is stale (checked
    against the old regions) and is dropped, not previewed."""
    s = session
    s.ok("KeyframeAdd", T=1.0, Pose="0.2 0.35 0.05")
    cid, gate = _plan_held(s)
    s.kf.invalidate_plan("regions changed")
    reply = _reply_after(s, cid, gate)
    assert reply.metadata["Status"] == "FAIL"
    assert reply.metadata["Error"] == (
        "plan 1 dropped: the keyframes changed meanwhile; plan again"
    )
    assert s.kf.plan is None and s.kf.stats()["plan"] is None
    s.start()
    assert "no plan is previewed" in s.refused("KeyframeAck", Plan=1)


def test_a_plan_checked_while_keyframes_and_regions_changed_is_dropped(session: Session) -> None:
    """A keyframe added while the planner works, then the regions changed: still stale."""
    s = session
    s.ok("KeyframeAdd", T=1.0, Pose="0.2 0.35 0.05")
    cid, gate = _plan_held(s)
    _add_keyframe_meanwhile(s)
    s.kf.invalidate_plan("regions changed")
    reply = _reply_after(s, cid, gate)
    assert reply.metadata["Status"] == "FAIL", reply.metadata
    assert "dropped" in reply.metadata["Error"]
    assert s.kf.plan is None


# --------------------------------------------------------------------------- the run


def test_an_ik_failure_during_a_run_stops_it_where_it_is(
    session: Session, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A Cartesian run whose IK fails at run time (checked offline, so only a fault can do
    it): the run is dropped, counted, announced, logged, and the robot holds its last
    setpoint."""
    caplog.set_level(logging.INFO, logger="occ.controllers.keyframe")
    s = session
    s.ok("KeyframeAdd", T=1.0, Pose="-6 30 226", Space="cartesian")
    s.start()
    frame = s.kf.ctx.frame  # type: ignore[union-attr]

    def fails(*args: Any, **kwargs: Any) -> Any:
        raise KinematicsError("injected")

    def ended() -> list[tuple[str, int, str]]:
        return [
            (m.error_name, m.code, m.status_message)  # type: ignore[attr-defined]
            for m in s.slicer.messages("STATUS")
            if m.error_name == "KEYFRAME_ENDED"  # type: ignore[attr-defined]
        ]

    for run in (1, 2):
        plan_id = s.plan_and_ack()
        s.step(300)
        held = list(s.setpoints[-1])
        assert held != HOME
        with monkeypatch.context() as patch:
            patch.setattr(type(frame), "ik_clamped", fails)
            s.step(50)
        assert all(sp == held for sp in s.setpoints[-50:])
        stats = s.kf.stats()
        assert stats["running"] is None and stats["ik_failures"] == run
        text = f"plan {plan_id} stopped at t=0.301 s: tip unreachable"
        assert stats["status"] == text
        assert stats["last_error"] == f"plan {plan_id}: IK failed at t=0.301 s: injected"
        assert ended()[-1] == ("KEYFRAME_ENDED", 15, text)
        assert _logged(caplog, logging.WARNING)[-1] == f"keyframes: {text}"
        assert len(ended()) == run
        assert s.robot.state is RobotState.RUNNING
        s.ok("KeyframeClear")
        s.ok("KeyframeAdd", T=1.0, Pose="-6 30 226", Space="cartesian")
    assert s.kf.stats()["runs_completed"] == 0


# --------------------------------------------------------------------------- where, in words


def test_a_refusal_names_the_keyframe_within_half_a_period_else_the_segment() -> None:
    times, labels = [0.0, 2.0, 3.0], ["A", "B", "C"]
    assert _where(2.0, times, labels, 0.5) == "at B"
    assert _where(0.0, times, labels, 0.5) == "at A"
    assert _where(2.25, times, labels, 0.5) == "at B"  # exactly half a period away
    assert _where(1.75, times, labels, 0.5) == "at B"
    assert _where(2.5, times, labels, 0.5) == "at t=2.500 s, between B and C"
    assert _where(1.5, times, labels, 0.5) == "at t=1.500 s, between A and B"
    assert _where(0.5, times, labels, 0.5) == "at t=0.500 s, between A and B"
    assert _where(2.8, times, labels, 0.5) == "at C"


def test_a_run_ends_in_the_tick_that_commands_its_last_keyframe(session: Session) -> None:
    """The run is over (counted, announced, the controller holds) in the very tick whose
    setpoint is the last keyframe, not a tick later."""
    s = session
    s.ok("KeyframeAdd", T=1.0, Pose="0.2 0.35 0.05")
    s.start()
    s.step(37)
    s.plan_and_ack()  # this tick is t = 0 of the run
    s.step(999)
    assert s.kf.stats()["running"] == 1 and s.setpoints[-1] != [0.2, 0.35, 0.05]
    s.step(1)  # t = 1 s
    assert s.setpoints[-1] == [0.2, 0.35, 0.05]
    stats = s.kf.stats()
    assert stats["running"] is None and stats["runs_completed"] == 1
    assert stats["status"] == "plan 1 completed (1.000 s)"


@pytest.mark.parametrize("end", ["completed", "ik failure", "stopped"])
def test_a_plan_checked_across_a_run_is_dropped(
    session: Session, monkeypatch: pytest.MonkeyPatch, end: str
) -> None:
    """Plan 2 is asked for (and checked from the pose before the run) while plan 1 is
    previewed; plan 1 is acknowledged and runs; a keyframe is added meanwhile; the run ends.
    Plan 2, checked from a pose the robot has left and from keyframes that changed, is
    dropped, not previewed."""
    s = session
    s.ok("KeyframeAdd", T=1.0, Pose="-6 30 226", Space="cartesian")
    s.start()
    s.ok("KeyframePlan")
    s.step(20)
    cid, gate = _plan_held(s, xml("KeyframePlan", Mode="continuous"))
    # the planner is busy: commands answered on the loop, without waiting for it
    ack = s.slicer.send_command("KeyframeAck", xml("KeyframeAck", Plan=1))
    s.step(1)
    assert s.slicer.reply_to(ack).metadata["Message"] == "plan 1 running: 1.000 s"  # type: ignore[union-attr]
    added = s.slicer.send_command(
        "KeyframeAdd", xml("KeyframeAdd", T=2.0, Pose="-6 32 224", Space="cartesian")
    )
    s.step(300)
    assert s.slicer.reply_to(added).metadata["Status"] == "SUCCESS"  # type: ignore[union-attr]
    if end == "ik failure":
        frame = s.kf.ctx.frame  # type: ignore[union-attr]

        def fails(*args: Any, **kwargs: Any) -> Any:
            raise KinematicsError("injected")

        with monkeypatch.context() as patch:
            patch.setattr(type(frame), "ik_clamped", fails)
            s.step(2)
    elif end == "stopped":
        stop = s.slicer.send_command("Stop")
        s.step(2)
        assert s.slicer.reply_to(stop).metadata["Status"] == "SUCCESS"  # type: ignore[union-attr]
    else:
        s.step(800)
    assert s.kf.stats()["running"] is None
    assert s.kf.stats()["status"].startswith("plan 1 ")
    reply = _reply_after(s, cid, gate)
    assert reply.metadata["Status"] == "FAIL", reply.metadata
    assert reply.metadata["Error"] == "plan 2 dropped: the keyframes changed meanwhile; plan again"
    assert s.kf.plan is None


# --------------------------------------------------------------------------- frames


def test_cartesian_keyframes_are_world_positions_on_a_moved_and_turned_base(
    session: Session,
) -> None:
    """The robot's base turned 90 degrees about z and moved (a tracker's pose, world <- base):
    Cartesian keyframes are world millimetres (what 3D Slicer shows), the tip meets them in
    the world, and the preview is drawn in the world too."""
    s = session
    base = np.array(
        [[0.0, -1.0, 0.0, 0.010], [1.0, 0.0, 0.0, -0.020], [0.0, 0.0, 1.0, 0.005], [0, 0, 0, 1]]
    )
    s.robot.data.base = base
    frame = s.robot.frame

    def world_mm(q: list[float]) -> np.ndarray:
        tip = np.asarray(frame.tip_position(q))
        return np.asarray((base[:3, :3] @ tip + base[:3, 3]) / 1e-3)

    target_base_mm = np.array([-12.0, 46.0, 201.0])
    target = (base[:3, :3] @ (target_base_mm * 1e-3) + base[:3, 3]) / 1e-3
    s.ok("KeyframeAdd", T=1.0, Pose=" ".join(f"{v:.9f}" for v in target), Space="cartesian")
    s.start()
    s.ok("KeyframePlan")
    s.step(20)
    (keys,) = s.slicer.messages("POINT", "Keyframes")
    (path,) = s.slicer.messages("POLYDATA", "KeyframePath")
    assert np.allclose(keys.points[0].position, world_mm(HOME), atol=1e-3)
    assert np.allclose(keys.points[1].position, target, atol=1e-3)
    assert np.allclose(path.points[0], world_mm(HOME), atol=1e-3)
    assert np.allclose(path.points[-1], target, atol=1e-3)
    s.setpoints.clear()
    s.ok("KeyframeAck", Plan=1)
    s.step(1100)
    assert np.max(np.abs(world_mm(s.setpoints[1000]) - target)) < 1e-6
    assert s.limit_events() == 0


def test_orientations_on_a_three_joint_arm_are_refused_by_name() -> None:
    s = Session(
        {
            "space": "cartesian",
            "keyframes": [{"t": 1.0, "pose": [-6.0, 30.0, 226.0], "rotation": [0, 0, 0, 1]}],
        }
    )
    try:
        name = s.robot.frame.name
        assert s.refused("KeyframePlan") == (
            f"plan 1 refused: the keyframes have orientations, but {name!r} has 3 joints: "
            "orientation needs a 6-DOF arm"
        )
    finally:
        s.close()


# --------------------------------------------------------------------------- a 6-DOF arm


def _ur5_plan(keyframes: list[dict[str, Any]]) -> dict[str, str]:
    """KeyframePlan on configs/ur5-keyframe.yaml with these keyframes: the reply's metadata."""
    import yaml

    from occ_testkit.testing import CONFIGS, SimRobot

    cfg = yaml.safe_load((CONFIGS / "ur5-keyframe.yaml").read_text())
    params = cfg["controller"]["params"]
    params.update(file=None, keyframe_dir=None, space="cartesian", keyframes=keyframes)
    sim = SimRobot(cfg)
    try:
        op = sim.peer("slicer")
        kf: Any = sim.robot.controller.controllers[0]
        cid = op.send_command("KeyframePlan", "")
        sim.step(1)
        assert kf.wait_idle(60.0)
        sim.step(1)
        reply = op.reply_to(cid)
        assert reply is not None
        return dict(reply.metadata)
    finally:
        sim.close()


def _ur5_home_turned(angle_deg: float) -> tuple[list[float], list[float]]:
    """The UR5's home tip (world mm) and its orientation turned about the tool's z axis."""
    import math

    import pinocchio as pin
    import yaml

    from occ.core.assembly import build_hardware
    from occ.core.loader import load_config
    from occ.samples import rotation_to_quaternion
    from occ_testkit.testing import CONFIGS

    cfg = yaml.safe_load((CONFIGS / "ur5-keyframe.yaml").read_text())
    home_q = [j["home"] for j in cfg["robot"]["joints"]]
    _, frame, _ = build_hardware(load_config(CONFIGS / "ur5.yaml").robot)
    home = np.asarray(frame.fk(home_q))
    turned = home[:3, :3] @ pin.utils.rpyToMatrix(0.0, 0.0, math.radians(angle_deg))
    return (home[:3, 3] * 1e3).tolist(), list(rotation_to_quaternion(turned))


@pytest.mark.parametrize(
    ("t0", "angle", "refused"), [(0.0, 0.0, False), (0.0, 0.4, False), (0.0, 0.8, True)]
)
def test_an_oriented_keyframe_at_t0_must_be_turned_as_the_tool_is(
    t0: float, angle: float, refused: bool
) -> None:
    """start_tolerance_deg (0.5 deg): keyframe 0 at t = 0 turned 0.4 deg from the tool is
    the tool's pose; turned 0.8 deg it is refused with the angle."""
    pos, quat = _ur5_home_turned(angle)
    reply = _ur5_plan(
        [
            {"t": t0, "pose": pos, "rotation": quat, "name": "first"},
            {"t": 2.0, "pose": pos, "rotation": quat},
        ]
    )
    if refused:
        assert reply["Status"] == "FAIL"
        assert reply["Error"] == (
            "plan 1 refused: keyframe 0 'first' (t=0 s) is turned 0.8 deg from the tool "
            "(tolerance 0.5 deg): give keyframe 0 a later time so the robot turns there, or "
            "turn it"
        )
    else:
        assert reply["Status"] == "SUCCESS", reply


def test_an_oriented_first_keyframe_later_than_t0_may_be_turned() -> None:
    """Keyframe 0 at t = 1.5 s turned 20 deg: the robot turns there from where it is."""
    pos, quat = _ur5_home_turned(20.0)
    reply = _ur5_plan([{"t": 1.5, "pose": pos, "rotation": quat}])
    assert reply["Status"] == "SUCCESS", reply


# --------------------------------------------------------------------------- the start


def test_a_keyframe_at_t0_is_within_its_own_spaces_tolerance(session: Session) -> None:
    """start_tolerance_mm (0.5 mm) for Cartesian keyframes, start_tolerance (1e-3 rad or m)
    for joint ones, each with its unit; within it keyframe 0 is replaced by the robot's pose."""
    s = session
    tip_mm = np.asarray(s.robot.frame.tip_position(HOME)) / 1e-3

    def cartesian_at(dx_mm: float) -> str:
        p = tip_mm + np.array([dx_mm, 0.0, 0.0])
        s.ok("KeyframeClear")
        s.ok("KeyframeAdd", T=0.0, Pose=" ".join(f"{v:.9f}" for v in p), Space="cartesian")
        s.ok("KeyframeAdd", T=1.0, Pose="-6 30 226", Space="cartesian")
        meta = s.cmd("KeyframePlan").metadata
        return str(meta.get("Error") or meta["Message"])

    assert "keyframe 0 replaced by the robot's pose (0.3 mm away)" in cartesian_at(0.3)
    assert cartesian_at(0.8).endswith(
        "keyframe 0 (t=0 s) is 0.8 mm from where the robot is (tolerance 0.5): a run starts "
        "where the robot is; give keyframe 0 a later time so the robot moves there, or move it"
    )
    s.ok("KeyframeClear")
    s.ok("KeyframeAdd", T=0.0, Pose="0.0008 0.35 0.05")
    s.ok("KeyframeAdd", T=1.0, Pose="0.2 0.35 0.05")
    assert "keyframe 0 replaced by the robot's pose (0.0008 rad/m away)" in s.ok("KeyframePlan")
    s.ok("KeyframeClear")
    s.ok("KeyframeAdd", T=0.0, Pose=" ".join(map(str, HOME)))  # exactly there: nothing to say
    s.ok("KeyframeAdd", T=1.0, Pose="0.2 0.35 0.05")
    assert "replaced" not in s.ok("KeyframePlan")
    s.ok("KeyframeClear")
    s.ok("KeyframeAdd", T=0.0, Pose="0.0012 0.35 0.05")
    s.ok("KeyframeAdd", T=1.0, Pose="0.2 0.35 0.05")
    assert s.refused("KeyframePlan").endswith(
        "keyframe 0 (t=0 s) is 0.0012 rad/m from where the robot is (tolerance 0.001): a run "
        "starts where the robot is; give keyframe 0 a later time so the robot moves there, or "
        "move it"
    )


@pytest.mark.parametrize(("last", "refused"), [(10.0, False), (12.0, True)])
def test_a_plan_longer_than_max_duration_is_refused(last: float, refused: bool) -> None:
    s = Session(
        {
            "max_duration_s": 10.0,
            "keyframes": [
                {"t": 3.0, "pose": [0.2, 0.35, 0.05], "name": "there"},
                {"t": last, "pose": [0.0, 0.35, 0.05], "name": "back"},
            ],
        }
    )
    try:
        if refused:
            assert s.refused("KeyframePlan") == (
                "plan 1 refused: keyframe 1 'back' (t=12 s): the plan would last 12 s, more "
                "than max_duration_s (10)"
            )
        else:  # exactly the longest accepted
            assert "10.000 s" in s.ok("KeyframePlan")
    finally:
        s.close()


def test_the_plan_uses_the_ramp_asked_for_and_reports_its_peak_speed(session: Session) -> None:
    """KeyframePlan Ramp=0.4: the area rule with t_a = 0.4 T on the setpoints; the summary
    names the joint closest to its velocity limit and the share it uses; the preview path
    ends once, on the last keyframe."""
    s = session
    s.ok("KeyframeAdd", T=2.0, Pose="0.4 0.35 0.05")
    s.start()
    summary = s.ok("KeyframePlan", Ramp=0.4)
    # cruise v0 = D / (T - t_a) = 0.4 / 1.2 rad/s: 22 % of the 1.5 rad/s of yaw
    assert summary == (
        "plan 1: 1 keyframes (joint, linear, stop), 2.000 s; peak joint speed 22% of the limit "
        "(yaw); preview on its way to the viewers; acknowledge with KeyframeAck Plan=1"
    )
    s.step(20)
    (path,) = s.slicer.messages("POLYDATA", "KeyframePath")
    pts = np.asarray(path.points)
    assert not np.any(np.all(pts[1:] == pts[:-1], axis=1))  # no point twice in a row
    s.setpoints.clear()
    s.ok("KeyframeAck", Plan=1)
    s.step(2100)
    yaw = np.array(s.setpoints)[:, 0]
    ta, v0 = 0.8, 0.4 / 1.2
    assert yaw[800] == pytest.approx(ta * v0 / 2, rel=1e-12)  # the area rule at t_a


def test_the_last_keyframe_itself_is_checked(session: Session) -> None:
    """A forbidden region that holds the last keyframe's tip and nothing before it: the
    check reaches the end of the plan, not one period short of it."""
    s = session
    final = (0.3, 0.4, 0.07)
    end_tip = tuple(float(v) for v in s.robot.frame.tip_position(list(final)))
    s.kf.add_forbidden_check(lambda p: "the target" if tuple(p) == end_tip else None)
    s.ok("KeyframeAdd", T=1.0, Pose=" ".join(map(str, final)), Label="last")
    assert "forbidden region (the target) at keyframe 0 'last' (t=1 s)" in s.refused("KeyframePlan")


@pytest.mark.parametrize(
    ("duration", "points"), [(0.2, 201), (1.019, 256), (1.021, None), (2.041, None)]
)
def test_the_preview_has_every_tick_when_it_fits_and_never_more_than_preview_points(
    session: Session, duration: float, points: int | None
) -> None:
    """preview_points (256): a plan of 201 ticks is drawn tick by tick; longer ones are
    decimated to at most 256 points (1021 and 2041 ticks: where a stride one smaller would
    give 257), the last keyframe always the last point. The stride is the smallest that fits:
    1020 samples (255 strides of 4) give 255 points and the last, where a stride of 5 would
    give 205."""
    s = session
    s.ok("KeyframeAdd", T=duration, Pose="0.02 0.36 0.05")
    s.ok("KeyframePlan")
    s.step(20)
    (path,) = s.slicer.messages("POLYDATA", "KeyframePath")
    n = len(path.points)
    assert n == points if points is not None else 200 <= n <= 256, n
    end = np.asarray(s.robot.frame.tip_position([0.02, 0.36, 0.05])) / 1e-3
    assert np.allclose(path.points[-1], end, atol=1e-6)


def test_an_ik_that_fails_while_checking_refuses_the_plan_naming_where(
    session: Session, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The IK raising (a DLS that does not converge, say) at some tick of a Cartesian plan:
    refused, naming the segment and the IK's reason; nothing is previewed."""
    s = session
    frame_type = type(s.robot.frame)
    solve = frame_type.ik_clamped
    calls = {"n": 0}

    def fails_later(self: Any, *args: Any, **kwargs: Any) -> Any:
        calls["n"] += 1
        if calls["n"] > 500:
            raise KinematicsError("did not converge")
        return solve(self, *args, **kwargs)

    s.ok("KeyframeAdd", T=1.0, Pose="-6 30 226", Space="cartesian", Label="entry")
    monkeypatch.setattr(frame_type, "ik_clamped", fails_later)
    assert s.refused("KeyframePlan") == (
        "plan 1 refused: the tip is unreachable at t=0.500 s, between the start (the robot's "
        "pose) and keyframe 0 'entry' (t=1 s): did not converge"
    )
    assert s.kf.plan is None


def test_a_cartesian_refusal_names_where_the_tip_leaves_and_the_joint_at_its_limit(
    session: Session,
) -> None:
    s = session
    s.ok("KeyframeAdd", T=20.0, Pose="0 24 400", Space="cartesian", Label="far")
    assert s.refused("KeyframePlan") == (
        "plan 1 refused: the tip leaves the workspace at t=7.056 s, between the start (the "
        "robot's pose) and keyframe 0 'far' (t=20 s): (0.00, 24.00, 284.59) mm needs joint "
        "pitch beyond its limits"
    )
    s.ok("KeyframeClear")
    s.ok("KeyframeAdd", T=20.0, Pose="0 -24 400", Space="cartesian", Label="far")
    assert s.refused("KeyframePlan") == (
        "plan 2 refused: the tip leaves the workspace at t=6.883 s, between the start (the "
        "robot's pose) and keyframe 0 'far' (t=20 s): (0.00, 9.98, 282.68) mm needs joint "
        "insertion beyond its limits"
    )


def test_a_joint_plan_may_reach_its_limits_but_not_pass_them(session: Session) -> None:
    s = session
    s.ok("KeyframeAdd", T=3.0, Pose="1.0 0.35 0.0", Label="at both")  # yaw max, insertion min
    assert "plan 1:" in s.ok("KeyframePlan")
    s.ok("KeyframeClear")
    s.ok("KeyframeAdd", T=3.0, Pose="-1.05 0.35 0.05", Label="below")
    error = s.refused("KeyframePlan")
    assert error.startswith("plan 2 refused: joint 'yaw' position -1") and (
        "is outside its limits [-1, 1] at t=" in error
    ), error


def test_a_plan_may_use_exactly_the_velocity_limit_and_is_refused_past_it(
    session: Session,
) -> None:
    s = session
    # pitch 0.45 rad in 0.4 s: cruise D / (T - t_a) = 0.45 / 0.3 = 1.5 rad/s, its limit
    s.ok("KeyframeAdd", T=0.4, Pose="0.0 0.8 0.05", Label="fast")
    assert "peak joint speed 100% of the limit (pitch)" in s.ok("KeyframePlan")
    s.ok("KeyframeClear")
    s.ok("KeyframeAdd", T=1.0, Pose="0.0 0.35 0.05", Label="a")
    s.ok("KeyframeAdd", T=1.5, Pose="0.0 0.35 0.12", Label="deep")
    assert s.refused("KeyframePlan") == (
        "plan 2 refused: joint 'insertion' velocity 0.1023 exceeds its limit 0.1 at t=1.065 s, "
        "between keyframe 0 'a' (t=1 s) and keyframe 1 'deep' (t=1.5 s); give that segment "
        "more time"
    )


def test_the_workspace_box_checks_each_axis_against_its_own_bounds() -> None:
    """A box narrow in x and wide in y: a tip at y = 30 mm is inside it (y's bounds), though
    30 is outside x's."""
    s = Session({"workspace_mm": {"min_mm": [-20.0, 0.0, 150.0], "max_mm": [20.0, 60.0, 300.0]}})
    try:
        s.ok("KeyframeAdd", T=2.0, Pose="-6 30 226", Space="cartesian")
        assert "plan 1:" in s.ok("KeyframePlan")
    finally:
        s.close()


def test_workspace_and_forbidden_refusals_say_where_and_what() -> None:
    s = Session(
        {
            "workspace_mm": {"min_mm": [-50.0, -50.0, 150.0], "max_mm": [50.0, 50.0, 300.0]},
            "forbidden": [
                {"centre_mm": [-6.0, 35.0, 218.0], "radius_mm": 5.0, "name": "vessel"},
                {"point_mm": [0.0, 0.0, 150.0], "normal": [0.0, 0.0, 2.0], "name": "table"},
            ],
        }
    )
    try:
        s.ok("KeyframeAdd", T=2.0, Pose="-12 46 140", Space="cartesian", Label="low")
        assert s.refused("KeyframePlan") == (
            "plan 1 refused: the tip leaves workspace_mm at t=1.592 s, between the start (the "
            "robot's pose) and keyframe 0 'low' (t=2 s): (-10.73, 43.67, 149.96) mm"
        )
        s.ok("KeyframeClear")
        s.ok("KeyframeAdd", T=2.0, Pose="-6 30 226", Space="cartesian", Label="entry")
        s.ok("KeyframeAdd", T=4.0, Pose="-12 46 201", Space="cartesian", Label="target")
        assert s.refused("KeyframePlan") == (
            "plan 2 refused: the tip enters a forbidden region (forbidden sphere 'vessel') at "
            "t=2.479 s, between keyframe 0 'entry' (t=2 s) and keyframe 1 'target' (t=4 s): "
            "(-6.92, 32.44, 222.18) mm"
        )
        # a check that answers True (no description): the refusal says no more than that
        s.kf.add_forbidden_check(lambda p: True if p[2] < 0.2 else None)
        s.ok("KeyframeClear")
        s.ok("KeyframeAdd", T=2.0, Pose="-6 30 190", Space="cartesian", Label="deep")
        assert s.refused("KeyframePlan") == (
            "plan 3 refused: the tip enters a forbidden region at t=1.411 s, between the start "
            "(the robot's pose) and keyframe 0 'deep' (t=2 s): (-4.64, 28.64, 200.00) mm"
        )
    finally:
        s.close()


def test_a_new_set_is_counted_and_drops_a_plan_being_checked(session: Session) -> None:
    s = session
    assert s.kf.stats()["status"] == "no keyframes" and s.kf.stats()["sets"] == 0
    s.ok("KeyframeAdd", T=1.0, Pose="0.2 0.35 0.05")
    stats = s.kf.stats()
    assert stats["sets"] == 1
    assert stats["status"] == "1 keyframes from operator commands; send KeyframePlan"
    cid, gate = _plan_held(s)
    _add_keyframe_meanwhile(s)
    reply = _reply_after(s, cid, gate)
    assert reply.metadata["Error"] == "plan 1 dropped: the keyframes changed meanwhile; plan again"
    assert s.kf.plan is None and s.kf.stats()["sets"] == 2
    s.ok("KeyframeClear")
    assert s.kf.stats()["status"] == "no keyframes" and s.kf.stats()["sets"] == 2


def test_every_stop_of_a_run_is_counted_said_and_logged(
    session: Session, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="occ.controllers.keyframe")
    s = session
    s.ok("KeyframeAdd", T=1.0, Pose="0.2 0.35 0.05")
    s.start()
    for run in (1, 2):
        plan_id = s.plan_and_ack()
        s.step(250)
        s.ok("Stop")
        text = (
            f"plan {plan_id} stopped at t=0.251 s of 1.000 s (RUNNING -> STOPPED); the robot "
            "holds there; plan again to run the keyframes"
        )
        assert s.kf.stats()["status"] == text
        assert s.kf.stats()["runs_stopped"] == run
        assert _logged(caplog, logging.WARNING)[-1] == f"keyframes: {text}"
        s.ok("Run")


def test_a_keyframe_set_is_refused_with_the_reason() -> None:
    from occ.controllers.keyframe.sets import make_set

    def error(space: Any, items: Any, cap: int = 4) -> str:
        with pytest.raises(ValueError) as info:
            make_set(space, items, "test", joints=3, max_keyframes=cap)
        return str(info.value)

    q = (0.0, 0.0, 0.0, 1.0)
    assert error("joint", []) == "no keyframes"
    # exactly max_keyframes is a set; one more is not
    full = [(float(i + 1), [0.0, 0.0, 0.0], "") for i in range(4)]
    assert len(make_set("joint", full, "test", joints=3, max_keyframes=4).keyframes) == 4
    assert error("joint", full, cap=3) == "4 keyframes, more than max_keyframes (3)"
    assert error("joint", [(1.0, [0, 0, 0], "", q)]) == (
        "keyframe 0: a rotation needs Cartesian keyframes"
    )
    assert error("cartesian", [(1.0, [0, 0, 0], "", q), (2.0, [0, 0, 1], "")]) == (
        "keyframe 1: every keyframe of a set has a rotation, or none has"
    )
    assert error("cartesian", [(1.0, [0, 0], "")]) == (
        "keyframe 0: 2 values, a cartesian pose needs x y z (mm)"
    )
    assert error("joint", [(1.0, [0, 0], "")]) == (
        "keyframe 0: 2 values, a joint pose needs 3 joint positions"
    )
    assert error("joint", [(-1.0, [0, 0, 0], "")]) == (
        "keyframe 0: time -1 s is before the start (t = 0)"
    )


# ------------------------------------------------------------- KeyframePlan's arguments
def test_the_plans_steepness_and_ramp_are_checked_at_their_edges(session: Session) -> None:
    s = session
    s.ok("KeyframeAdd", T=1.0, Pose="0.2 0.35 0.05")
    assert s.refused("KeyframePlan", Steepness="inf") == "Steepness must be > 0, got inf"
    assert s.refused("KeyframePlan", Steepness=0) == "Steepness must be > 0, got 0"
    assert s.refused("KeyframePlan", Steepness="steep") == (
        "KeyframePlan: could not convert string to float: 'steep'"
    )
    assert s.refused("KeyframePlan", Ramp=0) == "Ramp must be in (0, 0.5], got 0"
    assert s.refused("KeyframePlan", Ramp=0.51) == "Ramp must be in (0, 0.5], got 0.51"
    assert "plan 1:" in s.ok("KeyframePlan", Steepness=0.5)  # a gentle sigmoid is a sigmoid
    assert "plan 2:" in s.ok("KeyframePlan", Ramp=0.5, Mode="continuous")
    assert s.kf.stats()["plans_checked"] == 2


def test_every_refused_plan_is_counted_and_said_in_the_stats(session: Session) -> None:
    s = session
    s.ok("KeyframeAdd", T=0.01, Pose="0.9 0.35 0.05")  # far too fast for yaw
    first = s.refused("KeyframePlan")
    assert first.startswith("plan 1 refused: ")
    second = s.refused("KeyframePlan")
    assert second.startswith("plan 2 refused: ")
    stats = s.kf.stats()
    assert stats["plans_refused"] == 2 and stats["plans_checked"] == 0
    assert stats["last_error"] == second and stats["status"] == second


def test_the_workspace_box_upper_bounds_are_millimetres() -> None:
    s = Session({"workspace_mm": {"min_mm": [-50.0, -50.0, 150.0], "max_mm": [5.0, 50.0, 300.0]}})
    try:
        s.ok("KeyframeAdd", T=2.0, Pose="10 30 226", Space="cartesian", Label="east")
        assert "leaves workspace_mm" in s.refused("KeyframePlan")
    finally:
        s.close()


def test_a_configured_forbidden_sphere_is_where_the_config_puts_it() -> None:
    s = Session({"forbidden": [{"centre_mm": [100.0, 0.0, 0.0], "radius_mm": 0.05}]})
    try:
        (check, *_) = s.kf.forbidden_checks
        assert check((0.1, 0.0, 0.0)) is not None  # its centre, in metres
        assert check((0.10006, 0.0, 0.0)) is None  # 0.06 mm off: outside its 0.05 mm
    finally:
        s.close()


def test_keyframes_from_a_cartesian_file_are_read_as_cartesian(tmp_path: Any) -> None:
    f = tmp_path / "kf.yaml"
    f.write_text("keyframes:\n  - {t: 2.0, pose: [-6, 30, 226]}\n")
    s = Session({"file": str(f), "space": "cartesian"})
    try:
        assert s.kf.stats()["space"] == "cartesian"
        assert "plan 1:" in s.ok("KeyframePlan")
    finally:
        s.close()


def test_a_controller_dropped_without_shutdown_ends_its_planner_thread() -> None:

    s = Session()
    try:
        ctrl = KeyframeController({})
        ctrl.configure(s.robot.data, s.kf.ctx)
        assert ctrl._planner is not None
        thread = ctrl._planner._thread
        del ctrl
        gc.collect()
        thread.join(timeout=10.0)  # a bound, not a timing: it ends at once when told
        assert not thread.is_alive()
    finally:
        s.close()


def test_without_joint_limits_in_the_context_the_models_own_bound_the_plan() -> None:
    s = Session()
    try:
        ctx = s.kf.ctx
        assert ctx is not None
        bare = dataclasses.replace(ctx, joint_limits=())  # a controller used on its own
        ctrl = KeyframeController({})
        ctrl.configure(s.robot.data, bare)
        frame = ctx.frame
        assert [(lim.min, lim.max) for lim in ctrl.limits] == list(
            zip(frame.lower.tolist(), frame.upper.tolist(), strict=True)
        )
        ctrl.shutdown()
    finally:
        s.close()


def test_what_keyframeplan_says_when_it_cannot_plan(session: Session) -> None:
    s = session
    assert s.refused("KeyframePlan") == "no keyframes to plan: load or send some first"
    s.ok("KeyframeAdd", T=1.0, Pose="0.2 0.35 0.05")
    assert s.refused("KeyframePlan", Interpolation="cubic") == (
        "Interpolation must be linear or spline, got 'cubic'"
    )
    assert s.refused("KeyframePlan", Mode="loop") == "Mode must be stop or continuous, got 'loop'"
    s.ok("KeyframePlan")
    assert s.kf.stats()["status"] == "plan 1 previewed; KeyframeAck Plan=1 runs it"
    s.step(20)
    s.start()
    s.ok("KeyframeAck", Plan=1)
    assert s.refused("KeyframePlan") == "plan 1 is running; wait or Stop"


def test_keyframes_in_the_config_are_said_to_come_from_the_config() -> None:
    s = Session({"keyframes": [{"t": 1.0, "pose": [0.2, 0.35, 0.05]}]})
    try:
        assert s.kf.stats()["source"] == "config"
        assert "keyframes: 1 joint from config" in s.kf.describe()
    finally:
        s.close()


def test_while_the_loop_runs_the_planner_works_only_in_the_quiet_part_of_its_period() -> None:
    """A plan checked while the control loop runs is paced (keyframe.Pacer): the planner
    thread waits for the quiet part of each 1 ms period before it takes the interpreter, so
    the loop's tick never waits for it; operators see the waits in the controller's
    `planner_waits`. Stepped without a loop (t0 NaN) there is no period to keep out of."""
    s = Session({"keyframes": [{"t": 1.0, "pose": [0.2, 0.35, 0.05]}]})
    try:
        s.ok("Enable")
        s.ok("KeyframePlan")
        assert s.kf.stats()["planner_waits"] == 0  # no loop runs: nothing to wait for
        # the loop runs from now, on the real clock the planner's pacer reads
        s.robot.loop.t0 = time.perf_counter()
        s.ok("KeyframePlan")
        stats = s.kf.stats()
        assert stats["plans_checked"] == 2
        waits = stats["planner_waits"]
        assert waits >= 1
        # the loop stopped: a plan checked now waits for nothing; the count is the run's total
        s.robot.loop.t0 = math.nan
        s.ok("KeyframePlan")
        assert s.kf.stats()["planner_waits"] == waits
    finally:
        s.close()


# --------------------------------------------------------------------------- one tick's checks
# _TickChecks and pose_ik called directly: the edges of their tolerances and the refusals'
# words for inputs the daemon's plans rarely produce (a tip off the x = 0 plane, two joints
# at their limits at once, a residual exactly at the bound)


def _tick_checks(**over: Any) -> _TickChecks:
    fields: dict[str, Any] = {
        "joint_names": ("a", "b"),
        "limits": (JointLimits(-1.0, 1.0, 2.0), JointLimits(-0.5, 0.5, 4.0)),
        "velocity_scale": 1.0,
        "period": 0.001,
        "port": None,
        "port_min_depth": 0.01,
        "workspace": None,
        "forbidden": (),
    }
    fields.update(over)
    return _TickChecks(SimpleNamespace(**fields), [0.0, 1.0], ["K0", "K1"])  # type: ignore[arg-type]


def test_a_joint_sample_within_the_rounding_margin_of_a_limit_passes() -> None:
    checks = _tick_checks()
    checks.joints(0.5, [-1.0 - 1e-12, 0.5 + 1e-12])  # the margin itself: within
    checks.joints(0.5, [1.0 + 1e-12, -0.5 - 1e-12])
    with pytest.raises(PlanRefused) as low:
        checks.joints(0.5, [math.nextafter(-1.0 - 1e-12, -2.0), 0.0])
    assert str(low.value) == (
        "joint 'a' position -1 is outside its limits [-1, 1] at t=0.500 s, between K0 and K1"
    )
    with pytest.raises(PlanRefused) as high:
        checks.joints(1.0, [0.0, math.nextafter(0.5 + 1e-12, 1.0)])
    assert str(high.value) == "joint 'b' position 0.5 is outside its limits [-0.5, 0.5] at K1"


def test_a_clamped_sample_names_every_joint_at_a_limit_and_the_tip_in_mm() -> None:
    checks = _tick_checks()
    with pytest.raises(PlanRefused) as both:
        checks.clamped(0.0, (0.0125, -0.25, 0.5), [-1.0 + 1e-12, 0.5 - 1e-12])
    assert str(both.value) == (
        "the tip leaves the workspace at K0: (12.50, -250.00, 500.00) mm needs joint a, b "
        "beyond its limits"
    )
    with pytest.raises(PlanRefused) as upper:
        checks.clamped(1.0, (0.001, 0.002, 0.003), [0.0, 0.5 - 1e-12])
    assert str(upper.value).endswith("(1.00, 2.00, 3.00) mm needs joint b beyond its limits")
    # just inside both margins: the IK said clamped but no joint is at a limit
    inside = [math.nextafter(-1.0 + 1e-12, 0.0), math.nextafter(0.5 - 1e-12, 0.0)]
    with pytest.raises(PlanRefused) as none:
        checks.clamped(1.0, (0.0, 0.0, 0.0), inside)
    assert str(none.value).endswith("(0.00, 0.00, 0.00) mm needs joint ? beyond its limits")


class _FakeIK:
    """A frame whose DLS answer is set by the test (residual, clamped)."""

    def __init__(self, error: float, clamped: list[int]) -> None:
        self.error, self.clamped = error, clamped
        self.asked: list[tuple[np.ndarray, list[float], dict[str, Any]]] = []

    def solve_ik(self, pose: np.ndarray, seed: list[float], **kw: Any) -> Any:
        self.asked.append((pose, seed, kw))
        return SimpleNamespace(q=np.array([0.25, -0.5]), error=self.error, clamped=self.clamped)


class _StillTraj:
    def position(self, t: float) -> np.ndarray:
        return np.array([0.1, 0.2, 0.3])

    def orientation(self, t: float) -> np.ndarray:
        return np.array([0.0, 0.0, math.sin(0.25), math.cos(0.25)])  # 0.5 rad about z


def test_pose_ik_accepts_a_residual_of_exactly_its_bound_and_refuses_more() -> None:
    traj: Any = _StillTraj()
    frame = _FakeIK(1e-6, [])
    assert pose_ik(frame, traj, 0.0, (0.0, 0.0)) == ([0.25, -0.5], False)  # type: ignore[arg-type]
    ((pose, seed, kw),) = frame.asked
    assert seed == [0.0, 0.0] and kw == {"clamp": True, "method": "dls"}
    assert pose[:3, 3].tolist() == [0.1, 0.2, 0.3]
    c, s_ = math.cos(0.5), math.sin(0.5)
    assert np.allclose(pose[:3, :3], [[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]], atol=1e-15)
    with pytest.raises(KinematicsError, match=r"the pose is not reached \(residual 1e-06\)"):
        pose_ik(_FakeIK(math.nextafter(1e-6, 1.0), []), traj, 0.0, (0.0, 0.0))  # type: ignore[arg-type]
    # a residual left by a joint held at its limit is the clamp's, said by the caller
    assert pose_ik(_FakeIK(0.5, [1]), traj, 0.0, (0.0, 0.0)) == ([0.25, -0.5], True)  # type: ignore[arg-type]


def test_the_tip_may_come_to_exactly_the_ports_least_depth_and_no_closer() -> None:
    checks = _tick_checks(port=np.array([0.0, 0.0, 0.0]), port_min_depth=0.01)
    checks.depth(0.0, (0.01, 0.0, 0.0))
    with pytest.raises(PlanRefused) as near:
        checks.depth(1.0, (0.0, 0.0, 0.005))
    assert str(near.value) == (
        "the tip comes 5 mm from the port at K1, closer than rcm_min_depth_mm (10)"
    )
    _tick_checks().depth(0.0, (0.0, 0.0, 0.0))  # no port: no depth to keep


def test_a_step_of_exactly_the_velocity_limit_passes_and_the_first_joint_wins_a_tie() -> None:
    still = _tick_checks()
    still.step(0.0, [0.0, 0.0], [0.0, 0.0])  # a plan that moves no joint names the first
    assert (still.peak_joint, still.peak_share) == (0, 0.0)
    checks = _tick_checks(period=1.0)
    # joint a: 2 rad/s is its limit, joint b: 4 rad/s; both at half theirs: the first is named
    checks.step(0.0, [1.0, 2.0], [0.0, 0.0])
    assert (checks.peak_joint, checks.peak_share) == (0, 0.5)
    checks.step(0.0, [1.0, 0.0], [0.0, 2.0])  # b's half again, from the other side
    assert (checks.peak_joint, checks.peak_share) == (0, 0.5)
    checks.step(0.0, [0.0, 2.0 + 1e-9], [0.0, 0.0])  # b a little more: b is the peak
    assert checks.peak_joint == 1
    checks.step(0.0, [2.0 * (1.0 + 1e-9), 0.0], [0.0, 0.0])  # the rounding margin itself
    assert (checks.peak_joint, checks.peak_share) == (0, 1.0 + 1e-9)
    with pytest.raises(PlanRefused) as fast:
        checks.step(1.0, [0.0, math.nextafter(-4.0 * (1.0 + 1e-9), -5.0)], [0.0, 0.0])
    assert str(fast.value) == (
        "joint 'b' velocity 4 exceeds its limit 4 at K1; give that segment more time"
    )
    scaled = _tick_checks(period=1.0, velocity_scale=0.5)
    with pytest.raises(PlanRefused) as slow:
        scaled.step(0.5, [1.5, 0.0], [0.0, 0.0])
    assert str(slow.value) == (
        "joint 'a' velocity 1.5 exceeds its limit 1 (velocity_scale 0.5 of 2) at K0; give that "
        "segment more time"
    )
    assert (scaled.peak_joint, scaled.peak_share) == (0, 0.75)  # of the unscaled limit


def test_the_workspace_box_is_closed_and_a_forbidden_region_says_what_it_hits() -> None:
    box = ((-0.1, -0.2, -0.3), (0.1, 0.2, 0.3))
    checks = _tick_checks(workspace=box)
    for corner in [(-0.1, -0.2, -0.3), (0.1, 0.2, 0.3), (-0.1, 0.2, -0.3), (0.1, -0.2, 0.3)]:
        checks.tip(0.0, corner)
    for axis in range(3):
        for side, sign in ((0, -1.0), (1, 1.0)):
            tip = [0.0, 0.0, 0.0]
            tip[axis] = math.nextafter(box[side][axis], sign)
            with pytest.raises(PlanRefused, match=r"^the tip leaves workspace_mm at K0: \("):
                checks.tip(0.0, (tip[0], tip[1], tip[2]))
    with pytest.raises(PlanRefused) as out:
        checks.tip(1.0, (0.0125, 0.0, 0.5))
    assert str(out.value) == "the tip leaves workspace_mm at K1: (12.50, 0.00, 500.00) mm"
    regions = (lambda p: None, lambda p: "the table" if p[2] < 0.0 else False, lambda p: True)
    named = _tick_checks(forbidden=regions[:2])
    named.tip(0.0, (0.0, 0.0, 0.0))
    with pytest.raises(PlanRefused) as hit:
        named.tip(1.0, (0.0125, 0.002, -0.003))
    assert str(hit.value) == (
        "the tip enters a forbidden region (the table) at K1: (12.50, 2.00, -3.00) mm"
    )
    with pytest.raises(PlanRefused) as unnamed:
        _tick_checks(forbidden=regions).tip(0.0, (0.0, 0.0, 0.0))
    assert str(unnamed.value) == "the tip enters a forbidden region at K0: (0.00, 0.00, 0.00) mm"


def test_an_acknowledgement_is_ready_only_seen_running_and_within_1e_9_of_the_start() -> None:
    plan: Any = SimpleNamespace(id=7, q_start=(0.0, 0.0))

    def data(state: str, setpoint: list[float]) -> Any:
        return SimpleNamespace(state=SimpleNamespace(value=state), setpoint=setpoint)

    ack_ready(plan, data("RUNNING", [1e-9, 0.0]), False)  # the tolerance itself
    ack_ready(plan, data("RUNNING", [0.0, -1e-9]), False)
    with pytest.raises(CommandError) as moved:
        ack_ready(plan, data("RUNNING", [0.0, math.nextafter(-1e-9, -1.0)]), False)
    assert str(moved.value) == (
        "KeyframeAck: the robot moved since plan 7 was checked (1e-09 rad/m); plan again"
    )
    with pytest.raises(CommandError) as stopped:
        ack_ready(plan, data("FAULT", [0.0, 0.0]), False)
    assert str(stopped.value) == (
        "KeyframeAck: the robot is FAULT; send Run first (it holds until a plan is acknowledged)"
    )
    with pytest.raises(CommandError) as unseen:
        ack_ready(plan, data("RUNNING", [0.0, 0.0]), True)
    assert str(unseen.value) == (
        "KeyframeAck: plan 7 has not been previewed yet (its preview goes out with the next "
        "keyframe-path output); look at it, then acknowledge"
    )


def test_a_run_tick_the_ik_clamps_holds_the_last_joints_and_counts_an_ik_failure() -> None:
    """Checked offline, a run's tick could still clamp at a joint limit if the IK were
    seeded differently: the tick holds the last joints and names the counter and the status
    the run ends with (no error of its own: the clamp is not an exception)."""

    class Clamps:
        def ik_clamped(self, tip: tuple[float, float, float], seed: list[float]) -> Any:
            return [9.0, 9.0], True

    traj = SimpleNamespace(position=lambda t: np.array([0.1, 0.2, 0.3]), has_rotation=False)
    run: Any = SimpleNamespace(id=4, space="cartesian", traj=traj)
    q, why = run_tick(Clamps(), run, 0.5, [0.25, -0.5])  # type: ignore[arg-type]
    assert q == [0.25, -0.5]
    assert why == ("ik_failures", "tip unreachable", None)


def test_the_plan_an_acknowledgement_runs_is_noted_for_the_black_box(session: Session) -> None:
    """The loop runs the planner's result from the acknowledged tick: the black box is told
    which plan, from when and for how long (a replay runs the same plan from the record)."""
    s = session
    notes: list[tuple[str, Any]] = []
    assert s.kf.ctx is not None
    s.kf.ctx = dataclasses.replace(s.kf.ctx, note=lambda what, obj: notes.append((what, obj)))
    s.start()
    s.ok("KeyframeAdd", T=1.0, Pose="0.2 0.35 0.05")
    s.plan_and_ack()
    assert notes == [("plan", {"id": 1, "t0": s.kf._t0, "duration": 1.0})]
    s.step(1100)
    assert len(notes) == 1  # a run is noted once, at its start


def test_a_run_tick_through_a_port_holds_at_most_the_shafts_bound_from_it() -> None:
    """A port plan's tick whose joints put the shaft exactly SHAFT_BOUND_M (0.05 mm) from the
    port runs; a little more stops the run, saying how far in mm (port_stops)."""
    turn = np.array([0.0, 0.0, 0.0, 1.0])
    port = np.array([0.0, 0.0, 0.1])
    frames = [Keyframe(0.0, np.zeros(3), turn), Keyframe(1.0, np.array([0.0, 0.0, -0.01]), turn)]
    traj = port_plan(frames, port)

    class Tool:
        """Any pose is reached; the tool's pose (axis down, past the port) is set by the test."""

        off = 0.0

        def solve_ik(self, pose: np.ndarray, seed: list[float], **kw: Any) -> Any:
            return SimpleNamespace(q=np.array([0.5, 0.5]), error=0.0, clamped=[])

        def fk(self, q: list[float]) -> np.ndarray:
            pose = np.diag([1.0, -1.0, -1.0, 1.0])
            pose[0, 3] = self.off
            return pose

    tool = Tool()
    run: Any = SimpleNamespace(id=6, space="cartesian", traj=traj)
    tool.off = SHAFT_BOUND_M
    assert run_tick(tool, run, 0.5, [0.0, 0.0]) == ([0.5, 0.5], None)  # type: ignore[arg-type]
    tool.off = 0.0001
    q, why = run_tick(tool, run, 0.5, [0.0, 0.0])  # type: ignore[arg-type]
    text = "the tool's shaft 0.1 mm from the port (bound 0.05 mm)"
    assert q == [0.0, 0.0]
    assert why == ("port_stops", text, f"plan 6: {text} at t=0.500 s")


def test_a_plan_through_a_port_is_timed_with_the_steepness_and_ramp_asked_for() -> None:
    from .test_keyframe_port import _request, _side_set

    frame, home_q, _, port, kset = _side_set(5.0, 0.5)
    req = dataclasses.replace(_request(frame, home_q, kset, port), steepness=3.0, ramp=0.4)
    traj = build_plan(req, frame.copy()).traj
    assert isinstance(traj, PortTrajectory)
    assert (traj.interpolation, traj.mode, traj.steepness, traj.ramp) == (
        "linear",
        "stop",
        3.0,
        0.4,
    )
    # what the planner itself refuses (KeyframePlan's own check comes first) is a refusal
    with pytest.raises(PlanRefused, match=r"^cannot plan: .*steepness") as bad:
        build_plan(dataclasses.replace(req, steepness=-1.0), frame.copy())
    assert isinstance(bad.value.__cause__, ValueError)


def test_the_whole_arm_check_is_given_every_sample_the_base_and_the_planners_pacer(
    session: Session,
) -> None:
    """A PathCheck gets the plan's joints at every period, the base pose and the Pacer the
    plan is checked with (a long check keeps out of the loop's tick as the sampling does)."""
    s = session
    seen: list[tuple[int, np.ndarray, Any]] = []

    class Recorder:
        def check_path(self, qs: Any, base: np.ndarray, pace: Any, /) -> None:
            seen.append((len(qs), np.array(base), pace))

    s.kf.add_forbidden_check(Recorder())
    s.ok("KeyframeAdd", T=0.5, Pose="0.2 0.35 0.05")
    s.ok("KeyframePlan")
    ((samples, base, pace),) = seen
    assert samples == round(0.5 / s.kf.ctx.period_s) + 1
    assert np.array_equal(base, s.robot.data.base)
    assert isinstance(pace, Pacer)


# --------------------------------------------------------------------------- the run's end
# _end_run called directly on a controller in a cell (its context has cell_stop): which ends
# stop the other members


@pytest.mark.req("SR-CELLPLAN-5")
@pytest.mark.parametrize(
    ("identity", "code", "stops"),
    [("c0ffee" * 4, 15, True), ("c0ffee" * 4, 1, False), (None, 15, False), (None, 1, False)],
)
def test_only_a_cell_plan_dropped_stops_the_cell(
    identity: str | None, code: int, stops: bool
) -> None:
    kf = KeyframeController()
    told: list[str] = []
    kf.ctx = SimpleNamespace(cell_stop=told.append, cell_member="left", alert=None)  # type: ignore[assignment]
    kf.cell.running = identity
    kf.active = SimpleNamespace(id=3)  # type: ignore[assignment]
    kf._end_run("runs_stopped", "plan 3 stopped", code)
    assert told == (["cell plan c0ffeec0ffee dropped in left: plan 3 stopped"] if stops else [])
    assert (kf.active, kf.cell.running, kf.status) == (None, None, "plan 3 stopped")
    assert kf.counters["runs_stopped"] == 1


def test_a_cell_plan_dropped_outside_a_cell_stops_nothing() -> None:
    kf = KeyframeController()
    kf.ctx = SimpleNamespace(cell_stop=None, cell_member=None, alert=None)  # type: ignore[assignment]
    kf.cell.running = "ab" * 8
    kf._end_run("runs_stopped", "plan 1 stopped", 15)
    assert kf.cell.running is None


def test_a_refused_plan_is_never_reported_as_previewed() -> None:
    """PlannerPort.plan_done with no checked plan keeps the refusal and answers False, as a
    checked plan of an older generation does (the port's contract, whoever calls it)."""
    kf = KeyframeController()
    req: Any = SimpleNamespace(id=2, pace=None)
    assert kf.plan_done(req, 0, None, "plan 2 refused: too far") is False
    assert (kf.status, kf.last_error) == ("plan 2 refused: too far", "plan 2 refused: too far")
    assert kf.plan_done(req, 1, None, "plan 2 refused: again") is False
    assert (kf.status, kf.last_error) == ("plan 2 refused: too far", "plan 2 refused: again")
    assert kf.counters["plans_refused"] == 2 and kf.plan is None


def test_a_plan_request_takes_the_ports_rules_from_the_params_in_radians_and_metres() -> None:
    """The port in the base frame, its tolerance in radians and its least depth in metres,
    each from its own parameter (none left at the request's defaults)."""
    params = KeyframeParams(
        rcm_mm=(10.0, 20.0, 300.0), rcm_tolerance_deg=2.0, rcm_min_depth_mm=25.0
    )
    base = np.eye(4)
    base[:3, 3] = [0.1, 0.0, -0.2]
    data: Any = SimpleNamespace(commanded=lambda: [0.1, 0.2], base=base, joint_names=("a", "b"))
    ctx: Any = SimpleNamespace(period_s=0.002, loop_t0=None)
    kset = make_set("joint", [(1.0, [0.0, 0.0], "")], "test", joints=2, max_keyframes=4)
    settings = PlanSettings("linear", "stop", 6.0, 0.25)
    req = plan_request(7, kset, settings, params, data, ctx, (), ((), ()))
    assert req.port is not None
    assert np.allclose(req.port, port_in_base((10.0, 20.0, 300.0), base))
    assert req.port_tolerance_rad == pytest.approx(math.radians(2.0))
    assert req.port_min_depth == pytest.approx(0.025)
    assert (req.id, req.q_start, req.period) == (7, (0.1, 0.2), 0.002)


# --------------------------------------------------------------------------- the preview's timing


def test_the_preview_goes_out_once_per_plan_and_again_exactly_every_repeat() -> None:
    """Per output: nothing before a plan was ever shown; a new plan at once; the same plan
    again when exactly ``repeat_s`` has passed, not before; an empty one once when the plan
    is dropped; with no repeat, once."""
    out_a, out_b = object(), object()
    preview = Preview(5.0)
    assert preview._due(out_a, 0.0) is None  # type: ignore[arg-type]
    plan: Any = SimpleNamespace(id=1)
    preview.show(plan)
    assert not preview.sent
    first = preview._due(out_a, 1.0)  # type: ignore[arg-type]
    assert first is not None and first.plan is plan and preview.sent
    assert preview._due(out_a, 1.0) is None  # type: ignore[arg-type]
    assert preview._due(out_a, math.nextafter(6.0, 0.0)) is None  # type: ignore[arg-type]
    assert preview._due(out_a, 6.0) is first  # type: ignore[arg-type]
    assert preview._due(out_b, 6.5) is first  # type: ignore[arg-type]  # each output its own
    preview.show(None)
    dropped = preview._due(out_a, 7.0)  # type: ignore[arg-type]
    assert dropped is not None and dropped.plan is None
    assert preview._due(out_a, 20.0) is None  # type: ignore[arg-type]  # an empty one once
    preview.show(None)  # nothing shown: nothing new to clear
    assert preview._due(out_a, 30.0) is None  # type: ignore[arg-type]
    once = Preview(None)
    once.show(plan)
    assert once._due(out_a, 0.0) is not None  # type: ignore[arg-type]
    assert once._due(out_a, 100.0) is None  # type: ignore[arg-type]


def test_the_same_plan_set_again_is_not_previewed_again() -> None:
    kf = KeyframeController()
    out = object()
    plan: Any = SimpleNamespace(id=1)
    kf._set_plan(plan)
    assert kf._preview._due(out, 0.0) is not None  # type: ignore[arg-type]
    kf._set_plan(plan)  # the same object: nothing new to show
    assert kf._preview._due(out, 0.1) is None  # type: ignore[arg-type]
    assert kf._preview.sent
    kf._set_plan(None)
    assert kf.plan is None and kf._preview._due(out, 0.2) is not None  # type: ignore[arg-type]


def test_the_planner_paces_itself_once_before_and_once_per_sample(
    session: Session, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The Pacer a KeyframePlan is checked with is asked once before the plan (``begin``) and
    once before each of the plan's samples (0.5 s at 1 ms: 501), so a long check gives the
    interpreter back to the loop throughout."""
    import occ.controllers.keyframe.plan as plan_module

    calls: list[str] = []

    class Counting:
        sleeps = 0

        def __init__(self, *args: Any) -> None:
            pass

        def begin(self) -> None:
            calls.append("begin")

        def __call__(self) -> None:
            calls.append("sample")

    monkeypatch.setattr(plan_module, "Pacer", Counting)
    s = session
    s.ok("KeyframeAdd", T=0.5, Pose="0.2 0.35 0.05")
    s.ok("KeyframePlan")
    assert calls == ["begin"] + ["sample"] * 501


def test_a_keyframe_at_t0_turned_exactly_as_the_tool_is_taken_though_its_dot_rounds_over_1() -> (
    None
):
    """The tool's turn from keyframe 0 is 2 acos |q0 . q|; for two equal unit quaternions the
    dot product may round to 1 + 2**-52, which acos refuses: it is taken as 1 (no turn)."""
    q = (0.21424427007839497, 0.5093606231982168, 0.20485384406841475, -0.8078898754434874)
    first = Keyframe(0.0, [0.1, 0.2, 0.3], q)
    here_rot = np.array(first.rotation)
    assert abs(float(np.dot(first.rotation, here_rot))) > 1.0  # the rounding this is about
    req: Any = SimpleNamespace(start_tolerance_rad=0.0087, start_tolerance_mm=0.5)
    tl = _Timeline([first], ["keyframe 0"], ["K0"], cart=True, oriented=True)
    _join_start(req, tl, (0.1, 0.2, 0.3), here_rot)
    assert tl.frames[0].rotation == first.rotation and tl.notes == []


def test_a_keyframe_at_t0_exactly_the_tolerance_away_is_replaced_by_where_the_robot_is() -> None:
    """The start tolerances are closed: keyframe 0 exactly ``start_tolerance`` from the
    robot's joints, or turned exactly ``start_tolerance_rad`` from the tool, is replaced by
    the robot's pose; with a tolerance one float smaller it is refused."""
    gap = float(np.linalg.norm(np.subtract([0.501, 0.2], [0.5, 0.2])))  # 1e-3 and a little
    req: Any = SimpleNamespace(start_tolerance=gap, start_tolerance_mm=0.5)
    tl = _Timeline(
        [Keyframe(0.0, [0.501, 0.2])], ["keyframe 0"], ["K0"], cart=False, oriented=False
    )
    _join_start(req, tl, (0.5, 0.2), None)
    assert tl.frames[0].pose == (0.5, 0.2)
    assert tl.notes == [f"keyframe 0 replaced by the robot's pose ({gap:.3g} rad/m away)"]
    req.start_tolerance = math.nextafter(gap, 0.0)
    tl = _Timeline(
        [Keyframe(0.0, [0.501, 0.2])], ["keyframe 0"], ["K0"], cart=False, oriented=False
    )
    with pytest.raises(PlanRefused, match="^keyframe 0 is 0.001 rad/m from where the robot is"):
        _join_start(req, tl, (0.5, 0.2), None)

    half = math.radians(0.25)
    turned = Keyframe(0.0, [0.1, 0.2, 0.3], (0.0, 0.0, math.sin(half), math.cos(half)))
    tool = np.array([0.0, 0.0, 0.0, 1.0])
    turn = 2.0 * math.acos(abs(float(np.dot(turned.rotation, tool))))  # about 0.5 degrees
    for tolerance, refused in ((turn, False), (math.nextafter(turn, 0.0), True)):
        req = SimpleNamespace(start_tolerance_rad=tolerance, start_tolerance_mm=0.5)
        tl = _Timeline([turned], ["keyframe 0"], ["K0"], cart=True, oriented=True)
        if refused:
            with pytest.raises(PlanRefused, match="^keyframe 0 is turned 0.5 deg from the tool"):
                _join_start(req, tl, (0.1, 0.2, 0.3), tool)
        else:
            _join_start(req, tl, (0.1, 0.2, 0.3), tool)
            assert tl.frames[0].rotation == (0.0, 0.0, 0.0, 1.0)
