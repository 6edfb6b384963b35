"""The shipped haptic master in simulated time: fixture definitions in (VFIXTURE, Slicer
Markups, files; all in the patient frame), the force on the effort interface, refusals, the
mapping, display, stats and recording. The slave is played by a :class:`SlaveTipFeed` (a tip
that follows the handle exactly, tip = 0.1 x handle), so forces are exact; the real pair is
tests/occ/test_return_channel.py, the paper's motion test tests/tools/test_fixture_motion.py."""

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
from occ.haptics.fixture_defs import DefinitionError, PatientMapping, from_markups_file
from occ.recording.record import Recorder, read_recording
from occ.core.safety import RobotState
from occ_testkit.rigs import SimMaster

from ..tools.tooling import load_tool

ROOT = Path(__file__).resolve().parents[2]
standin = load_tool("slicer_standin")


#: the master's controller ticks 25 times after Run: its force has faded in (tip_fade_ms, 20 ms)
SETTLE = 25


@pytest.fixture
def master():
    m = SimMaster(feed=True)
    yield m
    m.close()


def forbidden_at(centre, radius=1.0, k=1.0, name="VF") -> igtl.Message:
    """A forbidden VFIXTURE sphere, patient frame (mm): 1 mm there is 10 mm of the handle."""
    return igtl.VirtualFixtureMessage(
        hardness=k,
        spheres=((*centre, radius),),
        device_name=name,
        header_version=2,
        metadata={"kind": "forbidden"},
    )


# ------------------------------------------------------------------ the force on the effort interface
def test_force_is_commanded_only_while_running(master: SimMaster) -> None:
    master.command("Enable")
    t = master.feed.handle_mm()
    # 4 mm of the handle to the tool's +x, radius 10 mm of the handle: the tool 6 mm deep
    master.op.send(forbidden_at(master.feed.patient((t[0] + 4.0, t[1], t[2])), k=0.5))
    master.step(100)
    assert master.robot.data.effort_command == [0.0, 0.0, 0.0]  # ENABLED: the device is free
    assert master.robot.hardware.drivers[0]._cmd == [0.0, 0.0, 0.0]
    master.command("Run")
    master.step(25)  # faded in (tip_fade_ms)
    eff = master.robot.data.effort_command
    # out of the sphere (centred 4 mm to the tool's +x when sent; the hand has moved since)
    away = [a - c for a, c in zip(master.feed.handle_mm(), (t[0] + 4.0, t[1], t[2]))]
    assert math.hypot(*eff) > 2.5 and sum(e * a for e, a in zip(eff, away)) > 0.0
    assert master.robot.hardware.drivers[0]._cmd == pytest.approx(
        eff
    )  # what the drive got, this tick
    master.command("Stop")
    assert master.robot.state is RobotState.STOPPED
    master.step(1)
    assert master.robot.data.effort_command == [0.0, 0.0, 0.0]


def test_slicer_point_list_changes_the_force_within_one_tick(master: SimMaster) -> None:
    master.run(SETTLE)
    master.step(300)
    assert master.robot.data.effort_command == [0.0, 0.0, 0.0]
    # Slicer's RAS: where the slave's tip is (the Tip Slicer shows; 10:1)
    tip = master.feed.tip()
    # a forbidden point 0.2 mm (patient) = 2 mm (master) from the tool, radius 0.5 mm = 5 mm
    msg = standin.markups_points(
        [(tip[0] + 0.2, tip[1], tip[2])], "Keepout", kind="forbidden", radius=0.5
    )
    assert master.op.send(msg) == 1
    master.step(1)  # the tick after arrival
    eff = master.robot.data.effort_command
    assert eff[0] == pytest.approx(-3.0, abs=0.1) and abs(eff[1]) < 0.05 and abs(eff[2]) < 0.05
    assert master.robot.hardware.drivers[0]._cmd == pytest.approx(eff)
    stats = master.ctl.stats()
    assert stats["contact"] == ["Keepout-1"] and stats["fixture_sources"] == ["POINT:Keepout"]


