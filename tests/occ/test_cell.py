"""The cell (occ/core/cell.py, occ/net/celllink.py): a stop in one member stops every other.

Members are robots in simulated time (occ_testkit's SimRobot, their operator interfaces
in-process) whose cell links are real UDP sockets on 127.0.0.1, ticked in turn: a heartbeat
sent in one member's tick is in the other's socket when it ticks.
"""

from __future__ import annotations

import socket
from collections.abc import Iterator
from typing import Any

import pytest

from occ.config import DaemonConfig
from occ.core.safety import RobotState
from occ_testkit.testing import SimPeer, SimRobot

S = RobotState


def _udp_ports(n: int) -> list[int]:
    socks = []
    for _ in range(n):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        socks.append(s)
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def shipped_cell() -> list[dict[str, Any]]:
    """configs/cell/ur5-a.yaml and ur5-b.yaml as mappings, their cell links on free ports."""
    import yaml

    from occ_testkit.testing import CONFIGS

    ports = _udp_ports(2)
    raws = []
    for n in "ab":
        raw = yaml.safe_load((CONFIGS / "cell" / f"ur5-{n}.yaml").read_text())
        for m, port in zip(raw["cell"]["members"], ports, strict=True):
            m["address"] = f"127.0.0.1:{port}"
        raws.append(raw)
    return raws


def member_config(name: str, members: list[dict[str, Any]], **cell: Any) -> DaemonConfig:
    """A 3-DOF slave on simulated drives that holds where it is (no stream to lose), member
    ``name`` of the cell ``members``."""
    return DaemonConfig.model_validate(
        {
            "robot": {
                "name": name,
                "rate_hz": 1000,
                "frame": {"model": "occ_slave"},
                "joints": [
                    {"name": "yaw", "type": "revolute", "home": 0.0,
                     "limits": {"min": -1.0, "max": 1.0, "velocity": 1.5}},
                    {"name": "pitch", "type": "revolute", "home": 0.35,
                     "limits": {"min": -1.0, "max": 1.0, "velocity": 1.5}},
                    {"name": "insertion", "type": "prismatic", "home": 0.05,
                     "limits": {"min": 0.0, "max": 0.15, "velocity": 0.1}},
                ],
                "drivers": [{"name": "sim", "plugin": "sim",
                             "joints": ["yaw", "pitch", "insertion"]}],
            },
            "interfaces": [
                {"name": "operator", "transport": "tcp-server", "host": "127.0.0.1",
                 "port": 0, "role": "operator"},
            ],
            "safety": {"loss": {"enabled": False}},
            "cell": {"name": "or1", "members": members, **cell},
        }
    )  # fmt: skip


def ok(reply: Any) -> bool:
    return bool(reply.metadata.get("Status") == "SUCCESS")


def error_of(reply: Any) -> str:
    assert reply.metadata.get("Status") == "FAIL", reply.metadata
    return str(reply.metadata["Error"])


