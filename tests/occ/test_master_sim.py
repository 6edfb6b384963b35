"""The master robot in simulated time: the 500 Hz POSITION stream, inputs, clutch, fixtures.

The robot's interfaces are in-process channels (occ.testing.SimRobot): a peer on the ``slave``
channel receives the stream exactly as the slave would (decoded from the wire form), and the
operator's peer sends commands and fixtures and reads the replies sent to it.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

import igtl
from occ.config import InputConfig
from occ.loader import load_config
from occ.safety import RobotState
from occ.testing import SimRobot

ROOT = Path(__file__).resolve().parents[2]


class SimMaster:
    def __init__(self, config: object = None, **teleop: object) -> None:
        self.sim = SimRobot(config or ROOT / "configs" / "master.yaml", params=teleop or None)
        self.robot = self.sim.robot
        self.slave = self.sim.peer("slave")
        self.operator = self.sim.peer("operator", address=("127.0.0.1", 41000))
        #: the stream as the slave receives it
        self.sent = self.slave.received
        #: everything the robot sent to the operator
        self.replies = self.operator.received

    @property
    def k(self) -> int:
        return self.sim.k

    def ticks(self, n: int) -> None:
        self.sim.step(n)

    def command(self, name: str, text: str = "") -> igtl.Message:
        cid = self.operator.send_command(name, text)
        self.ticks(1)
        reply = self.operator.reply_to(cid)
        assert reply is not None, f"no RTS_COMMAND for {name}"
        return reply

    def close(self) -> None:
        self.sim.close()


@pytest.fixture
def master() -> SimMaster:
    m = SimMaster()
    yield m
    m.close()


def test_stream_is_500hz_v2_with_sequence_and_run_flag(master: SimMaster) -> None:
    master.ticks(100)  # READY: the stream already flows, run=0
    assert len(master.sent) == 50
    assert all(m.metadata["run"] == "0" for m in master.sent)
    for name in ("Enable", "Run"):
        assert master.command(name).metadata["Status"] == "SUCCESS"
    master.ticks(1000)
    msgs = master.sent
    ids = [m.message_id for m in msgs]
    assert ids == list(range(1, len(msgs) + 1))
    assert all(m.header_version == 2 and m.message_type == "POSITION" and m.layout == 24 for m in msgs)
    assert msgs[-1].metadata["run"] == "1" and msgs[-1].metadata["clutch"] == "0"


def test_simulated_operator_follows_paper_trajectory(master: SimMaster) -> None:
    master.command("Enable")
    master.command("Run")
    t_run = (master.k - 1) * 0.001
    master.ticks(2500)
    origin = master.robot.controller.controllers[0].origin * 1000.0
    last = master.sent[-1]
    t = (master.k - 1) * 0.001 - t_run
    expect = (origin[0] + 50.0 * math.sin(2 * math.pi * 0.1 * t),
              origin[1] + 50.0 * math.cos(2 * math.pi * 0.1 * t),
              origin[2] + 20.0)
    # the simulated servo lags the 0.1 Hz target by a few ms: within 0.5 mm
    for got, want in zip(last.position, expect):
        assert got == pytest.approx(want, abs=0.5)


def test_igtl_input_drives_the_handle() -> None:
    # the tracker's TRANSFORMs arrive on the operator interface in this test, as a command input
    cfg = load_config(ROOT / "configs" / "master.yaml")
    op = cfg.interface("operator")
    op = op.model_copy(update={"inputs": (*op.inputs, InputConfig(type="TRANSFORM", queue="command"))})
    cfg = cfg.model_copy(update={"interfaces": tuple(op if i.name == "operator" else i
                                                     for i in cfg.interfaces)})
    m = SimMaster(cfg, input="igtl", input_interface="operator")
    try:
        m.command("Enable")
        m.command("Run")
        origin = m.robot.controller.controllers[0].origin * 1000.0
        target = (origin[0] + 10.0, origin[1] - 5.0, origin[2] + 3.0)
        # the tracker is 10 mm away when Run starts: the handle joins it at half the velocity
        # limits (0.25 mm a tick here), never in one step
        limit = [0.5 * j.limits.velocity * 1e-3 for j in m.robot.joints]
        previous = list(m.robot.data.setpoint)
        for _ in range(300):
            assert m.operator.send(igtl.TransformMessage.from_position(target, device_name="Tracker")) == 1
            for _ in range(2):
                m.ticks(1)
                now = list(m.robot.data.setpoint)
                assert all(abs(a - b) <= lim + 1e-12 for a, b, lim in zip(now, previous, limit))
                previous = now
        assert m.sent[-1].position == pytest.approx(target, abs=0.05)
    finally:
        m.close()


def test_clutch_travels_with_the_stream(master: SimMaster) -> None:
    master.command("Enable")
    master.command("Run")
    r = master.command("Clutch", '<Command Name="Clutch" Value="1"/>')
    assert r.metadata["Status"] == "SUCCESS"
    master.ticks(4)
    assert master.sent[-1].metadata["clutch"] == "1"
    master.command("Clutch", '<Command Name="Clutch" Value="0"/>')
    master.ticks(4)
    assert master.sent[-1].metadata["clutch"] == "0"


def test_virtual_fixture_keeps_handle_out_and_reports_force(master: SimMaster) -> None:
    master.command("Enable")
    master.command("Run")
    master.ticks(200)
    handle = master.sent[-1].position
    # a sphere of 10 mm radius centred 4 mm from the handle (in +x): the handle is inside
    centre = (handle[0] + 4.0, handle[1], handle[2])
    fx = igtl.VirtualFixtureMessage(hardness=0.5, spheres=((*centre, 10.0),), device_name="Fixtures",
                                    header_version=2, metadata={"MRMLNodeName": "VF"})
    assert master.operator.send(fx) == 1
    master.ticks(1)
    stats = master.robot.controller.stats()
    assert stats["fixtures"] == 1 and stats["fixture_contacts"] >= 1
    assert stats["fixture_force_n"][0] < 0  # pushes back toward -x, out of the sphere
    master.ticks(100)
    p = master.sent[-1].position
    dist = math.dist(p, centre)
    assert dist >= 10.0 - 0.2


def test_stop_state_holds_and_reports(master: SimMaster) -> None:
    master.command("Enable")
    master.command("Run")
    master.ticks(100)
    master.command("Stop")
    assert master.robot.state is RobotState.STOPPED
    p0 = master.sent[-1].position
    master.ticks(200)
    assert master.sent[-1].metadata["run"] == "0"
    # holds the last commanded setpoint: the handle settles where it was told (the simulated
    # drive lags its command by ~0.3 mm at this speed) and then stays there
    p1 = master.sent[-1].position
    assert p1 == pytest.approx(p0, abs=0.5)
    master.ticks(100)
    assert master.sent[-1].position == pytest.approx(p1, abs=0.01)


def test_slicer_markups_points_become_fixture_spheres(master: SimMaster) -> None:
    from igtl.messages.point import PointElement

    master.command("Enable")
    master.command("Run")
    master.ticks(200)
    handle = master.sent[-1].position
    near = PointElement(name="F-1", group="Selected", rgba=(255, 0, 0, 255),
                        position=(handle[0] + 2.0, handle[1], handle[2]))
    hidden = PointElement(name="F-2", group="Selected", rgba=(0, 255, 0, 0),
                          position=(handle[0] - 2.0, handle[1], handle[2]))
    pts = igtl.PointMessage(points=(near, hidden), device_name="F", header_version=2,
                            metadata={"MRMLNodeName": "MarkupsFiducial"})
    assert master.operator.send(pts) == 1
    master.ticks(1)
    stats = master.robot.controller.stats()
    assert stats["fixtures"] == 1  # the hidden point (alpha 0) is not a fixture
    master.ticks(100)
    # default radius 5 mm around the visible point: the handle is kept out of it
    assert math.dist(master.sent[-1].position, near.position) >= 5.0 - 0.2
