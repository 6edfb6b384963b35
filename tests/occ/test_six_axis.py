"""A 6-axis sensor's reading kept (issue 37, item 5): its torques are no longer dropped.

- Read: six values are force and torque, scaled by the unit's prefix alike; a torque that is not
  finite refuses the reading; the torque is turned into the patient frame as the force is, sent
  only while the sensor is the source used.
- Sent: the slave's return channel (``SlaveTip``) and its force outputs to 3D Slicer carry
  ``torque_nm`` beside ``force_n`` (a 3-axis sensor: no key, as before); the master's
  ``ReturnLink`` parses it, refuses and counts a malformed one.
- Displayed where the master has the rotational axes: a 6-joint haptic master (the UR5's
  kinematics on the ``sim-hand`` device, a test config) gets ``J^T [F; T]`` on its efforts, the
  torque gated like the force, clamped to ``max_torque_nm`` and passivated against the handle's
  angular velocity; the shipped 3-axis master records it only (its stats, its recording).
- Recorded: the export's ``measured_cf`` carries the torque of the recorded ``SlaveTip``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

import igtl
from igtl.messages.sensor import NEWTON, Unit
from occ.net.decoders import event_of
from occ.haptics.forces import SlaveForce, sensor_wrench
from occ.kinematics.frame import Frame
from occ.recording.record import Recorder
from occ.recording.cli import main
from occ.haptics.returnlink import ReturnLink
from occ.samples import PoseSample
from occ_testkit.rigs import SimMaster
from occ_testkit.testing import CONFIGS, SimRobot, SlaveTipFeed

from .test_recexport import decode_mcap, require
from .test_sensor_tare import SENSOR_IFACE

pytestmark = pytest.mark.req("SR-FORCE-22")

SLAVE = Frame.builtin("occ_slave")


def sensor(values: tuple[float, ...], unit: Unit | int = NEWTON) -> Any:
    return igtl.SensorMessage(values, unit, device_name="ForceSensor")


# ------------------------------------------------------------------------------ read
def test_six_values_are_a_wrench_scaled_alike_and_refused_whole() -> None:
    assert sensor_wrench(event_of(sensor((1.0, 2.0, 3.0, 0.1, -0.2, 0.3)))) == (
        (1.0, 2.0, 3.0),
        (0.1, -0.2, 0.3),
        "",
    )
    milli = Unit(11, ((11, 1),))  # mN, so mN m
    f, t, _ = sensor_wrench(event_of(sensor((1000.0, 0.0, -500.0, 20.0, 0.0, -5.0), milli)))
    assert f == pytest.approx((1.0, 0.0, -0.5)) and t == pytest.approx((0.02, 0.0, -0.005))
    assert sensor_wrench(event_of(sensor((1.0, 2.0, 3.0)))) == ((1.0, 2.0, 3.0), None, "")
    assert sensor_wrench(event_of(sensor((1.0, 2.0, 3.0, math.nan, 0.0, 0.0)))) == (
        None,
        None,
        "not a torque: (nan, 0.0, 0.0)",
    )
    src = SlaveForce(("sensor",), sensor_interface="s")
    assert src.on_input(event_of(sensor((0.0, 0.0, 1.0, 0.0, 0.0, 0.2)), "s"), 0.0)
    assert not src.on_input(event_of(sensor((0.0, 0.0, 9.0, math.inf, 0.0, 0.0)), "s"), 0.001)
    assert src.sensor_refused == 1  # the last good reading kept, whole
    assert src.estimate(0.002, SLAVE, [0.0] * 3, [0.0] * 3, [0.0] * 3, np.eye(4), np.eye) == (
        0.0,
        0.0,
        1.0,
    )
    assert src.torque_nm == (0.0, 0.0, 0.2)


def test_the_torque_turns_with_the_force_and_is_sent_only_from_the_sensor() -> None:
    c, s = math.cos(0.7), math.sin(0.7)
    base = np.eye(4)
    base[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    tip = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    t = np.array([0.01, -0.03, 0.02])
    for frame, rot in (("patient", np.eye(3)), ("base", base[:3, :3]), ("tip", base[:3, :3] @ tip)):
        src = SlaveForce(("sensor", "effort"), sensor_interface="s", sensor_frame=frame)
        assert src.on_input(event_of(sensor((0.5, 0.0, 0.0, *t)), "s"), 0.0)
        f = src.estimate(0.0, SLAVE, [0.0, 0.35, 0.05], [0.0] * 3, [0.0] * 3, base, lambda: tip)
        assert f == pytest.approx(tuple(rot @ [0.5, 0.0, 0.0]), abs=1e-15)
        assert src.torque_nm == pytest.approx(tuple(rot @ t), abs=1e-15), frame
        assert src.stats(0.0)["torque_nm"] == [round(v, 4) for v in rot @ t]
        # the sensor silent: the effort estimate is sent, and it has no torque
        src.estimate(1.0, SLAVE, [0.0, 0.35, 0.05], [0.0] * 3, [0.0] * 3, base, lambda: tip)
        assert src.used == "effort" and src.torque_nm is None


# ------------------------------------------------------------------------------ sent
def slave_with_sensor() -> tuple[SimRobot, Any, Any, Any]:
    cfg = yaml.safe_load((CONFIGS / "wall.yaml").read_text())
    cfg["interfaces"].append(SENSOR_IFACE)
    cfg["controller"]["params"]["force"].update(
        sources=["sensor", "tissue"], sensor_interface="sensor", sensor_timeout_ms=50.0
    )
    sim = SimRobot(cfg)
    return (
        sim,
        sim.peer("master", address=("127.0.0.1", 40000)),
        sim.peer("sensor", address=("127.0.0.1", 40100)),
        sim.peer("slicer"),
    )


def test_the_slave_sends_the_torque_beside_the_force_and_nothing_for_three_axes() -> None:
    sim, master, sens, slicer = slave_with_sensor()
    try:
        for seq in range(1, 51):  # a master streaming (the return channel's owner)
            master.send_position((0.0, 50.0, 20.0), seq=seq, run=False)
            sens.send(sensor((0.1, -0.2, 0.3, 0.004, -0.005, 0.006)))
            sim.step(2)
        tips = master.messages("POSITION", "SlaveTip")
        assert len(tips) > 40
        last = tips[-1].metadata
        assert last["force_n"] == "0.1000,-0.2000,0.3000"
        assert last["torque_nm"] == "0.00400,-0.00500,0.00600"
        shown = slicer.messages("TRANSFORM", "TipForce")[-1].metadata
        assert shown["torque_nm"] == "0.00400,-0.00500,0.00600"
        for seq in range(51, 61):  # a 3-axis reading: no torque key at all (as before)
            master.send_position((0.0, 50.0, 20.0), seq=seq, run=False)
            sens.send(sensor((0.1, -0.2, 0.3)))
            sim.step(2)
        last = master.messages("POSITION", "SlaveTip")[-1].metadata
        assert last["force_n"] == "0.1000,-0.2000,0.3000" and "torque_nm" not in last
    finally:
        sim.close()


def tip_sample(seq: int, **meta: str) -> PoseSample:
    return PoseSample(
        "slave",
        None,
        "SlaveTip",
        (1.0, 2.0, 3.0),
        seq=seq,
        meta={"map": "1,0,0,0,1,0,0,0,1", **meta},
    )


def test_the_masters_link_takes_the_torque_and_refuses_a_malformed_one() -> None:
    link = ReturnLink("slave")
    assert link.on_sample(tip_sample(1, force_n="1,2,3", torque_nm="0.1,0.2,-0.3"), 0.0, 0.0)
    assert link.torque == (0.1, 0.2, -0.3) and link.stats(0.0)["torque_nm"] == [0.1, 0.2, -0.3]
    assert link.on_sample(tip_sample(2, force_n="1,2,3"), 0.002, 0.0)
    assert link.torque is None  # a 3-axis force now
    for seq, bad in ((3, "0.1,0.2"), (4, "x,0,0"), (5, "nan,0,0")):
        assert not link.on_sample(tip_sample(seq, force_n="1,2,3", torque_nm=bad), 0.004, 0.0)
    assert (
        link.bad_metadata == 3 and link.last_error == "seq 5: torque_nm 'nan,0,0' is not 3 numbers"
    )
    assert link.torque is None and link.seq == 2  # the refused samples' content not used


# ------------------------------------------------------------------------------ displayed
def six_joint_master(**params: Any) -> dict[str, Any]:
    """configs/master.yaml on a 6-joint haptic device: the UR5's kinematics (configs/ur5.yaml)
    as the handle's, the ``sim-hand`` device and hand on every joint, the hand holding the
    handle at home (no intended motion)."""
    cfg = yaml.safe_load((CONFIGS / "master.yaml").read_text())
    ur5 = yaml.safe_load((CONFIGS / "ur5.yaml").read_text())["robot"]
    homes = [j["home"] for j in ur5["joints"]]
    cfg["robot"]["frame"] = ur5["frame"]
    cfg["robot"]["joints"] = ur5["joints"]
    cfg["robot"]["drivers"][0].update(
        joints=[j["name"] for j in ur5["joints"]],
        params={"inertia": 0.05, "damping": 0.5, "hand_stiffness": 20.0, "hand_damping": 2.0,
                "intent_amplitude": [0.0] * 6, "intent_offset": homes},
    )  # fmt: skip
    cfg["controller"]["params"].update(params)
    return cfg


def six_master(**params: Any) -> SimMaster:
    """The six-joint master, its slave played by a tip feed, running."""
    m = SimMaster(six_joint_master(**params), feed=True)
    m.run()
    return m


def efforts_check(m: SimMaster) -> None:
    """The efforts the drives were told are J^T [F; T] of what is displayed."""
    data = m.sim.robot.data
    jac = m.sim.robot.frame.jacobian(data.q)
    want = jac[:3].T @ np.array(m.ctl.display.displayed_n) + jac[3:].T @ np.array(
        m.ctl.display.displayed_torque_nm
    )
    assert data.effort_command == pytest.approx(list(want), abs=1e-12)


def test_a_master_with_rotational_axes_displays_the_torque_clamped_and_gated() -> None:
    m = six_master()
    try:
        assert m.ctl.display.rotational
        m.feed.force = (0.0, 0.0, 1.0)
        m.feed.torque = (0.05, -0.1, 0.2)
        m.feed.step(1)
        assert m.ctl.display.gain == 1.0  # the tip fresh, the slave following: the force's own gain
        # the handle at rest: no damper without motion, the torque as sent
        assert m.ctl.display.feedback_torque_nm == pytest.approx((0.05, -0.1, 0.2), abs=1e-12)
        assert m.ctl.display.displayed_torque_nm == pytest.approx((0.05, -0.1, 0.2), abs=1e-12)
        efforts_check(m)
        m.feed.step(20)  # the hand yields: the passivity controller acts on what it gives
        assert m.ctl.display.torque_passivity.active_ticks > 0
        efforts_check(m)
        wrist = [abs(v) for v in m.sim.robot.data.effort_command[3:]]
        assert max(wrist) > 0.05  # the wrist's joints carry it
        # 2 N m: clamped to max_torque_nm (0.5)
        m.feed.torque = (0.0, 2.0, 0.0)
        m.feed.step(1)
        assert math.hypot(*m.ctl.display.displayed_torque_nm) == pytest.approx(0.5, abs=1e-12)
        efforts_check(m)
        # the slave lost (silent past the grace): zero at once, with the force
        m.feed.paused = True
        m.sim.step(120)
        assert m.ctl.display.displayed_torque_nm == (0.0, 0.0, 0.0)
        assert m.ctl.display.feedback_torque_nm == (0.0, 0.0, 0.0)
        efforts_check(m)
    finally:
        m.sim.close()


def test_the_displayed_torque_is_passivated_against_the_handles_rotation() -> None:
    """A torque held on a hand that yields (a soft wrist: 20 N m/rad) turns the handle: the
    torque gives the hand energy it never put in (the network's, as a stuck force would).
    Without passivity the observer shows it given (-0.93 mJ over 0.3 s); with it a damper takes
    the excess (20 N m s/rad at most here) and what shows is under 5 % of that: the ticks
    before the handle moves, where no damper can act (a step onto a handle at rest)."""
    energy = {}
    for on in (True, False):
        m = six_master(passivity=on, passivity_max_rot_damping=20.0)
        try:
            m.feed.torque = (0.0, 0.0, 0.1)
            m.feed.step(300)
            st = m.ctl.stats()["torque"]["passivity"]
            efforts_check(m)
        finally:
            m.sim.close()
        energy[on] = st["energy_mj"]
        assert (st["dissipated_mj"] > 0.05 and st["active_ticks"] > 10) is on
    assert energy[False] < -0.5
    assert 0.0 > energy[True] > 0.05 * energy[False]


def test_a_three_axis_master_records_the_torque_and_displays_the_force_only() -> None:
    sim = SimRobot(CONFIGS / "master.yaml")
    try:
        ctl: Any = sim.robot.controller.controllers[0]
        op = sim.peer("operator", address=("127.0.0.1", 41000))
        sim.step(1)
        feed = SlaveTipFeed(sim)
        for c in ("Enable", "Run"):
            op.send_command(c)
            feed.step(1)
        feed.force, feed.torque = (0.0, 0.0, 1.0), (0.05, -0.1, 0.2)
        feed.step(40)
        assert not ctl.display.rotational
        assert ctl.display.feedback_torque_nm == pytest.approx((0.05, -0.1, 0.2), abs=1e-12)
        assert ctl.display.displayed_torque_nm == (0.0, 0.0, 0.0)
        assert ctl.stats()["torque"]["displayed"] is False
        data = sim.robot.data
        jac = sim.robot.frame.jacobian(data.q)[:3]
        shown = ctl.display.displayed_n
        assert data.effort_command == pytest.approx(list(jac.T @ shown), abs=1e-12)
    finally:
        sim.close()


# ------------------------------------------------------------------------------ recorded
def test_the_export_carries_the_recorded_torque(tmp_path: Path) -> None:
    require("rosbags", "pip install -e .[record]")
    sim, master, sens, _ = slave_with_sensor()
    path = tmp_path / "slave.igtl"
    rec = Recorder(path, rate_hz=100).start()
    try:
        sim.robot.set_recorder(rec)
        for seq in range(1, 101):
            master.send_position((0.0, 50.0, 20.0), seq=seq, run=False)
            sens.send(sensor((0.1, -0.2, 0.3, 0.004, -0.005, 0.006 * (seq % 2))))
            sim.step(2)
    finally:
        rec.close()
        sim.close()
    out = tmp_path / "slave.mcap"
    assert main(["export", str(path), str(out)]) == 0
    cf = decode_mcap(out)["/occ/slave/measured_cf"]
    assert len(cf) > 90
    torques = {(w.torque.x, w.torque.y, w.torque.z) for w in (m.wrench for m, _ in cf)}
    assert torques == {(0.004, -0.005, 0.0), (0.004, -0.005, 0.006)}