class Cell:
    """``n`` members ``arm0..`` ticked in turn, each with an operator."""

    def __init__(self, n: int = 2, *, frames: bool = True, **cell: Any) -> None:
        ports = _udp_ports(n)
        self.members = [
            {"name": f"arm{i}", "address": f"127.0.0.1:{p}"}
            | ({"frame": {"model": "occ_slave"}} if frames else {})
            for i, p in enumerate(ports)
        ]
        self.sims: list[SimRobot] = []
        try:
            for i in range(n):
                self.sims.append(SimRobot(member_config(f"arm{i}", self.members, **cell)))
        except BaseException:
            self.close()
            raise
        self.ops: list[SimPeer] = [s.peer("operator") for s in self.sims]
        self.frozen: set[int] = set()

    def step(self, n: int = 1) -> None:
        for _ in range(n):
            for i, s in enumerate(self.sims):
                if i in self.frozen:
                    s.stall(1)  # a frozen process: its time goes on, it does nothing
                else:
                    s.tick()

    def command(self, i: int, name: str, text: str = "") -> Any:
        peer = self.ops[i]
        cid = peer.send_command(name, text)
        self.step(1)
        while self.sims[i].robot.effects.powering_up:
            assert self.sims[i].robot.effects.await_power_up(10.0)
            self.step(1)
        reply = peer.reply_to(cid)
        assert reply is not None, name
        return reply

    def state(self, i: int) -> RobotState:
        return self.sims[i].robot.state

    def run_all(self) -> None:
        self.step(10)  # every member heard by every other
        for i in range(len(self.sims)):
            for cmd in ("Enable", "Run"):
                reply = self.command(i, cmd)
                assert ok(reply), (i, cmd, reply.metadata)
        assert all(self.state(i) is S.RUNNING for i in range(len(self.sims)))

    def cell_stats(self, i: int) -> dict[str, Any]:
        return dict(self.sims[i].robot.snapshot()["cell"])

    def cell_stats_full(self, i: int) -> dict[str, Any]:
        """Member ``i``'s GetStats as JSON carries it (what the staff console reads)."""
        import json

        return dict(json.loads(json.dumps(self.sims[i].robot.snapshot(), default=str)))

    def close(self) -> None:
        for s in self.sims:
            s.close()


@pytest.fixture
def cell() -> Iterator[Cell]:
    c = Cell(3)
    yield c
    c.close()


@pytest.mark.req("SR-CELL-1")
def test_an_estop_in_one_member_holds_every_other_in_the_next_tick(cell: Cell) -> None:
    cell.run_all()
    assert ok(cell.command(0, "EStop"))
    assert cell.state(0) is S.ESTOP
    cell.step(1)
    assert cell.state(1) is S.STOPPED and cell.state(2) is S.STOPPED
    for i in (1, 2):
        st = cell.cell_stats(i)
        assert "arm0" in st["latched"] and "ESTOP" in st["latched"]["arm0"]
        assert st["last_stop"]["origin"] == "arm0"
        ops = cell.ops[i]
        alerts = [m for m in ops.messages("STATUS") if m.error_name == "CELL"]
        assert alerts and "arm0" in alerts[-1].status_message, [m.status_message for m in alerts]


@pytest.mark.req("SR-CELL-2")
def test_a_held_member_runs_again_only_once_the_origin_runs(cell: Cell) -> None:
    cell.run_all()
    assert ok(cell.command(0, "EStop"))
    cell.step(2)
    why = error_of(cell.command(1, "Run"))
    assert "arm0" in why and "ESTOP" in why and "CellForget arm0" in why
    assert cell.state(1) is S.STOPPED
    # the origin reset: READY is not running, the others still wait
    assert ok(cell.command(0, "Reset"))
    cell.step(3)
    assert "arm0" in error_of(cell.command(1, "Run"))
    for cmd in ("Enable", "Run"):
        assert ok(cell.command(0, cmd))
    cell.step(3)
    for i in (1, 2):
        assert ok(cell.command(i, "Run")), i
        assert cell.state(i) is S.RUNNING


@pytest.mark.req("SR-CELL-1")
@pytest.mark.parametrize("kind", ["write", "heartbeat"])
def test_a_drive_fault_in_one_member_holds_the_others(cell: Cell, kind: str) -> None:
    cell.run_all()
    cell.sims[2].robot.hardware.drivers[0].inject(kind)  # type: ignore[attr-defined]
    for _ in range(60):
        cell.step(1)
        if cell.state(2) is S.FAULT:
            break
    assert cell.state(2) is S.FAULT
    cell.step(1)
    assert cell.state(0) is S.STOPPED and cell.state(1) is S.STOPPED
    last = cell.cell_stats(0)["last_stop"]
    assert last["origin"] == "arm2" and "FAULT" in last["cause"]
    assert last["propagation_ms"] is not None and 0.0 <= last["propagation_ms"] <= 2.0