def test_point_list_as_a_guide(master: SimMaster) -> None:
    master.run(SETTLE)
    master.step(10)
    t = master.feed.handle_mm()
    # a straight guide 3 mm of the handle (0.3 mm in the patient) above the tool
    msg = standin.markups_points(
        [
            master.feed.patient((t[0] - 50, t[1], t[2] + 3.0)),
            master.feed.patient((t[0] + 50, t[1], t[2] + 3.0)),
        ],
        "Path",
        kind="guide",
        stiffness=0.5,
    )
    master.op.send(msg)
    master.step(1)
    assert master.robot.data.effort_command[2] == pytest.approx(1.5, abs=0.05)


# ------------------------------------------------------------------ refusals
def bad_messages():
    pt = PointElement(name="p", rgba=(255, 0, 0, 255), position=(0.0, 0.0, math.nan))
    ok_pt = PointElement(name="p", rgba=(255, 0, 0, 255), position=(0.0, 0.0, 0.0))
    return [
        (
            "negative radius",
            igtl.VirtualFixtureMessage(
                hardness=1.0, spheres=((0, 0, 0, -1.0),), device_name="VF", header_version=2
            ),
        ),
        (
            "nan hardness",
            igtl.VirtualFixtureMessage(
                hardness=math.nan, spheres=((0, 0, 0, 1.0),), device_name="VF", header_version=2
            ),
        ),
        (
            "unknown kind",
            igtl.VirtualFixtureMessage(
                hardness=1.0,
                spheres=((0, 0, 0, 1.0),),
                device_name="VF",
                header_version=2,
                metadata={"kind": "sticky"},
            ),
        ),
        (
            "unknown version",
            igtl.VirtualFixtureMessage(
                hardness=1.0, spheres=((0, 0, 0, 1.0),), version=7, device_name="VF"
            ),
        ),
        ("nan point", igtl.PointMessage(points=(pt,), device_name="P", header_version=2)),
        (
            "bad stiffness",
            igtl.PointMessage(
                points=(ok_pt,), device_name="P", header_version=2, metadata={"stiffness": "stiff"}
            ),
        ),
        (
            "guide of one point",
            igtl.PointMessage(
                points=(ok_pt,), device_name="P", header_version=2, metadata={"kind": "guide"}
            ),
        ),
        (
            "too many",
            igtl.VirtualFixtureMessage(
                hardness=1.0, spheres=((0, 0, 0, 1.0),) * 65, device_name="VF", header_version=2
            ),
        ),
        (
            "zero normal",
            igtl.TransformMessage(
                elements=(0.0,) * 12,
                device_name="Plane",
                header_version=2,
                metadata={"kind": "plane"},
            ),
        ),
        (
            "bad frame",
            igtl.PointMessage(
                points=(ok_pt,), device_name="P", header_version=2, metadata={"frame": "world"}
            ),
        ),
        # one frame for every fixture: the patient's (the master's workspace is none)
        (
            "master frame",
            igtl.VirtualFixtureMessage(
                hardness=1.0,
                spheres=((0, 0, 0, 1.0),),
                device_name="VF",
                header_version=2,
                metadata={"frame": "master"},
            ),
        ),
    ]


@pytest.mark.parametrize("why,msg", bad_messages(), ids=[b[0] for b in bad_messages()])
def test_invalid_definitions_are_refused_and_the_previous_set_stays(
    master: SimMaster, why, msg
) -> None:
    master.run(SETTLE)
    master.step(100)
    t = master.feed.handle_mm()
    master.op.send(forbidden_at(master.feed.patient((t[0] + 4.0, t[1], t[2])), name="Good"))
    master.step(1)
    before = master.robot.data.effort_command[:]
    assert before[0] < -5.0
    active = master.ctl.fixtures.active
    n = len(master.op.received)
    master.op.send(msg)
    master.step(1)
    replies = [m for m in master.op.received[n:] if m.message_type == "STATUS"]
    assert replies and "refused" in replies[-1].status_message, why
    assert replies[-1].code == igtl.StatusCode.ILLEGAL_INSTRUCTION
    assert master.ctl.fixtures.active is active  # not swapped
    stats = master.ctl.stats()
    assert stats["fixtures"] == 1 and stats["fixtures_refused"] == 1
    assert master.robot.state is RobotState.RUNNING  # refused, not a fault
    assert master.robot.data.effort_command[0] == pytest.approx(before[0], abs=0.2)


