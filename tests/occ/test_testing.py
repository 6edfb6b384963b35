"""occ_testkit.testing: the helper the simulated-time tests stand on routes like the real daemon."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

import igtl
from occ.errors import ConfigError
from occ.core.loader import parse_config
from occ.core.safety import RobotState
from occ_testkit.testing import SimRobot

ROOT = Path(__file__).resolve().parents[2]
SLAVE = ROOT / "configs" / "slave.yaml"


@pytest.mark.req("SR-ROUTE-1")
def test_each_operator_gets_its_own_replies_and_every_operator_the_broadcasts() -> None:
    with SimRobot(SLAVE) as sim:
        alice, bob = sim.peer("operator"), sim.peer("operator")
        viewer = sim.peer("slicer")
        assert alice.connected and bob.connected
        cid = alice.send_command("Enable")
        sim.step()
        reply = alice.reply_to(cid)
        assert reply is not None and reply.metadata["Status"] == "SUCCESS"
        assert bob.messages("RTS_COMMAND") == []  # the reply went to the one who asked
        # the state change is broadcast to every operator and viewer, after each one's greeting
        for peer in (alice, bob, viewer):
            states = [m.error_name for m in peer.messages("STATUS")]
            assert states == ["READY", "ENABLED"], states
        assert sim.robot.state is RobotState.ENABLED


def test_outputs_follow_simulated_time_and_old_clients_get_version_1() -> None:
    with SimRobot(SLAVE) as sim:
        new, old = sim.peer("slicer"), sim.peer("slicer", header_version=1)
        sim.run_for(1.0)
        assert sim.k == 1000 and sim.now == pytest.approx(1.0)
        tips = new.messages("TRANSFORM", "Tip")
        assert len(tips) == 10  # 10 Hz
        assert all(m.header_version == 2 for m in tips)
        assert all(m.header_version == 1 for m in old.messages("TRANSFORM", "Tip"))
        # the robot's side of the channel: one interface, both peers, nothing on the wire
        stats = sim.robot.interfaces.stats()["slicer"]
        assert stats["transport"] == "inproc" and stats["peers"] == 2


def test_a_config_mapping_and_a_peer_that_leaves() -> None:
    data = yaml.safe_load(SLAVE.read_text())
    data["robot"]["name"] = "other"
    with SimRobot(data) as sim:
        peer = sim.peer("slicer")
        peer.close()
        assert sim.robot.interfaces.stats()["slicer"]["peers"] == 0
        assert peer.send(igtl.StringMessage("x", device_name="CMD_1")) == 0
        assert sim.robot.name == "other"


def test_inproc_interfaces_need_a_channel() -> None:
    text = SLAVE.read_text().replace("transport: udp", "transport: inproc")
    with pytest.raises(ConfigError, match="channel: required for transport 'inproc'"):
        parse_config(text, source=str(SLAVE))
    cfg = parse_config(
        text.replace("transport: inproc", "transport: inproc\n    channel: m"), source=str(SLAVE)
    )
    assert cfg.interface("master").channel == "m"


def test_getstats_as_plain_json() -> None:
    """`<Command Name="GetStats" Format="json"/>`: the answer is a STRING holding only the
    JSON (ACK_<id> for a PLUS-style request, STATS for a COMMAND), for scripts."""
    import json
    import time

    with SimRobot(SLAVE) as sim:
        op = sim.peer("operator")
        assert (
            op.send(
                igtl.StringMessage('<Command Name="GetStats" Format="json"/>', device_name="CMD_42")
            )
            == 1
        )
        cid = op.send_command("GetStats", '<Command Name="GetStats" Format="json"/>')
        sim.step()
        end = time.monotonic() + 5.0  # the worker thread builds the statistics
        while len(op.messages("STRING")) < 2 and time.monotonic() < end:
            time.sleep(0.005)
        by_device = {m.device_name: m for m in op.messages("STRING")}
        assert set(by_device) == {"ACK_42", "STATS"}, cid
        for m in by_device.values():
            stats = json.loads(m.string)
            assert stats["state"] == "READY" and "lateness_us" in stats


def test_the_module_docstring_example_runs() -> None:
    """occ_testkit.testing's own example (its module docstring) runs as written, from the root."""
    import os
    import textwrap

    import occ_testkit.testing

    doc = occ_testkit.testing.__doc__ or ""
    block = doc.split("::\n\n", 1)[1].split("\nTests use it", 1)[0]
    code = textwrap.dedent(block)
    assert "SimRobot(" in code
    here = os.getcwd()
    os.chdir(ROOT)  # the example names configs/slave.yaml
    try:
        scope: dict[str, object] = {}
        exec(compile(code, "occ_testkit.testing example", "exec"), scope)  # noqa: S102
    finally:
        os.chdir(here)
    tips = scope["tips"]
    assert isinstance(tips, list) and len(tips) >= 2  # 10 Hz for 200 ms of running


@pytest.mark.req("SR-LOSS-4")
def test_a_stalled_master_is_a_late_stream_the_slave_holds_through_not_a_loss() -> None:
    """SimPair.stall_master: the master's loop stops ticking while the slave's goes on. Nothing
    is sent meanwhile and no sequence number is skipped: the slave holds its setpoint at the
    deadline, counts no loss, and follows again by itself when the master's samples return;
    both keep running and stay on one clock."""
    from occ_testkit.testing import CONFIGS, SimPair

    with SimPair(CONFIGS / "master.yaml", SLAVE) as pair:
        pair.start()
        pair.step(200)
        slave = pair.slave.robot
        monitor = slave.streams.monitor
        assert monitor is not None
        before = monitor.counters()
        sent = pair.counts["forward"]
        pair.stall_master(20)
        held = list(slave.data.setpoint)
        pair.stall_master(10)  # 30 ms of silence in all: past the deadline, short of the grace
        assert list(slave.data.setpoint) == held  # holding
        assert pair.counts["forward"] == sent  # the master sent nothing
        c = monitor.counters()
        assert c["holds"] == before["holds"] + 1 and c["resumes"] == before["resumes"]
        pair.step(10)
        c = monitor.counters()
        assert c["resumes"] == before["resumes"] + 1
        assert c["lost_total"] == 0 and c["trips"] == 0
        assert pair.counts["forward"] > sent and list(slave.data.setpoint) != held
        assert slave.state is RobotState.RUNNING
        assert pair.master.robot.state is RobotState.RUNNING
        assert pair.master.k == pair.slave.k == pair.k
