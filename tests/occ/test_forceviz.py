"""occ/haptics/forceviz.py piece by piece: what 3D Slicer, a recording's reader and ``occd
--check`` get.

The arrow's documented proportions and its faces as a renderer takes them, the TRANSFORM's frame
for a force along any axis and at the exact minimum length, which messages carry a force (the
recordings' reader, occ/recording/export.py and occ/recording/plot.py), the output checks' exact
errors, and the output source ``force`` on a slave alone in simulated time: every type's force,
timestamp, header version and metadata, from each force source (the tissue, the drives'
efforts, a force sensor on the tool, a 6-axis sensor's torque). No pair and no wall clock: each
test is quick (the mutation run of ``forceviz`` runs them per mutant; docs/VERIFICATION.md).
"""

from __future__ import annotations

import math
import re
from typing import Any, cast

import numpy as np
import pytest
import yaml

import igtl
from igtl.messages.sensor import Unit
from occ.core.loader import parse_config
from occ.errors import ConfigError, OCCError
from occ.events import VectorOut
from occ.haptics.forceviz import MIN_LENGTH_MM, arrow_mesh, force_matrix, parse_force
from occ.net.decoders import message_force
from occ.net.outputs import Output
from occ.net.packers import pack_output
from occ_testkit.testing import CONFIGS, SimRobot

Vec3 = tuple[float, float, float]
NEWTON = Unit(0, ((11, 1),))


