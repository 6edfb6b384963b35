"""The slave's contact force made visible to 3D Slicer (issue 27, "Visible"; occ/haptics/forceviz.py).

The geometry (the TRANSFORM whose z axis is the force, the arrow mesh) is checked as numbers;
the output source ``force`` on the shipped wall pair (configs/master.yaml + configs/wall.yaml,
:class:`occ_testkit.testing.SimPair`) through the daemons' own code in simulated time: what 3D
Slicer's port receives against what the slave sent its master on the return channel and against the
simulated tissue's force.
"""

from __future__ import annotations

import math
from collections import Counter
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import yaml

import igtl
from occ.errors import ConfigError
from occ.haptics.forceviz import MIN_LENGTH_MM, arrow_mesh, force_matrix, parse_force
from occ.core.loader import parse_config
from occ_testkit.testing import CONFIGS, SimPair, SimRobot

MM_PER_N = 10.0


def wall() -> dict[str, Any]:
    return dict(yaml.safe_load((CONFIGS / "wall.yaml").read_text()))


# ------------------------------------------------------------------------------ geometry
@pytest.mark.parametrize(
    "force", [(1.0, 0.0, 0.0), (-0.3, 2.0, 0.5), (0.0, 0.0, -4.0), (1e-3, -1e-3, 0.0)]
)
def test_the_transform_puts_the_force_on_z_at_the_tip(force: tuple[float, float, float]) -> None:
    tip = (12.5, -3.0, 40.0)
    m = force_matrix(tip, force, MM_PER_N)
    f = np.array(force)
    assert np.allclose(m[:3, 3], tip) and np.allclose(m[3], (0, 0, 0, 1))
    assert np.allclose(m[:3, 2], f * MM_PER_N)  # z: the force, mm per N
    x, y = m[:3, 0], m[:3, 1]
    assert np.isclose(np.linalg.norm(x), 1.0) and np.isclose(np.linalg.norm(y), 1.0)
    assert abs(x @ y) < 1e-12 and abs(x @ f) < 1e-12 and abs(y @ f) < 1e-12
    # right-handed: a model under it is not mirrored
    assert np.linalg.det(m[:3, :3]) == pytest.approx(np.linalg.norm(f) * MM_PER_N)


def test_no_force_is_a_short_invertible_transform() -> None:
    m = force_matrix((1.0, 2.0, 3.0), (0.0, 0.0, 0.0), MM_PER_N)
    assert np.allclose(m[:3, :3], np.diag([1.0, 1.0, MIN_LENGTH_MM]))
    assert np.isfinite(np.linalg.inv(m)).all()


def _edges(polys: tuple[tuple[int, ...], ...]) -> Counter[tuple[int, int]]:
    return Counter((p[i], p[(i + 1) % len(p)]) for p in polys for i in range(len(p)))


def _signed_volume(points: np.ndarray, polys: tuple[tuple[int, ...], ...]) -> float:
    vol = 0.0
    for p in polys:
        a = points[p[0]]
        for i in range(1, len(p) - 1):
            vol += float(np.dot(a, np.cross(points[p[i]], points[p[i + 1]]))) / 6.0
    return vol


@pytest.mark.parametrize("force", [(2.0, 0.0, 0.0), (0.3, -0.4, 1.2), (0.0, 0.0, -0.05)])
def test_the_arrow_is_a_closed_outward_mesh_from_the_tip(
    force: tuple[float, float, float],
) -> None:
    tip = np.array([5.0, -7.0, 30.0])
    points, polys = arrow_mesh(tuple(tip), force, MM_PER_N)
    f = np.array(force)
    length = float(np.linalg.norm(f)) * MM_PER_N
    d = f / np.linalg.norm(f)
    # closed and consistently oriented: every directed edge once, its reverse once
    edges = _edges(polys)
    assert all(n == 1 for n in edges.values())
    assert all(edges[(b, a)] == 1 for a, b in edges)
    # faces outward: positive volume, about a shaft plus a cone
    along = (points - tip) @ d
    assert along.min() == pytest.approx(0.0, abs=1e-9)
    assert along.max() == pytest.approx(length)
    apex = points[int(np.argmax(along))]
    assert np.allclose(apex, tip + f * MM_PER_N)
    radial = np.linalg.norm((points - tip) - np.outer(along, d), axis=1)
    r_shaft, r_head = sorted(set(np.round(radial[radial > 1e-9], 9)))
    head = length - float(np.round(along[np.isclose(radial, r_head)][0], 9))
    neck = length - head
    sides = 12
    # the prisms and cones inscribed in the circles: n/2 sin(2 pi/n) r^2 is a polygon's area
    area = sides / 2 * math.sin(2 * math.pi / sides)
    expected = area * (r_shaft**2 * neck + r_head**2 * head / 3.0)
    assert _signed_volume(points - tip, polys) == pytest.approx(expected, rel=1e-6)


