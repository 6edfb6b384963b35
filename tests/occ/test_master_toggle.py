"""One master driving two slaves (issue 12), in simulated time: selection by command and by a
clutch tap, each slave's stream its own sequence numbers, and no jump when a slave is selected.

The shipped master with two ``teleop`` outputs (``left``, ``right``) on in-process channels; what
it sends on each is forwarded, decoded, to a shipped slave's master interface, and the three
robots tick in lockstep on their own simulated clocks.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import pytest

import igtl
from occ.config import DaemonConfig
from occ.core.loader import load_config
from occ.core.safety import RobotState
from occ.errors import ConfigError
from occ_testkit.testing import SimPeer, SimRobot

ROOT = Path(__file__).resolve().parents[2]
SIDES = ("left", "right")


def _master_config() -> DaemonConfig:
    cfg = load_config(ROOT / "configs" / "master.yaml")
    link = cfg.interface("slave")
    others = [i for i in cfg.interfaces if i.name != "slave"]
    links = [link.model_copy(update={"name": side}) for side in SIDES]
    cfg = cfg.model_copy(update={"interfaces": (*others, *links)})
    return cfg.with_params(slaves=list(SIDES))


class ToggleRig:
    def __init__(self) -> None:
        self.master = SimRobot(_master_config())
        self.op = self.master.peer("operator", address=("127.0.0.1", 41000))
        self.slaves: dict[str, SimRobot] = {}
        self.slave_ops: dict[str, SimPeer] = {}
        self.streams: dict[str, list[igtl.Message]] = {}
        for side in SIDES:
            slave = SimRobot(ROOT / "configs" / "slave.yaml")
            inbox = slave.peer("master", address=("127.0.0.1", 40000 + len(self.slaves)))
            self.streams[side] = seen = []

            def forward(msg: igtl.Message, inbox: SimPeer = inbox, seen: list = seen) -> None:
                seen.append(msg)
                inbox.send(msg)

            self.master.peer(side, on_message=forward)
            self.slaves[side] = slave
            self.slave_ops[side] = slave.peer("operator")

    def tick(self, n: int = 1) -> None:
        for _ in range(n):
            self.master.tick()
            for slave in self.slaves.values():
                slave.tick()

    def command(self, peer: SimPeer, name: str, text: str = "") -> igtl.Message:
        cid = peer.send_command(name, text)
        self.tick()
        reply = peer.reply_to(cid)
        assert reply is not None, name
        return reply

    def tip_mm(self, side: str) -> tuple[float, ...]:
        r = self.slaves[side].robot
        return tuple(v * 1e3 for v in r.frame.tip_position(r.data.setpoint))

    def close(self) -> None:
        self.master.close()
        for s in self.slaves.values():
            s.close()


@pytest.fixture
def rig() -> Iterator[ToggleRig]:
    r = ToggleRig()
    try:
        for side in SIDES:
            for cmd in ("Enable", "Run"):
                assert r.command(r.slave_ops[side], cmd).metadata["Status"] == "SUCCESS"
        for cmd in ("Enable", "Run"):
            assert r.command(r.op, cmd).metadata["Status"] == "SUCCESS"
        r.tick(300)
        yield r
    finally:
        r.close()


def runs(msgs: list[igtl.Message]) -> set[str]:
    return {m.metadata["run"] for m in msgs}


def test_only_the_selected_slave_follows_and_numbers_stay_consecutive(rig: ToggleRig) -> None:
    n = {s: len(rig.streams[s]) for s in SIDES}
    start = {s: rig.tip_mm(s) for s in SIDES}
    rig.tick(1000)
    assert runs(rig.streams["left"][n["left"] :]) == {"1"}
    assert runs(rig.streams["right"][n["right"] :]) == {"0"}
    # the hand's energy goes to the slave it drives, never to the other (whose port would
    # spend a budget the hand never gave it)
    assert all("energy_j" in m.metadata for m in rig.streams["left"][n["left"] :])
    assert not any("energy_j" in m.metadata for m in rig.streams["right"])
    assert math.dist(rig.tip_mm("left"), start["left"]) > 1.0  # 31 mm/s x 0.1 for 1 s
    assert math.dist(rig.tip_mm("right"), start["right"]) < 1e-9  # holds, stream alive
    for side in SIDES:
        ids = [m.message_id for m in rig.streams[side]]
        assert ids == list(range(1, len(ids) + 1)), side  # each stream its own numbers
        slave = rig.slaves[side].robot
        assert slave.state is RobotState.RUNNING
        assert slave.streams.monitor is not None and slave.streams.monitor.lost_total == 0


def test_toggle_select_and_a_clutch_tap_switch_without_a_jump(rig: ToggleRig) -> None:
    rig.tick(500)
    before = rig.tip_mm("right")
    reply = rig.command(rig.op, "Toggle")
    assert "left -> right" in reply.metadata["Message"]
    path = [rig.tip_mm("right")]
    left_at = rig.tip_mm("left")
    for _ in range(800):
        rig.tick()
        path.append(rig.tip_mm("right"))
    steps = [math.dist(a, b) for a, b in zip(path, path[1:], strict=False)]
    # the master's hand moves at 2 pi 0.1 Hz 50 mm = 31 mm/s: 6.3 um per 2 ms sample at 10:1;
    # the newly selected slave starts from where it held, with no step
    assert math.dist(path[0], before) < 1e-9 and max(steps) < 0.0065, max(steps)
    assert math.dist(path[-1], before) > 1.0  # and then it follows
    assert math.dist(rig.tip_mm("left"), left_at) < 1e-9  # the other one holds
    # Select by name; a clutch tap (pressed and released within 300 ms) toggles back
    assert (
        "right already selected"
        in rig.command(rig.op, "Select", '<Command Name="Select" To="right"/>').metadata["Message"]
    )
    rig.command(rig.op, "Clutch", '<Command Name="Clutch" Value="1"/>')
    rig.tick(100)
    reply = rig.command(rig.op, "Clutch", '<Command Name="Clutch" Value="0"/>')
    assert "right -> left" in reply.metadata["Message"]
    # a long press is a clutch, not a tap
    rig.command(rig.op, "Clutch", '<Command Name="Clutch" Value="1"/>')
    rig.tick(400)
    reply = rig.command(rig.op, "Clutch", '<Command Name="Clutch" Value="0"/>')
    assert reply.metadata["Message"] == "clutch released"
    ctrl = rig.master.robot.controller.controllers[0]
    assert ctrl.selector.selected == "left" and ctrl.stats()["slaves"]["switches"] == 2
    # refusals: an unknown slave
    reply = rig.command(rig.op, "Select", '<Command Name="Select" To="middle"/>')
    assert reply.metadata["Status"] == "FAIL"
    assert "'middle' is not one of" in reply.metadata.get("Error", "") + reply.metadata.get(
        "Message", ""
    )
    assert ctrl.selector.selected == "left"
    for side in SIDES:
        assert rig.slaves[side].robot.state is RobotState.RUNNING


def test_slaves_must_name_teleop_outputs(tmp_path: Path) -> None:
    text = (ROOT / "configs" / "master.yaml").read_text()
    marker = "  params:\n"
    assert marker in text
    path = tmp_path / "master.yaml"
    path.write_text(text.replace(marker, marker + "    slaves: [slave, operator]\n", 1))
    with pytest.raises(ConfigError, match="has no output with source teleop"):
        load_config(path)
