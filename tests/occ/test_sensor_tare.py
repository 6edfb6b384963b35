"""The instrument's force sensor as the German Heart Center used it (issue 37, item 5): its tare
and the weight of what hangs beyond it (occ/haptics/forces.py).

- The tare: the mean of the last ``tare_window_ms`` of readings (the weight removed), older
  readings not counted, subtracted from every later one, force and torque; the drives' bias with
  it. Refused with its reason, nothing changed and the refusal counted, when the tip moves (now,
  or over the window), when the simulated tissue touches it, when the readings vary, when too
  much is left once the weight is removed, when the sensor gave too few readings.
- The weight: ``m g`` and ``c x m g`` rotated into the sensor's frame from the tip's pose, in
  each reporting frame; a tare taken at one pose leaves no phantom force at another.
- Through the slave (configs/wall.yaml with a 6-axis sensor on a UDP interface, simulated time):
  the operator's ``ForceTare`` refused with too few readings, refused while the tool moves and in
  the tissue, taken at rest; after it the tool turns and presses, and the slave sends the
  tissue's force alone.

The simulated sensor here is the test's own: what a sensor on the slave's instrument reads at
the robot's pose (an offset, the weight, the tissue's force), written out independently of
occ/haptics/forces.py.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
import yaml

import igtl
from igtl.messages.sensor import NEWTON
from occ.core.loader import parse_config
from occ.errors import ConfigError
from occ.haptics.forces import SlaveForce, TareRefused, gravity_wrench
from occ.kinematics.frame import Frame
from occ.net.decoders import event_of
from occ_testkit.testing import CONFIGS, SimRobot

SLAVE = Frame.builtin("occ_slave")
G = (0.0, 0.0, -9.81)
OFFSET = (0.31, -0.42, 0.17)
OFFSET_T = (0.004, -0.002, 0.001)


def rot(axis: str, a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return {
        "x": np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]),
        "y": np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]),
        "z": np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]),
    }[axis]


def pose(r: np.ndarray, p: tuple[float, float, float] = (0.0, 0.0, 0.1)) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = p
    return m


def reading(tip: np.ndarray, mass: float, com: np.ndarray, load_tip: Any = (0, 0, 0)) -> Any:
    """What a 6-axis sensor in the tip frame reads: its offset, plus the weight beyond it (the
    force on the tool, gravity, in the sensor's axes, and its moment about the sensor's
    origin), plus a load ``load_tip`` (N, the sensor's axes) at its origin."""
    w = mass * (tip[:3, :3].T @ np.array(G))
    f = np.array(OFFSET) + w + np.asarray(load_tip, dtype=float)
    t = np.array(OFFSET_T) + np.cross(com, w)
    return tuple(f.tolist() + t.tolist())


def msg(values: Any) -> Any:
    return igtl.SensorMessage(tuple(values), NEWTON, device_name="ForceSensor")


class Posed:
    """The robot's pose as SlaveForce is lent it: the tip in the base frame, and the base."""

    def __init__(self, tip: np.ndarray, base: np.ndarray | None = None) -> None:
        self.tip = tip
        self.base = np.eye(4) if base is None else base

    def __call__(self) -> tuple[np.ndarray, np.ndarray]:
        return self.tip, self.base


def feed(src: SlaveForce, posed: Posed, t0: float, t1: float, values: Any) -> float:
    """Readings every 2 ms from ``t0`` to ``t1`` (``values(t)`` or one tuple); the last time."""
    t = t0
    while t <= t1 + 1e-12:
        v = values(t) if callable(values) else values
        assert src.on_input(event_of(msg(v), "s"), t)
        t = round(t + 0.002, 9)
    return t - 0.002


def estimate(src: SlaveForce, now: float, posed: Posed) -> tuple[Any, Any]:
    f = src.estimate(
        now, SLAVE, [0.0] * 3, [0.0] * 3, [0.0] * 3, posed.base, lambda: posed.tip[:3, :3]
    )
    return f, src.torque_nm


# ------------------------------------------------------------------------------ the tare
@pytest.mark.req("SR-FORCE-20")
def test_a_tare_at_rest_takes_the_windows_mean_and_subtracts_it_from_then_on() -> None:
    posed = Posed(pose(np.eye(3)))
    src = SlaveForce(
        ("sensor", "effort"), sensor_interface="s", sensor_frame="tip", pose=posed,
    )  # fmt: skip
    # 200 ms ago the sensor read something else (it was warming up): outside the window
    feed(src, posed, 0.0, 0.098, (5.0, 5.0, 5.0, 1.0, 1.0, 1.0))
    # the last 100 ms: its offset, +-10 mN of noise alternating
    end = feed(
        src, posed, 0.1, 0.2,
        lambda t: tuple(
            v + (0.01 if round(t / 0.002) % 2 else -0.01) for v in (*OFFSET, *OFFSET_T)
        ),
    )  # fmt: skip
    reply = src.tare_all(end, [0.5, -0.25, 2.0], 0.0)
    # 51 readings 0.1..0.2 s: 26 at -10 mN, 25 at +10 mN: a mean 0.2 mN under the offset
    expect = tuple(v - 0.01 / 51 for v in OFFSET)
    assert src.offset_n == pytest.approx(expect, abs=1e-12)
    assert src.offset_nm == pytest.approx(tuple(v - 0.01 / 51 for v in OFFSET_T), abs=1e-12)
    assert src.bias == [0.5, -0.25, 2.0]  # the drives' bias with it
    assert reply == (
        "force tare taken: effort bias [0.5, -0.25, 2]; sensor offset [0.3098, -0.4202, 0.1698] "
        "N [0.00380, -0.00220, 0.00080] N m from 51 readings"
    )
    # a load of (1, -2, 0.5) N read on top of the offset: the load alone, torque too
    src.on_input(
        event_of(msg((OFFSET[0] + 1.0, OFFSET[1] - 2.0, OFFSET[2] + 0.5, *OFFSET_T)), "s"), 0.21
    )
    f, t = estimate(src, 0.21, posed)
    assert f == pytest.approx((1.0 + 0.01 / 51, -2.0 + 0.01 / 51, 0.5 + 0.01 / 51), abs=1e-12)
    assert t == pytest.approx((0.01 / 51,) * 3, abs=1e-12)
    st = src.stats(0.21)
    assert st["tared"] is True
    assert st["tare"] == {
        "taken": 1,
        "refused": 0,
        "last": reply.removeprefix("force tare "),
        "t": end,
        "readings": 51,
        "offset_n": [0.3098, -0.4202, 0.1698],
        "offset_nm": [0.0038, -0.0022, 0.0008],
    }


def refusal(src: SlaveForce, now: float, speed: float = 0.0, contact: str | None = None) -> str:
    before = (src.offset_n, src.offset_nm, src.bias, src.tares, src.tares_refused)
    with pytest.raises(TareRefused) as err:
        src.tare_all(now, [1.0, 2.0, 3.0], speed, contact)
    # nothing changed but the count
    assert (src.offset_n, src.offset_nm, src.bias, src.tares) == before[:4]
    assert src.tares_refused == before[4] + 1
    assert src.stats(now)["tare"]["last"] == str(err.value)
    return str(err.value)


@pytest.mark.req("SR-FORCE-20")
def test_a_tare_is_refused_with_its_reason_when_not_at_rest_or_in_contact() -> None:
    posed = Posed(pose(np.eye(3)))
    src = SlaveForce(("sensor", "effort"), sensor_interface="s", pose=posed)
    # too few readings: a sensor not heard (4), or heard over less than half the window
    feed(src, posed, 0.0, 0.006, OFFSET)
    assert refusal(src, 0.006) == (
        "force tare refused: the sensor 'ForceSensor' gave 4 readings over 6 ms of the last "
        "100 ms (at least 5, over half of it): it must be heard at rest"
    )
    feed(src, posed, 0.008, 0.046, OFFSET)
    assert "gave 24 readings over 46 ms" in refusal(src, 0.046)
    end = feed(src, posed, 0.048, 0.1, OFFSET)
    # the tip moving now (exactly at the limit it is at rest)
    assert refusal(src, end, speed=0.0006) == (
        "force tare refused: the instrument is moving (tip 0.60 mm/s, limit 0.5 mm/s)"
    )
    # touching the simulated tissue
    assert refusal(src, end, contact="simulated tissue 'wall' 0.40 mm deep") == (
        "force tare refused: the instrument is in contact (simulated tissue 'wall' 0.40 mm "
        "deep): a tare now would hide that force"
    )
    # the tip moved within the window: 0.06 mm in 100 ms is over 0.5 mm/s on average
    posed.tip = pose(np.eye(3), (0.0, 0.00006, 0.1))
    end = feed(src, posed, 0.102, 0.11, OFFSET)
    assert refusal(src, end) == (
        "force tare refused: the instrument moved 0.060 mm in the last 100 ms (limit 0.05 mm: "
        "0.5 mm/s)"
    )
    # at rest again for a window, but the force ramps by 0.2 N over it: not an offset
    end = feed(src, posed, 0.112, 0.3, lambda t: (OFFSET[0] + 2.0 * (t - 0.2), *OFFSET[1:]))
    assert refusal(src, end) == (
        "force tare refused: the sensor's reading varied by 0.100 N over the last 100 ms "
        "(limit 0.05 N): not at rest (a contact, a vibration)"
    )
    # steady but 1.2 N: a load, not the sensor's zero
    end = feed(src, posed, 0.302, 0.45, (1.2, 0.0, 0.0))
    assert refusal(src, end) == (
        "force tare refused: 1.200 N left (limit 1 N): a load on the instrument, or a wrong "
        "tool model (mass, centre of mass), not the sensor's zero"
    )
    assert src.stats(end)["tare"]["refused"] == 7
    # the effort source alone: only motion and contact can refuse it
    eff = SlaveForce(("effort",))
    assert "moving" in refusal(eff, 0.0, speed=0.01)
    assert eff.tare_all(0.0, [1.0, 2.0, 3.0], 0.0) == "force tare taken: effort bias [1, 2, 3]"
    assert eff.bias == [1.0, 2.0, 3.0]


def test_every_tare_taken_is_counted_and_one_with_nothing_to_tare_says_so() -> None:
    eff = SlaveForce(("effort",))
    eff.tare_all(0.0, [1.0, 2.0, 3.0], 0.0)
    eff.tare_all(0.001, [2.0, 2.0, 2.0], 0.0)
    assert eff.tares == 2 and eff.tare_last == "taken: effort bias [2, 2, 2]"
    world = SlaveForce(("tissue",), environment=object())  # the tissue's force: no zero to take
    assert world.tare_all(0.0, [], 0.0) == "force tare taken: nothing to tare"
    assert world.tare_last == "taken: nothing to tare" and world.tares == 1


def test_the_statistics_give_the_tools_centre_of_mass_in_mm_and_whether_a_tare_was_taken() -> None:
    src = SlaveForce(("sensor",), tool_mass_kg=0.25, tool_com_m=(0.0123456, -0.0004, 0.05))
    assert src.stats(0.0)["tool"] == {"mass_kg": 0.25, "com_mm": [12.346, -0.4, 50.0]}
    assert not src.stats(0.0)["tared"]
    world = SlaveForce(("tissue",), environment=object())
    world.tare_all(0.0, [], 0.0)
    assert world.bias is None and world.stats(0.0)["tared"]  # one tare, no bias: tared


# ------------------------------------------------------------------------------ the weight
MASS = 0.25  # kg: an instrument with its drive
COM = np.array([0.004, -0.002, 0.06])  # m, the tip frame's axes, from the sensor's origin


@pytest.mark.req("SR-FORCE-21")
@pytest.mark.parametrize("frame", ["tip", "base", "patient"])
def test_the_weight_beyond_the_sensor_is_removed_at_every_pose_in_each_frame(frame: str) -> None:
    """A sensor reporting in ``frame`` reads the weight (force on the tool, m g) and its moment
    about its origin in that frame's axes; with the tool's mass and centre of mass configured
    the slave reads nothing, at poses turned every way, and without them the weight is a force
    on the instrument (what the master's hand would have felt)."""
    base = pose(rot("z", 0.7) @ rot("x", 0.2), (0.1, -0.2, 0.3))
    for r in (np.eye(3), rot("x", 1.1), rot("y", -0.6) @ rot("z", 2.0), rot("x", math.pi)):
        tip = pose(r)
        w = MASS * np.array(G)  # the base frame
        c = r @ COM  # the base frame
        to = {"tip": r.T, "base": np.eye(3), "patient": base[:3, :3]}[frame]
        values = (*(to @ w), *(to @ np.cross(c, w)))
        got = gravity_wrench(MASS, tuple(COM), G, frame, r, base[:3, :3])
        assert np.concatenate(got) == pytest.approx(values, abs=1e-15)
        posed = Posed(tip, base)
        kw: Any = {"sensor_interface": "s", "sensor_frame": frame, "pose": posed}
        src = SlaveForce(("sensor",), tool_mass_kg=MASS, tool_com_m=tuple(COM), **kw)
        assert src.on_input(event_of(msg(values), "s"), 0.0)
        f, t = estimate(src, 0.0, posed)
        assert f == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
        assert t == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
        bare = SlaveForce(("sensor",), **kw)
        assert bare.on_input(event_of(msg(values), "s"), 0.0)
        f, _ = estimate(bare, 0.0, posed)
        assert f == pytest.approx(tuple(base[:3, :3] @ w), abs=1e-12)  # the weight, patient


@pytest.mark.req("SR-FORCE-21")
def test_a_tare_at_one_pose_shows_no_phantom_force_at_another() -> None:
    """Tared at one orientation, the tool turned 70 degrees and then loaded: the weight
    compensated sends the load alone (force and the load's moment); a sensor tared without the
    tool's model shows the weight's change as a force (a phantom of ~1.9 N here)."""
    a, b = pose(rot("y", 0.3)), pose(rot("x", 1.22) @ rot("y", 0.3))
    load = np.array([0.4, -0.3, 1.0])  # N, the sensor's axes, at its origin
    for model, expect_phantom in ((True, False), (False, True)):
        posed = Posed(a)
        kw: Any = {"tool_mass_kg": MASS, "tool_com_m": tuple(COM)} if model else {}
        src = SlaveForce(("sensor",), sensor_interface="s", sensor_frame="tip", pose=posed, **kw)
        end = feed(src, posed, 0.0, 0.1, reading(a, MASS, COM))
        if model:
            src.tare_all(end, [], 0.0)
            assert src.offset_n == pytest.approx(OFFSET, abs=1e-12)
            assert src.offset_nm == pytest.approx(OFFSET_T, abs=1e-12)
        else:  # the weight is part of its zero: 2.5 N would be refused as a load, so the
            # offset is taken as the sensor read it (the mechanism; a config sets no limit)
            src.tare_max_offset_n = 10.0
            src.tare_all(end, [], 0.0)
        posed.tip = b
        src.on_input(event_of(msg(reading(b, MASS, COM, load)), "s"), end + 0.002)
        f, t = estimate(src, end + 0.002, posed)
        want = b[:3, :3] @ load  # the patient frame (base: identity)
        phantom = float(np.linalg.norm(np.array(f) - want))
        if expect_phantom:
            assert phantom > 1.5
        else:
            assert phantom < 1e-12
            assert t == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)  # the load at the origin