def test_no_force_is_no_arrow() -> None:
    points, polys = arrow_mesh((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), MM_PER_N)
    assert points.shape == (0, 3) and polys == ()
    points, polys = arrow_mesh((0.0, 0.0, 0.0), (math.nan, 0.0, 0.0), MM_PER_N)
    assert points.shape == (0, 3) and polys == ()


def test_parse_force() -> None:
    assert parse_force("1,-2.5,3e-2") == (1.0, -2.5, 0.03)
    for bad in (None, "", "1,2", "1,2,3,4", "1,x,3", "nan,0,0", "inf,0,0"):
        assert parse_force(bad) is None


# ------------------------------------------------------------------------------ config
def test_a_force_output_needs_a_force_and_a_type_that_carries_it() -> None:
    cfg = wall()
    cfg["interfaces"][0]["outputs"].append(
        {"type": "POINT", "device": "F", "source": "force", "rate_hz": 10}
    )
    with pytest.raises(ConfigError, match="source 'force' goes as TRANSFORM, POLYDATA"):
        parse_config(yaml.safe_dump(cfg))
    cfg = yaml.safe_load((CONFIGS / "slave.yaml").read_text())
    cfg["interfaces"][0]["outputs"].append(
        {"type": "TRANSFORM", "device": "TipForce", "source": "force", "rate_hz": 10}
    )
    with pytest.raises(ConfigError, match="source 'force' needs the controller's force"):
        parse_config(yaml.safe_dump(cfg))


# ------------------------------------------------------------------------------ the pair
@pytest.fixture(scope="module")
def pair_run() -> dict[str, Any]:
    """8 s of the wall pair; per slave tick: the tissue's force, the force sent on the
    return channel; what Slicer's port got."""
    returned: list[Any] = []

    def keep(direction: str, msg: Any, index: int) -> bool:
        if direction == "return":
            returned.append(msg)
        return False  # nothing lost

    with SimPair(CONFIGS / "master.yaml", wall(), drop=keep) as p:
        slicer = p.slave.peer("slicer")
        p.start()
        env = p.slave.robot.hardware.environment
        ctl: Any = p.slave.robot.controller.controllers[0]
        own = ctl.stats()["force"]["display"]["own_estimates"]
        truth = []
        start = len(slicer.received)
        for _ in range(8000):
            p.step(1)
            truth.append(env.force_n)
        got = slicer.received[start:]
        return {
            "own_estimates": ctl.stats()["force"]["display"]["own_estimates"] - own,
            "got": got,
            "returned": [m for m in returned if m.device_name == "SlaveTip"],
            "truth": np.array(truth),
            "stats": ctl.stats()["force"],
            "states": (p.master.robot.state.value, p.slave.robot.state.value),
        }


def test_slicer_gets_the_arrow_and_the_transform_at_10_hz(pair_run: dict[str, Any]) -> None:
    assert pair_run["states"] == ("RUNNING", "RUNNING")
    got = pair_run["got"]
    tf = [m for m in got if m.message_type == "TRANSFORM" and m.device_name == "TipForce"]
    arrows = [m for m in got if m.message_type == "POLYDATA" and m.device_name == "ForceArrow"]
    tips = [m for m in got if m.message_type == "TRANSFORM" and m.device_name == "Tip"]
    assert len(tf) == len(arrows) == len(tips) == 80  # 10 Hz for 8 s
    assert pair_run["own_estimates"] == 0  # the return channel's estimates, every time
    forces = np.array([parse_force(m.metadata["force_n"]) for m in tf])
    mags = np.linalg.norm(forces, axis=1)
    assert mags.max() > 1.0  # the paper's motion presses into the wall
    for m, arrow, tip, f in zip(tf, arrows, tips, forces, strict=True):
        assert m.header_version == 2 and m.metadata["frame"] == "patient"
        assert m.metadata["source"] == "tissue" and m.metadata["MRMLNodeName"] == "LinearTransform"
        assert float(m.metadata["force_mag_n"]) == pytest.approx(np.linalg.norm(f), abs=2e-4)
        assert arrow.metadata["force_n"] == m.metadata["force_n"]
        assert arrow.metadata["MRMLNodeName"] == "Model"
        # at the Tip Slicer is sent in the same tick, z the force at 10 mm per N
        assert np.allclose(m.matrix[:3, 3], tip.matrix[:3, 3], atol=1e-4)
        length = np.linalg.norm(f) * MM_PER_N
        if length >= MIN_LENGTH_MM:
            assert np.allclose(m.matrix[:3, 2], f * MM_PER_N, atol=2e-3)
            pts = np.asarray(arrow.points, dtype=float)
            along = (pts - tip.matrix[:3, 3]) @ (f / np.linalg.norm(f))
            assert along.max() == pytest.approx(length, abs=2e-3)
            assert len(arrow.polygons) == 48
        else:
            assert len(arrow.points) == 0


