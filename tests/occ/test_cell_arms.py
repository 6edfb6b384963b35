"""Arm against arm through the cell link (issue 40): two UR5 keyframe robots, members of one
cell whose heartbeats (real UDP on 127.0.0.1, occ/net/celllink.py) carry each arm's joints and
base to the other's collision guard (occ/core/wiring.py). The geometry is
tests/occ/test_collision_arms.py's: the second arm 1.6 m along x, turned half round."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import yaml

from occ.core.safety import RobotState
from occ_testkit.testing import CONFIGS, SimRobot
from tests.occ.test_cell import _udp_ports, shipped_cell
from tests.occ.test_collision_arms import REACH, b_base, command, pair_model

UR5_FRAME = {
    "package": "example-robot-data",
    "package_urdf": "robots/ur_description/urdf/ur5_joint_limited_robot.urdf",
    "tip_link": "tool0",
    "base_link": "base_link",
}


def member(name: str, members: list[dict[str, Any]], goal: list[float]) -> SimRobot:
    cfg: dict[str, Any] = yaml.safe_load((CONFIGS / "ur5.yaml").read_text())
    cfg["robot"]["name"] = name
    cfg["safety"]["collision"] = {"margin_mm": 20.0, "self_collision": False}
    cfg["safety"]["loss"] = {"enabled": False}
    cfg["interfaces"] = cfg["interfaces"][:2]  # no master stream
    cfg["interfaces"][1]["outputs"] = [  # the plan's preview: it may be acknowledged once sent
        {"type": "POLYDATA", "device": "KeyframePath", "source": "keyframe-path", "rate_hz": 10}
    ]
    cfg["controller"] = {
        "plugin": "keyframe",
        "params": {"space": "joint", "keyframes": [{"t": 2.5, "pose": goal, "name": "reach"}]},
    }
    cfg["cell"] = {"name": "or1", "members": members}
    sim = SimRobot(cfg)
    if name == "ur5-b":
        sim.robot.data.base = b_base()
    return sim


class ArmCell:
    def __init__(self) -> None:
        ports = _udp_ports(2)
        members = [
            {"name": n, "address": f"127.0.0.1:{p}", "frame": UR5_FRAME, "velocities": [1.0] * 6}
            for n, p in zip(("ur5-a", "ur5-b"), ports, strict=True)
        ]
        self.a = member("ur5-a", members, REACH)
        self.b = member("ur5-b", members, REACH)

    def step(self, n: int = 1) -> None:
        for _ in range(n):
            self.a.step(1)
            self.b.step(1)

    def plan_and_run(self, sim: SimRobot) -> None:
        reply = command(sim, "KeyframePlan")
        assert reply["Status"] == "SUCCESS", reply
        plan_id = reply["Message"].split(":")[0].split()[1]
        self.step(150)
        assert command(sim, "Run")["Status"] == "SUCCESS"
        assert command(sim, "KeyframeAck", Plan=plan_id)["Status"] == "SUCCESS"

    def close(self) -> None:
        self.a.close()
        self.b.close()


@pytest.fixture
def cell() -> Any:
    c = ArmCell()
    yield c
    c.close()


@pytest.mark.req("SR-ARMS-2")
def test_two_arms_of_a_cell_driven_toward_each_other_both_stop_before_contact(
    cell: ArmCell,
) -> None:
    cell.step(10)  # each arm heard by the other: its geometry known
    for sim in (cell.a, cell.b):
        assert command(sim, "Enable")["Status"] == "SUCCESS"
    cell.step(5)
    for sim in (cell.a, cell.b):
        cell.plan_and_run(sim)  # each plan clears the other arm where it stands (at home)
    judge = pair_model()
    peer, checker = judge.peer("ur5-b"), judge.checker()
    closest = math.inf
    for _ in range(3500):
        cell.step(1)
        peer.update(cell.b.robot.data.q, b_base(), 0.0)
        checker.clearance(cell.a.robot.data.q, np.eye(4))
        closest = min(closest, checker.peer_seen[0][2])
    for sim, other in ((cell.a, "ur5-b"), (cell.b, "ur5-a")):
        r = sim.robot
        assert r.state is RobotState.STOPPED, (r.state, r.last_alert)
        assert f"of the arm '{other}'" in r.last_alert or f"cell or1: {other}" in r.last_alert
    # at least one stopped for the other arm itself (the other may have been held by the cell)
    assert any(" vs ur5-" in s.robot.last_alert for s in (cell.a, cell.b))
    assert closest >= 0.01, closest  # the measured arms: never closer than half the margin


@pytest.mark.req("SR-ARMS-3")
def test_a_plan_into_the_other_arm_of_the_cell_is_refused_naming_both_links(
    cell: ArmCell,
) -> None:
    cell.step(10)
    assert command(cell.b, "Enable")["Status"] == "SUCCESS"
    cell.step(5)
    cell.plan_and_run(cell.b)  # ur5-b stretches out alone: ur5-a stands at home
    cell.step(3000)
    assert max(abs(v - g) for v, g in zip(cell.b.robot.data.q, REACH, strict=True)) < 0.01
    assert command(cell.a, "Enable")["Status"] == "SUCCESS"
    reply = command(cell.a, "KeyframePlan")
    assert reply["Status"] == "FAIL", reply
    err = reply["Error"]
    assert "of the arm 'ur5-b'" in err and " vs ur5-b:" in err, err


@contextlib.contextmanager
def shipped_rigs() -> Iterator[list[Any]]:
    """configs/cell/'s two UR5 slaves (tests/occ/test_cell.py's ``shipped_cell``), each with
    its master's stream (occ_testkit.rigs.SlaveRig), heard by each other and RUNNING."""
    from occ_testkit.rigs import SlaveRig

    rigs: list[Any] = []
    try:
        for raw in shipped_cell():
            rigs.append(SlaveRig(raw))
        for _ in range(10):
            for rig in rigs:
                rig.step(1)
        for rig in rigs:
            rig.running()
        yield rigs
    finally:
        for rig in rigs:
            rig.close()