@pytest.mark.req("SR-FORCE-21")
def test_the_tool_model_is_checked_at_load() -> None:
    cfg = yaml.safe_load((CONFIGS / "wall.yaml").read_text())
    force = cfg["controller"]["params"]["force"]
    force["tool_mass_kg"] = 0.2
    with pytest.raises(ConfigError, match=r"tool_mass_kg: the weight beyond the sensor .*needs "
                       r"`sensor` in sources"):  # fmt: skip
        parse_config(yaml.safe_dump(cfg))
    cfg["interfaces"].append(SENSOR_IFACE)
    force.update(sources=["sensor"], sensor_interface="sensor", gravity_mps2=[0.0, 0.0, -98.1])
    with pytest.raises(ConfigError, match=r"gravity_mps2: magnitude 98.1 m/s\^2: the Earth's"):
        parse_config(yaml.safe_dump(cfg))
    force["gravity_mps2"] = [0.0, 9.81, 0.0]  # a base on a wall: any direction
    parse_config(yaml.safe_dump(cfg))
    for key, value, error in (
        ("tool_mass_kg", -0.1, "tool_mass_kg: must be >= 0, got -0.1"),
        ("tool_mass_kg", 25.0, "tool_mass_kg: must be <= 20, got 25.0"),
        ("tool_com_mm", [0.0, 1.0], r"tool_com_mm\[2\]: missing required field"),
        ("tare_window_ms", 0.0, "tare_window_ms: must be > 0, got 0.0"),
        ("tare_max_speed_mm_s", -1.0, "tare_max_speed_mm_s: must be > 0, got -1.0"),
        ("tare_max_spread_n", 0.0, "tare_max_spread_n: must be > 0, got 0.0"),
        ("tare_max_offset_n", "x", "tare_max_offset_n: expected a number, got 'x'"),
    ):
        bad = {**force, key: value}
        cfg["controller"]["params"]["force"] = bad
        with pytest.raises(ConfigError, match=error):
            parse_config(yaml.safe_dump(cfg))


