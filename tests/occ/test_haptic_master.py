"""The shipped haptic master in simulated time: fixture definitions in (VFIXTURE, Slicer
Markups, files), the force on the effort interface, refusals, frames, display, stats and
recording. The paper's motion test itself is tests/tools/test_fixture_motion.py."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

import igtl
from igtl.messages.point import PointElement
from occ.fixture_defs import DefinitionError, PatientMapping, from_markups_file
from occ.record import Recorder, read_recording
from occ.safety import RobotState
from occ.testing import SimRobot

from ..tools.tooling import load_tool

ROOT = Path(__file__).resolve().parents[2]
standin = load_tool("slicer_standin")


class Master:
    def __init__(self, config: object = None, recorder: Recorder | None = None, **params: object) -> None:
        self.sim = SimRobot(config or ROOT / "configs" / "master.yaml", params=params or None,
                            recorder=recorder)
        self.robot = self.sim.robot
        self.ctrl = self.robot.controller.controllers[0]
        self.hand = self.robot.drivers[0][0]
        self.op = self.sim.peer("operator", address=("127.0.0.1", 41000))

    def command(self, name: str, text: str = "") -> igtl.Message:
        cid = self.op.send_command(name, text)
        self.sim.step(1)
        reply = self.op.reply_to(cid)
        assert reply is not None
        return reply

    def run(self) -> None:
        for c in ("Enable", "Run"):
            assert self.command(c).metadata["Status"] == "SUCCESS"

    @property
    def tool(self) -> tuple[float, float, float]:
        x, y, z = self.robot.frame.tip_position(self.robot.data.q)
        return (x * 1e3, y * 1e3, z * 1e3)

    def close(self) -> None:
        self.sim.close()


@pytest.fixture
def master():
    m = Master()
    yield m
    m.close()


def forbidden_at(centre, radius=10.0, k=1.0, name="VF") -> igtl.Message:
    return igtl.VirtualFixtureMessage(hardness=k, spheres=((*centre, radius),), device_name=name,
                                      header_version=2, metadata={"kind": "forbidden"})


# ------------------------------------------------------------------ the force on the effort interface
def test_force_is_commanded_only_while_running(master: Master) -> None:
    master.command("Enable")
    t = master.tool
    master.op.send(forbidden_at((t[0] + 4.0, t[1], t[2]), k=0.5))  # the tool 6 mm deep
    master.sim.step(100)
    assert master.robot.data.effort_command == [0.0, 0.0, 0.0]  # ENABLED: the device is free
    assert master.hand._cmd == [0.0, 0.0, 0.0]
    master.command("Run")
    eff = master.robot.data.effort_command
    # out of the sphere (centred 4 mm to the tool's +x when sent; the hand has moved since)
    away = [a - c for a, c in zip(master.tool, (t[0] + 4.0, t[1], t[2]))]
    assert math.hypot(*eff) > 2.5 and sum(e * a for e, a in zip(eff, away)) > 0.0
    assert master.hand._cmd == pytest.approx(eff)  # what the drive got, this tick
    master.command("Stop")
    assert master.robot.state is RobotState.STOPPED
    master.sim.step(1)
    assert master.robot.data.effort_command == [0.0, 0.0, 0.0]


def test_slicer_point_list_changes_the_force_within_one_tick(master: Master) -> None:
    master.run()
    master.sim.step(300)
    assert master.robot.data.effort_command == [0.0, 0.0, 0.0]
    # Slicer's RAS: where the slave's tip is for this handle (scale 10:1, no registration)
    tip = master.ctrl.fixtures.mapping.master_to_patient(master.tool)
    # a forbidden point 0.2 mm (patient) = 2 mm (master) from the tool, radius 0.5 mm = 5 mm
    msg = standin.markups_points([(tip[0] + 0.2, tip[1], tip[2])], "Keepout",
                                 kind="forbidden", radius=0.5)
    assert master.op.send(msg) == 1
    master.sim.step(1)  # the tick after arrival
    eff = master.robot.data.effort_command
    assert eff[0] == pytest.approx(-3.0, abs=0.1) and abs(eff[1]) < 0.05 and abs(eff[2]) < 0.05
    assert master.hand._cmd == pytest.approx(eff)
    stats = master.ctrl.stats()
    assert stats["contact"] == ["Keepout-1"] and stats["fixture_sources"] == ["POINT:Keepout"]


def test_point_list_as_a_guide(master: Master) -> None:
    master.run()
    master.sim.step(10)
    t = master.tool
    # a straight guide 3 mm above the handle, in the master frame
    msg = standin.markups_points([(t[0] - 50, t[1], t[2] + 3.0), (t[0] + 50, t[1], t[2] + 3.0)],
                                 "Path", kind="guide", frame="master", stiffness=0.5)
    master.op.send(msg)
    master.sim.step(1)
    assert master.robot.data.effort_command[2] == pytest.approx(1.5, abs=0.05)


# ------------------------------------------------------------------ refusals
def bad_messages():
    pt = PointElement(name="p", rgba=(255, 0, 0, 255), position=(0.0, 0.0, math.nan))
    ok_pt = PointElement(name="p", rgba=(255, 0, 0, 255), position=(0.0, 0.0, 0.0))
    return [
        ("negative radius", igtl.VirtualFixtureMessage(hardness=1.0, spheres=((0, 0, 0, -1.0),),
                                                       device_name="VF", header_version=2)),
        ("nan hardness", igtl.VirtualFixtureMessage(hardness=math.nan, spheres=((0, 0, 0, 1.0),),
                                                    device_name="VF", header_version=2)),
        ("unknown kind", igtl.VirtualFixtureMessage(hardness=1.0, spheres=((0, 0, 0, 1.0),),
                                                    device_name="VF", header_version=2,
                                                    metadata={"kind": "sticky"})),
        ("unknown version", igtl.VirtualFixtureMessage(hardness=1.0, spheres=((0, 0, 0, 1.0),),
                                                       version=7, device_name="VF")),
        ("nan point", igtl.PointMessage(points=(pt,), device_name="P", header_version=2)),
        ("bad stiffness", igtl.PointMessage(points=(ok_pt,), device_name="P", header_version=2,
                                            metadata={"stiffness": "stiff"})),
        ("guide of one point", igtl.PointMessage(points=(ok_pt,), device_name="P", header_version=2,
                                                 metadata={"kind": "guide"})),
        ("too many", igtl.VirtualFixtureMessage(hardness=1.0, spheres=((0, 0, 0, 1.0),) * 65,
                                                device_name="VF", header_version=2)),
        ("zero normal", igtl.TransformMessage(elements=(0.0,) * 12, device_name="Plane",
                                              header_version=2, metadata={"kind": "plane"})),
        ("bad frame", igtl.PointMessage(points=(ok_pt,), device_name="P", header_version=2,
                                        metadata={"frame": "world"})),
    ]


@pytest.mark.parametrize("why,msg", bad_messages(), ids=[b[0] for b in bad_messages()])
def test_invalid_definitions_are_refused_and_the_previous_set_stays(master: Master, why, msg) -> None:
    master.run()
    t = master.tool
    master.op.send(forbidden_at((t[0] + 4.0, t[1], t[2]), name="Good"))
    master.sim.step(1)
    before = master.robot.data.effort_command[:]
    assert before[0] < -5.0
    active = master.ctrl.fixtures.active
    n = len(master.op.received)
    master.op.send(msg)
    master.sim.step(1)
    replies = [m for m in master.op.received[n:] if m.message_type == "STATUS"]
    assert replies and "refused" in replies[-1].status_message, why
    assert replies[-1].code == igtl.StatusCode.ILLEGAL_INSTRUCTION
    assert master.ctrl.fixtures.active is active  # not swapped
    stats = master.ctrl.stats()
    assert stats["fixtures"] == 1 and stats["fixtures_refused"] == 1
    assert master.robot.state is RobotState.RUNNING  # refused, not a fault
    assert master.robot.data.effort_command[0] == pytest.approx(before[0], abs=0.2)


def test_too_many_planes_refused(master: Master) -> None:
    plane = lambda i: igtl.TransformMessage.from_position((0.0, 0.0, -100.0 - i),  # noqa: E731
                                                          device_name=f"P{i}", header_version=2,
                                                          metadata={"kind": "plane"})
    for i in range(8):
        master.op.send(plane(i))
    master.op.send(plane(8))
    master.sim.step(1)
    stats = master.ctrl.stats()
    assert stats["fixture_kinds"]["plane"] == 8 and stats["fixtures_refused"] == 1
    assert "max_planes" in stats["fixture_last_error"]


def test_empty_definition_removes_its_source_only(master: Master) -> None:
    master.op.send(forbidden_at((0.0, 0.0, 0.0), name="A"))
    master.op.send(forbidden_at((0.0, 0.0, 50.0), name="B"))
    master.sim.step(1)
    assert master.ctrl.stats()["fixtures"] == 2
    master.op.send(igtl.VirtualFixtureMessage(hardness=1.0, spheres=(), device_name="A"))
    master.sim.step(1)
    assert master.ctrl.stats()["fixture_sources"] == ["VFIXTURE:B"]
    assert master.command("ClearFixtures").metadata["Status"] == "SUCCESS"
    assert master.ctrl.stats()["fixtures"] == 0


# ------------------------------------------------------------------ encodings
def test_vfixture_paper_layout_and_default_kind_accessible(master: Master) -> None:
    # the paper's 8 + 16 n layout, from a v1 sender (no metadata): an accessible sphere
    import struct

    content = struct.pack(">BxHf", 1, 1, 1.0) + struct.pack(">4f", 0.0, 0.0, 250.0, 100.0)
    raw = igtl.RawMessage(type_name="VFIXTURE", device_name="VF", content=content).pack()
    assert master.op.send(raw) == 1
    master.sim.step(1)
    (prim,) = master.ctrl.fixtures.active.primitives
    assert prim.kind == "accessible" and prim.radius == 100.0


def test_markups_plane_as_transform(master: Master) -> None:
    master.run()
    t = master.tool
    # a plane 2 mm above the tool, normal -z (its z axis: the allowed side is below): free
    m = np.eye(4)
    m[:3, 2] = (0.0, 0.0, -1.0)
    m[:3, 0] = (-1.0, 0.0, 0.0)
    m[:3, 3] = (t[0], t[1], t[2] + 2.0)
    master.op.send(igtl.TransformMessage.from_matrix(
        m, device_name="Floor", header_version=2,
        metadata={"kind": "plane", "frame": "master", "stiffness": "2.0", "MRMLNodeName": "Floor"}))
    master.sim.step(1)
    assert master.robot.data.effort_command[2] == pytest.approx(0.0, abs=1e-9)
    # moved 2 mm below the tool (the same source: it replaces the first): 2 mm deep
    m[:3, 3] = (t[0], t[1], t[2] - 2.0)
    master.op.send(igtl.TransformMessage.from_matrix(
        m, device_name="Floor", header_version=2,
        metadata={"kind": "plane", "frame": "master", "stiffness": "2.0"}))
    master.sim.step(1)
    assert master.robot.data.effort_command[2] == pytest.approx(-4.0, abs=0.1)


def test_polydata_lines_as_guides(master: Master) -> None:
    master.run()
    t = master.tool
    pts = np.array([(t[0] - 40, t[1] + 2.0, t[2]), (t[0] + 40, t[1] + 2.0, t[2])])
    msg = igtl.PolyDataMessage(points=pts, lines=((0, 1),), device_name="Guide",
                               header_version=2, metadata={"kind": "guide", "frame": "master"})
    master.op.send(msg)
    master.sim.step(1)
    assert master.robot.data.effort_command[1] == pytest.approx(2.0, abs=0.05)


def test_markups_file_from_yaml_lps_to_ras(tmp_path: Path) -> None:
    doc = {
        "@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/"
                   "Markups/Resources/Schema/markups-schema-v1.0.3.json#",
        "markups": [
            {"type": "Fiducial", "coordinateSystem": "LPS", "name": "Targets",
             "controlPoints": [{"label": "T-1", "position": [10.0, 20.0, 30.0]},
                               {"label": "T-2", "position": [0.0, 0.0, 0.0], "visibility": False}]},
            {"type": "Line", "coordinateSystem": "RAS", "name": "Path",
             "controlPoints": [{"position": [0, 0, 0]}, {"position": [0, 0, 10]}]},
            {"type": "Plane", "coordinateSystem": "LPS", "name": "Wall", "center": [1, 2, 3],
             "normal": [1, 0, 0], "controlPoints": []},
        ],
    }
    path = tmp_path / "plan.mrk.json"
    path.write_text(json.dumps(doc))
    defs = from_markups_file(path, kind="forbidden", radius_mm=2.0)
    (t1, line, wall) = defs
    assert t1.kind == "forbidden" and t1.points == ((-10.0, -20.0, 30.0),) and t1.radius == 2.0
    assert t1.frame == "patient" and t1.name == "T-1"
    assert line.kind == "guide" and line.points == ((0, 0, 0), (0, 0, 10))
    assert wall.kind == "plane" and wall.points == ((-1.0, -2.0, 3.0),)
    assert wall.normal == (-1.0, 0.0, 0.0)
    # loaded at start from the YAML, relative to the config file
    raw = yaml.safe_load((ROOT / "configs" / "master.yaml").read_text())
    raw["controller"]["params"]["fixture_files"] = [
        {"file": "plan.mrk.json", "kind": "forbidden", "radius_mm": 2.0}]
    cfg_path = tmp_path / "master.yaml"
    cfg_path.write_text(yaml.safe_dump(raw))
    m = Master(cfg_path)
    try:
        assert m.ctrl.stats()["fixture_kinds"] == {"accessible": 0, "forbidden": 1, "plane": 1,
                                                   "guide": 1}
        (src,) = m.ctrl.stats()["fixture_sources"]
        assert src == f"file:{tmp_path / 'plan.mrk.json'}"
    finally:
        m.close()
    with pytest.raises(DefinitionError, match="markups"):
        bad = tmp_path / "bad.mrk.json"
        bad.write_text("{}")
        from_markups_file(bad)


# ------------------------------------------------------------------ frames
def test_patient_to_master_mapping_scale_registration_and_clutch() -> None:
    rz = [[0.0, -1.0, 0.0, 100.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, -20.0],
          [0.0, 0.0, 0.0, 1.0]]  # the slave's base: 90 deg about z, at (100, 0, -20)
    m = PatientMapping(0.1, registration=rz, slave_ref=(0.0, 0.0, 50.0))
    m.start_following((0.0, 0.0, 0.0))
    # the slave's tip is at the patient point for the handle at 0: maps back to 0
    p0 = m.master_to_patient((0.0, 0.0, 0.0))
    assert p0 == pytest.approx((100.0, 0.0, 30.0))
    assert m.point(p0) == pytest.approx((0.0, 0.0, 0.0))
    # 1 mm in the patient along the base's x (patient +y) is 10 mm on the master's x
    assert m.point((100.0, 1.0, 30.0)) == pytest.approx((10.0, 0.0, 0.0))
    assert m.length(2.0) == pytest.approx(20.0)
    assert m.direction((0.0, 1.0, 0.0)) == pytest.approx((1.0, 0.0, 0.0))
    # clutch: the handle moves 10 mm, clutch pressed, moves back 30 mm, released
    m.stop_following((10.0, 0.0, 0.0))
    v = m.version
    m.start_following((-20.0, 0.0, 0.0))
    assert m.version > v
    # the slave stopped at the patient point of handle (10, 0, 0); that is now under the
    # handle at (-20, 0, 0): the fixtures moved by -30 mm on the master
    assert m.point((100.0, 1.0, 30.0)) == pytest.approx((-20.0, 0.0, 0.0))
    # 1 mm further in the patient: 10 mm on the master at 10:1, 5 mm at 5:1
    assert m.point((100.0, 2.0, 30.0)) == pytest.approx((-10.0, 0.0, 0.0))
    m.set_scale(0.2)
    assert m.point((100.0, 2.0, 30.0)) == pytest.approx((-15.0, 0.0, 0.0))
    # a measured slave tip re-anchors
    m.slave_tip((100.0, 0.0, 30.0), (-20.0, 0.0, 0.0))
    assert m.point((100.0, 0.0, 30.0)) == pytest.approx((-20.0, 0.0, 0.0))


def test_clutch_moves_patient_fixtures_on_the_master(master: Master) -> None:
    master.run()
    master.sim.step(100)
    tip = master.ctrl.fixtures.mapping.master_to_patient(master.tool)
    master.op.send(standin.markups_points([tip], "Target", kind="accessible", radius=3.0))
    master.sim.step(1)
    (before,) = master.ctrl.fixtures.active.primitives
    assert before.radius == pytest.approx(30.0)  # 3 mm in the patient at 10:1
    assert math.dist(before.centre, master.tool) < 0.5
    master.command("Clutch", '<Command Name="Clutch" Value="1"/>')
    h0 = master.tool
    master.sim.step(1500)  # the hand moves on while the clutch is pressed
    master.command("Clutch", '<Command Name="Clutch" Value="0"/>')
    master.sim.step(1)
    h1 = master.tool
    (after,) = master.ctrl.fixtures.active.primitives
    moved = [a - b for a, b in zip(after.centre, before.centre)]
    assert moved == pytest.approx([b - a for a, b in zip(h0, h1)], abs=0.3)
    assert math.dist(h0, h1) > 5.0


def test_registration_transform_updates_the_mapping(master: Master) -> None:
    master.op.send(standin.markups_points([(0.0, 0.0, 0.0)], "T", kind="forbidden", radius=1.0))
    master.sim.step(1)
    (a,) = master.ctrl.fixtures.active.primitives
    reg = np.eye(4)
    reg[:3, 3] = (-5.0, 0.0, 0.0)  # the slave's base 5 mm to the left in the patient frame
    master.op.send(igtl.TransformMessage.from_matrix(reg, device_name="Base", header_version=2))
    master.sim.step(1)
    (b,) = master.ctrl.fixtures.active.primitives
    # the same patient point is 5 mm to the right of the base: 50 mm on the master
    assert b.centre[0] - a.centre[0] == pytest.approx(50.0)


# ------------------------------------------------------------------ display, stats, recording
def test_models_and_proxy_shown_in_slicer(master: Master) -> None:
    slicer = master.sim.peer("operator")
    master.run()
    t = master.tool
    master.op.send(forbidden_at((t[0] + 4.0, t[1], t[2]), name="Keepout"))
    plane = igtl.TransformMessage.from_position((0.0, 0.0, 0.0), device_name="Floor",
                                                header_version=2, metadata={"kind": "plane"})
    master.op.send(plane)
    master.sim.step(200)
    models = slicer.messages("POLYDATA", "VirtualFixtures")
    master.sim.step(300)
    assert slicer.messages("POLYDATA", "VirtualFixtures") == models  # on change only
    model = models[-1]
    assert model.metadata["MRMLNodeName"] == "VirtualFixtures"
    kinds = model.attributes[0].data[:, 0]
    assert set(kinds.tolist()) == {2.0, 3.0}  # forbidden sphere, plane
    assert len(kinds) == len(model.lines) + len(model.polygons)
    proxies = slicer.messages("TRANSFORM", "FixtureProxy")
    assert proxies and all(p.metadata["MRMLNodeName"] == "FixtureProxy" for p in proxies)
    touching = [p for p in proxies if p.metadata["contact"] == "Keepout-0"]
    assert touching and float(touching[0].metadata["force_n"].split(",")[0]) < 0.0
    # the hand moved on out of the sphere: one message says so, then the output is quiet
    assert proxies[-1].metadata["contact"] == "none"
    assert [p.metadata["contact"] for p in proxies].count("none") <= 2
    # GetFixtures sends the model again
    assert master.command("GetFixtures").metadata["Status"] == "SUCCESS"
    master.sim.step(100)
    assert len(slicer.messages("POLYDATA", "VirtualFixtures")) == len(models) + 1


def test_getstats_and_recording_have_tool_and_force(tmp_path: Path) -> None:
    path = tmp_path / "master.igtl"
    rec = Recorder(path, rate_hz=100).start()
    m = Master(recorder=rec)
    try:
        m.run()
        t = m.tool
        m.op.send(forbidden_at((t[0] + 4.0, t[1], t[2])))
        m.sim.step(300)
        cid = m.op.send_command("GetStats")
        m.sim.step(1)
        end = time.monotonic() + 5.0
        while m.op.reply_to(cid) is None and time.monotonic() < end:
            time.sleep(0.005)  # the worker thread builds the statistics
        reply = m.op.reply_to(cid)
        assert reply is not None and reply.metadata["Status"] == "SUCCESS"
        ctrl = json.loads(reply.command)["controller"] if reply.command.startswith("{") else None
        stats = ctrl if ctrl is not None else m.robot.snapshot()["controller"]
        assert stats["tool_mm"] == pytest.approx(m.tool, abs=0.5)
        assert stats["force_n"][0] < -1.0
    finally:
        m.close()
        rec.close()
    states = [x for x in read_recording(path) if x.message_type == "NDARRAY"
              and x.device_name == "OCCState"]
    cols = states[-1].metadata["columns"].split(",")
    row = dict(zip(cols, states[-1].array.ravel().tolist()))
    assert {"tip.x_mm", "eff.x", "eff.y", "eff.z"} <= set(cols)
    assert row["eff.x"] < -1.0


def test_a_burst_beyond_the_tick_budget_is_refused_busy_then_taken(master: Master) -> None:
    spheres = tuple((float(i), 0.0, 0.0, 5.0) for i in range(40))
    msg = igtl.VirtualFixtureMessage(hardness=1.0, spheres=spheres, device_name="Big",
                                     header_version=2)
    master.op.send(msg)
    master.op.send(msg)  # the same tick: 80 definitions to compile, over max_fixtures (64)
    master.sim.step(1)
    statuses = [m for m in master.op.received if m.message_type == "STATUS"
                and "busy" in m.status_message]
    assert len(statuses) == 1 and master.ctrl.stats()["fixtures"] == 40
    master.op.send(msg)
    master.sim.step(1)  # next tick: taken
    assert master.ctrl.stats()["fixtures_applied"] == 2