@pytest.mark.req("SR-CELL-1")
def test_an_operators_stop_or_disable_stops_no_other_member(cell: Cell) -> None:
    cell.run_all()
    assert ok(cell.command(0, "Stop"))
    assert ok(cell.command(1, "Disable"))
    cell.step(5)
    assert cell.state(2) is S.RUNNING
    assert cell.cell_stats(2)["latched"] == {}
    assert ok(cell.command(0, "Run"))


@pytest.mark.req("SR-CELL-4")
def test_a_silent_member_holds_the_others_after_the_grace_not_before(cell: Cell) -> None:
    cell.run_all()
    cell.frozen.add(1)  # SIGSTOP: nothing from it
    # its last heartbeat was up to one period (5 ms) before: silent for the grace (100 ms)
    # only after 95 ms at the earliest, and noticed in the first tick past the grace
    cell.step(94)
    assert cell.state(0) is S.RUNNING and cell.state(2) is S.RUNNING
    for _ in range(7):
        cell.step(1)
        if cell.state(0) is S.STOPPED:
            break
    assert cell.state(0) is S.STOPPED and cell.state(2) is S.STOPPED
    assert "arm1 silent" in cell.cell_stats(0)["latched"]["arm1"]
    # it comes back: its own loop saw the gap (its watchdog holds it); the others wait for it
    cell.frozen.clear()
    cell.step(5)
    assert cell.state(1) is S.FAULT  # its drive's heartbeat: the drive stopped itself
    assert "arm1 FAULT" in error_of(cell.command(0, "Run"))
    for cmd in ("Reset", "Enable", "Run"):
        assert ok(cell.command(1, cmd)), cmd
    cell.step(3)
    assert ok(cell.command(0, "Run")) and ok(cell.command(2, "Run"))


@pytest.mark.req("SR-CELL-1")
def test_a_hung_loop_is_announced_from_the_supervisors_thread(cell: Cell) -> None:
    cell.run_all()
    robot = cell.sims[0].robot
    cell.frozen.add(0)  # its loop hangs: it sends nothing itself
    robot.alarms.supervisor_trip("no tick for 25 ms")  # what the supervisor thread calls
    cell.step(1)
    assert cell.state(1) is S.STOPPED and cell.state(2) is S.STOPPED
    assert "arm0 hung loop: supervisor: no tick" in cell.cell_stats(1)["latched"]["arm0"]


@pytest.mark.req("SR-CELL-2")
def test_a_relayed_stop_ends_when_its_origin_runs_again() -> None:
    c = Cell(3)
    try:
        c.run_all()
        assert ok(c.command(0, "EStop"))
        c.step(2)
        st = c.cell_stats(2)
        assert c.cell_stats(1)["origin"] == "arm0"  # arm1's own stop relays arm0's
        assert set(st["latched"]) == {"arm0"}
        for cmd in ("Reset", "Enable", "Run"):
            assert ok(c.command(0, cmd))
        c.step(2)
        # arm1 still relays arm0's stop (it waits for its operator): arm2 sees arm0 running
        assert ok(c.command(2, "Run"))
        assert ok(c.command(1, "Run"))
    finally:
        c.close()


@pytest.mark.req("SR-CELL-2")
def test_two_members_that_lost_each_other_may_both_run_again() -> None:
    c = Cell(2)
    try:
        c.run_all()
        links = [s.robot.cell.link for s in c.sims]  # type: ignore[union-attr]
        sends = [link.send for link in links]
        for link in links:  # the network between them cut: nothing either way
            link.send = lambda beat: 0  # type: ignore[method-assign]
        c.step(110)
        assert c.state(0) is S.STOPPED and c.state(1) is S.STOPPED
        for link, send in zip(links, sends, strict=True):
            link.send = send  # type: ignore[method-assign]
        c.step(10)
        # each one's stop is only the other's relay of its own silence: an operator may Run
        assert ok(c.command(0, "Run")), c.cell_stats(0)
        c.step(2)
        assert ok(c.command(1, "Run")), c.cell_stats(1)
    finally:
        c.close()