# ------------------------------------------------------------------------------ the arrow
def _axial(points: np.ndarray, tip: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each point's distance along ``d`` from the tip and from the arrow's axis."""
    along = (points - tip) @ d
    radial = np.linalg.norm((points - tip) - np.outer(along, d), axis=1)
    return along, radial


@pytest.mark.parametrize(
    ("length", "r_shaft", "head"),
    [
        (1.0, 0.2, 0.3),  # the thinnest shaft: 0.2 mm
        (10.0, 0.4, 3.0),  # 4 % and 30 % of the length
        (25.0, 1.0, 7.5),  # 4 % is the thickest shaft: 1 mm
        (50.0, 1.0, 8.0),  # the longest head: 8 mm
    ],
)
def test_the_arrow_has_the_documented_proportions(
    length: float, r_shaft: float, head: float
) -> None:
    """Shaft radius 4 % of the length (0.2 to 1 mm), the cone's 2.5 times it, the cone 30 % of
    the length (at most 8 mm): each ring of 12 points at its place (arrow_mesh's docstring)."""
    d = np.array([0.36, -0.48, 0.8])  # a unit vector
    tip = np.array([3.0, -4.0, 25.0])
    mm_per_n = 2.5
    points, polys = arrow_mesh(tuple(tip), tuple(d * length / mm_per_n), mm_per_n)
    assert points.shape == (38, 3) and len(polys) == 48
    along, radial = _axial(points, tip, d)
    neck = length - head
    rings = {(round(float(a), 6), round(float(r), 6)) for a, r in zip(along, radial, strict=True)}
    assert rings == {
        (0.0, 0.0),  # the base cap's centre: the tip
        (0.0, r_shaft),  # the base ring
        (round(neck, 6), r_shaft),  # the shaft's top
        (round(neck, 6), 2.5 * r_shaft),  # the cone's base
        (round(length, 6), 0.0),  # the apex
    }
    for a, r in ((0.0, r_shaft), (neck, r_shaft), (neck, 2.5 * r_shaft)):
        ring = np.isclose(along, a, atol=1e-9) & np.isclose(radial, r, atol=1e-9)
        assert ring.sum() == 12


def _newell(p: np.ndarray) -> np.ndarray:
    """A polygon's normal (Newell's method: right-handed with the vertex order)."""
    n = np.zeros(3)
    for i in range(len(p)):
        a, b = p[i], p[(i + 1) % len(p)]
        n += np.array(
            [
                (a[1] - b[1]) * (a[2] + b[2]),
                (a[2] - b[2]) * (a[0] + b[0]),
                (a[0] - b[0]) * (a[1] + b[1]),
            ]
        )
    return n


@pytest.mark.parametrize(
    "force",
    [(2.0, 0.0, 0.0), (0.0, -0.7, 0.0), (0.3, -0.4, 1.2), (0.0, 0.0, -0.05), (1.0, 1.0, 0.0)],
)
def test_every_face_is_convex_and_counter_clockwise_seen_from_outside(force: Vec3) -> None:
    """VTK draws a polygon as its fan of triangles: each face must be convex, its corners
    counter-clockwise seen from outside (the caps and the cone's underside face back along
    the force, the shaft and the cone away from the axis)."""
    tip = np.array([5.0, -7.0, 30.0])
    points, polys = arrow_mesh(tuple(tip), force, 10.0)
    d = np.array(force) / np.linalg.norm(force)
    for poly in polys:
        p = points[list(poly)]
        n = _newell(p)
        assert np.linalg.norm(n) > 1e-9, poly  # not degenerate
        n /= np.linalg.norm(n)
        for i in range(len(p)):  # every corner turns the same way: convex
            a, b, c = p[i], p[(i + 1) % len(p)], p[(i + 2) % len(p)]
            assert np.cross(b - a, c - b) @ n > 1e-12, poly
        centre = p.mean(axis=0)
        along = (centre - tip) @ d
        out = (centre - tip) - along * d  # away from the axis
        if abs(n @ d) > 1.0 - 1e-9:
            assert n @ d < 0.0, poly  # a flat ring or cap: faces back, to the tip
        else:
            assert n @ out > 0.0, poly


@pytest.mark.parametrize(
    "force",
    [
        (3.0, 0.0, 0.0), (-3.0, 0.0, 0.0), (0.0, 3.0, 0.0), (0.0, -3.0, 0.0),
        (0.0, 0.0, 3.0), (0.0, 0.0, -3.0), (1.0, 1.0, 0.0), (1.0, 0.0, 1.0), (0.0, 1.0, 1.0),
        (-1.0, 1.0, 0.0), (0.9, math.sqrt(1.0 - 0.81), 0.0), (2.0, 1e-9, -1e-9),
    ],
)  # fmt: skip
def test_a_force_along_any_axis_is_a_right_handed_frame_and_a_whole_arrow(force: Vec3) -> None:
    """Along the axes, their diagonals and where the helper axis changes (the force 0.9 along
    x): the TRANSFORM's x and y unit, at right angles to the force and each other, x cross y
    along it; the arrow finite, as long as the force, its rings round."""
    tip = (1.0, 2.0, 3.0)
    f = np.array(force)
    m = force_matrix(tip, force, 10.0)
    assert np.isfinite(m).all()
    x, y, z = m[:3, 0], m[:3, 1], m[:3, 2]
    assert np.allclose(z, f * 10.0)
    assert np.isclose(np.linalg.norm(x), 1.0) and np.isclose(np.linalg.norm(y), 1.0)
    assert abs(x @ y) < 1e-12 and abs(x @ f) < 1e-12 and abs(y @ f) < 1e-12
    assert np.allclose(np.cross(x, y), f / np.linalg.norm(f))
    points, polys = arrow_mesh(tip, force, 10.0)
    assert np.isfinite(points).all() and points.shape == (38, 3)
    d = f / np.linalg.norm(f)
    along, radial = _axial(points, np.array(tip), d)
    assert along.max() == pytest.approx(np.linalg.norm(f) * 10.0)
    assert np.allclose(np.sort(radial)[-12:], 2.5 * min(max(0.04 * along.max(), 0.2), 1.0))


def test_an_arrow_exactly_min_length_long_is_drawn_and_shown_in_its_direction() -> None:
    """The boundary: a force of exactly MIN_LENGTH_MM is an arrow and the TRANSFORM's z axis
    points along it; one a rounding step shorter is no arrow and the short z axis."""
    tip = (10.0, 20.0, 30.0)
    force = (-1e-3, 0.0, 0.0)
    assert float(np.linalg.norm(force)) * 1.0 == MIN_LENGTH_MM  # exactly, in floating point
    m = force_matrix(tip, force, 1.0)
    assert np.array_equal(m[:3, 2], [-MIN_LENGTH_MM, 0.0, 0.0])
    points, polys = arrow_mesh(tip, force, 1.0)
    assert points.shape == (38, 3) and len(polys) == 48
    assert np.allclose(points[np.argmin(points[:, 0])], (10.0 - MIN_LENGTH_MM, 20.0, 30.0))
    shorter = (float(np.nextafter(-1e-3, 0.0)), 0.0, 0.0)
    m = force_matrix(tip, shorter, 1.0)
    assert np.array_equal(m[:3, :3], np.diag([1.0, 1.0, MIN_LENGTH_MM]))
    points, polys = arrow_mesh(tip, shorter, 1.0)
    assert points.shape == (0, 3) and polys == ()


# ------------------------------------------------------------------------------ the checks
def _errors(cfg: dict[str, Any]) -> list[str]:
    """parse_config's error lines, without the line numbers."""
    with pytest.raises(ConfigError) as err:
        parse_config(yaml.safe_dump(cfg))
    return [re.sub(r"^<string>:\d+ ", "", line) for line in str(err.value).splitlines()]


def _wall() -> dict[str, Any]:
    return dict(yaml.safe_load((CONFIGS / "wall.yaml").read_text()))


def test_occd_check_names_each_force_output_of_a_type_that_cannot_carry_it() -> None:
    cfg = _wall()
    cfg["interfaces"][0]["outputs"].append(
        {"type": "POINT", "device": "F", "source": "force", "rate_hz": 10}
    )
    master = next(i for i in cfg["interfaces"] if i["name"] == "master")
    master["outputs"].append({"type": "STATUS", "device": "G", "source": "force", "rate_hz": 10})
    assert _errors(cfg) == [
        "controller.params.force: interface 'slicer', output 'F': source 'force' goes as "
        "TRANSFORM, POLYDATA, SENSOR, NDARRAY, not POINT",
        "controller.params.force: interface 'master', output 'G': source 'force' goes as "
        "TRANSFORM, POLYDATA, SENSOR, NDARRAY, not STATUS",
    ]


def test_occd_check_names_each_force_output_of_a_slave_without_force() -> None:
    """Only the outputs of source ``force``: the slave's other outputs (Tip, Base, Joints, its
    return channel) are no problem."""
    cfg = dict(yaml.safe_load((CONFIGS / "slave.yaml").read_text()))
    cfg["interfaces"][0]["outputs"].append(
        {"type": "TRANSFORM", "device": "TipForce", "source": "force", "rate_hz": 10}
    )
    cfg["interfaces"][0]["outputs"].append(
        {"type": "SENSOR", "device": "Force", "source": "force", "rate_hz": 10}
    )
    assert _errors(cfg) == [
        "controller.params.force: interface 'slicer', output 'TipForce': source 'force' needs "
        "the controller's force",
        "controller.params.force: interface 'slicer', output 'Force': source 'force' needs "
        "the controller's force",
    ]


def test_occd_check_takes_a_force_output_of_every_type_that_carries_it() -> None:
    cfg = _wall()
    cfg["interfaces"][0]["outputs"] += [
        {"type": "SENSOR", "device": "Force", "source": "force", "rate_hz": 10},
        {"type": "NDARRAY", "device": "ForceArray", "source": "force", "rate_hz": 10},
    ]
    config = parse_config(yaml.safe_dump(cfg))
    types = [o.type for o in config.interfaces[0].outputs if o.source == "force"]
    assert sorted(types) == ["NDARRAY", "POLYDATA", "SENSOR", "TRANSFORM"]


# ------------------------------------------------------------------------------ recordings
def _wire(msg: igtl.Message) -> Any:
    """The message as a recording's reader decodes it."""
    return igtl.unpack(msg.pack())


def _transform(device: str, meta: dict[str, str]) -> Any:
    return _wire(igtl.TransformMessage.from_matrix(
        np.eye(4), device_name=device, header_version=2, metadata=meta
    ))  # fmt: skip


def _position(meta: dict[str, str]) -> Any:
    return _wire(igtl.PositionMessage(
        (1.0, 2.0, 3.0), device_name="SlaveTip", header_version=2, metadata=meta
    ))  # fmt: skip


def _sensor(values: tuple[float, ...], device: str = "Force", **meta: str) -> Any:
    return _wire(igtl.SensorMessage(
        values, NEWTON, device_name=device, header_version=2, metadata=meta
    ))  # fmt: skip


def _ndarray(values: Any, device: str = "Force", **meta: str) -> Any:
    return _wire(igtl.NDArrayMessage(
        array=np.asarray(values, dtype=np.float64), device_name=device, header_version=2,
        metadata=meta,
    ))  # fmt: skip


def test_a_recording_finds_the_slaves_force_in_its_return_channel_and_its_slicer_outputs() -> None:
    f = "0.5000,-1.2500,2.0000"
    got = (0.5, -1.25, 2.0)
    # the return channel (its map rides along) and the TRANSFORM to Slicer (mm_per_n)
    assert message_force(_position({"force_n": f, "map": "1,0,0;0,1,0;0,0,1"})) == (
        "patient", got
    )  # fmt: skip
    assert message_force(_transform("TipForce", {"force_n": f, "mm_per_n": "10"})) == (
        "patient", got
    )  # fmt: skip
    assert message_force(_position({"force_n": f, "mm_per_n": "10"})) == ("patient", got)
    assert message_force(_transform("TipForce", {"force_n": f, "map": "x"})) == ("patient", got)


def test_a_recording_takes_no_force_from_a_pose_without_one_or_from_the_masters_fixtures() -> None:
    # the master's FixtureProxy: a force_n in the master's axes, neither map nor mm_per_n
    assert message_force(_transform("FixtureProxy", {"force_n": "1,2,3", "contact": "s"})) is None
    assert message_force(_position({"force_n": "1,2,3"})) is None
    # a return channel before any force, a Tip, a force_n that is no force
    assert message_force(_position({"map": "1,0,0;0,1,0;0,0,1"})) is None
    assert message_force(_transform("Tip", {"mm_per_n": "10"})) is None
    for bad in ("1,2", "1,2,x", "nan,0,0", ""):
        assert message_force(_position({"force_n": bad, "map": "m"})) is None
        assert message_force(_transform("TipForce", {"force_n": bad, "mm_per_n": "1"})) is None
    # a force_n on a type that carries none
    point = _wire(igtl.PointMessage(device_name="F", header_version=2, metadata={
        "force_n": "1,2,3", "map": "m", "mm_per_n": "1"
    }))  # fmt: skip
    assert message_force(point) is None


def test_a_recording_finds_a_force_device_in_sensor_and_ndarray_in_its_frame() -> None:
    # the slave's force output (frame patient); the master's displayed force (its own axes)
    assert message_force(_sensor((0.5, -1.5, 2.5), frame="patient")) == (
        "patient", (0.5, -1.5, 2.5)
    )  # fmt: skip
    assert message_force(_sensor((0.5, -1.5, 2.5))) == ("base", (0.5, -1.5, 2.5))
    assert message_force(_sensor((0.5, -1.5, 2.5), frame="tip")) == ("base", (0.5, -1.5, 2.5))
    assert message_force(_ndarray([0.5, -1.5, 2.5], frame="patient")) == (
        "patient", (0.5, -1.5, 2.5)
    )  # fmt: skip
    assert message_force(_ndarray([[0.5], [-1.5], [2.5]])) == ("base", (0.5, -1.5, 2.5))
    # force and torque: the force; a torque that is not finite does not matter
    six = (0.5, -1.5, 2.5, math.nan, math.inf, 0.01)
    assert message_force(_sensor(six, frame="patient")) == ("patient", (0.5, -1.5, 2.5))
    assert message_force(_ndarray(np.array(six).reshape(2, 3))) == ("base", (0.5, -1.5, 2.5))


def test_a_recording_refuses_a_force_device_that_is_no_force() -> None:
    for values in ((1.0, 2.0), (1.0, 2.0, 3.0, 4.0), (1.0,) * 7, ()):
        assert message_force(_sensor(values)) is None
        assert message_force(_ndarray(list(values))) is None
    for i in range(3):
        for bad in (math.nan, math.inf, -math.inf):
            v = [1.0, 2.0, 3.0]
            v[i] = bad
            assert message_force(_sensor(tuple(v))) is None
            assert message_force(_ndarray(v)) is None
            assert message_force(_sensor((*v, 0.0, 0.0, 0.0))) is None
    # another device (a force sensor's own stream), another type
    assert message_force(_sensor((1.0, 2.0, 3.0), device="ForceSensor")) is None
    assert message_force(_ndarray([1.0, 2.0, 3.0], device="Joints")) is None
    status = _wire(igtl.StatusMessage(device_name="Force", header_version=2, metadata={
        "force_n": "1,2,3", "map": "m"
    }))  # fmt: skip
    assert message_force(status) is None


# ------------------------------------------------------------------------------ on the tick
def _alone(force: dict[str, Any], outputs: list[dict[str, Any]]) -> dict[str, Any]:
    """The wall slave without a master (no return channel: the source estimates the force
    itself), Slicer's outputs ``outputs``, an interface ``ft`` for a force sensor."""
    cfg = _wall()
    master = next(i for i in cfg["interfaces"] if i["name"] == "master")
    del master["outputs"]
    cfg["controller"]["params"]["force"] = force
    cfg["interfaces"][0]["outputs"] = outputs
    cfg["interfaces"].append({
        "name": "ft", "transport": "udp", "host": "127.0.0.1", "port": 18990,
        "inputs": [{"type": "SENSOR", "queue": "stream", "depth": 10}],
    })  # fmt: skip
    with SimRobot(cfg) as probe:
        tip_x = probe.robot.data.world_tip()[0, 3] * 1e3
    # the wall 1 mm behind the tip at home: 0.5 N/mm pushes the tool back along -x
    cfg["environment"]["contacts"][0]["point_mm"] = [tip_x - 1.0, 0.0, 0.0]
    return cfg


#: every type, 100 Hz; a SENSOR first (exact floats: the first output of a tick is compared)
EVERY_TYPE = [
    {"type": "SENSOR", "device": "Force", "source": "force", "rate_hz": 100},
    {"type": "TRANSFORM", "device": "TipForce", "source": "force", "rate_hz": 100},
    {"type": "POLYDATA", "device": "ForceArrow", "source": "force", "rate_hz": 100},
    {"type": "NDARRAY", "device": "ForceArray", "source": "force", "rate_hz": 100},
    {"type": "TRANSFORM", "device": "Tip", "source": "tip", "rate_hz": 100},
]


OUTPUTS = {o["device"] for o in EVERY_TYPE}


def _meta(f: Vec3, source: str, mm_per_n: str) -> dict[str, str]:
    return {
        "force_n": f"{f[0]:.4f},{f[1]:.4f},{f[2]:.4f}",
        "force_mag_n": f"{math.sqrt(f[0] ** 2 + f[1] ** 2 + f[2] ** 2):.4f}",
        "source": source,
        "frame": "patient",
        "mm_per_n": mm_per_n,
    }


def _check_tick(got: list[Any], f: Vec3, stamp: float, source: str, mm_per_n: float) -> None:
    """One tick's outputs to Slicer against the force ``f`` (N) it should show."""
    got = [m for m in got if m.device_name in OUTPUTS]
    by = {m.device_name: m for m in got}
    assert set(by) == OUTPUTS and len(got) == len(OUTPUTS)
    meta = _meta(f, source, f"{mm_per_n:g}")
    for m in got:
        assert m.header_version == 2
        assert m.timestamp == pytest.approx(stamp, abs=1e-6)  # the tick's (simulated) time
    sensor, array = by["Force"], by["ForceArray"]
    assert sensor.data == pytest.approx(f, abs=1e-12) and str(sensor.unit) == "N"
    assert dict(sensor.metadata) == meta
    assert np.asarray(array.array).tolist() == pytest.approx(list(f), abs=1e-12)
    assert dict(array.metadata) == {**meta, "unit": "N"}
    tip = by["Tip"].matrix[:3, 3]
    tf = by["TipForce"]
    assert dict(tf.metadata) == {**meta, "MRMLNodeName": "LinearTransform"}
    assert np.allclose(tf.matrix[:3, 3], tip, atol=1e-4)
    length = float(np.linalg.norm(f)) * mm_per_n
    z = np.array(f) * mm_per_n if length >= MIN_LENGTH_MM else (0.0, 0.0, MIN_LENGTH_MM)
    assert np.allclose(tf.matrix[:3, 2], z, atol=1e-5)
    arrow = by["ForceArrow"]
    assert dict(arrow.metadata) == {**meta, "MRMLNodeName": "Model"}
    pts = np.asarray(arrow.points, dtype=float)
    if length < MIN_LENGTH_MM:
        assert pts.shape == (0, 3) and len(arrow.polygons) == 0  # no force, no arrow
        return
    assert pts.shape == (38, 3) and len(arrow.polygons) == 48
    apex = pts[int(np.argmax(np.linalg.norm(pts - tip, axis=1)))]
    assert np.allclose(apex, tip + np.array(f) * mm_per_n, atol=1e-4)  # float32 on the wire
    assert np.linalg.norm(apex - tip) == pytest.approx(length, abs=1e-4)


def test_every_type_shows_the_force_of_its_own_tick() -> None:
    """The tissue's force (a force sensor at the instrument, exact) as the slave presses into
    the wall after Enable: each tick's SENSOR, NDARRAY, TRANSFORM and POLYDATA carry the force
    of that very tick, one estimate a tick for the four."""
    cfg = _alone({"sources": ["tissue"], "display_mm_per_n": 2.5}, EVERY_TYPE)
    with SimRobot(cfg) as sim:
        slicer = sim.peer("slicer")
        env = sim.robot.hardware.environment
        ctl: Any = sim.robot.controller.controllers[0]
        sim.peer("operator").send_command("Enable")
        ticks = 0
        for _ in range(200):
            start = len(slicer.received)
            sim.step(1)
            got = slicer.received[start:]
            if any(m.device_name in OUTPUTS for m in got):
                ticks += 1
                _check_tick(got, env.force_n, sim.clock.wall_time(), "tissue", 2.5)
        assert ticks == 20
        assert abs(env.force_n[0]) > 0.4  # pressed: the force is there to show
        assert ctl.stats()["force"]["display"] == {"sent": 80, "own_estimates": 20}


def test_the_efforts_estimate_is_shown_when_it_is_the_source() -> None:
    """The drives' efforts (with their friction and inertia taken out: both need the joints'
    velocities and efforts) give the tissue's force at rest."""
    force = {
        "sources": ["effort"],
        "effort_inertia": [0.05, 0.05, 1.0],
        "effort_damping": [0.1, 0.1, 0.1],
    }
    cfg = _alone(force, EVERY_TYPE)
    with SimRobot(cfg) as sim:
        slicer = sim.peer("slicer")
        env = sim.robot.hardware.environment
        sim.peer("operator").send_command("Enable")
        sim.run_for(0.5)
        start = len(slicer.received)
        sim.step(10)
        got = slicer.received[start:]
        shown: Any = next(m for m in got if m.device_name == "Force")
        assert shown.metadata["source"] == "effort"
        assert np.allclose(shown.data, env.force_n, atol=0.01), (shown.data, env.force_n)
        assert abs(shown.data[0]) > 0.4
        _check_tick(got, shown.data, sim.clock.wall_epoch + 0.5, "effort", 10.0)


def test_a_force_sensor_on_the_tool_is_shown_in_the_patient_frame() -> None:
    """A sensor reading in the tool's axes (``sensor_frame: tip``) turned by the tool's
    orientation; when the sensor falls silent, no force and the source ``none``."""
    force = {"sources": ["sensor"], "sensor_interface": "ft", "sensor_frame": "tip"}
    cfg = _alone(force, EVERY_TYPE)
    with SimRobot(cfg) as sim:
        slicer = sim.peer("slicer")
        ft = sim.peer("ft")
        sim.step(5)
        reading = (0.3, -1.2, 0.8)
        ft.send(igtl.SensorMessage(reading, NEWTON, device_name="ForceSensor"))
        start = len(slicer.received)
        sim.step(6)  # the outputs of tick 10
        got = slicer.received[start:]
        rot = sim.robot.data.world_tip()[:3, :3]
        assert not np.allclose(rot, np.eye(3), atol=0.1)  # the tool is turned
        f = rot @ np.array(reading)
        _check_tick(
            got,
            (float(f[0]), float(f[1]), float(f[2])),
            sim.clock.wall_epoch + 0.010,
            "sensor",
            10.0,
        )
        sim.step(40)  # 20 ms without a reading: not used
        start = len(slicer.received)
        sim.step(10)
        _check_tick(
            slicer.received[start:], (0.0, 0.0, 0.0), sim.clock.wall_epoch + 0.060, "none", 10.0
        )


def test_a_six_axis_sensors_torque_goes_beside_the_force_in_every_type() -> None:
    """A 6-axis reading's torque (N m, turned into the patient frame as the force is) is
    ``torque_nm`` in the metadata of each output of the source ``force``, its three components
    in order, 5 decimals; a 3-axis reading has no such key (old readers see what they saw)."""
    force = {"sources": ["sensor"], "sensor_interface": "ft", "sensor_frame": "tip"}
    devices = ("Force", "TipForce", "ForceArrow", "ForceArray")
    with SimRobot(_alone(force, EVERY_TYPE)) as sim:
        slicer, ft = sim.peer("slicer"), sim.peer("ft")
        sim.step(5)
        torque = (0.004, -0.005, 0.006)
        ft.send(igtl.SensorMessage((0.3, -1.2, 0.8, *torque), NEWTON, device_name="ForceSensor"))
        start = len(slicer.received)
        sim.step(6)
        got = [m for m in slicer.received[start:] if m.device_name in devices]
        t = sim.robot.data.world_tip()[:3, :3] @ np.array(torque)
        assert len(set(t.round(5).tolist())) == 3  # three different numbers to tell apart
        want = f"{t[0]:.5f},{t[1]:.5f},{t[2]:.5f}"
        assert sorted(m.device_name for m in got) == sorted(devices)
        assert all(m.metadata["torque_nm"] == want for m in got), [m.metadata for m in got]
        ft.send(igtl.SensorMessage((0.3, -1.2, 0.8), NEWTON, device_name="ForceSensor"))
        start = len(slicer.received)
        sim.step(10)
        got = [m for m in slicer.received[start:] if m.device_name in devices]
        assert len(got) == 4 and all("torque_nm" not in m.metadata for m in got)


# ------------------------------------------------------------------------------ the source
@pytest.fixture
def view() -> Any:
    """The output source ``force`` of a slave alone, pressed into the wall: (the simulation,
    the source, the force it shows)."""
    cfg = _alone({"sources": ["tissue"]}, EVERY_TYPE)
    with SimRobot(cfg) as sim:
        sim.peer("operator").send_command("Enable")
        sim.run_for(0.3)
        ctl: Any = sim.robot.controller.controllers[0]
        f = sim.robot.hardware.environment.force_n
        assert abs(f[0]) > 0.4
        yield sim, ctl.force_view, f


def _out(type_: str, version: int = 2, device: str = "Force") -> Output:
    return Output(cast(Any, None), type_, device, "force", 1, version)


def test_a_type_that_cannot_carry_the_force_is_refused_with_the_types_that_can(view: Any) -> None:
    _, source, _ = view
    for t in ("POINT", "POSITION", "STATUS"):
        with pytest.raises(OCCError) as err:
            source(_out(t), 0.0)
        assert str(err.value) == (
            f"output source 'force' goes as TRANSFORM, POLYDATA, SENSOR, NDARRAY, not {t}"
        )


@pytest.mark.parametrize("type_", ["TRANSFORM", "POLYDATA"])
@pytest.mark.parametrize("version", [1, 2])
def test_the_message_is_in_the_outputs_header_version_as_a_datagram_sender_packs_it(
    view: Any, type_: str, version: int
) -> None:
    """A UDP or tcp-client interface packs a message in its own header version (no client to
    answer in kind): version 1 carries no metadata (packing it with some is an error), version
    2 all of it; the time stamp is the tick's."""
    sim, source, f = view
    out = _out(type_, version, "Dev")
    value = source(out, sim.now)
    assert not isinstance(value, igtl.Message)  # a typed value: occ/net/packers.py packs it
    back = igtl.unpack(pack_output(value, out).pack())
    assert back.message_type == type_ and back.device_name == "Dev"
    assert back.header_version == version
    assert back.timestamp == pytest.approx(sim.clock.wall_time(), abs=1e-6)
    assert sim.clock.wall_time() > 1e9
    if version == 1:
        assert dict(back.metadata) == {}
    else:
        tag = "LinearTransform" if type_ == "TRANSFORM" else "Model"
        assert dict(back.metadata) == {**_meta(f, "tissue", "10"), "MRMLNodeName": tag}
        # a recording's reader takes the force from the TRANSFORM (the arrow is its picture)
        got = parse_force(back.metadata["force_n"])
        assert message_force(back) == (("patient", got) if type_ == "TRANSFORM" else None)


@pytest.mark.parametrize("type_", ["SENSOR", "NDARRAY"])
@pytest.mark.parametrize("version", [1, 2])
def test_the_readings_go_in_newtons_in_either_version(view: Any, type_: str, version: int) -> None:
    sim, source, f = view
    out = _out(type_, version)
    value = source(out, sim.now)
    assert isinstance(value, VectorOut)
    back: Any = igtl.unpack(pack_output(value, out).pack())
    assert back.header_version == version
    assert back.timestamp == pytest.approx(sim.clock.wall_time(), abs=1e-6)
    values = back.data if type_ == "SENSOR" else tuple(np.asarray(back.array).tolist())
    assert values == f
    if type_ == "SENSOR":
        assert str(back.unit) == "N"
    meta = _meta(f, "tissue", "10")
    if version == 1:
        assert dict(back.metadata) == {}
        assert message_force(back) == ("base", f)  # no frame said: a recording cannot know
    else:
        assert dict(back.metadata) == (meta if type_ == "SENSOR" else {**meta, "unit": "N"})
        assert message_force(back) == ("patient", f)  # what a recording's reader finds


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")  # the norm of 1e200s
@pytest.mark.parametrize(
    "force",
    [(math.nan, 0.0, 0.0), (0.0, math.inf, 0.0), (-math.inf, math.inf, 1.0), (1e200, 1e200, 0.0)],
)
def test_a_force_whose_arrow_has_no_finite_length_is_drawn_as_no_force(force: Vec3) -> None:
    """Not finite, or finite but too large for its length to be (1e200 N on two axes: a force
    sensor's reading in N): the short invertible transform and no arrow, never a NaN that 3D
    Slicer cannot invert or draw (before: a NaN matrix and NaN points)."""
    tip = (1.0, 2.0, 3.0)
    m = force_matrix(tip, force, 10.0)
    assert np.array_equal(m[:3, :3], np.diag([1.0, 1.0, MIN_LENGTH_MM]))
    assert np.array_equal(m[:3, 3], tip) and np.isfinite(np.linalg.inv(m)).all()
    points, polys = arrow_mesh(tip, force, 10.0)
    assert points.shape == (0, 3) and polys == ()