def test_the_force_shown_is_the_force_sent_to_the_master(pair_run: dict[str, Any]) -> None:
    """Each TipForce carries the force of the last SlaveTip sent before it (500 Hz: at most
    2 ms older; in a tick with both, Slicer's interface sends first), and it follows the
    tissue's force (the effort estimate's error aside)."""
    returned = pair_run["returned"]
    stamps = np.array([m.timestamp for m in returned])
    tf = [m for m in pair_run["got"] if m.device_name == "TipForce"]
    for m in tf:
        i = int(np.searchsorted(stamps, m.timestamp, side="left")) - 1
        assert i >= 0 and 0.0 < m.timestamp - stamps[i] <= 0.002 + 1e-6
        assert m.metadata["force_n"] == returned[i].metadata["force_n"]
    shown = np.array([parse_force(m.metadata["force_n"]) for m in tf])
    truth = pair_run["truth"][99::100]  # the tissue at each output's tick
    peak = float(np.linalg.norm(pair_run["truth"], axis=1).max())
    err = np.linalg.norm(shown - truth, axis=1)
    assert float(np.sqrt((err**2).mean())) < 0.1 * peak, (err.max(), peak)


def test_without_a_master_the_source_estimates_itself() -> None:
    """A slave alone (no return channel) pressed into the tissue at rest: Slicer still gets
    the force, estimated by the source itself (``tissue``: the simulated sensor)."""
    cfg = wall()
    cfg["controller"]["params"]["force"] = {"sources": ["tissue"]}
    master = next(i for i in cfg["interfaces"] if i["name"] == "master")
    del master["outputs"]  # no return channel: nobody else estimates the force
    with SimRobot(cfg) as probe:
        tip_x = probe.robot.data.world_tip()[0, 3] * 1e3
    # the wall 1 mm behind the tip at home: 0.5 N/mm pushes the tool back along -x
    cfg["environment"]["contacts"][0]["point_mm"] = [tip_x - 1.0, 0.0, 0.0]
    with SimRobot(cfg) as sim:
        slicer = sim.peer("slicer")
        op = sim.peer("operator")
        op.send_command("Enable")
        sim.run_for(1.0)
        tf = slicer.messages("TRANSFORM", "TipForce")
        assert len(tf) >= 10
        f = parse_force(tf[-1].metadata["force_n"])
        assert f is not None and f[0] < -0.3 and abs(f[1]) < 0.05 and abs(f[2]) < 0.05
        assert tf[-1].metadata["source"] == "tissue"
        ctl: Any = sim.robot.controller.controllers[0]
        display = ctl.stats()["force"]["display"]
        assert display["own_estimates"] == display["sent"] / 2  # once a tick for two outputs
        arrow = slicer.messages("POLYDATA", "ForceArrow")[-1]
        assert len(arrow.points) == 38


# ------------------------------------------------------------------ the master's display alone
class _Fixtures:
    """A stand-in for the master's fixtures: a raw force set by the test, the displayed one
    kept; the slave's map a rotation by 90 degrees about z with kp = 0.1."""

    def __init__(self) -> None:
        self.raw_force_n = (0.0, 0.0, 0.0)
        self.force_n = (0.0, 0.0, 0.0)
        self.steps: list[Any] = []
        self.mapping = SimpleNamespace(force=lambda f: (-f[1], f[0], f[2]), factor=0.1)

    def displayed(self, f: Any) -> None:
        self.force_n = tuple(f)

    def step(self, tip: Any, t: Any) -> None:
        self.steps.append((tip, t))


def _display(nq: int = 3, **params: Any) -> Any:
    """occ/controllers/teleop/display.py's HapticDisplay on stand-ins: an ``nq``-joint master
    whose Jacobian the test sets (identity blocks to start with; its handle at q + 5), the
    fixtures above, alerts kept."""
    from occ.controllers.teleop.display import HapticDisplay
    from occ.core.safety import RobotState

    p = dict(
        force_output=True, tip_fade_ms=20.0, force_feedback=True, force_scale=1.0,
        max_force_n=10.0, passivity=False, passivity_max_damping=200.0, feedback_fade_ms=300.0,
        external_force_device="ServoCF", external_force_timeout_ms=100.0, max_torque_nm=0.5,
        passivity_max_rot_damping=2.0,
    )  # fmt: skip
    p.update(params)
    alerts: list[Any] = []
    d = HapticDisplay(SimpleNamespace(**p), _Fixtures(), lambda *a: alerts.append(a))
    jac = np.zeros((6, nq))
    jac[:3, :3] = np.eye(3)
    if nq >= 6:
        jac[3:, 3:6] = np.eye(3)
    frame = SimpleNamespace(
        nq=nq, jacobian=lambda q: jac, tip_position=lambda q: np.asarray(q[:3], dtype=float) + 5.0
    )
    data = SimpleNamespace(
        joint_names=[f"j{i}" for i in range(nq)], q=[0.0] * nq, qdot=[0.0] * nq,
        state=RobotState.RUNNING,
    )  # fmt: skip
    ctx = SimpleNamespace(frame=frame, clock=SimpleNamespace(wall_time=lambda: 99.0))
    d.bind(data, ctx)
    return d, data, jac, alerts