@pytest.mark.req("SR-CELL-1")
def test_alert_only_tells_without_holding() -> None:
    c = Cell(2, policy="alert-only")
    try:
        c.run_all()
        assert ok(c.command(0, "EStop"))
        c.step(2)
        assert c.state(1) is S.RUNNING
        st = c.cell_stats(1)
        assert st["policy"] == "alert-only" and "arm0" in st["latched"] and st["holds"] == 0
        assert any(m.error_name == "CELL" for m in c.ops[1].messages("STATUS"))
    finally:
        c.close()


@pytest.mark.req("SR-CELL-2")
def test_a_member_that_left_stops_no_one_and_is_stopped_by_no_one(cell: Cell) -> None:
    cell.run_all()
    assert ok(cell.command(0, "CellLeave"))
    cell.step(2)
    assert ok(cell.command(0, "EStop"))
    cell.step(3)
    assert cell.state(1) is S.RUNNING and cell.state(2) is S.RUNNING
    assert cell.cell_stats(1)["members"]["arm0"]["left"] is True
    assert ok(cell.command(1, "EStop"))
    cell.step(2)
    assert cell.state(2) is S.STOPPED
    # arm0 left: already in ESTOP by its own hand, nothing of arm1's reached it
    assert cell.cell_stats(0)["latched"] == {}


@pytest.mark.req("SR-CELL-2")
def test_a_killed_member_can_be_forgotten_by_an_operator(cell: Cell) -> None:
    cell.run_all()
    cell.sims[2].robot.cell.link.stop()  # type: ignore[union-attr]  # kill -9: silence
    cell.frozen.add(2)
    cell.step(105)
    assert cell.state(0) is S.STOPPED
    assert "arm2" in error_of(cell.command(0, "Run"))
    reply = cell.command(0, "CellForget", '<Command Name="CellForget" Member="arm2"/>')
    assert ok(reply), reply.metadata
    assert ok(cell.command(0, "Run"))
    why = error_of(cell.command(0, "CellForget", '<Command Name="CellForget" Member="arm9"/>'))
    assert "arm9" in why and "arm0, arm1, arm2" not in why and "arm1" in why


@pytest.mark.req("SR-CELL-2")
def test_run_waits_for_every_member_to_be_heard() -> None:
    ports = _udp_ports(2)
    members = [{"name": f"arm{i}", "address": f"127.0.0.1:{p}"} for i, p in enumerate(ports)]
    with SimRobot(member_config("arm0", members)) as sim:
        op = sim.peer("operator")
        assert ok(sim.command(op, "Enable"))
        why = error_of(sim.command(op, "Run"))
        assert "not heard yet from arm1" in why
        assert ok(sim.command(op, "CellForget", '<Command Name="CellForget" Member="arm1"/>'))
        assert ok(sim.command(op, "Run"))


@pytest.mark.req("SR-CELL-1")
def test_a_shut_down_member_holds_the_others(cell: Cell) -> None:
    cell.run_all()
    cell.sims[1].robot.shutdown()
    cell.frozen.add(1)
    cell.step(1)
    assert cell.state(0) is S.STOPPED and cell.state(2) is S.STOPPED
    assert cell.cell_stats(0)["latched"]["arm1"] == "arm1 shut down"


@pytest.mark.req("SR-CELL-2")
def test_a_member_whose_chain_is_not_its_urdf_is_not_trusted() -> None:
    ports = _udp_ports(2)
    members = [
        {"name": "arm0", "address": f"127.0.0.1:{ports[0]}", "frame": {"model": "occ_slave"}},
        {"name": "arm1", "address": f"127.0.0.1:{ports[1]}", "frame": {"model": "master3"}},
    ]
    sims = [SimRobot(member_config(f"arm{i}", members)) for i in range(2)]
    try:
        for _ in range(10):
            for s in sims:
                s.tick()
        st = sims[0].robot.snapshot()["cell"]
        assert st["members"]["arm1"]["chain_ok"] is False
        assert st["last_stop"]["propagation_ms"] is None  # no stop time: the chain is wrong
        op = sims[0].peer("operator")
        assert ok(sims[0].command(op, "Enable"))
        assert "kinematic chain" in error_of(sims[0].command(op, "Run"))
    finally:
        for s in sims:
            s.close()


