"""The slave's tip force (occ/haptics/forces.py) on its own: what is sent to the master, source by
source, without a robot around it (test_contact.py has the same sources on the simulated
slave; this file is the module's unit tests, the `tipforce` selection of scripts/mutate).

- ``effort``: efforts made from a known tip force through the shipped slave's Jacobian
  (``tau = -J^T F``, base frame) give that force back in the patient frame; the damped least
  squares scales each direction of the force by ``s^2 / (s^2 + l^2)`` (``s`` its singular
  value); a tare is subtracted; the momentum observer takes the joints' inertia and viscous
  friction out (each term alone and both); efforts that are not finite give no estimate.
- ``tissue``: the simulated world's contact force, as it is.
- ``sensor``: newtons scaled from milli- and kilo-newtons on every axis, only the force read;
  a reading exactly as old as the timeout is used, an older one is not (one ALERT per silence,
  its text and code; "back" when it speaks again); before its first reading, no force and no
  ALERT.
- the order of preference, zero when no source is healthy, the counters and the statistics
  (every field), and the class's defaults being the configuration's.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

import igtl
from igtl.messages.sensor import Unit
from occ.config import ContactConfig
from occ.haptics.contact import Contact, Environment
from occ.controllers.teleop_params import SlaveForceParams
from occ.net.decoders import event_of
from occ.haptics.forces import SlaveForce, sensor_force
from occ.kinematics.frame import Frame

pytestmark = pytest.mark.req("SR-FORCE-3")

SLAVE = Frame.builtin("occ_slave")
Q = [0.1, 0.35, 0.05]
ZERO3 = [0.0, 0.0, 0.0]


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def base_pose() -> np.ndarray:
    """The base turned 0.7 rad about z and moved (the move must not matter to a force)."""
    b = np.eye(4)
    b[:3, :3] = rot_z(0.7)
    b[:3, 3] = [0.1, -0.2, 0.3]
    return b


def held(force_patient: Any, base: np.ndarray, q: list[float] = Q) -> np.ndarray:
    """The efforts of drives holding the tip against ``force_patient`` (N): ``-J^T F`` with
    ``F`` in the base frame (what occ/haptics/contact.py loads the ``sim`` drives with, opposed)."""
    jac = SLAVE.jacobian(q)[:3]
    f_base = base[:3, :3].T @ np.asarray(force_patient, dtype=float)
    return -(jac.T @ f_base)


def estimate(src: SlaveForce, now: float, effort: Any, *, base: Any = None, **kw: Any) -> Any:
    b = np.eye(4) if base is None else base
    return src.estimate(
        now, SLAVE, kw.get("q", Q), kw.get("qdot", ZERO3), list(effort), b, kw.get("tip", np.eye)
    )


def sensor(values: tuple[float, ...], unit: Unit | int = 0, device: str = "ForceSensor") -> Any:
    return igtl.SensorMessage(values, unit, device_name=device)


def newtons(prefix: int = 0) -> Unit:
    return Unit(prefix, ((11, 1),))


class Alerts:
    """The controller's ``alert`` (name, text, code): three arguments, as ctx.alert takes."""

    def __init__(self) -> None:
        self.got: list[tuple[str, str, int]] = []

    def __call__(self, name: str, text: str, code: int) -> None:
        self.got.append((name, text, code))


# ------------------------------------------------------------------ effort
def test_the_effort_source_inverts_the_jacobian_transpose_into_the_patient_frame() -> None:
    base = base_pose()
    force = (0.3, -0.7, 1.1)
    src = SlaveForce(("effort",))
    f = estimate(src, 0.0, held(force, base), base=base)
    # the default damping (1e-4 m) against the smallest singular value (24 mm here): 2e-5 rel.
    assert f == pytest.approx(force, abs=1e-4)
    assert isinstance(f, tuple) and all(type(c) is float for c in f)
    assert src.used == "effort" and src.force_n == f and src.estimates == {"effort": f}
    # the same efforts with the base unturned: the base-frame force, not the patient-frame one
    g = estimate(SlaveForce(("effort",)), 0.0, held(force, base))
    assert g == pytest.approx(tuple(base[:3, :3].T @ force), abs=1e-4)


def test_the_damping_scales_each_direction_of_the_force_by_its_singular_value() -> None:
    """Damped least squares: along each left singular vector ``u`` of J (its singular value
    ``s``), the estimate is the force's component times ``s^2 / (s^2 + l^2)``: a direction the
    joints barely move (``s`` under ``l``) is read weakly, never amplified."""
    lam = 0.05  # 50 mm: above the slave's two smaller singular values here (24 and 70 mm)
    force = np.array([0.3, -0.7, 1.1])
    u, s, _ = np.linalg.svd(SLAVE.jacobian(Q)[:3])
    expect = u @ np.diag(s**2 / (s**2 + lam**2)) @ u.T @ force
    f = estimate(SlaveForce(("effort",), damping=lam), 0.0, held(force, np.eye(4)))
    assert f == pytest.approx(tuple(expect), rel=1e-9, abs=1e-12)
    assert np.linalg.norm(f) < np.linalg.norm(force)