def _link(**kw: Any) -> Any:
    link = dict(
        status="fresh", new=True, tip=(1.0, 2.0, 3.0), t_tip=0.0, following=True, force=None,
        energy=None, torque=None, slave_state="RUNNING", interface="slave",
    )  # fmt: skip
    link.update(kw)
    return SimpleNamespace(**link)


@pytest.mark.req("SR-FORCE-2")
def test_the_display_counts_the_external_force_and_reports_every_stat_to_its_places() -> None:
    from igtl.messages.sensor import NEWTON
    from occ.net.decoders import event_of

    d, data, jac, _ = _display()

    def servo_cf(device: str) -> Any:
        m = igtl.SensorMessage((0.123456, -0.5, 1.5), NEWTON, device_name=device, header_version=2)
        return event_of(m)

    assert d.external(servo_cf("Other"), 0.0) is False and d.external_samples == 0
    assert d.external(servo_cf("ServoCF"), 1.0) is True
    assert d.external(servo_cf("ServoCF"), 1.001) is True
    assert d.external_samples == 2 and d.external_n == (0.123456, -0.5, 1.5)
    # shown with the slave's force, each axis added
    d.tick(1.001, _link(force=(0.5, -1.0, 2.0)), False)  # the gains at 0 on the first tick
    d.tick(1.021, _link(force=(0.5, -1.0, 2.0)), False)  # 20 ms: the slave's force whole
    assert d.displayed_n == pytest.approx((1.0 + 0.123456, 0.5 - 0.5, 2.0 + 1.5))
    d.displayed_n = (1.234567, -2.345678, 0.1)
    d.fixtures.force_n = (0.123456, 0.0, -0.654321)
    d.feedback_n = (1.111111, 2.222222, -3.333333)
    d.feedback_torque_nm = (0.0123456, -0.0654321, 0.1)
    d.displayed_torque_nm = (0.0011111, 0.0022222, -0.0033333)
    d.clamped_ticks = 3
    d.feedback_gain = 0.123456
    d.gain = 0.654321
    assert d.stats(1.05) == {
        "force_n": [1.2346, -2.3457, 0.1],
        "fixture_force_n": [0.1235, 0.0, -0.6543],
        "feedback_n": [1.1111, 2.2222, -3.3333],
        "force_feedback": True,
        "force_scale": 1.0,
        "feedback_torque_nm": [0.01235, -0.06543, 0.1],
        "torque": {
            "displayed": False,
            "torque_nm": [0.00111, 0.00222, -0.00333],
            "passivity": d.torque_passivity.stats(),
        },
        "external_n": [0.1235, -0.5, 1.5],
        "external_samples": 2,
        "external_fresh": True,
        "force_clamped_ticks": 3,
        "passivity": {"on": False, **d.passivity.stats()},
        "feedback_gain": 0.1235,
        "fixture_gain": 0.6543,
        "force_output": True,
    }
    assert d.stats(1.1005)["external_fresh"] is True  # 99.5 ms after the last: fresh
    assert d.stats(1.1015)["external_fresh"] is False


def test_the_handles_position_and_velocity_on_a_master_that_is_not_cartesian() -> None:
    d, data, jac, _ = _display()
    assert d._jt is None  # bound at q = 0: no constant Jacobian taken
    data.q, data.qdot = [0.1, 0.2, 0.3], [1.0, -2.0, 3.0]
    jac[:3, :3] = [[1.0, 0.5, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, -1.0]]
    assert d.handle_velocity() == (0.0, -4.0, -3.0)
    assert d.handle_position() == pytest.approx((5.1, 5.2, 5.3))


