"""Arms that plan together (issue 40, item 5; docs/SAFETY.md SR-CELLPLAN-1..5): a cell keyframe
set, one part per arm, loaded by each member, planned by each, checked against each other's
planned paths at the same times, acknowledged as one, run on one clock and stopped as one.

Two UR5 keyframe robots, members of one cell over the real cell link (UDP on 127.0.0.1), in
simulated time, as tests/occ/test_cell_arms.py: the second 1.6 m along x, turned half round.
Stretched out (MID) at the same time they overlap; each stretched out alone clears the other
at home. The coordinator is occ_testkit/cellplan.py's, the one tools/cell_plan.py runs, here
over in-process operator channels.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

import igtl
from occ.controllers.keyframe.cellset import CellKeyframeFile, cell_set
from occ.core.safety import RobotState
from occ.kinematics.cellpaths import ArmPath, cross_check, path_digest
from occ.kinematics.collision import PeerState
from occ_testkit.cellplan import CellOutcome, coordinate
from occ_testkit.testing import CONFIGS, SimPeer, SimRobot, wait_until
from tests.occ.test_cell import _udp_ports
from tests.occ.test_cell_arms import UR5_FRAME
from tests.occ.test_collision_arms import HOME, REACH, b_base, pair_model

S = RobotState
#: stretched out 0.6 of the way: 72 mm from the other arm at home, into it when both are
MID = [h + 0.6 * (r - h) for h, r in zip(HOME, REACH, strict=True)]

#: both stretch out at once: each part alone clears the other standing at home
CROSS = {
    "arms": {
        "ur5-a": {"keyframes": [{"t": 2.5, "pose": MID, "name": "reach"}]},
        "ur5-b": {"keyframes": [{"t": 2.5, "pose": MID, "name": "reach"}]},
    }
}
#: one after the other: ur5-a out and back by 5 s, ur5-b out from 5 s
TURNS = {
    "space": "joint",
    "arms": {
        "ur5-a": {
            "keyframes": [
                {"t": 2.5, "pose": MID, "name": "reach"},
                {"t": 5.0, "pose": HOME, "name": "home"},
            ]
        },
        "ur5-b": {
            "keyframes": [
                {"t": 5.0, "pose": HOME, "name": "wait"},
                {"t": 7.5, "pose": MID, "name": "reach"},
            ]
        },
    },
}


def member(name: str, members: list[dict[str, Any]], folder: Path) -> SimRobot:
    cfg: dict[str, Any] = yaml.safe_load((CONFIGS / "ur5.yaml").read_text())
    cfg["robot"]["name"] = name
    cfg["safety"]["collision"] = {"margin_mm": 20.0, "self_collision": False}
    cfg["safety"]["loss"] = {"enabled": False}
    cfg["interfaces"] = cfg["interfaces"][:2]  # no master stream
    cfg["interfaces"][1]["inputs"] = [
        {"type": "NDARRAY", "device": "CellPath", "queue": "command", "depth": 4}
    ]
    cfg["interfaces"][1]["outputs"] = [
        {"type": "POLYDATA", "device": "KeyframePath", "source": "keyframe-path", "rate_hz": 10}
    ]
    cfg["controller"] = {
        "plugin": "keyframe",
        "params": {"space": "joint", "keyframe_dir": str(folder)},
    }
    cfg["cell"] = {"name": "or1", "members": members}
    sim = SimRobot(cfg)
    if name == "ur5-b":
        sim.robot.data.base = b_base()
    return sim


class Link:
    """A member's operator port in simulated time (occ_testkit/cellplan.py ``MemberLink``):
    a command goes in with a tick of the whole cell, and 50 more follow its answer (an
    operator's pace: the previews go out at 10 Hz before a plan is acknowledged)."""

    def __init__(self, cell: PlanCell, sim: SimRobot, name: str) -> None:
        self.cell, self.sim, self.name = cell, sim, name
        self.peer: SimPeer = sim.peer("operator")

    def ask(self, command: str, **args: str) -> tuple[bool, str]:
        attrs = "".join(f' {k}="{v}"' for k, v in args.items())
        cid = self.peer.send_command(command, f'<Command Name="{command}"{attrs}/>')
        self.cell.step(1)
        # the planner's and the desk worker's threads answer on the wall clock: wait for them
        # (the cell does not tick meanwhile), then the same ticks whatever they took
        reply = wait_until(lambda: self.peer.reply_to(cid), 60.0, 0.001)
        assert reply is not None, command
        self.cell.step(50)
        meta = reply.metadata
        return meta["Status"] == "SUCCESS", meta.get("Message") or meta.get("Error", "")

    def last_array(self, device: str) -> Any:
        found = self.peer.messages("NDARRAY", device)
        return found[-1] if found else None

    def give(self, msg: Any) -> None:
        self.peer.send(msg)


class PlanCell:
    def __init__(self, folder: Path) -> None:
        ports = _udp_ports(2)
        members = [
            {"name": n, "address": f"127.0.0.1:{p}", "frame": UR5_FRAME, "velocities": [1.0] * 6}
            for n, p in zip(("ur5-a", "ur5-b"), ports, strict=True)
        ]
        self.folder = folder
        self.a = member("ur5-a", members, folder)
        self.b = member("ur5-b", members, folder)
        self.links = [Link(self, self.a, "ur5-a"), Link(self, self.b, "ur5-b")]
        self.step(10)  # each arm heard by the other
        for link in self.links:
            assert link.ask("Enable")[0]
            assert link.ask("Run")[0]

    def write(self, name: str, content: dict[str, Any]) -> str:
        (self.folder / name).write_text(yaml.safe_dump(content))
        return name

    def step(self, n: int = 1) -> None:
        for _ in range(n):
            self.a.step(1)
            self.b.step(1)

    def wall(self) -> float:
        return self.a.clock.wall_time()

    def coordinate(self, name: str, lead_s: float = 0.5) -> CellOutcome:
        return coordinate(self.links, name, self.wall, lead_s)

    def kf(self, sim: SimRobot) -> Any:
        return sim.robot.controller.controllers[0]

    def close(self) -> None:
        self.a.close()
        self.b.close()


@pytest.fixture
def cell(tmp_path: Path) -> Any:
    c = PlanCell(tmp_path)
    yield c
    c.close()


def distance(sim_a: SimRobot, sim_b: SimRobot) -> float:
    """The measured arms' smallest distance (coal, the test's own model)."""
    judge = pair_model()
    peer, checker = judge.peer("ur5-b"), judge.checker()
    peer.update(sim_b.robot.data.q, b_base(), 0.0)
    checker.clearance(sim_a.robot.data.q, np.eye(4))
    return float(checker.peer_seen[0][2])


# ------------------------------------------------------------------------------ the set
@pytest.mark.req("SR-CELLPLAN-1")
def test_each_member_takes_its_own_part_and_keeps_the_whole_set(cell: PlanCell) -> None:
    name = cell.write("turns.yaml", TURNS)
    a, b = cell.links
    ok, text = a.ask("KeyframeLoad", File=name)
    assert ok and "part ur5-a of cell set" in text and "parts ur5-a, ur5-b" in text, text
    assert b.ask("KeyframeLoad", File=name)[0]
    ka, kb = cell.kf(cell.a), cell.kf(cell.b)
    assert len(ka.kset.keyframes) == 2 and ka.kset.keyframes[0].t == 2.5
    assert kb.kset.keyframes[0].t == 5.0
    # one set, one digest, whichever member (and however the file is written)
    assert ka.cell.cset.digest == kb.cell.cset.digest
    assert ka.cell.cset.file.arms["ur5-b"].keyframes[1].t == 7.5
    (cell.folder / "flow.yaml").write_text(yaml.safe_dump(TURNS, default_flow_style=True))
    assert a.ask("KeyframeLoad", File="flow.yaml")[0]
    assert cell.kf(cell.a).cell.cset.digest == kb.cell.cset.digest
    # any other set replaces it: no cell set any more
    assert a.ask("KeyframeAdd", T="1", Pose=" ".join(map(str, REACH)))[0]
    assert ka.cell.current(ka.kset) is None


@pytest.mark.req("SR-CELLPLAN-1")
def test_a_cell_set_that_cannot_be_used_is_refused_saying_why(cell: PlanCell) -> None:
    a = cell.links[0]
    other = cell.write("other.yaml", {"arms": {"ur5-b": CROSS["arms"]["ur5-b"], "ur5-c": {}}})
    ok, text = a.ask("KeyframeLoad", File=other)
    assert not ok and "keyframes" in text, text  # ur5-c's part has no keyframes
    other = cell.write(
        "other.yaml",
        {"arms": {"ur5-b": CROSS["arms"]["ur5-b"], "ur5-c": CROSS["arms"]["ur5-b"]}},
    )
    ok, text = a.ask("KeyframeLoad", File=other)
    assert not ok and "has no part for ur5-a (parts: ur5-b, ur5-c)" in text, text
    one = cell.write("one.yaml", {"arms": {"ur5-a": CROSS["arms"]["ur5-a"]}})
    ok, text = a.ask("KeyframeLoad", File=one)
    assert not ok and "arms" in text, text  # a cell set spans at least two arms
    bad = {"arms": {"ur5-a": {"keyframes": [{"t": 1.0, "pose": [0.0, 0.1]}]}, "ur5-b": {}}}
    bad["arms"]["ur5-b"] = CROSS["arms"]["ur5-b"]
    ok, text = a.ask("KeyframeLoad", File=cell.write("bad.yaml", bad))
    assert not ok and "arms.ur5-a: keyframe 0: 2 values" in text, text
    cf = CellKeyframeFile.model_validate(CROSS)
    with pytest.raises(ValueError, match="this robot is in no cell"):
        cell_set(cf, "cross.yaml", None, "joint", 6, 100)


# ------------------------------------------------------------------------------ the cross-check
@pytest.mark.req("SR-CELLPLAN-2", "SR-CELLPLAN-3")
def test_plans_that_meet_are_refused_though_each_clears_the_other_standing(
    cell: PlanCell,
) -> None:
    name = cell.write("cross.yaml", CROSS)
    out = cell.coordinate(name)
    assert not out.ok
    steps = [(m, c, ok) for m, c, ok, _ in out.replies]
    # each plan alone passed its own checks (the other arm standing at home)
    assert ("ur5-a", "KeyframePlan", True) in steps and ("ur5-b", "KeyframePlan", True) in steps
    assert out.why.startswith("ur5-a: KeyframeCellCheck refused: cell plan refused: at t="), out
    assert "of ur5-a comes" in out.why and "of ur5-b (ur5-a:" in out.why, out.why
    assert " vs ur5-b:" in out.why and "margin 20 mm" in out.why, out.why
    assert not any(c == "KeyframeAck" for _, c, _ in steps)  # none acknowledged
    # ur5-b refuses it too, naming the same meeting from its side
    ok, text = cell.links[1].ask("KeyframeCellCheck", Plan=str(out.plans["ur5-b"]))
    assert not ok and "of ur5-b comes" in text and "of ur5-a (ur5-b:" in text, text
    ka = cell.kf(cell.a)
    assert ka.cell.checked is None
    ok, text = cell.links[0].ask("KeyframeAck", Plan=str(out.plans["ur5-a"]))
    assert not ok and "runs only as one with the others" in text, text


@pytest.mark.req("SR-CELLPLAN-2", "SR-CELLPLAN-3")
def test_plans_clear_of_each_other_agree_on_one_identity(cell: PlanCell) -> None:
    name = cell.write("turns.yaml", TURNS)
    out = cell.coordinate(name, lead_s=0.5)
    assert out.ok, out.why
    checks = [t for _m, c, ok, t in out.replies if c == "KeyframeCellCheck"]
    assert len(checks) == 2 and all(t.startswith(f"cell plan {out.identity}:") for t in checks)
    assert "closest" in checks[0] and " vs ur5-b:" in checks[0], checks[0]
    ka, kb = cell.kf(cell.a), cell.kf(cell.b)
    assert ka.cell.running == kb.cell.running == out.identity


@pytest.mark.req("SR-CELLPLAN-2")
def test_a_path_that_is_not_what_it_claims_or_of_another_set_is_refused(
    cell: PlanCell,
) -> None:
    name = cell.write("turns.yaml", TURNS)
    a, b = cell.links
    for link in (a, b):
        assert link.ask("KeyframeLoad", File=name)[0]
        assert link.ask("KeyframePlan")[0]
    ok, text = a.ask("KeyframeCellCheck", Plan="1")
    assert not ok and "no path yet from ur5-b" in text, text
    assert b.ask("KeyframeCellPath", Plan="1")[0]
    msg = b.last_array("CellPath")
    assert msg.metadata["member"] == "ur5-b" and msg.array.shape == (7501, 6)
    forged = np.array(msg.array)
    forged[4000, 0] += 0.5
    a.give(
        igtl.NDArrayMessage(
            array=forged, device_name="CellPath", metadata=msg.metadata, header_version=2
        )
    )
    ok, text = a.ask("KeyframeCellCheck", Plan="1")
    assert not ok and "ur5-b's path does not match its digest" in text, text
    meta = {**msg.metadata, "set": "0" * 64}
    a.give(
        igtl.NDArrayMessage(
            array=msg.array, device_name="CellPath", metadata=meta, header_version=2
        )
    )
    cell.step(2)
    told = [str(m) for m in a.peer.received if m.message_type != "RTS_COMMAND"]
    assert any("for another cell set" in t for t in told), told[-3:]
    a.give(msg)  # the real one
    ok, text = a.ask("KeyframeCellCheck", Plan="1")
    assert ok and text.startswith("cell plan "), text


@pytest.mark.req("SR-CELLPLAN-2")
def test_the_time_aligned_check_never_skips_a_sample_inside_the_margin() -> None:
    """cross_check against a brute force over every sample: the first sample it refuses is
    the first where the distance, less the skew's motion, is inside the margin."""
    cm = pair_model()
    n = 2001
    s = np.linspace(0.0, 1.0, n)[:, None]
    qa = np.asarray(HOME) + s * (np.asarray(REACH) - np.asarray(HOME))
    qb = np.asarray(HOME) + np.clip(1.5 * s - 0.4, 0.0, 1.0) * (
        np.asarray(REACH) - np.asarray(HOME)
    )
    own = ArmPath("ur5-a", qa, np.eye(4), 1e-3)
    other = ArmPath("ur5-b", qb, b_base(), 1e-3)
    res = cross_check(cm, own, [other], 0.002)
    assert res.clash is not None and res.checked < n / 4  # advancement skips most samples
    checker, arm = cm.checker(), cm.peer("ur5-b")
    reach_b = np.asarray(arm.arm.reach)
    cum = np.concatenate(([0.0], np.cumsum(np.abs(np.diff(qb, axis=0)) @ reach_b)))
    first = None
    for j in range(n):
        lo, hi = max(j - 3, 0), min(j + 3, n - 1)
        d, _ = checker.arm_distance(
            qa[j].tolist(), np.eye(4), arm, PeerState(tuple(qb[j]), b_base(), 0.0)
        )
        if d - (cum[hi] - cum[lo]) < cm.margin:
            first = j
            break
    assert first is not None
    assert math.isclose(res.clash.t, first * 1e-3), (res.clash.t, first)
    assert path_digest(own) != path_digest(ArmPath("ur5-a", qa, b_base(), 1e-3))


# ------------------------------------------------------------------------------ one clock
@pytest.mark.req("SR-CELLPLAN-3", "SR-CELLPLAN-4")
def test_every_member_holds_until_the_common_start_then_both_run_their_parts(
    cell: PlanCell,
) -> None:
    name = cell.write("turns.yaml", TURNS)
    out = cell.coordinate(name, lead_s=0.5)
    assert out.ok, out.why
    start = out.start_at
    qa0, qb0 = list(cell.a.robot.data.setpoint), list(cell.b.robot.data.setpoint)
    while cell.wall() < start - 1e-9:
        assert list(cell.a.robot.data.setpoint) == qa0 and list(cell.b.robot.data.setpoint) == qb0
        cell.step(1)
    cell.step(200)
    assert list(cell.a.robot.data.setpoint) != qa0  # ur5-a's part moves from the start
    # ur5-b's part waits until 5 s (from where it stands to home, a few micro-radians)
    assert max(abs(v - w) for v, w in zip(cell.b.robot.data.setpoint, qb0, strict=True)) < 1e-5
    closest = math.inf
    for k in range(7600):
        cell.step(1)
        if k % 50 == 0:
            closest = min(closest, distance(cell.a, cell.b))
    ka, kb = cell.kf(cell.a), cell.kf(cell.b)
    assert ka.stats()["runs_completed"] == 1 and kb.stats()["runs_completed"] == 1
    assert cell.a.robot.state is S.RUNNING and cell.b.robot.state is S.RUNNING
    assert max(abs(v - g) for v, g in zip(cell.b.robot.data.q, MID, strict=True)) < 0.01
    assert closest > 0.02, closest


@pytest.mark.req("SR-CELLPLAN-4")
def test_a_common_start_in_the_past_or_too_far_ahead_is_refused(cell: PlanCell) -> None:
    name = cell.write("turns.yaml", TURNS)
    out = cell.coordinate(name, lead_s=-0.2)
    assert not out.ok and "s in the past" in out.why and "a common start must be ahead" in out.why
    out = cell.coordinate(name, lead_s=31.0)
    assert not out.ok and "more than cell_start_max_s (30)" in out.why, out.why


# ------------------------------------------------------------------------------ stopped as one
@pytest.mark.req("SR-CELLPLAN-5")
def test_an_operators_stop_in_one_member_drops_every_members_run(cell: PlanCell) -> None:
    name = cell.write("turns.yaml", TURNS)
    out = cell.coordinate(name, lead_s=0.2)
    assert out.ok, out.why
    cell.step(1500)  # ur5-a halfway out
    a, b = cell.links
    assert a.ask("Stop")[0]
    cell.step(5)
    ka, kb = cell.kf(cell.a), cell.kf(cell.b)
    assert cell.a.robot.state is S.STOPPED and cell.b.robot.state is S.STOPPED
    assert ka.stats()["runs_stopped"] == 1 and kb.stats()["runs_stopped"] == 1
    assert ka.active is None and kb.active is None
    assert "cell plan" in cell.b.robot.last_alert and "dropped in ur5-a" in cell.b.robot.last_alert
    held_b = list(cell.b.robot.data.setpoint)
    ok, text = b.ask("Run")
    assert not ok and "ur5-a" in text, text  # until the origin runs again
    assert a.ask("Run")[0]
    cell.step(5)
    assert b.ask("Run")[0]
    cell.step(500)
    assert list(cell.b.robot.data.setpoint) == held_b  # no resume mid-way: it holds there


@pytest.mark.req("SR-CELLPLAN-5")
def test_a_fault_in_one_member_drops_the_others_run_before_its_start(cell: PlanCell) -> None:
    name = cell.write("turns.yaml", TURNS)
    out = cell.coordinate(name, lead_s=1.0)
    assert out.ok, out.why
    ka = cell.kf(cell.a)
    # acknowledged as a cell plan (its identity's first 12 characters) that starts later
    head = f"plan {ka.active.id} (cell plan {ka.cell.running[:12]}) running (starts in "
    assert len(ka.cell.running) > 12 and ka.status.startswith(head), ka.status
    lead = float(ka.status[len(head) :].split(" s, ")[0])
    assert 0.0 < lead <= 1.0 and ka.status.endswith(" s, 5.000 s)"), ka.status
    qa0 = list(cell.a.robot.data.setpoint)
    assert cell.links[1].ask("EStop")[0]
    cell.step(1500)
    assert cell.a.robot.state is S.STOPPED and cell.kf(cell.a).active is None
    assert list(cell.a.robot.data.setpoint) == qa0  # ur5-a never started its part


# ------------------------------------------------------------------------------ shipped
class ShippedCell(PlanCell):
    """configs/cell/ur5-a-keyframe.yaml and ur5-b-keyframe.yaml (bases 600 mm apart), the cell
    link on free ports, the shipped sets of configs/keyframes/."""

    def __init__(self) -> None:
        ports = _udp_ports(2)
        sims = []
        for n in "ab":
            raw = yaml.safe_load((CONFIGS / "cell" / f"ur5-{n}-keyframe.yaml").read_text())
            for m, port in zip(raw["cell"]["members"], ports, strict=True):
                m["address"] = f"127.0.0.1:{port}"
            raw["controller"]["params"]["keyframe_dir"] = str(CONFIGS / "keyframes")
            sims.append(SimRobot(raw))
        self.a, self.b = sims
        self.links = [Link(self, self.a, "ur5-a"), Link(self, self.b, "ur5-b")]
        self.step(10)
        for link in self.links:
            assert link.ask("Enable")[0]
            assert link.ask("Run")[0]


@pytest.mark.req("SR-CELLPLAN-2", "SR-CELLPLAN-3")
def test_the_shipped_cell_sets_one_refused_one_run_in_turns() -> None:
    cell = ShippedCell()
    try:
        out = cell.coordinate("cell-cross.yaml")
        plans = [(m, ok) for m, c, ok, _ in out.replies if c == "KeyframePlan"]
        assert plans == [("ur5-a", True), ("ur5-b", True)], out.replies
        assert "KeyframeCellCheck refused: cell plan refused: at t=" in out.why, out.why
        assert "of ur5-a comes" in out.why and "of ur5-b (ur5-a:" in out.why, out.why
        out = cell.coordinate("cell-turns.yaml", lead_s=0.2)
        assert out.ok, out.why
        closest = math.inf
        judge = pair_model()
        peer, checker = judge.peer("ur5-b"), judge.checker()
        b_at = np.eye(4)
        b_at[0, 3] = 0.6
        for k in range(18500):
            cell.step(1)
            if k % 50 == 0:
                peer.update(cell.b.robot.data.q, b_at, 0.0)
                checker.clearance(cell.a.robot.data.q, np.eye(4))
                closest = min(closest, checker.peer_seen[0][2])
        for sim in (cell.a, cell.b):
            assert sim.robot.state is S.RUNNING, sim.robot.last_alert
            assert cell.kf(sim).stats()["runs_completed"] == 1
        assert closest > 0.04, closest
    finally:
        cell.close()