def test_too_many_planes_refused(master: SimMaster) -> None:
    plane = lambda i: igtl.TransformMessage.from_position(
        (0.0, 0.0, -100.0 - i),  # noqa: E731
        device_name=f"P{i}",
        header_version=2,
        metadata={"kind": "plane"},
    )
    for i in range(8):
        master.op.send(plane(i))
    master.op.send(plane(8))
    master.step(1)
    stats = master.ctl.stats()
    assert stats["fixture_kinds"]["plane"] == 8 and stats["fixtures_refused"] == 1
    assert "max_planes" in stats["fixture_last_error"]


def test_empty_definition_removes_its_source_only(master: SimMaster) -> None:
    master.op.send(forbidden_at((0.0, 0.0, 0.0), name="A"))
    master.op.send(forbidden_at((0.0, 0.0, 50.0), name="B"))
    master.step(1)
    assert master.ctl.stats()["fixtures"] == 2
    master.op.send(igtl.VirtualFixtureMessage(hardness=1.0, spheres=(), device_name="A"))
    master.step(1)
    assert master.ctl.stats()["fixture_sources"] == ["VFIXTURE:B"]
    assert master.command("ClearFixtures").metadata["Status"] == "SUCCESS"
    assert master.ctl.stats()["fixtures"] == 0


# ------------------------------------------------------------------ encodings
def test_vfixture_paper_layout_and_default_kind_accessible(master: SimMaster) -> None:
    # the paper's 8 + 16 n layout, from a v1 sender (no metadata): an accessible sphere
    import struct

    content = struct.pack(">BxHf", 1, 1, 1.0) + struct.pack(">4f", 0.0, 0.0, 250.0, 100.0)
    raw = igtl.RawMessage(type_name="VFIXTURE", device_name="VF", content=content).pack()
    assert master.op.send(raw) == 1
    master.step(1)
    (prim,) = master.ctl.fixtures.active.primitives
    # 100 patient mm at 10:1: 1000 mm of the master's motion
    assert prim.kind == "accessible" and prim.radius == pytest.approx(1000.0)
    assert master.ctl.fixtures.groups["VFIXTURE:VF"][0].radius == 100.0


def test_markups_plane_as_transform(master: SimMaster) -> None:
    master.run(SETTLE)
    t = master.feed.handle_mm()
    # a plane 2 mm above the tool, normal -z (its z axis: the allowed side is below): free
    m = np.eye(4)
    m[:3, 2] = (0.0, 0.0, -1.0)
    m[:3, 0] = (-1.0, 0.0, 0.0)
    m[:3, 3] = master.feed.patient((t[0], t[1], t[2] + 2.0))
    master.op.send(
        igtl.TransformMessage.from_matrix(
            m,
            device_name="Floor",
            header_version=2,
            metadata={"kind": "plane", "stiffness": "2.0", "MRMLNodeName": "Floor"},
        )
    )
    master.step(1)
    assert master.robot.data.effort_command[2] == pytest.approx(0.0, abs=1e-9)
    # moved 2 mm below the tool (the same source: it replaces the first): 2 mm deep
    m[:3, 3] = master.feed.patient((t[0], t[1], t[2] - 2.0))
    master.op.send(
        igtl.TransformMessage.from_matrix(
            m,
            device_name="Floor",
            header_version=2,
            metadata={"kind": "plane", "frame": "patient", "stiffness": "2.0"},
        )
    )
    master.step(1)
    assert master.robot.data.effort_command[2] == pytest.approx(-4.0, abs=0.1)