def test_a_tare_is_subtracted_from_the_efforts_from_then_on() -> None:
    bias = [0.02, -0.5, 3.0]  # gravity and friction at rest: no force on the tool
    force = (0.0, 0.4, -0.9)
    src = SlaveForce(("effort",))
    assert src.stats(0.0)["tared"] is False
    untared = estimate(src, 0.0, held(force, np.eye(4)) + bias)
    assert untared != pytest.approx(force, abs=1e-2)  # the bias reads as a force
    src.tare(bias)
    bias[2] = 100.0  # the caller's list is copied
    assert estimate(src, 0.0, held(force, np.eye(4)) + [0.02, -0.5, 3.0]) == pytest.approx(
        force, abs=1e-4
    )
    assert src.used == "effort" and src.stats(0.0)["tared"] is True


@pytest.mark.parametrize(
    ("inertia", "damping"),
    [((0.02, 0.05, 0.3), (0.01, 0.02, 0.5)), ((0.02, 0.05, 0.3), None), (None, (0.01, 0.02, 0.5))],
    ids=["inertia-and-friction", "inertia", "friction"],
)
def test_the_momentum_observer_takes_the_joints_own_dynamics_out(
    inertia: tuple[float, ...] | None, damping: tuple[float, ...] | None
) -> None:
    """Efforts that are the load plus the joints' momentum change over the estimate's
    interval (``M dqdot / dt``) plus their viscous friction (``b qdot``, at the interval's
    mean velocity once there is an interval) give the load back; the first estimate has no
    interval, only the friction at its velocity."""
    force = (0.5, -0.2, 0.8)
    m = np.zeros(3) if inertia is None else np.array(inertia)
    b = np.zeros(3) if damping is None else np.array(damping)
    src = SlaveForce(("effort",), effort_inertia=inertia, effort_damping=damping)
    t0, qd0 = 1.0, np.array([0.3, -0.1, 0.02])
    tau0 = held(force, np.eye(4)) + b * qd0
    assert estimate(src, t0, tau0, qdot=list(qd0)) == pytest.approx(force, abs=1e-4)
    dt, qd1 = 0.002, np.array([0.35, -0.16, 0.05])
    q1 = [0.11, 0.34, 0.051]
    mean = 0.5 * (qd0 + qd1) if inertia is not None else qd1
    tau1 = held(force, np.eye(4), q1) + m * (qd1 - qd0) / dt + b * mean
    f = estimate(src, t0 + dt, tau1, q=q1, qdot=list(qd1))
    assert f == pytest.approx(force, abs=1e-4)
    # the next interval starts where this one ended (the velocity and the time kept)
    qd2 = np.array([0.3, -0.2, 0.0])
    mean = 0.5 * (qd1 + qd2) if inertia is not None else qd2
    tau2 = held(force, np.eye(4), q1) + m * (qd2 - qd1) / 0.004 + b * mean
    assert estimate(src, t0 + dt + 0.004, tau2, q=q1, qdot=list(qd2)) == pytest.approx(
        force, abs=1e-4
    )


def test_without_the_observer_the_joints_dynamics_read_as_a_load() -> None:
    force = (0.5, -0.2, 0.8)
    qd0, qd1 = np.array([0.3, -0.1, 0.02]), np.array([0.35, -0.16, 0.05])
    tau1 = held(force, np.eye(4)) + 0.3 * (qd1 - qd0) / 0.002
    src = SlaveForce(("effort",))
    estimate(src, 1.0, held(force, np.eye(4)), qdot=list(qd0))
    assert estimate(src, 1.002, tau1, qdot=list(qd1)) != pytest.approx(force, abs=0.1)


def test_efforts_that_are_not_finite_give_no_estimate_and_the_next_source_is_sent() -> None:
    src = SlaveForce(("effort", "sensor"), sensor_interface="s")
    assert src.on_input(event_of(sensor((1.0, 2.0, 3.0)), "s"), 0.0)
    assert estimate(src, 0.01, [0.0, math.inf, 0.0]) == (1.0, 2.0, 3.0)
    assert src.used == "sensor" and src.estimates == {"effort": None, "sensor": (1.0, 2.0, 3.0)}


