"""The keyframe controller (issue 11, items 2-4) in simulated time, with an ideal driver.

The planner's own properties (sigmoid normalisation, spline continuity...) are tested in
tests/occ/test_trajectory.py; here the same promises are checked on what the robot's drivers
were actually told, tick by tick, through the daemon's own command path (a SimPeer sending
COMMAND and POINT/TRAJ over an in-process channel).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np
import pytest
import yaml

import igtl
from occ.net.commands import Deferred
from occ.controllers.keyframe import KeyframeController
from occ.controllers.keyframe.sets import make_set
from occ.net.decoders import event_of
from occ.kinematics.keyframe_inputs import items_from_event
from occ.drivers import register_driver
from occ.drivers.base import Driver
from occ.errors import ConfigError
from occ.core.loader import load_config, parse_config
from occ.core.safety import RobotState
from occ_testkit.testing import SimPeer, SimRobot

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"
PERIOD = 1e-3
HOME = [0.0, 0.35, 0.05]
LIMITS = {"yaw": (-1.0, 1.0, 1.5), "pitch": (-1.0, 1.0, 1.5), "insertion": (0.0, 0.15, 0.1)}


class IdealDriver(Driver):
    """Measured = commanded, at once (the drivers' base still checks every limit)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.last = [j.home for j in self.joints]

    def _read(self, now: float) -> tuple[Sequence[float], Sequence[float], Sequence[float]]:
        n = len(self.last)
        return self.last, [0.0] * n, [0.0] * n

    def _write(self, values: Sequence[float], now: float) -> None:
        self.last = list(values)


IDEAL = "ideal-keyframe-test"


def ideal_driver() -> str:
    """Register the ideal driver (at run time, not at import: tests/occ/test_contracts.py
    wants a rig for every driver registered when it is collected) and return its name."""
    register_driver(IDEAL, IdealDriver)
    return IDEAL


def config(params: dict[str, Any] | None = None, *, preview_hz: float = 100.0) -> dict[str, Any]:
    joints = [
        {
            "name": name,
            "type": "prismatic" if name == "insertion" else "revolute",
            "limits": {"min": lo, "max": hi, "velocity": v},
            "home": HOME[i],
        }
        for i, (name, (lo, hi, v)) in enumerate(LIMITS.items())
    ]
    return {
        "robot": {
            "name": "kf",
            "frame": {"model": "occ_slave"},
            "joints": joints,
            "drivers": [
                {
                    "name": "ideal",
                    "plugin": ideal_driver(),
                    "joints": list(LIMITS),
                    "on_limit": "fault",  # a checked plan never reaches a limit
                }
            ],
        },
        "interfaces": [
            {
                "name": "slicer",
                "transport": "inproc",
                "channel": "kf-slicer",
                "role": "operator",
                "inputs": [
                    {"type": "POINT", "queue": "command"},
                    {"type": "TRAJ", "queue": "command"},
                ],
                "outputs": [
                    {
                        "type": "POLYDATA",
                        "device": "KeyframePath",
                        "source": "keyframe-path",
                        "rate_hz": preview_hz,
                    },
                    {
                        "type": "POINT",
                        "device": "Keyframes",
                        "source": "keyframe-points",
                        "rate_hz": preview_hz,
                    },
                ],
            }
        ],
        "safety": {"loss": {"enabled": False}},
        "controller": {"plugin": "keyframe", "params": params or {}},
    }


def xml(name: str, **args: Any) -> str:
    attrs = "".join(f" {k}={quoteattr(str(v))}" for k, v in args.items())
    return f"<Command Name={quoteattr(name)}{attrs}/>"


class Session:
    """A keyframe robot, an operator (Slicer) peer, and the setpoints of every tick."""

    def __init__(
        self, params: dict[str, Any] | None = None, recorder: Any = None, **kw: Any
    ) -> None:
        self.sim = SimRobot(config(params, **kw), recorder=recorder)
        self.robot = self.sim.robot
        (ctrl,) = self.robot.controller.controllers
        assert isinstance(ctrl, KeyframeController)
        self.kf = ctrl
        self.slicer: SimPeer = self.sim.peer("slicer")
        self.setpoints: list[list[float]] = []

    def cmd(self, name: str, **args: Any) -> Any:
        cid = self.slicer.send_command(name, xml(name, **args) if args else "")
        self.step(1)
        assert self.kf.wait_idle(30.0)
        reply = self.slicer.reply_to(cid)
        assert reply is not None, f"no reply to {name}"
        return reply

    def ok(self, name: str, **args: Any) -> str:
        reply = self.cmd(name, **args)
        assert reply.metadata["Status"] == "SUCCESS", reply.metadata
        return str(reply.metadata["Message"])

    def refused(self, name: str, **args: Any) -> str:
        reply = self.cmd(name, **args)
        assert reply.metadata["Status"] == "FAIL", reply.metadata
        return str(reply.metadata["Error"])

    def step(self, n: int) -> None:
        for _ in range(n):
            self.sim.tick()
            self.setpoints.append(list(self.robot.data.commanded()))

    def start(self) -> None:
        self.ok("Enable")
        self.ok("Run")

    def plan_and_ack(self, **args: Any) -> int:
        text = self.ok("KeyframePlan", **args)
        plan_id = int(text.split(":")[0].split()[1])
        self.step(20)  # the preview goes out with the next output tick
        self.setpoints.clear()
        self.ok("KeyframeAck", Plan=plan_id)  # this tick is t = 0 of the run
        return plan_id

    def limit_events(self) -> int:
        return sum(d.stats()["limit_events"] for d in self.robot.hardware.drivers)

    def close(self) -> None:
        self.sim.close()


@pytest.fixture
def session() -> Iterator[Session]:
    s = Session()
    try:
        yield s
    finally:
        s.close()


def joint_keyframes(*frames: tuple[float, list[float]]) -> list[dict[str, Any]]:
    return [{"t": t, "pose": pose, "name": f"k{i}"} for i, (t, pose) in enumerate(frames)]


SWEEP = joint_keyframes(
    (1.0, [0.3, 0.35, 0.05]),
    (2.0, [0.3, 0.5, 0.08]),
    (3.5, [-0.2, 0.45, 0.08]),
    (5.0, [0.0, 0.35, 0.05]),
)


def speeds(q: np.ndarray) -> np.ndarray:
    """Per-tick joint velocities from consecutive setpoints (what the drivers see)."""
    return np.diff(q, axis=0) / PERIOD


# ============================================================================ the run
@pytest.mark.parametrize("interpolation", ["linear", "spline"])
@pytest.mark.parametrize("mode", ["stop", "continuous"])
def test_every_keyframe_met_on_its_tick_from_rest_to_rest(interpolation: str, mode: str) -> None:
    s = Session({"keyframes": SWEEP, "interpolation": interpolation, "mode": mode})
    try:
        s.start()
        s.plan_and_ack()
        s.step(5200)
        q = np.array(s.setpoints)
        # setpoints[j] is the tick j periods after the acknowledgement
        assert np.array_equal(q[0], HOME)
        for kf in SWEEP:
            j = round(kf["t"] / PERIOD)
            assert np.max(np.abs(q[j] - kf["pose"])) <= 1e-6, (kf, q[j])
        v = speeds(q)
        peak = np.max(np.abs(v))
        assert np.max(np.abs(v[0])) <= 1e-3 * peak  # starts at rest
        assert np.all(v[5000:] == 0.0)  # rests at the end, exactly at the last keyframe
        assert np.array_equal(q[-1], SWEEP[-1]["pose"])
        if mode == "stop":  # rests at every keyframe
            for kf in SWEEP[:-1]:
                j = round(kf["t"] / PERIOD)
                assert np.max(np.abs(v[j - 1 : j + 1])) <= 1e-3 * peak, kf
        jumps = np.max(np.abs(np.diff(v, axis=0)), axis=1)
        if interpolation == "linear" and mode == "continuous":
            # the documented corner: the direction turns at a keyframe, the speed does not jump
            # (Euclidean speed of the joint vector; the planner's path length is that norm)
            speed = np.linalg.norm(v, axis=1)
            assert np.max(np.abs(np.diff(speed))) <= 0.02 * peak
            corners = {round(kf["t"] / PERIOD) for kf in SWEEP[:-1]}
            big = {j + 1 for j in np.flatnonzero(jumps > 0.02 * peak)}
            assert big and big <= corners | {c - 1 for c in corners} | {c + 1 for c in corners}
        else:
            assert np.max(jumps) <= 0.02 * peak  # velocity continuous: no jump anywhere
        assert s.limit_events() == 0 and s.robot.state is RobotState.RUNNING
        assert s.kf.stats()["runs_completed"] == 1
    finally:
        s.close()


def test_sigmoid_half_speed_at_half_ramp_and_area_rule_on_the_setpoints() -> None:
    d, big_t, ramp, n = 0.4, 2.0, 0.25, 6.0
    s = Session(
        {"keyframes": joint_keyframes((big_t, [d, 0.35, 0.05])), "steepness": n, "ramp": ramp}
    )
    try:
        s.start()
        s.plan_and_ack()
        s.step(2100)
        yaw = np.array(s.setpoints)[:, 0]
        ta = ramp * big_t
        v0 = d / (big_t - ta)  # the paper's v0 = D / (T - t_a/2 - t_b/2)
        ja = round(ta / PERIOD)
        # area rule: the acceleration ramp covers exactly t_a v0 / 2
        assert yaw[ja] == pytest.approx(ta * v0 / 2, rel=1e-12, abs=1e-15)
        # half speed at t_a / 2 (central difference over the two ticks around it)
        jh = round(ta / 2 / PERIOD)
        v_half = (yaw[jh + 1] - yaw[jh - 1]) / (2 * PERIOD)
        assert v_half == pytest.approx(v0 / 2, rel=1e-5)
        # cruise at v0, and the deceleration mirrors the acceleration
        assert (yaw[1001] - yaw[999]) / (2 * PERIOD) == pytest.approx(v0, rel=1e-9)
        assert d - yaw[round((big_t - ta) / PERIOD)] == pytest.approx(ta * v0 / 2, rel=1e-12)
    finally:
        s.close()


def test_nothing_moves_without_the_acknowledgement(session: Session) -> None:
    s = session
    s.ok("KeyframeAdd", T=1.0, Pose="0.2 0.35 0.05")
    s.start()
    text = s.ok("KeyframePlan")
    assert text.startswith("plan 1:") and "KeyframeAck Plan=1" in text
    error = s.refused("KeyframeAck", Plan=1)  # not previewed yet: no output tick since
    assert "not been previewed" in error
    s.step(3000)
    assert all(sp == HOME for sp in s.setpoints)  # RUNNING, planned, previewed: still holds
    assert "not the previewed plan" in s.refused("KeyframeAck", Plan=7)
    assert "needs Plan" in s.refused("KeyframeAck")
    s.ok("Stop")
    assert "send Run first" in s.refused("KeyframeAck", Plan=1)
    s.ok("Run")
    s.setpoints.clear()
    s.ok("KeyframeAck", Plan=1)
    s.step(1100)
    assert s.setpoints[-1] == [0.2, 0.35, 0.05]
    assert "not the previewed plan" in s.refused("KeyframeAck", Plan=1)  # used up


def test_operator_stop_drops_the_run_and_the_robot_holds_where_it_stopped(
    session: Session,
) -> None:
    s = session
    for kf in SWEEP:
        s.ok("KeyframeAdd", T=kf["t"], Pose=" ".join(map(str, kf["pose"])))
    s.start()
    plan_id = s.plan_and_ack()
    s.step(1500)
    s.ok("Stop")  # mid-way between keyframes 1 and 2, moving
    stopped = list(s.robot.data.setpoint)
    assert s.robot.state is RobotState.STOPPED
    assert s.robot.data.hold_setpoint == stopped
    assert stopped != SWEEP[1]["pose"] and stopped != SWEEP[2]["pose"]
    s.step(2000)
    assert all(sp == stopped for sp in s.setpoints[-2000:])  # holds there
    status = s.kf.stats()["status"]
    assert f"plan {plan_id} stopped at t=1.50" in status and "RUNNING -> STOPPED" in status
    s.ok("Run")  # running again does not resume the plan
    s.step(1000)
    assert all(sp == stopped for sp in s.setpoints[-1000:])
    assert "not the previewed plan" in s.refused("KeyframeAck", Plan=plan_id)
    # the keyframes are kept: a new plan starts where the robot stopped, and meets them all
    assert s.kf.stats()["keyframes"] == 4
    s.plan_and_ack()
    assert s.setpoints[0] == stopped
    s.step(5100)
    q = np.array(s.setpoints)
    for kf in SWEEP:
        assert np.max(np.abs(q[round(kf["t"] / PERIOD)] - kf["pose"])) <= 1e-6
    assert s.limit_events() == 0
    assert s.kf.stats()["runs_stopped"] == 1 and s.kf.stats()["runs_completed"] == 1


def test_a_run_is_announced_when_it_starts_and_when_it_ends(session: Session) -> None:
    """STATUS KEYFRAME_RUNNING when a plan starts, KEYFRAME_ENDED when it completes or is
    dropped, to every viewer and operator: what ROS 2's is_busy follows (occ_ros2)."""
    s = session

    def runs() -> list[tuple[str, int, str]]:
        return [
            (m.error_name, m.code, m.status_message)  # type: ignore[attr-defined]
            for m in s.slicer.messages("STATUS")
            if m.error_name.startswith("KEYFRAME_")  # type: ignore[attr-defined]
        ]

    s.ok("KeyframeAdd", T=0.5, Pose="0.1 0.35 0.05")
    s.start()
    s.ok("KeyframePlan")
    s.step(20)
    assert runs() == []  # planned and previewed: nothing runs yet
    s.ok("KeyframeAck", Plan=1)
    s.step(5)
    assert runs() == [("KEYFRAME_RUNNING", 1, "plan 1 running (0.500 s)")]
    s.step(400)
    assert len(runs()) == 1  # still running
    s.step(200)
    assert runs()[1:] == [("KEYFRAME_ENDED", 1, "plan 1 completed (0.500 s)")]
    # dropped by a Stop: ended, code DISABLED (what a STOPPED robot's STATUS carries)
    s.ok("KeyframeAdd", T=1.0, Pose="0.0 0.35 0.05")
    plan_id = s.plan_and_ack()
    s.step(300)
    s.ok("Stop")
    s.step(2)
    name, code, text = runs()[-1]
    assert runs()[-2][:2] == ("KEYFRAME_RUNNING", 1)
    assert (name, code) == ("KEYFRAME_ENDED", 15)
    assert text.startswith(f"plan {plan_id} stopped at t=0.30") and "RUNNING -> STOPPED" in text
    assert len(runs()) == 4


# ============================================================================ refusals
def test_refused_on_a_joint_velocity_limit_naming_the_segment(session: Session) -> None:
    s = session
    s.ok("KeyframeAdd", T=1.0, Pose="0.0 0.35 0.05", Label="a")
    s.ok("KeyframeAdd", T=1.5, Pose="0.0 0.35 0.12", Label="deep")  # 70 mm in 0.5 s
    error = s.refused("KeyframePlan")
    assert "plan 1 refused: joint 'insertion' velocity" in error
    assert "exceeds its limit 0.1" in error
    assert "between keyframe 0 'a' (t=1 s) and keyframe 1 'deep' (t=1.5 s)" in error
    assert s.kf.plan is None and s.kf.stats()["plans_refused"] == 1
    s.start()
    assert "no plan is previewed" in s.refused("KeyframeAck", Plan=1)
    s.step(500)
    assert all(sp == HOME for sp in s.setpoints)


def test_refused_on_a_position_limit_and_with_a_velocity_scale() -> None:
    s = Session(
        {
            "keyframes": joint_keyframes(
                (3.0, [0.95, 0.35, 0.05]), (6.0, [-0.95, 0.35, 0.05]), (9.0, [0.95, 0.35, 0.05])
            ),
            "interpolation": "spline",
            "mode": "continuous",
        }
    )
    try:
        # the natural spline through +-0.95 overshoots past 1.0 (by 5 %)
        error = s.refused("KeyframePlan")
        assert "joint 'yaw' position" in error and "outside its limits [-1, 1]" in error
        assert "keyframe" in error
        fine = s.ok("KeyframePlan", Interpolation="linear", Mode="stop")
        assert "peak joint speed" in fine
    finally:
        s.close()
    s = Session({"keyframes": joint_keyframes((1.4, [0.0, 0.35, 0.12])), "velocity_scale": 0.5})
    try:
        # 70 mm in 1.4 s: 0.067 m/s at cruise is within 0.1, not within half of it
        error = s.refused("KeyframePlan")
        assert "exceeds its limit 0.05" in error and "velocity_scale 0.5" in error
    finally:
        s.close()


def test_cartesian_refused_outside_the_workspace_and_the_box() -> None:
    s = Session({"workspace_mm": {"min_mm": [-50.0, -50.0, 150.0], "max_mm": [50.0, 50.0, 300.0]}})
    try:
        s.ok("KeyframeAdd", T=20.0, Pose="0 24 400", Space="cartesian", Label="far")
        error = s.refused("KeyframePlan")
        assert "the tip leaves the workspace" in error and "'far'" in error
        assert "beyond its limits" in error
        s.ok("KeyframeClear")
        s.ok("KeyframeAdd", T=2.0, Pose="-12 46 140", Space="cartesian", Label="low")
        error = s.refused("KeyframePlan")
        assert "leaves workspace_mm" in error and "keyframe 0 'low'" in error
    finally:
        s.close()


def test_refused_when_the_path_crosses_a_forbidden_region(session: Session) -> None:
    s = session
    centre, radius = np.array([-6.0, 35.0, 218.0]) * 1e-3, 5e-3

    def sphere(p: tuple[float, float, float]) -> str | None:
        return "sphere 'vessel'" if np.linalg.norm(np.subtract(p, centre)) < radius else None

    s.kf.add_forbidden_check(sphere)
    s.ok("KeyframeAdd", T=2.0, Pose="-6 30 226", Space="cartesian", Label="entry")
    s.ok("KeyframeAdd", T=4.0, Pose="-12 46 201", Space="cartesian", Label="target")
    error = s.refused("KeyframePlan")
    assert "enters a forbidden region (sphere 'vessel')" in error
    assert "between keyframe 0 'entry' (t=2 s) and keyframe 1 'target' (t=4 s)" in error
    # a plan checked before the region appeared cannot be acknowledged once it is there
    s.kf.forbidden_checks.clear()
    s.start()
    s.ok("KeyframePlan")
    s.step(20)
    s.kf.add_forbidden_check(sphere)
    s.kf.invalidate_plan("fixtures changed")
    assert "no plan is previewed" in s.refused("KeyframeAck", Plan=2)
    assert "invalidated: fixtures changed" in s.kf.stats()["status"]


def test_forbidden_fixtures_from_the_config_refuse_a_plan() -> None:
    """The YAML's forbidden spheres and planes (the virtual fixtures' primitives, base frame,
    mm) are the collision check of every plan."""
    from occ.errors import ConfigError

    s = Session(
        {
            "forbidden": [
                {"centre_mm": [-6.0, 35.0, 218.0], "radius_mm": 5.0, "name": "vessel"},
                {"point_mm": [0.0, 0.0, 150.0], "normal": [0.0, 0.0, 2.0], "name": "table"},
            ]
        }
    )
    try:
        s.ok("KeyframeAdd", T=2.0, Pose="-6 30 226", Space="cartesian", Label="entry")
        s.ok("KeyframeAdd", T=4.0, Pose="-12 46 201", Space="cartesian", Label="target")
        error = s.refused("KeyframePlan")
        assert "forbidden sphere 'vessel'" in error and "keyframe 0 'entry'" in error
        s.ok("KeyframeClear")
        s.ok("KeyframeAdd", T=2.0, Pose="-12 46 140", Space="cartesian", Label="low")
        assert "forbidden plane 'table'" in s.refused("KeyframePlan")
    finally:
        s.close()
    with pytest.raises((ConfigError, ValueError), match="normal is zero"):
        Session({"forbidden": [{"point_mm": [0, 0, 0], "normal": [0, 0, 0]}]}).close()


def test_a_first_keyframe_at_t0_must_be_where_the_robot_is(session: Session) -> None:
    s = session
    s.ok("KeyframeAdd", T=0.0, Pose="0.1 0.35 0.05")
    s.ok("KeyframeAdd", T=1.0, Pose="0.2 0.35 0.05")
    error = s.refused("KeyframePlan")
    assert "keyframe 0 (t=0 s) is 0.1 rad/m from where the robot is" in error
    s.ok("KeyframeClear")
    s.ok("KeyframeAdd", T=0.0, Pose="0.0005 0.35 0.05")  # within start_tolerance 1e-3
    s.ok("KeyframeAdd", T=1.0, Pose="0.2 0.35 0.05")
    assert "keyframe 0 replaced by the robot's pose" in s.ok("KeyframePlan")


# ============================================================================ inputs
def point_message(
    points: list[tuple[float, float, float]], times: str | None = None, hidden: int | None = None
) -> igtl.PointMessage:
    return igtl.PointMessage(
        points=tuple(
            igtl.PointElement(
                name=f"F-{i + 1}",
                group="Fiducial",
                rgba=(255, 0, 0, 0 if i == hidden else 255),
                position=p,
            )
            for i, p in enumerate(points)
        ),
        device_name="F",
        header_version=2,
        metadata={"times": times} if times is not None else {},
    )


def test_a_slicer_point_list_becomes_cartesian_keyframes_met_by_the_tip(session: Session) -> None:
    s = session
    entry, mid, target = (-6.0, 30.0, 226.0), (0.0, 38.0, 215.0), (-12.0, 46.0, 201.0)
    s.slicer.send(point_message([entry, mid, target], times="1.5, 2.5, 4"))
    s.step(1)
    listing = s.ok("KeyframeList")
    assert "3 cartesian from POINT 'F' from slicer" in listing
    assert "#1 'F-2' t=2.5 s pose=[0 38 215] mm" in listing
    s.start()
    s.plan_and_ack(Interpolation="spline", Mode="continuous")
    s.step(4100)
    frame = s.robot.frame
    for t, p in ((1.5, entry), (2.5, mid), (4.0, target)):
        tip = np.array(frame.tip_position(s.setpoints[round(t / PERIOD)])) / 1e-3
        assert np.max(np.abs(tip - p)) <= 1e-6, (t, tip)
    assert s.limit_events() == 0


def test_traj_and_bad_inputs(session: Session) -> None:
    s = session
    traj = igtl.TrajectoryMessage(
        trajectories=(
            igtl.TrajectoryElement(
                name="needle", type=3, entry=(-6.0, 30.0, 226.0), target=(-12.0, 46.0, 201.0)
            ),
        ),
        device_name="T",
    )
    s.slicer.send(traj)
    s.step(1)
    kset = s.kf.kset
    assert kset is not None and kset.space == "cartesian"
    assert kset.names == ("needle entry", "needle target")
    assert [k.t for k in kset.keyframes] == [2.0, 4.0]  # point_interval_s
    before = kset
    # too few times, times not increasing: refused, counted, the set unchanged
    s.slicer.send(point_message([(0.0, 30.0, 226.0), (0.0, 31.0, 226.0)], times="1"))
    s.slicer.send(point_message([(0.0, 30.0, 226.0), (0.0, 31.0, 226.0)], times="2, 1"))
    s.step(1)
    assert s.kf.kset is before and s.kf.stats()["inputs_refused"] == 2
    assert "times must increase" in s.kf.stats()["last_error"]
    # a hidden point (alpha 0, as Slicer marks it) is left out with its time
    s.slicer.send(
        point_message(
            [(0.0, 30.0, 226.0), (9.0, 9.0, 9.0), (0.0, 31.0, 226.0)], times="1 2 3", hidden=1
        )
    )
    s.step(1)
    assert [k.t for k in s.kf.kset.keyframes] == [1.0, 3.0]  # type: ignore[union-attr]


def test_preview_is_a_named_polyline_and_points_and_is_cleared(session: Session) -> None:
    s = session
    s.ok("KeyframeAdd", T=1.0, Pose="0.3 0.35 0.05", Label="right")
    s.ok("KeyframeAdd", T=2.0, Pose="0.3 0.5 0.08", Label="deeper")
    s.step(50)
    assert s.slicer.messages("POLYDATA") == []  # nothing planned, nothing previewed
    s.ok("KeyframePlan")
    s.step(20)
    (path,) = s.slicer.messages("POLYDATA", "KeyframePath")
    (keys,) = s.slicer.messages("POINT", "Keyframes")
    assert path.metadata["MRMLNodeName"] == "KeyframePath"
    assert keys.metadata["MRMLNodeName"] == "Keyframes"
    pts = np.asarray(path.points)
    assert 100 <= len(pts) <= 256 and path.lines == (tuple(range(len(pts))),)
    frame = s.robot.frame
    home_mm = np.array(frame.tip_position(HOME)) / 1e-3
    end_mm = np.array(frame.tip_position([0.3, 0.5, 0.08])) / 1e-3
    assert np.allclose(pts[0], home_mm, atol=1e-3) and np.allclose(pts[-1], end_mm, atol=1e-3)
    assert [p.name for p in keys.points] == ["start t=0s", "right t=1s", "deeper t=2s"]
    assert np.allclose(keys.points[2].position, end_mm, atol=1e-3)
    s.step(5100)  # repeated every preview_repeat_s (5 s) for viewers that came later
    assert len(s.slicer.messages("POLYDATA")) == 2
    s.ok("KeyframeClear")
    s.step(20)
    last = s.slicer.messages("POLYDATA")[-1]
    assert len(last.points) == 0 and s.slicer.messages("POINT")[-1].points == ()
    s.step(6000)
    assert len(s.slicer.messages("POLYDATA")) == 3  # the empty one is sent once


def test_add_list_clear_load_and_the_planner_thread(tmp_path: Path) -> None:
    (tmp_path / "ok.yaml").write_text(
        "space: joint\nkeyframes:\n  - {t: 1.0, pose: [0.1, 0.35, 0.05], name: a}\n"
    )
    (tmp_path / "bad.yaml").write_text("keyframes:\n  - {t: 1.0, pose: [0.1, 0.35]}\n")
    s = Session({"keyframe_dir": str(tmp_path)})
    try:
        assert "keyframes: none" in s.ok("KeyframeList")
        assert "needs T and Pose" in s.refused("KeyframeAdd", T=1.0)
        assert "a joint pose needs 3 joint positions" in s.refused("KeyframeAdd", T=1.0, Pose="1 2")
        s.ok("KeyframeAdd", T=2.0, Pose="0.2 0.35 0.05")
        s.ok("KeyframeAdd", T=1.0, Pose="0.1 0.35 0.05")  # inserted in time order
        assert "already" in s.refused("KeyframeAdd", T=1.0, Pose="0.1 0.35 0.05")
        assert "are joint; KeyframeClear first" in s.refused(
            "KeyframeAdd", T=3.0, Pose="1 2 3", Space="cartesian"
        )
        assert [k.t for k in s.kf.kset.keyframes] == [1.0, 2.0]  # type: ignore[union-attr]
        assert "keyframes and plan cleared" in s.ok("KeyframeClear")
        assert "no keyframes to plan" in s.refused("KeyframePlan")
        assert "not inside the keyframe folder" in s.refused("KeyframeLoad", File="../x.yaml")
        assert "not inside the keyframe folder" in s.refused("KeyframeLoad", File="/etc/passwd")
        error = s.refused("KeyframeLoad", File="bad.yaml")
        assert "KeyframeLoad refused" in error and "3 joint positions" in error
        assert "cannot read" in s.refused("KeyframeLoad", File="missing.yaml")
        assert "1 keyframes (joint) from ok.yaml" in s.ok("KeyframeLoad", File="ok.yaml")
        assert "#0 'a' t=1 s" in s.ok("KeyframeList")
        # the planner runs beside the loop: held busy, the loop ticks on and a second
        # request is refused, not queued
        gate, entered = threading.Event(), threading.Event()

        def slow(p: tuple[float, float, float]) -> None:
            entered.set()
            gate.wait(30.0)

        s.kf.add_forbidden_check(slow)
        cid = s.slicer.send_command("KeyframePlan")
        s.step(1)
        assert entered.wait(30.0)
        s.step(100)  # the loop is not waiting for the planner
        assert s.slicer.reply_to(cid) is None
        busy = s.slicer.send_command("KeyframePlan")
        s.step(1)
        assert "busy" in s.slicer.reply_to(busy).metadata["Error"]  # type: ignore[union-attr]
        gate.set()
        assert s.kf.wait_idle(30.0)
        assert s.slicer.reply_to(cid).metadata["Status"] == "SUCCESS"  # type: ignore[union-attr]
    finally:
        s.close()


def test_keyframe_load_is_off_without_a_folder(session: Session) -> None:
    assert "no keyframe_dir" in session.refused("KeyframeLoad", File="x.yaml")


# ============================================================================ configuration
def test_the_example_config_loads_its_file_relative_to_itself(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.chdir(tmp_path)  # not the repository: the file is found beside the config
    cfg = load_config(CONFIGS / "keyframe.yaml")
    params = cfg.controllers[0].params
    assert params["file"] == str(CONFIGS / "keyframes" / "demo.yaml")
    assert params["keyframe_dir"] == str(CONFIGS / "keyframes")
    with SimRobot(cfg) as sim:
        (kf,) = sim.robot.controller.controllers
        assert kf.stats()["keyframes"] == 4 and kf.stats()["source"] == "file demo.yaml"


def test_config_problems_name_the_parameter() -> None:
    base = yaml.safe_load((CONFIGS / "keyframe.yaml").read_text())

    def problems(params: dict[str, Any], drop_outputs: bool = False) -> list[str]:
        data = yaml.safe_load(yaml.safe_dump(base))
        data["controller"]["params"] = params
        if drop_outputs:
            data["interfaces"][0]["outputs"] = data["interfaces"][0]["outputs"][:1]
        with pytest.raises(ConfigError) as info:
            parse_config(yaml.safe_dump(data), source="kf.yaml", base_dir=CONFIGS)
        return info.value.errors

    (e,) = problems({"keyframes": [{"t": 1.0, "pose": [1.0, 2.0]}]})
    assert "controller.params.keyframes: keyframe 0: 2 values" in e
    (e,) = problems({"input_interface": "slicr"})
    assert "unknown interface 'slicr' (did you mean 'slicer'?)" in e
    (e,) = problems({"file": "keyframes/demo.yaml", "keyframes": [{"t": 1, "pose": [0, 0, 0]}]})
    assert "not both" in e
    (e,) = problems({}, drop_outputs=True)
    assert "controller.params.preview_required: no interface sends the preview" in e
    (e,) = problems({"file": "keyframes/nope.yaml"})
    assert "controller.params.file" in e


# ============================================================================ pieces
def test_deferred_answers_once_whenever_it_is_bound() -> None:
    early = Deferred()
    early.resolve("done")
    early.fail("ignored: the first answer stands")
    got: list[tuple[bool, str]] = []
    early.bind(lambda ok, text: got.append((ok, text)))
    late = Deferred()
    late.bind(lambda ok, text: got.append((ok, text)))
    assert not late.done
    late.fail("no")
    assert got == [(True, "done"), (False, "no")] and late.result == (False, "no")


def test_make_set_and_messages_refuse_bad_keyframes() -> None:
    with pytest.raises(ValueError, match="keyframe 1: time 1 s does not follow keyframe 0"):
        make_set(
            "joint", [(1.0, [0, 0, 0], ""), (1.0, [0, 0, 0], "")], "x", joints=3, max_keyframes=10
        )
    with pytest.raises(ValueError, match="more than max_keyframes"):
        make_set(
            "joint", [(float(i), [0, 0, 0], "") for i in range(5)], "x", joints=3, max_keyframes=4
        )
    with pytest.raises(ValueError, match="must be finite"):
        make_set("cartesian", [(1.0, [math.nan, 0, 0], "")], "x", joints=3, max_keyframes=4)
    with pytest.raises(ValueError, match="no visible points"):
        items_from_event(event_of(point_message([(0.0, 0.0, 0.0)], hidden=0)), 1.0)
    with pytest.raises(ValueError, match="metadata 'times'"):
        items_from_event(event_of(point_message([(0.0, 0.0, 0.0)], times="soon")), 1.0)
    with pytest.raises(ValueError, match="no keyframes"):
        items_from_event(event_of(igtl.StringMessage("x", device_name="S")), 1.0)


# ============================================================================ real sockets
@pytest.mark.realtime
def test_over_loopback_tcp_with_the_real_loop() -> None:
    """configs/keyframe.yaml on an ephemeral port with its real 1 kHz loop: a TCP client (as
    Slicer) sends a point list and the commands, sees the preview, acknowledges, and the run
    ends at the last keyframe."""
    import time

    from igtl.transport import TCPClient
    from occ.core.robot import build_robot

    data = yaml.safe_load((CONFIGS / "keyframe.yaml").read_text())
    data["interfaces"][0]["port"] = 0
    data["robot"]["realtime"] = {"gc": "default"}
    data["robot"]["drivers"][0]["plugin"] = ideal_driver()
    data["robot"]["drivers"][0]["params"] = {}
    cfg = parse_config(yaml.safe_dump(data), source="kf.yaml", base_dir=CONFIGS)
    robot = build_robot(cfg)
    robot.configure()
    robot.activate()
    loop = threading.Thread(target=robot.run, name="kf-loop", daemon=True)
    loop.start()
    got: list[igtl.Message] = []
    port = robot.interfaces["slicer"].address[1]  # type: ignore[index]
    client = TCPClient("127.0.0.1", port, on_message=lambda p, m: got.append(m))
    client.start()

    def wait(match: Any, timeout: float = 20.0) -> igtl.Message:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for m in list(got):
                if match(m):
                    return m
            time.sleep(0.005)
        raise AssertionError(f"nothing matched; got {[m.message_type for m in got]}")

    ids = iter(range(1, 100))

    def command(name: str, **args: Any) -> str:
        cid = next(ids)
        client.send(
            igtl.CommandMessage(
                command_id=cid, command_name=name, command=xml(name, **args), header_version=2
            )
        )
        reply = wait(lambda m: m.message_type == "RTS_COMMAND" and m.command_id == cid)
        assert reply.metadata["Status"] == "SUCCESS", reply.metadata
        return str(reply.metadata["Message"])

    try:
        assert client.wait_connected(5.0)
        command("Enable")
        command("Run")
        entry, target = (-6.0, 30.0, 226.0), (-12.0, 46.0, 201.0)
        client.send(point_message([entry, target], times="0.5 1.0"))
        assert "2 cartesian from POINT 'F'" in wait_text(command, "KeyframeList", "2 cartesian")
        text = command("KeyframePlan", Interpolation="linear")
        plan_id = int(text.split(":")[0].split()[1])
        path = wait(lambda m: m.message_type == "POLYDATA" and len(m.points) > 0)
        assert path.device_name == "KeyframePath" and path.metadata["MRMLNodeName"]
        command("KeyframeAck", Plan=plan_id)
        wait_text(command, "KeyframeList", f"plan {plan_id} completed")
        tip = np.array(robot.frame.tip_position(robot.data.setpoint)) / 1e-3
        assert np.max(np.abs(tip - target)) <= 1e-6
        assert robot.state is RobotState.RUNNING
    finally:
        client.stop()
        robot.stop_loop()
        loop.join(5.0)
        robot.shutdown()


def wait_text(command: Any, name: str, text: str, timeout: float = 20.0) -> str:
    import time

    end = time.monotonic() + timeout
    while True:
        reply = str(command(name))
        if text in reply or time.monotonic() > end:
            assert text in reply, reply
            return reply
        time.sleep(0.05)


def test_the_pacer_keeps_the_planner_out_of_the_loops_deadlines(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import occ.controllers.keyframe.pacer as module

    slept: list[float] = []
    monkeypatch.setattr(module.time, "sleep", slept.append)
    clock = [0.0]
    pacer = module.Pacer(lambda: clock[0], lambda: 10.0, 1e-3)  # deadlines at 10 s + k ms

    def at(phase_us: float) -> float:
        clock[0] = 10.0 + 5e-3 + phase_us * 1e-6
        slept.clear()
        pacer.begin()
        return slept[0] * 1e6

    assert at(100) == pytest.approx(250)  # mid-tick: wait until 350 us past the deadline
    assert at(500) == pytest.approx(module.PACE_HANDBACK_S * 1e6)  # quiet: work, hand back
    assert at(750) == pytest.approx(600)  # too close to the next deadline: skip past it
    clock[0] += 50e-6  # within a work slice: no sleep at all
    slept.clear()
    pacer()
    assert slept == []
    stepped = module.Pacer(lambda: clock[0], lambda: math.nan, 1e-3)  # no loop running
    slept.clear()
    stepped.begin()
    assert slept == [module.PACE_HANDBACK_S]


def test_plus_style_string_commands_are_answered_too(session: Session) -> None:
    s = session
    s.ok("KeyframeAdd", T=1.0, Pose="0.2 0.35 0.05")
    for uid, text in (("7", '<Command Name="KeyframeList"/>'), ("8", "KeyframePlan")):
        s.slicer.send(igtl.StringMessage(text, device_name=f"CMD_{uid}", header_version=2))
        s.step(1)
        assert s.kf.wait_idle(30.0)
        (ack,) = s.slicer.messages("STRING", f"ACK_{uid}")
        assert 'Status="SUCCESS"' in ack.string  # type: ignore[attr-defined]
    assert "plan 1:" in s.slicer.messages("STRING", "ACK_8")[0].string  # type: ignore[attr-defined]
    s.slicer.send(igtl.StringMessage("KeyframeAck", device_name="CMD_9", header_version=2))
    s.step(1)
    (ack,) = s.slicer.messages("STRING", "ACK_9")
    assert 'Status="FAIL"' in ack.string and "needs Plan" in ack.string  # type: ignore[attr-defined]


def test_a_robot_built_without_the_loader_refuses_bad_keyframes_as_a_config_error() -> None:
    with pytest.raises(ConfigError, match="controller keyframe: keyframe 0: 2 values"):
        SimRobot(config({"keyframes": [{"t": 1.0, "pose": [0.0, 0.0]}]})).close()


def test_shutting_the_robot_down_ends_the_planner_thread() -> None:
    """Controllers get a shutdown hook: the keyframe planner's thread ends with the daemon
    (before the drivers' safe shutdown), not only when the process exits."""
    s = Session()
    try:
        s.cmd("KeyframeAdd", T=1.0, Pose="0.1 0.35 0.05")
        s.cmd("KeyframePlan")
        planner = s.kf._planner
        assert planner is not None and planner._thread.is_alive()
    finally:
        s.close()
    planner._thread.join(5.0)
    assert not planner._thread.is_alive()
    assert s.kf._planner is None


def test_a_controller_shutdown_error_does_not_skip_the_drivers(
    caplog: pytest.LogCaptureFixture,
) -> None:
    s = Session()
    drivers = [d for d in s.robot.hardware.drivers]

    def broken() -> None:
        raise RuntimeError("plugin bug at shutdown")

    s.kf.shutdown = broken  # type: ignore[method-assign]
    s.close()
    assert "controller keyframe: shutdown failed" in caplog.text
    assert all(d.state.value == "shutdown" for d in drivers)


def test_a_deferred_answer_is_recorded(tmp_path: Path) -> None:
    """The planner's answer goes out later, from its own thread; a recording holds it like
    every other reply (through the recorder's any-thread entry)."""
    from occ.recording.record import Recorder, read_recording

    path = tmp_path / "kf.igtl"
    rec = Recorder(path, rate_hz=10).start()
    s = Session(recorder=rec)
    try:
        s.cmd("KeyframeAdd", T=1.0, Pose="0.1 0.35 0.05")
        answer = s.cmd("KeyframePlan")
        assert "plan" in str(answer).lower()
    finally:
        s.close()
        rec.close()
    outs = [m for m in read_recording(path) if m.metadata.get("rec.dir") == "out"]
    replies = [m for m in outs if m.message_type == "RTS_COMMAND"]
    # KeyframeAdd answered at once, KeyframePlan later by the planner thread: both recorded
    assert len(replies) == 2, [m.device_name for m in outs]
    assert rec.stats()["records"] >= rec.late_records == 1