def test_polydata_lines_as_guides(master: SimMaster) -> None:
    master.run(SETTLE)
    t = master.feed.handle_mm()
    pts = np.array(
        [
            master.feed.patient((t[0] - 40, t[1] + 2.0, t[2])),
            master.feed.patient((t[0] + 40, t[1] + 2.0, t[2])),
        ]
    )
    msg = igtl.PolyDataMessage(
        points=pts,
        lines=((0, 1),),
        device_name="Guide",
        header_version=2,
        metadata={"kind": "guide"},
    )
    master.op.send(msg)
    master.step(1)
    assert master.robot.data.effort_command[1] == pytest.approx(2.0, abs=0.05)


def test_markups_file_from_yaml_lps_to_ras(tmp_path: Path) -> None:
    doc = {
        "@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/"
        "Markups/Resources/Schema/markups-schema-v1.0.3.json#",
        "markups": [
            {
                "type": "Fiducial",
                "coordinateSystem": "LPS",
                "name": "Targets",
                "controlPoints": [
                    {"label": "T-1", "position": [10.0, 20.0, 30.0]},
                    {"label": "T-2", "position": [0.0, 0.0, 0.0], "visibility": False},
                ],
            },
            {
                "type": "Line",
                "coordinateSystem": "RAS",
                "name": "Path",
                "controlPoints": [{"position": [0, 0, 0]}, {"position": [0, 0, 10]}],
            },
            {
                "type": "Plane",
                "coordinateSystem": "LPS",
                "name": "Wall",
                "center": [1, 2, 3],
                "normal": [1, 0, 0],
                "controlPoints": [],
            },
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
        {"file": "plan.mrk.json", "kind": "forbidden", "radius_mm": 2.0}
    ]
    cfg_path = tmp_path / "master.yaml"
    cfg_path.write_text(yaml.safe_dump(raw))
    m = SimMaster(cfg_path, feed=True)
    try:
        assert m.ctl.stats()["fixture_kinds"] == {
            "accessible": 0,
            "forbidden": 1,
            "plane": 1,
            "guide": 1,
        }
        (src,) = m.ctl.stats()["fixture_sources"]
        assert src == f"file:{tmp_path / 'plan.mrk.json'}"
    finally:
        m.close()
    with pytest.raises(DefinitionError, match="markups"):
        bad = tmp_path / "bad.mrk.json"
        bad.write_text("{}")
        from_markups_file(bad)


# ------------------------------------------------------------------ frames
def test_patient_to_master_map_scale_registration_and_the_slaves_own_map() -> None:
    rz = [
        [0.0, -1.0, 0.0, 100.0],
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, -20.0],
        [0.0, 0.0, 0.0, 1.0],
    ]  # the slave's base: 90 deg about z, at (100, 0, -20)
    m = PatientMapping(0.1, registration=rz)
    assert m.source == "params" and m.factor == pytest.approx(0.1)
    # 1 mm in the patient along the base's x (patient +y) is 10 mm on the master's x;
    # only differences matter (the translation never enters)
    a, b = m.point((100.0, 0.0, 30.0)), m.point((100.0, 1.0, 30.0))
    assert [q - p for p, q in zip(a, b)] == pytest.approx([10.0, 0.0, 0.0])
    assert m.master_to_patient(b) == pytest.approx((100.0, 1.0, 30.0))
    assert m.length(2.0) == pytest.approx(20.0)
    assert m.direction((0.0, 1.0, 0.0)) == pytest.approx((1.0, 0.0, 0.0))
    assert m.patient_direction((1.0, 0.0, 0.0)) == pytest.approx((0.0, 1.0, 0.0))
    # the slave's own map (its base rotation x scale x rotation) wins over the parameters
    v = m.version
    assert m.set_linear(((0.2, 0.0, 0.0), (0.0, 0.2, 0.0), (0.0, 0.0, 0.2)))
    assert not m.set_linear(((0.2, 0.0, 0.0), (0.0, 0.2, 0.0), (0.0, 0.0, 0.2)))
    assert m.source == "slave" and m.version == v + 1
    m.set_registration(np.eye(4).tolist())
    assert m.point((1.0, 0.0, 0.0)) == pytest.approx((5.0, 0.0, 0.0))
    with pytest.raises(DefinitionError, match="scaled rotation"):
        m.set_linear(((0.1, 0.0, 0.0), (0.0, 0.2, 0.0), (0.0, 0.0, 0.1)))


