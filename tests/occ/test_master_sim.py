"""The master robot in simulated time: the 500 Hz POSITION stream, inputs, clutch, fixtures.

The robot's interfaces are in-process channels (occ_testkit.testing.SimRobot): a peer on the
``slave`` channel receives the stream exactly as the slave would (decoded from the wire form), and
the operator's peer sends commands and fixtures and reads the replies sent to it.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import yaml

import igtl
from occ.core.safety import RobotState
from occ_testkit.rigs import SimMaster, SlaveTipFeed

ROOT = Path(__file__).resolve().parents[2]


def position_master(**params: object) -> dict:
    """configs/master.yaml with a position-commanded master: the ``sim`` driver following
    the controller's target (``input: sim``, the paper's motion played as positions, or
    ``igtl``), instead of the shipped simulated hand."""
    raw = yaml.safe_load((ROOT / "configs" / "master.yaml").read_text())
    raw["robot"]["drivers"] = [
        {
            "name": "sim",
            "plugin": "sim",
            "joints": ["x", "y", "z"],
            "on_limit": "clamp",
            "params": {"bandwidth_hz": 30.0},
        }
    ]
    raw["controller"]["params"] = {
        "input": "sim",
        "amplitude_mm": [50.0, 50.0, 0.0],
        "offset_mm": [0.0, 0.0, 20.0],
        "frequency_hz": 0.1,
        **params,
    }
    return raw


@pytest.fixture
def master() -> SimMaster:
    m = SimMaster()
    yield m
    m.close()


def test_stream_is_500hz_v2_with_sequence_and_run_flag(master: SimMaster) -> None:
    master.step(100)  # READY: the stream already flows, run=0
    assert len(master.sent) == 50
    assert all(m.metadata["run"] == "0" for m in master.sent)
    for name in ("Enable", "Run"):
        assert master.command(name).metadata["Status"] == "SUCCESS"
    master.step(1000)
    msgs = master.sent
    ids = [m.message_id for m in msgs]
    assert ids == list(range(1, len(msgs) + 1))
    assert all(
        m.header_version == 2 and m.message_type == "POSITION" and m.layout == 24 for m in msgs
    )
    assert msgs[-1].metadata["run"] == "1" and msgs[-1].metadata["clutch"] == "0"


def test_simulated_operator_follows_paper_trajectory(master: SimMaster) -> None:
    master.command("Enable")
    master.command("Run")
    t_run = (master.k - 1) * 0.001
    master.step(2500)
    origin = master.robot.controller.controllers[0].origin * 1000.0
    last = master.sent[-1]
    t = (master.k - 1) * 0.001 - t_run
    expect = (
        origin[0] + 50.0 * math.sin(2 * math.pi * 0.1 * t),
        origin[1] + 50.0 * math.cos(2 * math.pi * 0.1 * t),
        origin[2] + 20.0,
    )
    # the simulated servo lags the 0.1 Hz target by a few ms: within 0.5 mm
    for got, want in zip(last.position, expect):
        assert got == pytest.approx(want, abs=0.5)


def test_igtl_input_drives_the_handle() -> None:
    # the tracker's TRANSFORMs arrive on the operator interface in this test, as a command
    # input (the shipped master takes TRANSFORM there for planes and the registration)
    m = SimMaster(position_master(input="igtl", input_interface="operator"))
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
            assert (
                m.op.send(igtl.TransformMessage.from_position(target, device_name="Tracker")) == 1
            )
            for _ in range(2):
                m.step(1)
                now = list(m.robot.data.setpoint)
                assert all(abs(a - b) <= lim + 1e-12 for a, b, lim in zip(now, previous, limit))
                previous = now
        assert m.sent[-1].position == pytest.approx(target, abs=0.05)
    finally:
        m.close()


@pytest.mark.req("SR-CLUTCH-1")
def test_clutch_travels_with_the_stream(master: SimMaster) -> None:
    master.command("Enable")
    master.command("Run")
    r = master.command("Clutch", '<Command Name="Clutch" Value="1"/>')
    assert r.metadata["Status"] == "SUCCESS"
    master.step(4)
    assert master.sent[-1].metadata["clutch"] == "1"
    master.command("Clutch", '<Command Name="Clutch" Value="0"/>')
    master.step(4)
    assert master.sent[-1].metadata["clutch"] == "0"


def hand(master: SimMaster):
    return master.robot.hardware.drivers[0]


def test_forbidden_sphere_pushes_the_hand_out_and_reports_force(master: SimMaster) -> None:
    master.command("Enable")
    master.command("Run")
    feed = SlaveTipFeed(master.sim)  # the slave's tip (patient) = 0.1 x the handle
    feed.step(200)
    handle = master.sent[-1].position
    # a forbidden sphere of 10 mm radius (of the handle's motion) centred 4 mm from the handle
    # (in +x): the tool is inside. Sent in the patient frame: 1 mm there is 10 on the master
    centre = (handle[0] + 4.0, handle[1], handle[2])
    fx = igtl.VirtualFixtureMessage(
        hardness=0.5,
        spheres=((*feed.patient(centre), 1.0),),
        device_name="Fixtures",
        header_version=2,
        metadata={"MRMLNodeName": "VF", "kind": "forbidden"},
    )
    assert master.op.send(fx) == 1
    feed.step(1)
    stats = master.robot.controller.stats()
    assert stats["fixtures"] == 1 and stats["fixture_contacts"] == 1
    assert stats["force_n"][0] < -2.0  # pushes back toward -x, out of the sphere: 0.5 N/mm x 4 mm
    # the force reached the hand's drive (its effort interface), this very tick
    assert hand(master)._cmd[0] == pytest.approx(stats["force_n"][0], abs=1e-3)
    feed.step(100)
    # the hand yields: the handle is pushed out toward the surface, away from where the hand
    # means to be (the arm, 300 N/m, against the fixture, 500 N/m)
    p = master.sent[-1].position
    intended = [
        v * 1000.0 + o
        for v, o in zip(
            hand(master).intended(), master.robot.controller.controllers[0].origin * 1000.0
        )
    ]
    assert math.dist(p, centre) > math.dist(intended, centre) + 2.0


@pytest.mark.req("SR-HOLD-1")
def test_stop_state_holds_and_reports() -> None:
    master = SimMaster(position_master())
    master.command("Enable")
    master.command("Run")
    master.step(100)
    master.command("Stop")
    assert master.robot.state is RobotState.STOPPED
    p0 = master.sent[-1].position
    master.step(200)
    assert master.sent[-1].metadata["run"] == "0"
    # holds the last commanded setpoint: the handle settles where it was told (the simulated
    # drive lags its command by ~0.3 mm at this speed) and then stays there
    p1 = master.sent[-1].position
    assert p1 == pytest.approx(p0, abs=0.5)
    master.step(100)
    assert master.sent[-1].position == pytest.approx(p1, abs=0.01)
    master.close()


def test_slicer_markups_points_become_fixture_spheres(master: SimMaster) -> None:
    from igtl.messages.point import PointElement

    master.command("Enable")
    master.command("Run")
    feed = SlaveTipFeed(master.sim)  # the slave's tip (patient) = 0.1 x the handle
    feed.step(200)
    handle = master.sent[-1].position
    near = PointElement(
        name="F-1",
        group="Selected",
        rgba=(255, 0, 0, 255),
        position=feed.patient((handle[0] + 2.0, handle[1], handle[2])),
    )
    hidden = PointElement(
        name="F-2",
        group="Selected",
        rgba=(0, 255, 0, 0),
        position=feed.patient((handle[0] - 2.0, handle[1], handle[2])),
    )
    pts = igtl.PointMessage(
        points=(near, hidden),
        device_name="F",
        header_version=2,
        metadata={"MRMLNodeName": "MarkupsFiducial", "kind": "forbidden", "radius": "0.5"},
    )
    assert master.op.send(pts) == 1
    feed.step(1)
    stats = master.robot.controller.stats()
    assert stats["fixtures"] == 1  # the hidden point (alpha 0) is not a fixture
    assert stats["contact"] == ["F-1"]
    # radius 0.5 mm (patient: 5 mm of the handle) around the visible point, 1 N/mm: the tool
    # 2 mm of the handle from its centre is 3 mm deep, pushed back toward -x
    assert stats["force_n"][0] == pytest.approx(-3.0, abs=0.1)
