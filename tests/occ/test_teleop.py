"""The teleoperation mapping of the slave, exact to float precision (occ/controllers/teleop.py).

``target = slave_ref + scale * R * (master - master_ref)``: the slave robot (configs/slave.yaml)
on in-process channels, stepped tick by tick; the master's stream comes from a peer. The
slave's inverse kinematics is analytic, so the tip of the setpoint it writes is the mapped
target to ~1e-9 mm, and every entry of ``scale * R`` can be read back from it. Each of these
tests was written against a mutant that the older, coarser tests let live
(docs/VERIFICATION.md, "teleop").
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import igtl
from occ.safety import RobotState
from occ.testing import SimRobot

ROOT = Path(__file__).resolve().parents[2]
MASTER = ("127.0.0.1", 40000)


def rotation(yaw: float, pitch: float, roll: float) -> list[list[float]]:
    """A rotation whose nine entries all differ (a swapped index changes the mapping)."""
    cz, sz = math.cos(yaw), math.sin(yaw)
    cy, sy = math.cos(pitch), math.sin(pitch)
    cx, sx = math.cos(roll), math.sin(roll)
    rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    return (rz @ ry @ rx).tolist()


R = rotation(0.3, -0.5, 0.7)


class Rig:
    """The slave, its master's stream (a sample every 2 ms) and an operator."""

    def __init__(self, **params: Any) -> None:
        self.sim = SimRobot(ROOT / "configs" / "slave.yaml", params=params or None)
        self.robot = self.sim.robot
        self.ctl: Any = self.robot.controller
        self.master = self.sim.peer("master", address=MASTER)
        self.operator = self.sim.peer("operator", address=("127.0.0.1", 40001))
        self.seq = 0
        self.pos = [0.0, 50.0, 270.0]
        self.run = True
        self.clutch = False

    def send(self, **kw: Any) -> None:
        self.seq += 1
        self.master.send_position(self.pos, seq=self.seq, run=self.run, clutch=self.clutch, **kw)

    def step(self, ms: int) -> None:
        for _ in range(ms):
            if self.sim.k % 2 == 0:
                self.send()
            self.sim.tick()

    def command(self, name: str) -> None:
        cid = self.operator.send_command(name)
        self.sim.tick()
        reply = self.operator.reply_to(cid)
        assert reply is not None and reply.metadata["Status"] == "SUCCESS", name

    def running(self) -> None:
        self.command("Enable")
        self.command("Run")
        self.step(20)
        assert self.robot.state is RobotState.RUNNING

    def tip_mm(self) -> np.ndarray:
        """FK of the setpoint the slave writes, mm."""
        return np.array(self.robot.frame.tip_position(self.robot.data.setpoint)) * 1e3

    def close(self) -> None:
        self.sim.close()


@pytest.fixture
def rig() -> Any:
    r = Rig()
    yield r
    r.close()


@pytest.mark.req("SR-TELE-1")
def test_every_entry_of_scale_times_rotation_is_applied() -> None:
    rig = Rig(scale=0.2, rotation=R)
    try:
        rig.running()
        start = rig.tip_mm()
        stats = rig.ctl.stats()
        assert stats["slave_ref_mm"] == pytest.approx(start.tolist(), abs=1e-6)
        assert stats["master_ref_mm"] == pytest.approx(rig.pos)
        m0 = list(rig.pos)
        for axis in range(3):  # 3 mm along each master axis in turn: one column of 0.2 R each
            rig.pos = list(m0)
            rig.pos[axis] += 3.0
            rig.step(2)
            moved = rig.tip_mm() - start
            expect = [0.2 * 3.0 * R[row][axis] for row in range(3)]
            assert moved.tolist() == pytest.approx(expect, abs=1e-6), axis
        rig.pos = [m0[0] + 1.0, m0[1] - 2.0, m0[2] + 4.0]  # a general displacement
        rig.step(2)
        d = np.array([1.0, -2.0, 4.0])
        assert (rig.tip_mm() - start).tolist() == pytest.approx((0.2 * np.array(R) @ d).tolist(), abs=1e-6)
        assert rig.ctl.stats()["reindexes"] == 1
    finally:
        rig.close()