@pytest.mark.req("SR-FIX-2", "SR-FORCE-5")
def test_the_fixtures_gain_and_the_feedbacks_rise_and_fall_with_the_link() -> None:
    """The fixtures' share rises to 1 within tip_fade_ms (20 ms) while the slave follows with a
    fresh link and falls as fast otherwise, 0 at once when the tip is lost or missing; the
    slave's force rises as fast but falls within feedback_fade_ms (300 ms), and only a missing
    tip drops it at once. The force on the hand is J^T of the sum, the slave's turned by the
    map (90 degrees about z here)."""
    d, data, jac, _ = _display()
    d.fixtures.raw_force_n = (0.0, 0.0, 2.0)
    link = _link(force=(1.0, 0.0, 0.0))
    gains = []
    for t in (0.0, 0.005, 0.01, 0.02, 0.03):
        eff = d.tick(t, link, False)
        gains += [d.gain, d.feedback_gain]
    assert gains == pytest.approx([0, 0, 0.25, 0.25, 0.5, 0.5, 1, 1, 1, 1])
    assert d.fixtures.force_n == (0.0, 0.0, 2.0) and d.feedback_n == (0.0, 1.0, 0.0)
    assert eff == pytest.approx([0.0, 1.0, 2.0]) and d.displayed_n == pytest.approx((0, 1, 2))
    assert len(d.fixtures.steps) == 1 and link.new is False  # one tip, one step
    d.tick(0.035, link, True)  # the clutch: both fall, each at its own rate
    assert (d.gain, d.feedback_gain) == pytest.approx((0.75, 1.0 - 0.005 / 0.3))
    link.status = "stale"
    d.tick(0.04, link, False)
    assert (d.gain, d.feedback_gain) == pytest.approx((0.5, 1.0 - 0.01 / 0.3))
    link.status = "lost"  # the fixtures' force off at once, the slave's still fading
    d.tick(0.045, link, False)
    assert d.gain == 0.0 and d.feedback_gain == pytest.approx(1.0 - 0.015 / 0.3)
    assert d.fixtures.force_n == (0.0, 0.0, 0.0)
    link.status = "none"
    d.tick(0.05, link, False)
    assert (d.gain, d.feedback_gain) == (0.0, 0.0) and d.feedback_n == (0.0, 0.0, 0.0)
    link.status = "fresh"
    d.tick(0.055, None, False)  # no driving slave at all: no fixtures' force
    assert d.gain == 0.0 and d.fixtures.force_n == (0.0, 0.0, 0.0)
    for t in (0.06, 0.08):  # fresh and following again: both back to 1
        d.tick(t, link, False)
    assert (d.gain, d.feedback_gain) == (1.0, 1.0)
    link.status = "none"  # no tip at all: both 0 at once
    d.tick(0.081, link, False)
    assert (d.gain, d.feedback_gain) == (0.0, 0.0)


def test_without_a_fade_the_gains_jump_and_a_stop_resets_them() -> None:
    d, data, jac, _ = _display(tip_fade_ms=0.0)
    link = _link(force=(0.0, 2.0, 0.0))
    d.fixtures.raw_force_n = (1.0, 0.0, 0.0)
    d.tick(0.0, link, False)
    assert (d.gain, d.feedback_gain) == (1.0, 1.0)
    assert d.displayed_n == pytest.approx((1.0 - 2.0, 0.0, 0.0))  # (0, 2, 0) turned: (-2, 0, 0)
    d.tick(0.001, link, True)  # the clutch: the fixtures' off at once, the slave's fading
    assert d.gain == 0.0 and d.feedback_gain == pytest.approx(1.0 - 0.001 / 0.3)
    d.reset()
    assert (d.gain, d.feedback_gain) == (0.0, 0.0)
    assert d.fixtures.force_n == (0.0, 0.0, 0.0) and d.feedback_n == (0.0, 0.0, 0.0)
    assert d.displayed_n == (0.0, 0.0, 0.0) and d.displayed_torque_nm == (0.0, 0.0, 0.0)


def _news(d: Any, t: float, state: str, force: Any) -> None:
    d.tick(t, _link(slave_state=state, force=force), False)


@pytest.mark.req("SR-FORCE-6")
def test_the_hand_is_told_when_its_slave_stops_while_pressing() -> None:
    """A slave that goes from RUNNING to STOPPED, FAULT or ESTOP while its force (as displayed,
    x force_scale) is over 0.2 N lets go of the tissue: the running master's operators are told
    once, with the force and the fade; not for a lighter touch, another state, or a master that
    is itself not running."""
    from occ.core.safety import RobotState

    for stop in ("STOPPED", "FAULT", "ESTOP"):
        d, data, jac, alerts = _display(force_scale=2.0)
        # 0.3 N on the hand: (0, 0.09, 0.12) turned to (-0.09, 0, 0.12), x 2
        _news(d, 0.0, "RUNNING", (0.0, 0.09, 0.12))
        assert alerts == []
        _news(d, 0.001, stop, (0.0, 0.09, 0.12))
        assert alerts == [
            (
                "ALERT",
                f"slave on slave {stop} while pressing 0.3 N: it lets go of the tissue; its "
                "force fades out within 300 ms",
                int(igtl.StatusCode.TIME_OUT),
            )
        ]
        _news(d, 0.002, stop, (0.0, 0.09, 0.12))  # the same state again: said once
        assert len(alerts) == 1
    d, data, jac, alerts = _display()
    _news(d, 0.0, "RUNNING", (0.0, 0.19, 0.0))  # 0.19 N: not pressing
    _news(d, 0.001, "STOPPED", (0.0, 0.19, 0.0))
    _news(d, 0.002, "RUNNING", (0.0, 0.0, 0.2))  # 0.2 N exactly: not over it
    _news(d, 0.003, "ESTOP", (0.0, 0.0, 0.2))
    _news(d, 0.004, "RUNNING", (0.0, 0.5, 0.0))
    _news(d, 0.005, "PAUSED", (0.0, 0.5, 0.0))  # no stop
    _news(d, 0.006, "RUNNING", (0.0, 0.5, 0.0))
    data.state = RobotState.STOPPED  # the master itself stopped: nothing on its hand
    _news(d, 0.007, "STOPPED", (0.0, 0.5, 0.0))
    _news(d, 0.008, "STOPPED", (0.0, 0.5, 0.0))
    assert alerts == []
    d, data, jac, alerts = _display()
    _news(d, 0.0, "STOPPED", (0.0, 0.5, 0.0))  # a stop not from RUNNING
    _news(d, 0.001, "FAULT", (0.0, 0.5, 0.0))
    assert alerts == []