@pytest.mark.req("SR-CELL-2")
def test_the_shipped_cell_agrees_and_its_arms_hold_for_each_other() -> None:
    """configs/cell/: both slaves list the same cell, each member's URDF is the one the member
    announces (its chain hash), and on free ports the two UR5s hold for each other."""
    from occ.core.loader import load_config
    from occ_testkit.testing import CONFIGS

    a, b = (load_config(CONFIGS / "cell" / f"ur5-{n}.yaml") for n in "ab")
    assert a.cell is not None and b.cell is not None
    assert a.cell.model_dump() | {"member": None} == b.cell.model_dump() | {"member": None}
    sims = []
    try:
        for raw in shipped_cell():
            sims.append(SimRobot(raw))
        for _ in range(10):
            for s in sims:
                s.tick()
        for s in sims:
            (m,) = s.robot.snapshot()["cell"]["members"].values()
            assert m["chain_ok"] is True and m["state"] == "READY"
        ops = [s.peer("operator") for s in sims]
        for s, op in zip(sims, ops, strict=True):
            for cmd in ("Enable", "Run"):
                assert ok(s.command(op, cmd)), cmd
        assert ok(sims[1].command(ops[1], "EStop"))
        sims[0].tick()
        assert sims[0].robot.state is S.STOPPED
    finally:
        for s in sims:
            s.close()


def test_a_robots_base_stands_where_its_file_says() -> None:
    """``robot.base_mm`` and ``base_rpy_deg``: the base pose in the patient frame (what the
    other members of a cell see in its heartbeats), R = Rz(yaw) Ry(pitch) Rx(roll)."""
    import numpy as np

    from occ.core.wiring import base_pose

    ports = _udp_ports(2)
    members = [{"name": f"arm{i}", "address": f"127.0.0.1:{p}"} for i, p in enumerate(ports)]
    raw = member_config("arm0", members).model_dump(mode="json")
    raw["robot"]["base_mm"] = [600.0, -20.0, 5.0]
    raw["robot"]["base_rpy_deg"] = [0.0, 0.0, 90.0]
    with SimRobot(DaemonConfig.model_validate(raw)) as sim:
        b = sim.robot.data.base
        assert np.allclose(b[:3, 3], [0.6, -0.02, 0.005])
        assert np.allclose(b[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    r = base_pose([0, 0, 0], [30.0, 20.0, 10.0])[:3, :3]
    assert np.allclose(r @ r.T, np.eye(3)) and np.isclose(np.linalg.det(r), 1.0)
    # roll first about x, then pitch about y, then yaw about z (fixed axes)
    rx = base_pose([0, 0, 0], [30.0, 0, 0])[:3, :3]
    ry = base_pose([0, 0, 0], [0, 20.0, 0])[:3, :3]
    rz = base_pose([0, 0, 0], [0, 0, 10.0])[:3, :3]
    assert np.allclose(r, rz @ ry @ rx)


@pytest.mark.req("SR-CELL-1")
def test_a_controller_may_stop_the_whole_cell(cell: Cell) -> None:
    """ControllerContext.cell_stop (a plan run by the whole cell dropped in one member): the
    others hold, naming it, until that member runs again."""
    cell.run_all()
    ctx = cell.sims[0].robot.controller.controllers[0].ctx
    assert ctx is not None and ctx.cell_member == "arm0" and ctx.cell_stop is not None
    ctx.cell_stop("cell plan 3 dropped: an operator's Stop")
    cell.step(1)
    assert cell.state(1) is S.STOPPED and cell.state(2) is S.STOPPED
    assert "cell plan 3 dropped" in cell.cell_stats(1)["latched"]["arm0"]
    assert ok(cell.command(0, "Stop")) and ok(cell.command(0, "Run"))
    cell.step(2)
    assert ok(cell.command(1, "Run")) and ok(cell.command(2, "Run"))