@pytest.mark.req("SR-CLUTCH-1")
def test_clutch_holds_exactly_and_release_reindexes_where_the_master_is(rig: Rig) -> None:
    rig.running()
    rig.pos[0] += 5.0
    rig.step(2)
    before = rig.tip_mm()
    setpoint = list(rig.robot.data.setpoint)
    assert rig.ctl.stats()["reindexes"] == 1
    rig.clutch = True
    for _ in range(10):
        rig.pos[1] += 2.0
        rig.step(2)
        assert list(rig.robot.data.setpoint) == setpoint  # not one bit of motion
    stats = rig.ctl.stats()
    assert stats["master_clutch"] is True and stats["master_ref_mm"] is None
    rig.clutch = False
    rig.step(2)  # released 20 mm away: the new references are here, no jump
    stats = rig.ctl.stats()
    assert stats["master_clutch"] is False and stats["reindexes"] == 2
    assert stats["master_ref_mm"] == pytest.approx(rig.pos)
    assert rig.tip_mm().tolist() == pytest.approx(before.tolist(), abs=1e-6)
    rig.pos[2] -= 10.0
    rig.step(2)
    assert (rig.tip_mm() - before).tolist() == pytest.approx([0.0, 0.0, -1.0], abs=1e-6)
    assert rig.ctl.stats()["reindexes"] == 2  # pressing and holding does not re-index again


@pytest.mark.req("SR-CLUTCH-1")
def test_run_flag_zero_holds_and_its_rising_edge_reindexes(rig: Rig) -> None:
    rig.running()
    setpoint = list(rig.robot.data.setpoint)
    before = rig.tip_mm()
    rig.run = False
    rig.pos[0] += 30.0
    rig.step(10)
    assert list(rig.robot.data.setpoint) == setpoint
    assert rig.ctl.stats()["master_run"] is False
    rig.run = True
    rig.step(2)
    stats = rig.ctl.stats()
    assert stats["master_run"] is True and stats["reindexes"] == 2
    assert rig.tip_mm().tolist() == pytest.approx(before.tolist(), abs=1e-6)
    rig.pos[0] += 1.0
    rig.step(2)
    assert (rig.tip_mm() - before).tolist() == pytest.approx([0.1, 0.0, 0.0], abs=1e-6)


@pytest.mark.req("SR-TELE-1")
def test_entering_running_reindexes_from_the_held_pose(rig: Rig) -> None:
    rig.running()
    rig.pos[0] += 10.0
    rig.step(4)
    rig.command("Stop")
    held = rig.tip_mm()
    rig.pos[0] += 40.0  # the master moves on while the slave is stopped
    rig.step(10)
    rig.command("Run")
    rig.step(2)
    assert rig.robot.state is RobotState.RUNNING
    assert rig.ctl.stats()["reindexes"] == 2
    assert rig.tip_mm().tolist() == pytest.approx(held.tolist(), abs=1e-6)


def test_samples_are_counted_and_filtered_by_interface_device_and_type() -> None:
    rig = Rig(input_device="Master")
    try:
        rig.running()
        stats = rig.ctl.stats()
        n = stats["samples"]
        assert stats["last_seq"] == rig.seq and stats["source"] == "master"
        assert stats["source_changes"] == 0
        before = rig.tip_mm()
        # another device on the same interface: ignored
        rig.seq += 1
        rig.master.send_position((rig.pos[0] + 50.0, rig.pos[1], rig.pos[2]), seq=rig.seq,
                                 device="Other")
        rig.sim.tick()
        rig.sim.tick()
        assert rig.ctl.stats()["samples"] == n
        assert rig.tip_mm().tolist() == pytest.approx(before.tolist(), abs=1e-9)
    finally:
        rig.close()


def test_a_sample_on_another_interface_is_not_followed() -> None:
    rig = Rig()
    try:
        rig.running()
        n = rig.ctl.stats()["samples"]
        before = rig.tip_mm()
        other = rig.sim.peer("operator", address=("127.0.0.1", 40009))
        other.send_position((rig.pos[0] + 50.0, rig.pos[1], rig.pos[2]), seq=1)
        rig.sim.tick()
        rig.sim.tick()
        assert rig.ctl.stats()["samples"] == n and rig.ctl.stats()["source"] == "master"
        assert rig.tip_mm().tolist() == pytest.approx(before.tolist(), abs=1e-9)
    finally:
        rig.close()