@pytest.mark.req("SR-FORCE-22")
def test_the_slaves_torque_is_gated_turned_clamped_and_added_on_rotational_axes() -> None:
    d, data, jac, _ = _display(nq=6, force_scale=0.5)
    assert d.rotational
    link = _link(torque=(0.4, 0.0, 0.0))
    d.tick(0.0, link, False)  # the gain still 0: nothing
    assert d.feedback_torque_nm == (0.0, 0.0, 0.0) and d.displayed_torque_nm == (0.0, 0.0, 0.0)
    d.tick(0.01, link, False)  # gain 0.5: 0.4 x 0.5 x 0.5, turned onto y
    assert d.feedback_torque_nm == pytest.approx((0.0, 0.1, 0.0))
    eff = d.tick(0.02, link, False)  # gain 1: 0.2 N m about y, on joint 4's row
    assert d.displayed_torque_nm == pytest.approx((0.0, 0.2, 0.0))
    assert eff == pytest.approx([0.0, 0.0, 0.0, 0.0, 0.2, 0.0])
    link.torque = (0.0, -3.0, 4.0)  # 2.5 N m after the scale: clamped to 0.5, same direction
    eff = d.tick(0.03, link, False)
    assert d.feedback_torque_nm == pytest.approx((1.5, 0.0, 2.0))
    assert d.displayed_torque_nm == pytest.approx((0.3, 0.0, 0.4))
    assert eff == pytest.approx([0.0, 0.0, 0.0, 0.3, 0.0, 0.4])
    st = d.source_force(None, 0.03)
    assert st.meta == {"torque_nm": "0.30000,0.00000,0.40000"} and st.unit == "N"
    link.torque = None  # none sent: none shown
    d.tick(0.04, link, False)
    assert d.displayed_torque_nm == (0.0, 0.0, 0.0)
    d2, *_ = _display(nq=3)  # three axes: the torque in the stats only
    d2.tick(0.0, link, False)
    link2 = _link(torque=(0.4, 0.0, 0.0))
    d2.tick(0.0, link2, False)
    d2.tick(0.02, link2, False)
    assert not d2.rotational and d2.feedback_torque_nm == pytest.approx((0.0, 0.4, 0.0))
    assert d2.displayed_torque_nm == (0.0, 0.0, 0.0) and d2.source_force(None, 0.0).meta is None
    d3, *_ = _display(nq=6, force_feedback=False)  # no feedback: no torque either
    link3 = _link(torque=(0.4, 0.0, 0.0))
    for t in (0.0, 0.02, 0.04):
        d3.tick(t, link3, False)
    assert d3.feedback_torque_nm == (0.0, 0.0, 0.0)
    d4, *_ = _display(nq=6, force_output=False)  # no force on a hand: the torque in the stats
    assert not d4.rotational
    link4 = _link(torque=(0.4, 0.0, 0.0))
    assert d4.tick(0.0, link4, False) is None and d4.tick(0.02, link4, False) is None
    assert d4.feedback_torque_nm == pytest.approx((0.0, 0.4, 0.0))
    assert d4.stats(0.02)["feedback_torque_nm"] == [0.0, 0.4, 0.0]


@pytest.mark.req("SR-FORCE-1")
def test_the_energy_the_slave_sent_reaches_the_masters_port_and_the_hands_goes_back() -> None:
    """The slave's ``energy_j`` (J at its instrument) enters the master's port x kf / kp (the
    force scale over the map's position factor); the hand's own energy goes back / that; a
    master that displays no feedback, or no force on a hand, or without passivity sends none."""
    d, data, jac, _ = _display(passivity=True, force_scale=2.0)
    d.tick(0.0, _link(force=(0.0, 0.0, 0.0), energy=0.25), False)
    assert d.passivity.account.peer == pytest.approx(0.25 * 2.0 / 0.1)
    d.passivity.account.e_in = 0.3
    assert d.energy_out() == pytest.approx(0.3 * 0.1 / 2.0)
    for off in (
        dict(passivity=False), dict(force_feedback=False), dict(force_output=False),
        dict(force_scale=0.0),
    ):  # fmt: skip
        d, *_ = _display(**{"passivity": True, **off})
        d.tick(0.0, _link(force=(0.0, 0.0, 0.0), energy=0.25), False)
        assert d.energy_out() is None, off
        if off.get("force_scale") == 0.0:
            assert d.passivity.account.received == 0