# ------------------------------------------------------------------ tissue
def test_the_tissue_source_is_the_simulated_contact_force() -> None:
    far = Contact.from_config(
        ContactConfig(kind="wall", point_mm=(1e3, 0.0, 0.0), normal=(0.0, 0.0, 1.0))
    )
    p, _ = Environment([far], SLAVE, lambda: np.eye(4)).tip(Q)
    wall = Contact.from_config(
        ContactConfig(kind="wall", point_mm=(p[0], p[1], p[2] + 2.0), normal=(0.3, -0.2, 1.0))
    )
    env = Environment([wall], SLAVE, lambda: np.eye(4))
    assert env.efforts(Q, ZERO3) is not None and env.in_contact
    src = SlaveForce(("tissue", "effort"), environment=env)
    f = estimate(src, 0.0, ZERO3)
    assert f == env.force_n and math.hypot(*f) > 0.1
    assert src.used == "tissue" and src.estimates == {"tissue": f, "effort": (0.0, 0.0, 0.0)}
    with pytest.raises(ValueError, match="^force source 'tissue' needs a simulated environment$"):
        SlaveForce(("tissue",))


# ------------------------------------------------------------------ sensor
def test_sensor_units_scale_every_axis_and_only_the_force_is_read() -> None:
    assert sensor_force(event_of(sensor((1000.0, -2000.0, 500.0), newtons(11)))) == (
        (1.0, -2.0, 0.5),
        "",
    )
    assert sensor_force(event_of(sensor((0.001, 0.002, -0.003), newtons(3)))) == (
        pytest.approx((1.0, 2.0, -3.0)),
        "",
    )
    # six values: force and torque; the torque is not used, so not judged
    assert sensor_force(event_of(sensor((1.0, 2.0, 3.0, math.nan, 0.0, 0.0)))) == (
        (1.0, 2.0, 3.0),
        "",
    )
    assert sensor_force(event_of(igtl.StringMessage("x"))) == (None, "STRING is not a SENSOR")
    # a force that is not finite: refused, the error showing the force (not the torque)
    assert sensor_force(event_of(sensor((1.0, math.nan, 3.0, 4.0, 5.0, 6.0)))) == (
        None,
        "not a force: (1.0, nan, 3.0)",
    )


def test_a_reading_too_large_for_newtons_is_refused_and_counted() -> None:
    """1e306 kN is a finite number on the wire but no finite number of newtons: refused and
    counted like a NaN (before: an infinite force, sent to the master as ``inf`` and drawn in
    3D Slicer as a transform and an arrow of NaN), the last good reading kept."""
    assert sensor_force(event_of(sensor((1e306, 0.0, 0.0, 4.0, 5.0, 6.0), newtons(3)))) == (
        None,
        "not a force: (1e+306, 0.0, 0.0) kiloN is not finite in N",  # the force, not the torque
    )
    src = SlaveForce(("sensor",), sensor_interface="s")
    assert src.on_input(event_of(sensor((0.0, 0.0, 2.0)), "s"), 1.0)
    assert not src.on_input(event_of(sensor((0.0, -1e306, 1.0), newtons(3)), "s"), 1.001)
    assert src.sensor_refused == 1 and src.sensor_samples == 1
    assert src.sensor_last_error == (
        "SENSOR 'ForceSensor': not a force: (0.0, -1e+306, 1.0) kiloN is not finite in N"
    )
    assert estimate(src, 1.002, ZERO3) == (0.0, 0.0, 2.0)


def test_a_reading_as_old_as_the_timeout_is_used_and_an_older_one_is_not() -> None:
    timeout = 1.0 / 64.0  # exact in binary: the age at the boundary is exactly the timeout
    src = SlaveForce(("sensor",), sensor_interface="s", sensor_timeout_s=timeout)
    assert src.on_input(event_of(sensor((0.0, 0.0, 2.0)), "s"), 1.0)
    assert estimate(src, 1.0 + timeout, ZERO3) == (0.0, 0.0, 2.0)
    assert estimate(src, 1.0 + 2 * timeout, ZERO3) == (0.0, 0.0, 0.0) and src.used is None


def test_a_sensor_never_heard_gives_no_force_and_no_alert() -> None:
    alerts = Alerts()
    src = SlaveForce(("sensor",), sensor_interface="s", alert=alerts)
    assert src.force_n == (0.0, 0.0, 0.0) and src.used is None and src.estimates_made == 0
    f = estimate(src, 5.0, ZERO3)
    assert f == (0.0, 0.0, 0.0) and isinstance(f, tuple)
    assert src.used is None and src.estimates == {"sensor": None} and alerts.got == []
    assert src.estimates_made == 1
    estimate(src, 5.1, ZERO3)
    assert src.estimates_made == 2