def test_clutch_leaves_the_fixtures_where_they_are_and_fades_the_force(master: SimMaster) -> None:
    master.run(SETTLE)
    master.step(100)
    t = master.feed.handle_mm()
    master.op.send(
        forbidden_at(master.feed.patient((t[0] + 4.0, t[1], t[2])), k=0.5, name="Keepout")
    )
    master.step(1)
    (before,) = master.ctl.fixtures.active.primitives
    f0 = math.hypot(*master.robot.data.effort_command)
    assert f0 > 2.5
    master.command("Clutch", '<Command Name="Clutch" Value="1"/>')
    master.feed.following = False  # the slave stops following (it tells the master so)
    master.step(20)  # tip_fade_ms: 20 ms
    assert master.robot.data.effort_command == pytest.approx([0.0, 0.0, 0.0], abs=1e-9)
    master.step(1500)  # the hand moves on while the clutch is pressed
    master.command("Clutch", '<Command Name="Clutch" Value="0"/>')
    master.feed.following = True
    master.step(1)
    (after,) = master.ctl.fixtures.active.primitives
    # patient fixtures stay put on the master: the tool is where the slave measures it
    assert after.centre == pytest.approx(before.centre)
    assert master.ctl.stats()["fixture_map"] == {"source": "slave", "scale": 0.1}


def test_registration_transform_sets_the_map_when_the_slave_sends_none(master: SimMaster) -> None:
    master.close()
    m = SimMaster(feed=True)
    try:
        m.feed.paused = True  # a slave that sends no map (and no tip)
        m.op.send(standin.markups_points([(1.0, 0.0, 0.0)], "T", kind="forbidden", radius=1.0))
        m.step(1)
        (a,) = m.ctl.fixtures.active.primitives
        assert a.centre == pytest.approx((10.0, 0.0, 0.0))
        reg = np.eye(4)
        reg[:3, 3] = (-5.0, 0.0, 0.0)  # a translation moves nothing on the master
        m.op.send(igtl.TransformMessage.from_matrix(reg, device_name="Base", header_version=2))
        m.step(1)
        assert m.ctl.fixtures.active.primitives[0].centre == pytest.approx((10.0, 0.0, 0.0))
        reg[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]  # 90 deg about z
        m.op.send(igtl.TransformMessage.from_matrix(reg, device_name="Base", header_version=2))
        m.step(1)
        assert m.ctl.fixtures.active.primitives[0].centre == pytest.approx((0.0, -10.0, 0.0))
    finally:
        m.close()


# ------------------------------------------------------------------ display, stats, recording
def test_models_and_proxy_shown_in_slicer(master: SimMaster) -> None:
    slicer = master.sim.peer("operator")
    master.run(SETTLE)
    master.step(100)
    t = master.feed.handle_mm()
    master.op.send(forbidden_at(master.feed.patient((t[0] + 4.0, t[1], t[2])), name="Keepout"))
    plane = igtl.TransformMessage.from_position(
        (0.0, 0.0, 0.0), device_name="Floor", header_version=2, metadata={"kind": "plane"}
    )
    master.op.send(plane)
    master.step(200)
    models = slicer.messages("POLYDATA", "VirtualFixtures")
    master.step(300)
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
    master.step(100)
    assert len(slicer.messages("POLYDATA", "VirtualFixtures")) == len(models) + 1