def test_a_cartesian_master_takes_its_constant_jacobian_once() -> None:
    from occ.controllers.teleop.display import HapticDisplay

    for q, constant in (
        ([0.0, 0.0, 0.0], False),
        ([0.0, 2e-6, 0.0], True),
        ([0.0, 5e-7, 0.0], False),
        ([0.0, -1e-6, 0.0], False),  # moved by more than 1e-6 only
    ):
        d, data, jac, _ = _display()
        data.q = q
        jac[:3, :3] = [[1.0, 2.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 3.0]]
        d.bind(data, d.ctx)
        assert (d._jt is not None) is constant, q
        if constant:
            assert d._jt == [[1.0, 0.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 3.0]]
            d.fixtures.raw_force_n = (1.0, 1.0, 1.0)
            for t in (0.0, 0.02):
                eff = d.tick(t, _link(), False)
            jac[:3, :3] = 0.0  # the Jacobian taken once: the model's is not asked again
            assert d.tick(0.03, _link(), False) == pytest.approx([1.0, 3.0, 3.0]) == eff
    assert isinstance(d, HapticDisplay)

    # a Jacobian that changes with q (an entry of 0 by 1e-10 only, or the whole of it, but the
    # same at 1 rad as at q): the model's is asked each time
    def jacobian(q: Any, c: float) -> Any:
        j = np.eye(6, 3)
        if q[0]:
            j[0, 1] += c
            j[:3, :3] *= 1.0 + c
        return j

    for q, changed in (([0.3, 0.0, 0.0], 1e-10), ([1.0, 1.0, 1.0], 0.5)):
        d, data, jac, _ = _display()
        data.q = q
        varying = SimpleNamespace(nq=3, jacobian=lambda q, c=changed: jacobian(q, c))
        d.bind(data, SimpleNamespace(frame=varying, clock=d.ctx.clock))
        assert d._jt is None, q
    d, *_ = _display()
    assert d.stats(0.0)["external_fresh"] is False  # none came yet


@pytest.mark.req("SR-FORCE-1")
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_the_passivity_controller_watches_a_force_along_any_single_axis(axis: int) -> None:
    """A slave's force of 2 N along one of the master's axes alone, on a handle moving with it
    at 0.1 m/s, with no energy from the slave: the first tick shows it whole (nothing to
    observe yet), the next observes the 0.2 mJ it gave the hand and cuts it to nothing."""
    d, data, jac, _ = _display(passivity=True, tip_fade_ms=0.0)
    slave = [(0.0, -2.0, 0.0), (2.0, 0.0, 0.0), (0.0, 0.0, 2.0)][axis]  # the map turns it
    data.qdot = [0.1 if i == axis else 0.0 for i in range(3)]
    d.tick(0.0, _link(force=slave), False)
    assert d.displayed_n[axis] == pytest.approx(2.0) and d.passivity.shown[axis] == 2.0
    data.q = [1e-4 if i == axis else 0.0 for i in range(3)]
    d.tick(0.001, _link(force=slave), False)
    assert d.passivity.account.e_out == pytest.approx(2e-4)
    assert d.displayed_n == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    assert d.passivity.active_ticks == 1


@pytest.mark.req("SR-FORCE-22")
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_the_torque_on_a_turning_handle_is_cut_or_observed_about_any_axis(axis: int) -> None:
    """0.2 N m about one of the master's axes on a handle turning with it at 1 rad/s: the
    first tick shows it whole; the next, with passivity, cuts it to nothing (nothing came in
    through this channel), and without passivity shows it and observes the 0.2 mJ given."""
    slave = [(0.0, -0.2, 0.0), (0.2, 0.0, 0.0), (0.0, 0.0, 0.2)][axis]  # the map turns it
    for passive in (True, False):
        d, data, jac, _ = _display(nq=6, passivity=passive, tip_fade_ms=0.0)
        data.qdot = [1.0 if i == 3 + axis else 0.0 for i in range(6)]
        d.tick(1.0, _link(torque=slave), False)
        assert d.displayed_torque_nm[axis] == pytest.approx(0.2)
        d.tick(1.001, _link(torque=slave), False)
        if passive:
            assert d.displayed_torque_nm == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
            assert d.torque_passivity.active_ticks == 1
        else:
            assert d.displayed_torque_nm[axis] == pytest.approx(0.2)
            assert d.torque_passivity.account.e_out == pytest.approx(2e-4)


