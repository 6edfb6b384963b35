"""The ``absolute`` mapping of ``teleop-slave``: an external command source (CRTK ``servo_cp``).

configs/servo.yaml on in-process channels, stepped tick by tick in simulated time: each sample
is the tip's target in the patient frame (mm). The tip reaches it exactly (the slave's inverse
kinematics is analytic), the joints never step faster than 0.9 times their velocity limits, a
target farther than ``max_jump_mm`` from the tip is refused with an ALERT and the robot holds,
``run=0`` and the clutch hold, and the stream keeps the master stream's loss rules.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest

import igtl
from occ.core.safety import RobotState
from occ_testkit.rigs import SlaveRig

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "configs" / "servo.yaml"


def servo(**params: Any) -> SlaveRig:
    """The servo slave, its command source (``ServoCP`` on the ``servo`` interface, a sample
    every 2 ms, at the tip to begin with) and an operator."""
    return SlaveRig(CONFIG, params=params, stream="servo", device="ServoCP")


@pytest.fixture
def rig() -> Any:
    r = servo()
    yield r
    r.close()


def max_speed(setpoints: list[list[float]], period: float) -> list[float]:
    q = np.array(setpoints)
    return (np.abs(np.diff(q, axis=0)).max(axis=0) / period).tolist()


@pytest.mark.req("SR-SERVO-1")
def test_the_tip_goes_to_the_target_within_the_velocity_limits(rig: SlaveRig) -> None:
    rig.running()
    start = rig.world_tip_mm()
    rig.target = (start + [4.0, -3.0, 6.0]).tolist()
    written = rig.step(400)
    assert rig.world_tip_mm().tolist() == pytest.approx(rig.target, abs=1e-6)
    limits = [j.limits.velocity for j in rig.robot.joints]
    speeds = max_speed(written, rig.sim.period)
    assert all(s <= 0.9 * v * (1 + 1e-9) for s, v in zip(speeds, limits, strict=True)), speeds
    # the insertion joint (0.1 m/s) was the slow one: limited on the way, not a jump
    assert rig.ctl.stats()["servo_rate_limited"] > 0
    assert rig.robot.state is RobotState.RUNNING
    assert rig.ctl.stats()["mapping"] == "absolute"


@pytest.mark.req("SR-SERVO-1")
@pytest.mark.parametrize("rpy", [(0.0, 0.0, 0.5236), (0.2, -0.3, 0.5)], ids=["about-z", "tilted"])
def test_the_target_is_in_the_patient_frame(rig: SlaveRig, rpy: tuple[float, float, float]) -> None:
    """The base turned 30 degrees about z (or tilted about every axis) and moved 10, 20, 30 mm
    (a tracker's TRANSFORM): a world displacement d moves the tip by R^T d in the base frame,
    and the world tip reaches the world target."""
    base = np.eye(4)
    base[:3, :3] = pin.rpy.rpyToMatrix(*rpy)
    base[:3, 3] = [0.010, 0.020, 0.030]
    rig.robot.data.base = base
    rig.target = rig.world_tip_mm().tolist()
    rig.running()
    local0 = np.array(rig.robot.frame.tip_position(rig.robot.data.setpoint)) * 1e3
    d = np.array([2.0, 1.0, -3.0])
    rig.target = (rig.world_tip_mm() + d).tolist()
    rig.step(300)
    assert rig.world_tip_mm().tolist() == pytest.approx(rig.target, abs=1e-6)
    local = np.array(rig.robot.frame.tip_position(rig.robot.data.setpoint)) * 1e3
    assert (local - local0).tolist() == pytest.approx((base[:3, :3].T @ d).tolist(), abs=1e-6)


@pytest.mark.req("SR-SERVO-2")
def test_a_far_target_is_refused_with_an_alert_and_the_robot_holds(
    rig: SlaveRig, caplog: pytest.LogCaptureFixture
) -> None:
    rig.running()
    here = rig.world_tip_mm()
    rig.target = (here + [0.0, 0.0, 10.5]).tolist()  # just beyond max_jump_mm (10)
    written = rig.step(100)
    assert np.abs(np.diff(np.array(written), axis=0)).max() == 0.0
    assert rig.world_tip_mm().tolist() == pytest.approx(here.tolist(), abs=1e-9)
    stats = rig.ctl.stats()
    assert stats["servo_refused"] == 50  # every sample of the far target
    alerts = [a for a in rig.alerts() if "servo target" in a]
    assert len(alerts) == 1, rig.alerts()
    assert alerts[0] == "servo target 10.5 mm from the tip refused (max_jump_mm 10): holding"
    assert [r.getMessage() for r in caplog.records if "servo target" in r.getMessage()] == [
        alerts[0]
    ]  # and the log says the same, once
    assert stats["master_ref_mm"] is None  # no target taken
    (status,) = [m for m in rig.operator.messages("STATUS") if "servo target" in m.status_message]
    assert status.error_name == "ServoTarget"
    assert status.code == igtl.StatusCode.UNKNOWN_ERROR  # an error, not PANICK_MODE (3)
    assert rig.robot.state is RobotState.RUNNING  # a refused command holds, it does not stop
    # a target within reach is taken again
    rig.target = (here + [0.0, 0.0, 9.5]).tolist()
    rig.step(400)
    assert rig.world_tip_mm().tolist() == pytest.approx(rig.target, abs=1e-6)
    # and a new far one is a new episode: alerted again
    rig.target = (here + [0.0, 0.0, 30.0]).tolist()
    rig.step(10)
    assert len([a for a in rig.alerts() if "servo target" in a]) == 2


@pytest.mark.req("SR-SERVO-2")
def test_a_far_first_target_is_refused_with_an_alert_too(rig: SlaveRig) -> None:
    """The very first target a source sends (none taken before it) is judged as every other:
    one too far is refused, the robot holds where it is and the operators are told, once."""
    rig.command("Enable")
    rig.command("Run")
    here = rig.world_tip_mm()
    rig.target = (here + [0.0, 0.0, 10.5]).tolist()  # just beyond max_jump_mm (10)
    rig.step(100)
    assert rig.robot.state is RobotState.RUNNING
    assert rig.world_tip_mm().tolist() == pytest.approx(here.tolist(), abs=1e-9)
    assert rig.ctl.stats()["servo_refused"] == 50 and rig.ctl.stats()["master_ref_mm"] is None
    alerts = [a for a in rig.alerts() if "servo target" in a]
    assert alerts == ["servo target 10.5 mm from the tip refused (max_jump_mm 10): holding"]


@pytest.mark.req("SR-SERVO-2")
@pytest.mark.parametrize("how", ["run", "clutch"])
def test_a_stopped_source_or_the_clutch_holds(rig: SlaveRig, how: str) -> None:
    rig.running()
    here = rig.world_tip_mm()
    if how == "run":
        rig.run = False
    else:
        rig.clutch = True
    rig.target = (here + [3.0, 0.0, 0.0]).tolist()
    rig.step(100)
    assert rig.world_tip_mm().tolist() == pytest.approx(here.tolist(), abs=1e-9)
    assert rig.ctl.stats()["master_ref_mm"] is None  # no target held while stopped
    rig.run, rig.clutch = True, False  # released: the target is taken (absolute: no re-index)
    rig.step(300)
    assert rig.world_tip_mm().tolist() == pytest.approx(rig.target, abs=1e-6)
    # GetStats: the last accepted target (world, mm)
    assert rig.ctl.stats()["master_ref_mm"] == pytest.approx(rig.target, abs=1e-5)


@pytest.mark.req("SR-SERVO-3")
def test_a_dead_source_stops_the_robot_by_the_loss_rules(rig: SlaveRig) -> None:
    rig.running()
    rig.sending = False
    rig.step(150)  # past the 100 ms grace
    assert rig.robot.state is RobotState.STOPPED
    assert any("servo" in a for a in rig.alerts()), rig.alerts()


@pytest.mark.req("SR-SERVO-2")
def test_not_a_number_is_no_target(rig: SlaveRig) -> None:
    rig.running()
    here = rig.world_tip_mm()
    rig.target = [float("nan"), here[1], here[2]]
    rig.step(40)
    assert rig.world_tip_mm().tolist() == pytest.approx(here.tolist(), abs=1e-9)
    assert rig.ctl.stats()["ik_failures"] == 20  # each of the 20 samples, once
    assert rig.robot.state is RobotState.RUNNING


@pytest.mark.req("SR-SERVO-1")
def test_run_again_after_a_stop_starts_from_where_the_drives_hold(rig: SlaveRig) -> None:
    rig.running()
    here = rig.world_tip_mm()
    rig.target = (here + [2.0, 2.0, 2.0]).tolist()
    rig.step(300)
    assert rig.ctl.stats()["reindexes"] == 1  # the first target after Run, not every one
    rig.command("Stop")
    held = rig.world_tip_mm()
    rig.step(20)
    rig.target = (held + [-2.0, 0.0, 1.0]).tolist()
    rig.command("Run")
    written = rig.step(300)
    assert rig.world_tip_mm().tolist() == pytest.approx(rig.target, abs=1e-6)
    first = np.array(rig.robot.frame.tip_position(written[0])) * 1e3
    assert np.linalg.norm(first - held) < 1.0  # no jump at the restart
    assert rig.ctl.stats()["reindexes"] == 2


@pytest.mark.req("SR-SERVO-2")
def test_the_jump_is_measured_from_where_the_tip_is(rig: SlaveRig) -> None:
    """``max_jump_mm`` is the distance from the tip, wherever it is: off the base's axes a
    target 9.5 mm away is taken and one 10.5 mm away refused."""
    rig.running()
    rig.target = (rig.world_tip_mm() + [8.0, 6.0, 0.0]).tolist()
    rig.step(300)
    here = rig.world_tip_mm()
    assert here.tolist() == pytest.approx(rig.target, abs=1e-6)
    assert abs(here[0]) > 7.0  # the tip is off the axes: x, y and z all count
    rig.target = (here + [0.0, -9.5, 0.0]).tolist()
    rig.step(300)
    assert rig.world_tip_mm().tolist() == pytest.approx(rig.target, abs=1e-6)
    assert rig.ctl.stats()["servo_refused"] == 0
    rig.target = (rig.world_tip_mm() + [-10.5, 0.0, 0.0]).tolist()
    rig.step(20)
    assert rig.ctl.stats()["servo_refused"] == 10


@pytest.mark.req("SR-SERVO-2")
def test_a_target_out_of_reach_is_clamped_and_one_at_the_port_is_no_target() -> None:
    """Past the insertion limit: the tool goes as deep as it can along the line to the target,
    each sample counted as clamped; at the port itself (no direction for the tool): no target,
    each sample counted as a failure, the robot holds and keeps running."""
    rig = servo(max_jump_mm=200.0)
    try:
        rig.running()
        port = np.array(rig.robot.frame.rcm) * 1e3
        tip = rig.world_tip_mm()
        axis = (tip - port) / np.linalg.norm(tip - port)
        rig.target = (port + axis * (20.0 + 150.0 + 5.0)).tolist()  # 5 mm past the limit
        rig.step(1400)  # 0.1 m of insertion at 0.09 m/s
        assert rig.robot.data.setpoint[2] == pytest.approx(0.15, abs=1e-12)
        assert rig.world_tip_mm().tolist() == pytest.approx(
            (port + axis * 170.0).tolist(), abs=1e-4
        )
        stats = rig.ctl.stats()
        assert stats["ik_clamped"] == 700 and stats["ik_failures"] == 0
        held = rig.world_tip_mm()
        rig.target = port.tolist()
        rig.step(40)
        assert rig.world_tip_mm().tolist() == pytest.approx(held.tolist(), abs=1e-9)
        assert rig.ctl.stats()["ik_failures"] == 20
        assert rig.robot.state is RobotState.RUNNING
    finally:
        rig.close()


def test_sample_to_write_latency_in_simulated_time(rig: SlaveRig) -> None:
    """GetStats' ``sample_to_write_us``: from the sample's time stamp to the tick that writes
    it, one per sample; in simulated time a sample sent between ticks is written by the next."""
    rig.timestamped = True
    rig.running()
    rig.step(100)
    lat = rig.ctl.stats()["sample_to_write_us"]
    assert lat["n"] == 60  # the 10 samples of running() and the 50 after
    # one tick (the histogram keeps about 0.1 us)
    assert lat["p50"] == pytest.approx(1000.0, abs=0.5) and lat["max"] == pytest.approx(
        1000.0, abs=0.5
    )


@pytest.mark.req("SR-SERVO-1")
def test_run_takes_the_last_target_checked_afresh(rig: SlaveRig) -> None:
    """Run again after a Stop, the source paused (inside its loss grace): the last target is
    checked against where the drives hold and taken, without waiting for a new sample."""
    rig.running()
    here = rig.world_tip_mm()
    rig.target = (here + [1.0, 0.0, 0.0]).tolist()
    rig.step(2)  # one sample of the new target
    rig.command("Stop")
    rig.sending = False
    rig.command("Run")
    rig.step(80)
    assert rig.robot.state is RobotState.RUNNING
    assert rig.world_tip_mm().tolist() == pytest.approx(rig.target, abs=1e-6)


@pytest.mark.req("SR-SERVO-2")
def test_while_rejoining_after_a_hold_the_servo_keeps_its_own_path(rig: SlaveRig) -> None:
    """After a hold the setpoint re-joins the servo's solution at half the velocity limits
    (occ/core/motion.py) while the servo goes on at 0.9 of them from its own last solution: a new
    target is judged, and stepped to, from there (where the tip is told to go), not from the
    setpoint trailing it; and the setpoint still never moves faster than half the limits."""
    rig.running()
    here0 = rig.world_tip_mm()
    direction = np.array([0.0, 0.0, 1.0])
    rig.target = (here0 + 9.5 * direction).tolist()
    rig.step(4)
    rig.sending = False  # the source goes quiet: the robot holds
    rig.step(20)
    rig.sending = True
    rejoining = rig.step(60)
    data = rig.robot.data
    (servo,) = rig.robot.controller.controllers
    solution = np.array(servo._q_last)  # the servo's own last solution
    base = data.base

    def world_mm(q: Any) -> np.ndarray:
        return (base @ np.append(np.array(rig.robot.frame.tip_position(list(q))), 1.0))[:3] * 1e3

    lead = float(np.linalg.norm(world_mm(solution) - world_mm(data.setpoint)))
    assert lead > 1.5  # the setpoint trails the servo by more than max_jump's margin below
    half = [0.5 * j.limits.velocity * 1e-3 * (1 + 1e-9) for j in rig.robot.joints]
    steps = np.abs(np.diff(np.array(rejoining), axis=0)).max(axis=0)
    assert all(s <= h for s, h in zip(steps.tolist(), half, strict=True))
    # 9 mm beyond where the servo is: within max_jump_mm (10) of it, not of the setpoint
    rig.target = (world_mm(solution) + 9.0 * direction).tolist()
    rig.step(600)
    assert rig.ctl.stats()["servo_refused"] == 0
    # the target as the wire carries it (float32: 250 mm to 15 nm)
    assert rig.world_tip_mm().tolist() == pytest.approx(rig.target, abs=2e-5)