def test_the_displayed_force_as_sensor_and_ndarray_outputs() -> None:
    """Output source ``force``: the displayed force (N, the master's axes) as SENSOR with the
    unit N, or as NDARRAY (unit in the v2 metadata): what ROS 2's measured_cf carries."""
    cfg = yaml.safe_load((ROOT / "configs" / "master.yaml").read_text())
    outputs = cfg["interfaces"][0]["outputs"]  # the shipped Force (50 Hz) replaced by 100 Hz
    outputs[:] = [o for o in outputs if o["source"] != "force"]
    outputs += [
        {"type": "SENSOR", "device": "Force", "source": "force", "rate_hz": 100},
        {"type": "NDARRAY", "device": "ForceArray", "source": "force", "rate_hz": 100},
    ]
    m = SimMaster(cfg, feed=True)
    try:
        viewer = m.sim.peer("operator")
        m.run(SETTLE)
        m.step(100)
        before = viewer.messages("SENSOR", "Force")
        assert before and all(x.data == (0.0, 0.0, 0.0) for x in before)
        t = m.feed.handle_mm()
        m.op.send(forbidden_at(m.feed.patient((t[0] + 4.0, t[1], t[2]))))
        m.step(30)
        # each message carries the force displayed in the tick that sent it
        checked = 0
        for _ in range(30):
            n = len(viewer.messages("SENSOR", "Force"))
            m.step(1)
            sent = viewer.messages("SENSOR", "Force")[n:]
            if not sent:
                continue
            force = tuple(m.ctl.fixtures.force_n)
            assert force[0] < -1.0  # pushed out of the sphere, toward -x
            (sensor,) = sent
            assert str(sensor.unit) == "N" and sensor.unit.units == ((11, 1),)
            assert sensor.data == pytest.approx(force, abs=1e-12)
            array = viewer.messages("NDARRAY", "ForceArray")[-1]
            assert array.metadata["unit"] == "N"
            assert array.array.ravel().tolist() == pytest.approx(force, abs=1e-12)
            checked += 1
        assert checked == 3  # 100 Hz of a 1 kHz loop
    finally:
        m.close()


def test_getstats_and_recording_have_tool_and_force(tmp_path: Path) -> None:
    path = tmp_path / "master.igtl"
    rec = Recorder(path, rate_hz=100).start()
    m = SimMaster(recorder=rec, feed=True)
    try:
        m.run(SETTLE)
        m.step(100)
        t = m.feed.handle_mm()
        m.op.send(forbidden_at(m.feed.patient((t[0] + 4.0, t[1], t[2]))))
        m.step(300)
        cid = m.op.send_command("GetStats")
        m.step(1)
        end = time.monotonic() + 5.0
        while m.op.reply_to(cid) is None and time.monotonic() < end:
            time.sleep(0.005)  # the worker thread builds the statistics
        reply = m.op.reply_to(cid)
        assert reply is not None and reply.metadata["Status"] == "SUCCESS"
        ctrl = json.loads(reply.command)["controller"] if reply.command.startswith("{") else None
        stats = ctrl if ctrl is not None else m.robot.snapshot()["controller"]
        # the tool is the slave's tip, in the patient frame (0.1 x the handle here)
        assert stats["tool_mm"] == pytest.approx(m.feed.tip(), abs=0.05)
        assert stats["tool_frame"] == "patient" and stats["slave_tip"]["status"] == "fresh"
        assert stats["force_n"][0] < -1.0
    finally:
        m.close()
        rec.close()
    states = [
        x
        for x in read_recording(path)
        if x.message_type == "NDARRAY" and x.device_name == "OCCState"
    ]
    cols = states[-1].metadata["columns"].split(",")
    row = dict(zip(cols, states[-1].array.ravel().tolist()))
    assert {"tip.x_mm", "eff.x", "eff.y", "eff.z"} <= set(cols)
    assert row["eff.x"] < -1.0


def test_a_burst_beyond_the_tick_budget_is_refused_busy_then_taken(master: SimMaster) -> None:
    spheres = tuple((float(i), 0.0, 0.0, 5.0) for i in range(40))
    msg = igtl.VirtualFixtureMessage(
        hardness=1.0, spheres=spheres, device_name="Big", header_version=2
    )
    master.op.send(msg)
    master.op.send(msg)  # the same tick: 80 definitions to compile, over max_fixtures (64)
    master.step(1)
    statuses = [
        m for m in master.op.received if m.message_type == "STATUS" and "busy" in m.status_message
    ]
    assert len(statuses) == 1 and master.ctl.stats()["fixtures"] == 40
    master.op.send(msg)
    master.step(1)  # next tick: taken
    assert master.ctl.stats()["fixtures_applied"] == 2