@pytest.mark.req("SR-FIX-1")
def test_the_sum_is_clamped_counted_and_the_port_told_what_was_shown() -> None:
    """Fixtures plus the slave's force over max_force_n (10 N) is scaled down to it, the same
    direction, each clamped tick counted; the passivity port is told the slave's part as
    really shown (scaled alike), and the whole of it again once under the limit. After a
    reset the first tick starts the fades from zero."""
    d, data, jac, _ = _display(tip_fade_ms=0.0)
    d.fixtures.raw_force_n = (6.0, 0.0, 0.0)
    d.tick(0.0, _link(force=(0.0, 0.0, 8.0)), False)  # (6, 0, 8): 10 N, not over
    assert d.displayed_n == pytest.approx((6.0, 0.0, 8.0)) and d.clamped_ticks == 0
    d.fixtures.raw_force_n = (6.0, 3.0, 0.0)
    d.tick(0.001, _link(force=(0.0, 0.0, 18.0)), False)  # (6, 3, 18): scaled by 10 / 19.2
    k = 10.0 / math.hypot(6.0, 3.0, 18.0)
    assert d.displayed_n == pytest.approx((6.0 * k, 3.0 * k, 18.0 * k)) and d.clamped_ticks == 1
    assert d.passivity.shown == pytest.approx((0.0, 0.0, 18.0 * k))
    d.tick(0.0015, _link(force=(0.0, 0.0, 18.0)), False)
    assert d.clamped_ticks == 2
    d.tick(0.002, _link(force=(0.0, 0.0, 2.0)), False)
    assert d.passivity.shown == (0.0, 0.0, 2.0) and d.clamped_ticks == 2
    assert d.stats(0.002)["force_clamped_ticks"] == 2
    d2, *_ = _display()  # the fades, reset in the middle of one
    d2.tick(0.0, _link(), False)
    d2.tick(0.01, _link(), False)
    assert d2.gain == pytest.approx(0.5)
    d2.reset()
    d2.tick(1.0, _link(), False)  # the first tick after the reset: from zero, no jump
    assert (d2.gain, d2.feedback_gain) == (0.0, 0.0)
    d2.tick(1.005, _link(), False)
    assert d2.gain == pytest.approx(0.25)


@pytest.mark.req("SR-FORCE-2")
def test_an_external_force_is_shown_to_the_end_of_its_timeout_and_no_longer() -> None:
    from igtl.messages.sensor import NEWTON
    from occ.net.decoders import event_of

    d, *_ = _display(external_force_timeout_ms=125.0)
    m = igtl.SensorMessage((0.0, 0.0, 1.5), NEWTON, device_name="ServoCF", header_version=2)
    d.external(event_of(m), 0.5)
    assert d.show(0.625, (0.0, 0.0, 0.0)) == (0.0, 0.0, 1.5)  # 125 ms after it came: shown
    assert d.stats(0.625)["external_fresh"] is True
    assert d.show(0.626, (0.0, 0.0, 0.0)) == (0.0, 0.0, 0.0)
    assert d.stats(0.626)["external_fresh"] is False


def test_the_first_tick_after_a_reset_shows_an_external_force_and_a_torque_whole() -> None:
    """After a reset (a change of state) nothing has been displayed: the first tick shows an
    external force and, without a fade, the slave's torque whole, with passivity on (nothing
    to passivate yet), and the fresh display's statistics read zero."""
    from igtl.messages.sensor import NEWTON
    from occ.net.decoders import event_of

    d, data, jac, _ = _display(nq=6, passivity=True, tip_fade_ms=0.0)
    st = d.stats(0.0)
    assert st["force_n"] == st["feedback_n"] == st["feedback_torque_nm"] == [0.0, 0.0, 0.0]
    assert st["torque"]["torque_nm"] == [0.0, 0.0, 0.0]
    link = _link(torque=(0.0, -0.2, 0.0), force=(0.0, 0.0, 0.0))
    d.tick(0.0, link, False)
    d.tick(0.001, _link(torque=(0.0, -0.2, 0.0), force=(0.0, 0.0, 0.0)), False)
    d.reset()
    m = igtl.SensorMessage((0.0, 0.0, 1.5), NEWTON, device_name="ServoCF", header_version=2)
    d.external(event_of(m), 5.0)
    d.tick(5.0, _link(torque=(0.0, -0.2, 0.0), force=(0.0, 0.0, 0.0)), False)
    assert d.displayed_n == (0.0, 0.0, 1.5)
    assert d.displayed_torque_nm == pytest.approx((0.2, 0.0, 0.0))


@pytest.mark.req("SR-FORCE-1")
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_the_port_acts_on_the_tick_a_force_appears_and_observes_the_tick_it_goes(axis: int) -> None:
    """The passivity port is skipped only when no force is shown now or was last tick: a force
    of exactly 1 N that appears on a handle moving with it is cut on its first tick (the ticks
    before it timed the handle); one the hand pushes against is observed over its last tick
    too, the tick it is gone."""
    slave = [(0.0, -1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)][axis]  # the map turns it
    d, data, jac, _ = _display(passivity=True, tip_fade_ms=0.0)
    data.qdot = [0.1 if i == axis else 0.0 for i in range(3)]
    d.tick(0.0, _link(force=None), False)
    d.tick(0.001, _link(force=slave), False)
    assert d.displayed_n == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    d, data, jac, _ = _display(passivity=True, tip_fade_ms=0.0)
    data.qdot = [-0.1 if i == axis else 0.0 for i in range(3)]  # the hand pushes into it
    for i, (t, f) in enumerate(((0.0, slave), (0.001, slave), (0.002, None))):
        data.q = [-1e-4 * i if j == axis else 0.0 for j in range(3)]
        d.tick(t, _link(force=f), False)
    assert d.displayed_n == (0.0, 0.0, 0.0)
    assert d.passivity.account.e_in == pytest.approx(2e-4)  # two ticks of 1 N over 0.1 mm
