"""Simulated tissue (occ/haptics/contact.py) and the slave's force sources (occ/haptics/forces.py).

- The force law: a wall and a sphere push the tool out along their normal, k d + b d', never
  pull; shapes add up.
- The load reaches the joints as J^T F: virtual work (tau . dq = F . dx) checked with finite
  differences on the slave's kinematics; the ``sim`` drive yields by tau / kp under it and,
  averaged over 2 ms, reports the effort that holds it.
- The ``effort`` source gives back the contact force from those efforts (static: to 1 mN of 1.5 N;
  moving, with the momentum observer: a few per cent); a bias is removed (``ForceTare`` refuses
  to take one in contact).
- The ``sensor`` source: a SENSOR in N, in the patient, base or tip frame; refused and counted
  when it is no force; silent past its timeout: not used, the next source instead, one ALERT.
- Configuration mistakes are errors at load.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

import igtl
from igtl.messages.sensor import Unit
from occ.config import ContactConfig
from occ.haptics.contact import Contact, Environment
from occ.net.decoders import event_of
from occ.errors import ConfigError
from occ.haptics.forces import SlaveForce
from occ.kinematics.frame import Frame
from occ.core.loader import parse_config
from occ.core.safety import RobotState
from occ_testkit.testing import CONFIGS, SimRobot

pytestmark = pytest.mark.req("SR-FORCE-3")

ROOT = Path(__file__).resolve().parents[2]
SLAVE = Frame.builtin("occ_slave")


def wall(**kw: Any) -> Contact:
    args = {"kind": "wall", "point_mm": (2.0, 0.0, 0.0), "normal": (-2.0, 0.0, 0.0)}
    return Contact.from_config(ContactConfig(**{**args, **kw}))


# ------------------------------------------------------------------ the force law
def test_a_wall_pushes_out_along_its_normal_and_never_pulls() -> None:
    c = wall(stiffness=0.5, damping=0.01)
    assert c.normal == (-1.0, 0.0, 0.0)  # made unit
    f, d = c.force((1.0, 5.0, 7.0), (0.0, 0.0, 0.0))
    assert f == (0.0, 0.0, 0.0) and d == pytest.approx(-1.0)  # outside: nothing
    f, d = c.force((5.0, 5.0, 7.0), (0.0, 0.0, 0.0))
    assert d == pytest.approx(3.0) and f == pytest.approx((-1.5, 0.0, 0.0))
    f, _ = c.force((5.0, 5.0, 7.0), (20.0, 0.0, 0.0))  # going deeper at 20 mm/s: + b d'
    assert f == pytest.approx((-1.7, 0.0, 0.0))
    f, _ = c.force((2.1, 0.0, 0.0), (-200.0, 0.0, 0.0))  # leaving fast: would pull; zero
    assert f == (0.0, 0.0, 0.0)


def test_a_sphere_pushes_out_radially() -> None:
    c = Contact.from_config(
        ContactConfig(kind="sphere", point_mm=(0.0, 0.0, 0.0), radius_mm=10.0, stiffness=2.0)
    )
    f, d = c.force((0.0, 6.0, 8.0), (0.0, 0.0, 0.0))  # 10 mm from the centre: the surface
    assert d == pytest.approx(0.0) and f == (0.0, 0.0, 0.0)
    f, d = c.force((0.0, 3.0, 4.0), (0.0, 0.0, 0.0))  # 5 mm in
    assert d == pytest.approx(5.0) and f == pytest.approx((0.0, 6.0, 8.0))


def test_the_load_reaches_the_joints_as_the_jacobian_transpose() -> None:
    """Virtual work: tau . dq = F . dx for a small joint motion (F in the patient frame, the
    base rotated and moved)."""
    base = np.eye(4)
    c, s = math.cos(0.4), math.sin(0.4)
    base[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    base[:3, 3] = [0.01, -0.02, 0.0]
    q = [0.1, 0.35, 0.05]
    env0 = Environment(
        [wall(point_mm=(1e3, 0.0, 0.0), normal=(0.0, 0.0, 1.0))], SLAVE, lambda: base
    )
    p, _ = env0.tip(q)
    env = Environment(
        [wall(point_mm=(p[0], p[1], p[2] + 2.0), normal=(0.3, -0.2, 1.0), stiffness=0.7)],
        SLAVE,
        lambda: base,
    )
    tau = env.efforts(q, [0.0, 0.0, 0.0])
    assert tau is not None and env.in_contact
    force = np.array(env.force_n)
    dq = np.array([1e-6, -2e-6, 1.5e-6])
    p1, _ = env.tip(list(np.array(q) + dq))
    dx = (np.array(p1) - np.array(p)) * 1e-3  # m
    assert float(np.dot(tau, dq)) == pytest.approx(float(force @ dx), rel=1e-4)


# ------------------------------------------------------------------ the sim drive under load
def pressed_slave(depth_mm: float, **params: Any) -> tuple[SimRobot, Any]:
    """configs/wall.yaml in simulated time, RUNNING, its tool held ``depth_mm`` into the wall:
    the controller takes absolute targets (``mapping: absolute``) and a peer on the master's
    link sends one behind the wall (x = 2 mm, normal -x) for 1.5 s."""
    cfg = yaml.safe_load((CONFIGS / "wall.yaml").read_text())
    cfg["controller"]["params"]["force"].update({"sources": ["effort"], **params})
    cfg["controller"]["params"].update(mapping="absolute", max_jump_mm=20.0, phase_lock_us=None)
    sim = SimRobot(cfg)
    op = sim.peer("operator", address=("127.0.0.1", 41001))
    source = sim.peer("master", address=("127.0.0.1", 40000))
    for c in ("Enable", "Run"):
        assert sim.command(op, c).metadata["Status"] == "SUCCESS"
    tip = sim.robot.data.world_tip()[:3, 3] * 1e3
    target = (2.0 + depth_mm, float(tip[1]), float(tip[2]))
    for seq in range(1, 751):
        source.send_position(target, seq=seq)
        sim.step(2)
    return sim, op


def test_the_drive_yields_under_the_load_and_its_averaged_effort_holds_it() -> None:
    sim, _ = pressed_slave(3.0)
    try:
        drv: Any = sim.robot.hardware.drivers[0]
        env = sim.robot.hardware.environment
        assert env.in_contact and env.depth_mm["wall"] == pytest.approx(3.0, abs=0.3)
        # at rest: the drive's mean effort is the load's opposite
        assert np.array(sim.robot.data.effort) == pytest.approx(
            -np.array(drv.external_effort), abs=1e-9
        )
        # the tool yielded: less deep than commanded (kp finite), by tau / kp per joint
        assert env.depth_mm["wall"] < 3.0
    finally:
        sim.close()


def test_the_effort_source_gives_the_contact_force_back() -> None:
    sim, op = pressed_slave(3.0)
    try:
        ctl: Any = sim.robot.controller.controllers[0]
        env = sim.robot.hardware.environment
        f = ctl.force.estimate(
            sim.now, sim.robot.frame, sim.robot.data.q, sim.robot.data.qdot,
            sim.robot.data.effort, sim.robot.data.base, lambda: sim.robot.data.tip[:3, :3],
        )  # fmt: skip
        # to 1 mN of 1.5 N: the damped inverse's bias (damping 1e-4 m against a Jacobian whose
        # smallest singular value is the yaw's 14 mm lever)
        assert f == pytest.approx(env.force_n, abs=1e-3)
        assert math.hypot(*f) > 1.0
        # the operator's tare is refused in contact (it would hide this force from then on;
        # tests/occ/test_sensor_tare.py): nothing changes
        reply = sim.command(op, "ForceTare")
        assert reply.metadata["Status"] == "FAIL", reply.metadata
        assert "in contact (simulated tissue 'wall'" in reply.metadata["Error"]
        assert ctl.force.bias is None
        # a bias taken all the same is subtracted from then on: the force reads zero here
        ctl.force.tare(sim.robot.data.effort)
        f = ctl.force.estimate(
            sim.now, sim.robot.frame, sim.robot.data.q, sim.robot.data.qdot,
            sim.robot.data.effort, sim.robot.data.base, lambda: sim.robot.data.tip[:3, :3],
        )  # fmt: skip
        assert math.hypot(*f) < 1e-3
    finally:
        sim.close()


# ------------------------------------------------------------------ the sensor source
def sensor(values: tuple[float, ...], unit: Unit | int = 0, device: str = "ForceSensor") -> Any:
    return igtl.SensorMessage(values, unit, device_name=device)


def newtons() -> Unit:
    return Unit(0, ((11, 1),))


def test_the_sensor_source_takes_newtons_in_its_frame() -> None:
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 deg about z
    base = np.eye(4)
    base[:3, :3] = rot
    tip = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # 90 deg about x
    for frame, expect in (
        ("patient", (1.0, 2.0, 3.0)),
        ("base", tuple(rot @ [1.0, 2.0, 3.0])),
        ("tip", tuple(rot @ tip @ [1.0, 2.0, 3.0])),
    ):
        src = SlaveForce(("sensor",), sensor_interface="sensor", sensor_frame=frame)
        assert src.on_input(event_of(sensor((1.0, 2.0, 3.0), newtons()), "sensor"), 0.0)
        f = src.estimate(0.005, SLAVE, [0.0] * 3, [0.0] * 3, [0.0] * 3, base, lambda: tip)
        assert f == pytest.approx(expect), frame
        assert src.used == "sensor"
    # a milli-newton sensor is scaled; six values (force and torque) are taken
    src = SlaveForce(("sensor",), sensor_interface="sensor")
    assert src.on_input(
        event_of(sensor((1000.0, 0.0, 0.0, 1.0, 1.0, 1.0), Unit(11, ((11, 1),))), "sensor"), 0.0
    )
    assert src.estimate(0.0, SLAVE, [0.0] * 3, [0.0] * 3, [0.0] * 3, np.eye(4), lambda: tip) == (
        pytest.approx((1.0, 0.0, 0.0))
    )


@pytest.mark.parametrize(
    ("msg", "error"),
    [
        (sensor((1.0, 2.0, 3.0), Unit(0, ((1, 1),))), "unit 'm' is not a force"),
        (sensor((1.0, 2.0)), "2 values"),
        (sensor((1.0, math.nan, 3.0)), "not a force"),
    ],
)
def test_a_reading_that_is_no_force_is_refused_and_counted(msg: Any, error: str) -> None:
    src = SlaveForce(("sensor",), sensor_interface="sensor")
    assert not src.on_input(event_of(msg, "sensor"), 0.0)
    st = src.stats(0.0)["sensor"]
    assert st["refused"] == 1 and st["samples"] == 0 and error in st["last_error"]


def test_other_devices_and_interfaces_are_not_the_sensor() -> None:
    src = SlaveForce(("sensor",), sensor_interface="sensor")
    assert not src.on_input(event_of(sensor((1.0, 2.0, 3.0), device="Other"), "sensor"), 0.0)
    assert not src.on_input(event_of(sensor((1.0, 2.0, 3.0)), "slicer"), 0.0)
    assert not src.on_input(
        event_of(igtl.StringMessage("x", device_name="ForceSensor"), "sensor"), 0.0
    )
    assert src.stats(0.0)["sensor"]["refused"] == 0


def test_a_silent_sensor_is_not_used_the_next_source_is_and_one_alert_says_so() -> None:
    alerts: list[tuple[str, str, int]] = []
    src = SlaveForce(
        ("sensor", "effort"), sensor_interface="sensor", sensor_timeout_s=0.02,
        alert=lambda *a: alerts.append(a),
    )  # fmt: skip
    q = [0.0, 0.35, 0.05]
    src.on_input(event_of(sensor((0.0, 0.0, 2.0)), "sensor"), 0.0)
    base = np.eye(4)
    assert src.estimate(0.01, SLAVE, q, [0.0] * 3, [0.0] * 3, base, np.eye) == (0.0, 0.0, 2.0)
    for t in (0.05, 0.06, 0.07):
        assert src.estimate(t, SLAVE, q, [0.0] * 3, [0.0] * 3, base, np.eye) == (0.0, 0.0, 0.0)
        assert src.used == "effort"
    assert len(alerts) == 1 and alerts[0][0] == "ALERT" and "silent" in alerts[0][1]
    src.on_input(event_of(sensor((0.0, 0.0, 1.0)), "sensor"), 0.08)  # back: used again, told
    assert src.estimate(0.081, SLAVE, q, [0.0] * 3, [0.0] * 3, base, np.eye) == (0.0, 0.0, 1.0)
    assert alerts[-1][0] == "STREAM" and "back" in alerts[-1][1]


# ------------------------------------------------------------------ configuration
def test_configuration_mistakes_are_errors_at_load() -> None:
    cfg = yaml.safe_load((CONFIGS / "wall.yaml").read_text())
    cfg["controller"]["params"]["force"] = {"sources": ["sensor"]}
    with pytest.raises(ConfigError, match="sensor_interface: required"):
        parse_config(yaml.safe_dump(cfg))
    cfg["controller"]["params"]["force"] = {"sources": ["effort"], "effort_inertia": [0.1]}
    with pytest.raises(ConfigError, match="effort_inertia: needs 3 values"):
        parse_config(yaml.safe_dump(cfg))
    cfg["controller"]["params"]["force"] = {"sources": ["tissue"]}
    del cfg["environment"]
    with pytest.raises(ConfigError, match="tissue needs an environment"):
        parse_config(yaml.safe_dump(cfg))
    cfg = yaml.safe_load((CONFIGS / "wall.yaml").read_text())
    cfg["environment"]["contacts"][0]["normal"] = [0.0, 0.0, 0.0]
    with pytest.raises(ConfigError, match="normal must not be zero"):
        parse_config(yaml.safe_dump(cfg))


def test_the_environment_needs_one_sim_driver_with_every_joint() -> None:
    cfg = yaml.safe_load((CONFIGS / "wall.yaml").read_text())
    drv = cfg["robot"]["drivers"][0]
    cfg["robot"]["drivers"] = [
        {**drv, "name": "a", "joints": ["yaw", "pitch"], "params": {}},
        {**drv, "name": "b", "joints": ["insertion"], "params": {}},
    ]
    with pytest.raises(ConfigError, match="needs one `sim` driver with every joint"):
        SimRobot(cfg)


# ------------------------------------------------------------------ tissue from 3D Slicer
def slicer_points(*points: tuple[tuple[float, float, float], float], **meta: str) -> Any:
    from igtl.messages.point import PointElement

    els = tuple(
        PointElement(name=f"T-{i}", group="Fiducial", rgba=(255, 0, 0, 255), position=c, radius=r)
        for i, (c, r) in enumerate(points)
    )
    return igtl.PointMessage(points=els, device_name="Tumour", header_version=2,
                             metadata={"MRMLNodeName": "Tumour", **meta})  # fmt: skip


def test_tissue_from_slicer_replaces_by_name_and_presses_on_the_drives() -> None:
    """A Markups point list with kind=tissue is spheres in the simulated world; sent again it
    replaces them; a Markups plane (TRANSFORM, kind=tissue) is a wall along its z axis; the
    tool inside a sphere feels it."""
    sim = SimRobot(CONFIGS / "wall.yaml")
    try:
        op = sim.peer("operator", address=("127.0.0.1", 41001))
        env = sim.robot.hardware.environment
        tip = sim.robot.data.world_tip()[:3, 3] * 1e3
        # a sphere whose surface is 2 mm past the tool: 2 mm deep at 0.8 N/mm
        centre = (float(tip[0]), float(tip[1]), float(tip[2]) - 8.0)
        op.send(slicer_points((centre, 10.0), ((50.0, 50.0, 50.0), 0.0), kind="tissue",
                              stiffness="0.8", radius="4"))  # fmt: skip
        sim.step(5)
        assert [c.name for c in env.contacts] == ["wall", "Tumour:0", "Tumour:1"]
        assert env.contacts[2].radius == 4.0  # no radius on the point: the attribute's
        assert env.depth_mm["Tumour:0"] == pytest.approx(2.0, abs=0.05)
        assert math.hypot(*env.force_n) == pytest.approx(1.6, abs=0.1)
        op.send(slicer_points(((0.0, 0.0, 0.0), 1.0), kind="tissue"))  # moved: replaced
        sim.step(1)
        assert [c.name for c in env.contacts] == ["wall", "Tumour:0"]
        m = np.array([[1.0, 0.0, 0.0, 5.0], [0.0, 0.0, -1.0, 6.0], [0.0, 1.0, 0.0, 7.0],
                      [0.0, 0.0, 0.0, 1.0]])  # fmt: skip
        plane = igtl.TransformMessage.from_matrix(
            m, device_name="Floor", header_version=2, metadata={"kind": "tissue"}
        )
        op.send(plane)
        sim.step(1)
        floor = [c for c in env.contacts if c.name == "Floor"][0]
        assert floor.kind == "wall" and floor.point == (5.0, 6.0, 7.0)
        assert floor.normal == pytest.approx((0.0, -1.0, 0.0))
        assert sim.robot.hardware.stats()["environment"]["definitions"] == 3
    finally:
        sim.close()


def test_bad_tissue_and_tissue_without_a_simulated_world_are_refused_with_a_reply() -> None:
    for config, msg, why in (
        ("wall.yaml", slicer_points(((0.0, 0.0, 0.0), 5.0), kind="tissue", stiffness="-1"),
         "stiffness -1.0 must be >= 0"),
        ("wall.yaml", slicer_points(((0.0, 0.0, 0.0), 5.0), kind="tissue", stiffness="soft"),
         "is not a number"),
        ("slave.yaml", slicer_points(((0.0, 0.0, 0.0), 5.0), kind="tissue"),
         "no simulated world"),
    ):  # fmt: skip
        cfg = yaml.safe_load((CONFIGS / config).read_text())
        for itf in cfg["interfaces"]:
            if itf["name"] == "operator":
                itf["inputs"] = [{"type": "POINT", "queue": "command", "depth": 4}]
        sim = SimRobot(cfg)
        try:
            op = sim.peer("operator", address=("127.0.0.1", 41001))
            before = (
                [c.name for c in env.contacts] if (env := sim.robot.hardware.environment) else []
            )
            op.send(msg)
            sim.step(2)
            text = " ".join(str(getattr(m, "status_message", "")) for m in op.messages())
            assert why in text, (config, text)
            after = [c.name for c in env.contacts] if env is not None else []
            assert after == before
        finally:
            sim.close()


# ------------------------------------------------------------------ the law, in every component
def test_an_oblique_wall_with_damping_in_three_dimensions() -> None:
    n = np.array([0.3, -0.4, 0.866])
    n = n / np.linalg.norm(n)
    c = wall(point_mm=(1.0, 2.0, 3.0), normal=tuple(n), stiffness=0.7, damping=0.02)
    p = np.array([1.0, 2.0, 3.0]) - 2.5 * n  # 2.5 mm into the tissue
    v = np.array([10.0, -20.0, 5.0])  # mm/s
    f, d = c.force(tuple(p), tuple(v))
    rate = -float(v @ n)
    assert d == pytest.approx(2.5)
    assert f == pytest.approx(tuple((0.7 * 2.5 + 0.02 * rate) * n))
    # on the surface, going in: no depth, no force (the damper alone never pushes)
    f, d = c.force((1.0, 2.0, 3.0), tuple(-50.0 * n))
    assert d == pytest.approx(0.0, abs=1e-12) and f == (0.0, 0.0, 0.0)


def test_a_sphere_seen_from_an_oblique_point_and_from_its_centre() -> None:
    c = Contact.from_config(
        ContactConfig(kind="sphere", point_mm=(1.0, -2.0, 3.0), radius_mm=10.0, stiffness=1.0)
    )
    r = np.array([2.0, -3.0, 6.0])  # |r| = 7
    d, n = c.depth(tuple(np.array([1.0, -2.0, 3.0]) + r))
    assert d == pytest.approx(3.0) and n == pytest.approx(tuple(r / 7.0))
    d, n = c.depth((1.0, -2.0, 3.0))
    assert d == 10.0 and n == (0.0, 0.0, 1.0)


def test_the_joints_feel_the_damper_through_the_tips_velocity() -> None:
    """Two walls (their forces add, every component), the tip moving with the joints: the
    damping uses the tip's velocity (J qdot, base rotated, mm/s), and the efforts are J^T of
    the sum; the statistics say so."""
    base = np.eye(4)
    c, s = math.cos(0.3), math.sin(0.3)
    base[:3, :3] = [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]
    base[:3, 3] = [0.02, -0.01, 0.03]  # and moved: the tip is base x FK
    q, qd = [0.1, 0.35, 0.05], [0.2, -0.1, 0.03]
    probe = Environment([], SLAVE, lambda: base)
    p, _ = probe.tip(q)
    fk = np.asarray(SLAVE.fk(q))
    assert p == pytest.approx(tuple((base @ fk)[:3, 3] * 1e3))
    n1 = np.array([0.2, 0.3, 0.93])
    n1 = n1 / np.linalg.norm(n1)
    n2 = np.array([-0.5, 0.1, 0.2])
    n2 = n2 / np.linalg.norm(n2)
    walls = [
        wall(name="w1", point_mm=tuple(np.array(p) + 1.5 * n1), normal=tuple(n1), stiffness=0.8,
             damping=0.01),
        wall(name="w2", point_mm=tuple(np.array(p) + 0.5 * n2), normal=tuple(n2), stiffness=0.3,
             damping=0.005),
    ]  # fmt: skip
    env = Environment(walls, SLAVE, lambda: base)
    tau = env.efforts(q, qd)
    assert tau is not None and env.in_contact and env.evaluations == 1
    # the tip's velocity by finite differences (mm/s, patient frame)
    eps = 1e-7
    p2, _ = env.tip(list(np.array(q) + eps * np.array(qd)))
    v = (np.array(p2) - np.array(p)) / eps
    expect = np.zeros(3)
    for n, depth, k, b in ((n1, 1.5, 0.8, 0.01), (n2, 0.5, 0.3, 0.005)):
        expect += (k * depth + b * -float(v @ n)) * n
    assert env.force_n == pytest.approx(tuple(expect), rel=1e-5)
    jac = SLAVE.jacobian(q)[:3]
    assert tau == pytest.approx((jac.T @ (base[:3, :3].T @ expect)).tolist(), rel=1e-5)
    st = env.stats()
    assert st["contacts"] == ["w1", "w2"] and st["in_contact"] and st["definitions"] == 0
    assert st["depth_mm"] == {"w1": pytest.approx(1.5), "w2": pytest.approx(0.5)}
    assert st["peak_force_n"] == pytest.approx(round(float(np.linalg.norm(expect)), 4))
    assert st["force_n"] == [round(v, 4) for v in env.force_n]
    # away from both: no efforts, out of contact; the peak stays
    far = list(q)
    far[2] = 0.0
    env2 = Environment(walls[:1], SLAVE, lambda: base)
    env2.peak_force_n = 7.0
    assert env2.efforts(far, qd) is None or env2.in_contact
    assert env2.peak_force_n >= 7.0


def test_tissue_from_slicer_defaults_visibility_and_refusals() -> None:
    from igtl.messages.point import PointElement
    from occ.haptics.contact import tissue_from_event

    def points(*els: Any, **meta: str) -> Any:
        return igtl.PointMessage(points=els, device_name="T", header_version=2,
                                 metadata={"kind": "tissue", **meta})  # fmt: skip

    def el(pos: tuple[float, float, float], r: float, alpha: int = 255) -> Any:
        return PointElement(name="p", group="G", rgba=(1, 2, 3, alpha), position=pos, radius=r)

    name, shapes = tissue_from_event(
        event_of(
            points(
                el((1.0, 2.0, 3.0), 0.0),
                el((9.0, 9.0, 9.0), 4.0, alpha=0),
                el((4.0, 5.0, 6.0), 0.5),
            )
        )
    )  # the hidden point is skipped; a radius of 0 takes the default (10 mm); 0.5 mm is kept
    assert name == "T" and [s.name for s in shapes] == ["T:0", "T:1"]
    assert [s.radius for s in shapes] == [10.0, 0.5]
    assert [(s.stiffness, s.damping) for s in shapes] == [(0.5, 0.0), (0.5, 0.0)]
    assert shapes[1].point == (4.0, 5.0, 6.0) and shapes[0].kind == "sphere"
    _, (wall_,) = tissue_from_event(event_of(igtl.TransformMessage.from_matrix(
            np.array([[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 3, 4], [0, 0, 0, 1]], dtype=float),
            device_name="W", header_version=2,
            metadata={"kind": "tissue", "stiffness": "2", "damping": "0.1"},
        )))  # fmt: skip
    assert wall_.normal == (0.0, 0.0, 1.0) and wall_.point == (1.0, 2.0, 4.0)
    assert (wall_.stiffness, wall_.damping, wall_.radius) == (2.0, 0.1, 0.0)
    assert tissue_from_event(event_of(igtl.StringMessage("x", device_name="S"))) is None
    for bad, why in (
        (points(el((0.0, 0.0, 0.0), 1.0), damping="-1"), "damping -1.0 must be >= 0"),
        (points(el((0.0, 0.0, 0.0), 0.0), radius="0"), "radius 0.0 must be >= 1e-09"),
        (points(el((0.0, 0.0, 0.0), 1.0), stiffness="nan"), "stiffness nan"),
        (igtl.StringMessage("x", device_name="S", header_version=2, metadata={"kind": "tissue"}),
         "a STRING defines no tissue"),
        (igtl.TransformMessage.from_matrix(
            np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]], dtype=float),
            device_name="Z", header_version=2, metadata={"kind": "tissue"}),
         "z axis is zero"),
    ):  # fmt: skip
        with pytest.raises(ValueError, match=why):
            tissue_from_event(event_of(bad))


def test_the_worlds_counters_before_and_away_from_any_contact() -> None:
    env = Environment([wall(name="w", point_mm=(1e4, 0.0, 0.0))], SLAVE, lambda: np.eye(4))
    assert env.stats() == {"contacts": ["w"], "definitions": 0, "force_n": [0.0, 0.0, 0.0],
                           "in_contact": False, "depth_mm": {}, "peak_force_n": 0.0}  # fmt: skip
    q = [0.0, 0.35, 0.05]
    assert env.efforts(q, [0.1, 0.1, 0.1]) is None and env.efforts(q, [0.0] * 3) is None
    assert env.evaluations == 2 and not env.in_contact and env.force_n == (0.0, 0.0, 0.0)
    env.peak_force_n = 3.0
    env.define("w", [])
    assert env.contacts == [] and env.stats()["definitions"] == 1 and env.peak_force_n == 3.0


def test_a_normal_is_made_unit_in_every_component_and_a_nan_plane_is_refused() -> None:
    from occ.haptics.contact import tissue_from_event

    assert wall(normal=(0.0, 3.0, 4.0)).normal == pytest.approx((0.0, 0.6, 0.8))
    assert wall(normal=(2.0, 0.0, -2.0)).normal == pytest.approx((0.7071068, 0.0, -0.7071068))
    m = np.eye(4)
    m[0, 3] = float("nan")
    with pytest.raises(ValueError, match="not a transform"):
        tissue_from_event(event_of(igtl.TransformMessage.from_matrix(
            m, device_name="N", header_version=2, metadata={"kind": "tissue"})))  # fmt: skip


# ------------------------------------------------------------------ the slave's tissue handler
def test_define_tissue_puts_slicers_tissue_in_the_world_or_refuses_it_saying_why(caplog) -> None:
    """occ/controllers/teleop/instrument.py's ``define_tissue`` alone: a tissue definition is
    put in the simulated world by its name (True, one log line), any other message is not its
    (False, nothing defined), and a robot without a simulated world refuses it naming it."""
    from types import SimpleNamespace

    from occ.controllers.teleop.instrument import define_tissue
    from occ.errors import CommandError

    defined: list[tuple[str, int]] = []
    world = SimpleNamespace(define=lambda name, shapes: defined.append((name, len(shapes))))
    ctx = SimpleNamespace(environment=world)
    tissue = event_of(slicer_points(((0.0, 0.0, 0.0), 5.0), ((9.0, 0.0, 0.0), 2.0), kind="tissue"))
    with caplog.at_level("INFO", logger="occ.controllers.teleop.slave"):
        assert define_tissue(tissue, ctx) is True
    assert defined == [("Tumour", 2)]
    assert [r.getMessage() for r in caplog.records] == [
        "tissue 'Tumour': 2 shape(s) from 3D Slicer"
    ]
    assert define_tissue(event_of(slicer_points(((0.0, 0.0, 0.0), 5.0))), ctx) is False
    assert defined == [("Tumour", 2)]
    for none in (None, SimpleNamespace(environment=None)):
        with pytest.raises(CommandError) as err:
            define_tissue(tissue, none)
        assert str(err.value) == (
            "tissue 'Tumour': this robot has no simulated world (config `environment`)"
        )
    bad = event_of(slicer_points(((0.0, 0.0, 0.0), 5.0), kind="tissue", stiffness="soft"))
    with pytest.raises(CommandError, match="stiffness 'soft' is not a number") as err:
        define_tissue(bad, ctx)
    assert isinstance(err.value.__cause__, ValueError)