SENSOR_IFACE = {
    "name": "sensor", "transport": "udp", "host": "127.0.0.1", "port": 18949,
    "inputs": [{"type": "SENSOR", "queue": "stream", "depth": 10}],
}  # fmt: skip


# ------------------------------------------------------------------------------ through the slave
class Bench:
    """configs/wall.yaml with a 6-axis sensor between the slave's last joint and its instrument
    (the tip frame's axes, its origin at the tip), the tool's model configured, the sensor's
    source first, following absolute targets (``mapping: absolute``) from a peer on the master's
    link; the sensor is the test's: each 2 ms it reads the offset, the weight at the robot's
    pose and the tissue's force (:func:`reading`)."""

    def __init__(self) -> None:
        cfg = yaml.safe_load((CONFIGS / "wall.yaml").read_text())
        cfg["interfaces"].append(SENSOR_IFACE)
        p = cfg["controller"]["params"]
        p["force"].update(
            sources=["sensor", "tissue"], sensor_interface="sensor", sensor_frame="tip",
            tool_mass_kg=MASS, tool_com_mm=[v * 1e3 for v in COM], sensor_timeout_ms=50.0,
        )  # fmt: skip
        p.update(mapping="absolute", max_jump_mm=20.0, phase_lock_us=None)
        self.sim = SimRobot(cfg)
        self.op = self.sim.peer("operator", address=("127.0.0.1", 41001))
        self.master = self.sim.peer("master", address=("127.0.0.1", 40000))
        self.sensor = self.sim.peer("sensor", address=("127.0.0.1", 40100))
        self.ctl: Any = self.sim.robot.controller.controllers[0]
        self.env = self.sim.robot.hardware.environment
        self.seq = 0
        self.target: tuple[float, ...] | None = None

    def read(self) -> tuple[float, ...]:
        data = self.sim.robot.data
        r = data.tip[:3, :3]  # the base is the patient frame here (base_mm 0)
        return reading(data.tip, MASS, COM, r.T @ np.array(self.env.force_n))

    def run_ms(self, ms: int, *, sensor: bool = True) -> None:
        for _ in range(ms // 2):
            if self.target is not None:
                self.seq += 1
                self.master.send_position(self.target, seq=self.seq)
            if sensor:
                self.sensor.send(igtl.SensorMessage(self.read(), NEWTON, device_name="ForceSensor"))
            self.sim.step(2)

    def tare(self) -> Any:
        return self.sim.command(self.op, "ForceTare")

    def sent(self) -> tuple[Any, Any]:
        """The force and torque the slave sends its master now (patient frame)."""
        f = self.ctl.force
        data = self.sim.robot.data
        out = f.estimate(
            self.sim.now, self.sim.robot.frame, data.q, data.qdot, data.effort, data.base,
            lambda: data.tip[:3, :3],
        )  # fmt: skip
        return out, f.torque_nm


@pytest.mark.req("SR-FORCE-20", "SR-FORCE-21")
def test_the_operators_tare_through_the_slave_refused_in_motion_and_contact() -> None:
    b = Bench()
    try:
        for c in ("Enable", "Run"):
            assert b.sim.command(b.op, c).metadata["Status"] == "SUCCESS"
        home = b.sim.robot.data.world_tip()[:3, 3] * 1e3
        b.target = tuple(float(v) for v in home)
        b.run_ms(30)
        reply = b.tare()  # 15 readings over 28 ms
        assert reply.metadata["Status"] == "FAIL"
        assert "gave 15 readings over 28 ms of the last 100 ms" in reply.metadata["Error"]
        b.run_ms(120)
        reply = b.tare()
        assert reply.metadata["Status"] == "SUCCESS", reply.metadata
        assert (
            "sensor offset [0.3100, -0.4200, 0.1700] N [0.00400, -0.00200, 0.00100] N m"
            in (reply.command)
            and "the tool's weight (0.25 kg) removed" in reply.command
        )
        assert b.ctl.force.offset_n == pytest.approx(OFFSET, abs=1e-9)
        f, t = b.sent()
        assert b.ctl.force.used == "sensor"
        assert f == pytest.approx((0, 0, 0), abs=1e-9) and t == pytest.approx((0, 0, 0), abs=1e-9)
        # 18 mm sideways and 5 down: yaw and pitch turn the instrument; refused while it moves
        r0 = b.sim.robot.data.tip[:3, :3].copy()
        b.target = (float(home[0]) - 2.0, float(home[1]) + 18.0, float(home[2]) - 5.0)
        b.run_ms(20)
        reply = b.tare()
        assert reply.metadata["Status"] == "FAIL"
        assert "force tare refused: the instrument is moving (tip " in reply.metadata["Error"]
        b.run_ms(1500)
        r1 = b.sim.robot.data.tip[:3, :3]
        turned = math.degrees(math.acos((np.trace(r0.T @ r1) - 1.0) / 2.0))
        phantom = MASS * float(np.linalg.norm((r1.T - r0.T) @ np.array(G)))
        assert turned > 10.0 and phantom > 0.4, (turned, phantom)  # a tare without the model
        f, t = b.sent()
        assert f == pytest.approx((0, 0, 0), abs=1e-6) and t == pytest.approx((0, 0, 0), abs=1e-6)
        # into the wall (x > 2 mm): refused in contact; the tissue's force sent, nothing else
        b.target = (3.0, float(home[1]) + 18.0, float(home[2]) - 5.0)
        b.run_ms(1500)
        assert b.env.in_contact
        reply = b.tare()
        assert reply.metadata["Status"] == "FAIL"
        assert (
            "force tare refused: the instrument is in contact (simulated tissue 'wall' "
            in (reply.metadata["Error"])
        )
        f, _ = b.sent()
        assert math.hypot(*b.env.force_n) > 0.3
        assert f == pytest.approx(b.env.force_n, abs=2e-3)
        st = b.ctl.stats()["force"]
        assert st["tare"]["taken"] == 1 and st["tare"]["refused"] == 3
        assert st["tool"] == {"mass_kg": MASS, "com_mm": [4.0, -2.0, 60.0]}
    finally:
        b.sim.close()


# ------------------------------------------------------------------ the slave's instrument
def test_the_slaves_force_is_built_from_every_force_parameter() -> None:
    """occ/controllers/teleop/instrument.py's ``build_force``: each ``force`` parameter reaches
    the force source in its unit (ms and mm/s to s and m/s, mm to m), none left at its default;
    the pose it removes the weight at is the robot's tip and base now."""
    from types import SimpleNamespace

    from occ.controllers.teleop.instrument import build_force

    fp = SimpleNamespace(
        sources=("sensor", "effort"), sensor_interface="ft", sensor_device="Nano17",
        sensor_frame="tool", sensor_timeout_ms=35.0, damping=3e-4,
        effort_damping=(0.1, 0.2), effort_inertia=(0.3, 0.4), tool_mass_kg=0.25,
        tool_com_mm=(1.0, -2.0, 30.0), gravity_mps2=(0.0, -9.8, 0.0), tare_window_ms=250.0,
        tare_max_speed_mm_s=0.8, tare_max_spread_n=0.07, tare_max_offset_n=2.5,
    )  # fmt: skip
    data = SimpleNamespace(tip=np.eye(4), base=np.eye(4) * 2.0)
    alerts: list[Any] = []
    ctx = SimpleNamespace(environment="world", alert=lambda *a: alerts.append(a))
    src = build_force(fp, data, ctx)
    assert src.sources == ("sensor", "effort") and src.sensor_interface == "ft"
    assert src.sensor_device == "Nano17" and src.sensor_frame == "tool"
    assert src.sensor_timeout_s == pytest.approx(0.035) and src.damping == 3e-4
    assert src.effort_damping == (0.1, 0.2) and src.effort_inertia == (0.3, 0.4)
    assert src.environment == "world" and src.tool_mass_kg == 0.25
    assert src.tool_com_m == pytest.approx((0.001, -0.002, 0.03))
    assert src.gravity == (0.0, -9.8, 0.0) and src.tare_window_s == pytest.approx(0.25)
    assert src.tare_max_speed == pytest.approx(0.8e-3) and src.tare_max_spread_n == 0.07
    assert src.tare_max_offset_n == 2.5
    assert src._pose is not None
    tip, base = src._pose()
    assert tip is data.tip and base is data.base
    assert src.alert is not None
    src.alert("ALERT", "x", 1)
    assert alerts == [("ALERT", "x", 1)]


@pytest.mark.req("SR-FORCE-20")
def test_force_tare_is_judged_on_the_tips_linear_speed_the_efforts_and_the_deepest_tissue() -> None:
    """occ/controllers/teleop/instrument.py's ``tare``: the force source is given the drives'
    efforts, the tip's linear speed (m/s: the Jacobian's first three rows, not its angular
    ones), and the deepest simulated tissue by name and depth; its refusal is a CommandError
    caused by it."""
    from types import SimpleNamespace

    from occ.controllers.teleop.instrument import tare
    from occ.errors import CommandError

    asked: list[Any] = []

    class Source:
        def tare_all(self, now: float, effort: Any, speed: float, contact: Any) -> str:
            asked.append((now, effort, speed, contact))
            if contact is not None:
                raise TareRefused(f"in contact: {contact}")
            return "taken"

    # the tip's linear velocity (3, 4, 0) mm/s; the angular rows turn fast (10 rad/s): no speed
    jac = np.array([[3e-3, 0.0], [0.0, 4e-3], [0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [0.0, 0.0]])
    frame = SimpleNamespace(jacobian=lambda q: jac)
    data = SimpleNamespace(q=[0.0, 0.0], qdot=[1.0, 1.0], effort=[0.5, -0.25])
    ctx = SimpleNamespace(frame=frame, environment=None)
    assert tare(Source(), data, ctx, 2.0) == "taken"
    assert asked == [(2.0, [0.5, -0.25], pytest.approx(5e-3, abs=1e-15), None)]
    env = SimpleNamespace(in_contact=True, depth_mm={"zeta": 0.5, "alpha": 1.25, "mid": 0.75})
    ctx = SimpleNamespace(frame=frame, environment=env)
    with pytest.raises(CommandError) as err:
        tare(Source(), data, ctx, 3.0)
    assert str(err.value) == "in contact: simulated tissue 'alpha' 1.25 mm deep"
    assert isinstance(err.value.__cause__, TareRefused)
    env.in_contact = False  # tissue defined, none touching: no contact said
    assert tare(Source(), data, ctx, 4.0) == "taken" and asked[-1][3] is None