def test_each_silence_is_one_alert_and_each_return_is_told() -> None:
    alerts = Alerts()
    src = SlaveForce(("sensor",), sensor_interface="s", alert=alerts)  # timeout: the default
    assert src.on_input(event_of(sensor((1.0, 0.0, 0.0)), "s"), 0.0)
    for t in (1.0, 1.5, 2.0):
        assert estimate(src, t, ZERO3) == (0.0, 0.0, 0.0)
    assert alerts.got == [
        (
            "ALERT",
            "force sensor 'ForceSensor' silent for 1000 ms (timeout 20 ms): its force is not used",
            2,
        )
    ]
    assert src.on_input(event_of(sensor((2.0, 0.0, 0.0)), "s"), 2.0)
    assert src.on_input(event_of(sensor((3.0, 0.0, 0.0)), "s"), 2.001)  # still back: not told again
    assert alerts.got[1:] == [("STREAM", "force sensor 'ForceSensor' back", 1)]
    assert estimate(src, 2.002, ZERO3) == (3.0, 0.0, 0.0)
    estimate(src, 2.5, ZERO3)  # silent again: told again
    assert [a[0] for a in alerts.got] == ["ALERT", "STREAM", "ALERT"]
    assert "silent for 499 ms" in alerts.got[2][1]


def test_the_sensor_in_the_base_and_tip_frames_is_turned_into_the_patient_frame() -> None:
    base = base_pose()
    tip = rot_z(-1.2) @ np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    v = np.array([0.2, -0.4, 1.5])
    for frame, expect in (
        ("patient", v),
        ("base", base[:3, :3] @ v),
        ("tip", base[:3, :3] @ tip @ v),
    ):
        src = SlaveForce(("sensor",), sensor_interface="s", sensor_frame=frame)
        assert src.on_input(event_of(sensor(tuple(v)), "s"), 0.0)
        f = estimate(src, 0.0, ZERO3, base=base, tip=lambda: tip)
        assert f == pytest.approx(tuple(expect), abs=1e-12), frame
        assert all(type(c) is float for c in f)


# ------------------------------------------------------------------ counters, statistics
#: a sensor source's tare before any (its statistics; tests/occ/test_sensor_tare.py has them after)
UNTARED = {
    "taken": 0,
    "refused": 0,
    "last": "",
    "t": None,
    "readings": 0,
    "offset_n": [0.0, 0.0, 0.0],
    "offset_nm": [0.0, 0.0, 0.0],
}


def test_the_statistics_report_every_source_and_the_sensors_counters() -> None:
    src = SlaveForce(("sensor", "effort"), sensor_interface="s")
    assert src.stats(3.0) == {
        "sources": ["sensor", "effort"],
        "used": None,
        "force_n": [0.0, 0.0, 0.0],
        "estimates_n": {"sensor": None, "effort": None},
        "tared": False,
        "sensor": {"samples": 0, "refused": 0, "age_ms": None, "last_error": ""},
        "torque_nm": None,
        "tare": UNTARED,
    }
    assert not src.on_input(event_of(sensor((1.0, 2.0)), "s"), 0.5)
    assert not src.on_input(event_of(sensor((1.0, 2.0, 3.0), Unit(0, ((1, 1),))), "s"), 0.6)
    assert src.on_input(event_of(sensor((9.0, 9.0, 9.0)), "s"), 0.7)
    assert src.on_input(event_of(sensor((0.123456, -1.000049, 2.5)), "s"), 1.0)
    estimate(src, 1.01, ZERO3)
    assert src.stats(1.0123456) == {
        "sources": ["sensor", "effort"],
        "used": "sensor",
        "force_n": [0.1235, -1.0, 2.5],
        "estimates_n": {"sensor": [0.1235, -1.0, 2.5], "effort": [0.0, 0.0, 0.0]},
        "tared": False,
        "sensor": {
            "samples": 2,
            "refused": 2,
            "age_ms": 12.3,
            "last_error": "SENSOR 'ForceSensor': unit 'm' is not a force (N)",
        },
        "torque_nm": None,  # three values: no torque
        "tare": UNTARED,
    }
    assert "sensor" not in SlaveForce(("effort",)).stats(0.0)


def test_the_defaults_are_the_configurations() -> None:
    p = SlaveForceParams()
    src = SlaveForce(p.sources)
    assert src.sources == ("effort",)
    assert src.sensor_device == p.sensor_device and src.sensor_frame == p.sensor_frame
    assert src.sensor_timeout_s == pytest.approx(p.sensor_timeout_ms * 1e-3)
    assert src.damping == p.damping
    assert src.effort_damping is None and src.effort_inertia is None