@pytest.mark.req("SR-ARMS-2")
def test_the_shipped_cells_arms_teleoperated_toward_each_other_both_stop() -> None:
    """configs/cell/ (bases 600 mm apart, the cell link on free ports), each UR5 following its
    master's stream at 500 Hz: the masters move the two tips toward each other at 100 mm/s of
    the tool; both arms stop, the measured arms never closer than half the margin (10 mm)."""
    with shipped_rigs() as rigs:
        b_base_m = np.eye(4)
        b_base_m[0, 3] = 0.6
        judge = pair_model()
        peer, checker = judge.peer("ur5-b"), judge.checker()
        closest = math.inf
        for k in range(4000):  # 4 s: 0.4 m of the tool each, far past where they would meet
            rigs[0].target[0] += 0.2  # master mm per tick (scale 0.5: 0.1 mm of the tool)
            rigs[1].target[0] -= 0.2
            for rig in rigs:
                rig.step(1)
            if k % 5 == 0:
                peer.update(rigs[1].robot.data.q, b_base_m, 0.0)
                checker.clearance(rigs[0].robot.data.q, np.eye(4))
                closest = min(closest, checker.peer_seen[0][2])
        states = [rig.robot.state for rig in rigs]
        alerts = [rig.robot.last_alert for rig in rigs]
        assert states == [RobotState.STOPPED] * 2, (states, alerts)
        assert any(" vs ur5-" in a for a in alerts), alerts
        assert 0.01 <= closest < 0.05, closest  # close, as driven, and never within 10 mm


@pytest.mark.req("SR-CELL-1")
def test_a_loss_stop_in_one_arm_of_the_shipped_cell_holds_the_other() -> None:
    """ur5-a's master falls silent: its loss monitor stops it (latched), and ur5-b, following
    its own master, holds for it, the alert naming ur5-a and the lost stream."""
    with shipped_rigs() as rigs:
        rigs[0].sending = False
        for _ in range(150):
            for rig in rigs:
                rig.step(1)
        assert rigs[0].robot.state is RobotState.STOPPED
        assert "packet loss" in rigs[0].robot.last_alert
        assert rigs[1].robot.state is RobotState.STOPPED
        why = rigs[1].robot.snapshot()["cell"]["latched"]["ur5-a"]
        assert why.startswith("ur5-a packet loss on master"), why
