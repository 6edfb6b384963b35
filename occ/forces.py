"""Forces at the slave: what the instrument feels, from the drives' efforts or a force sensor.

The slave (``teleop-slave`` with ``force``) sends its tip force to the master on the return
channel (occ/returnlink.py, metadata ``force_n``, N in the patient frame). Two sources, used in
the configured order of preference (the first one healthy is sent; every one is in the
statistics, so a sensor and the drives cross-check each other):

``effort``
    The drives' measured efforts ``tau`` (each joint's effort state interface) mapped to a tip
    force through the transpose of the kinematic model's Jacobian (pinocchio, base frame):
    a drive holding a load ``J^T F`` exerts ``-J^T F``, so ``F = -(J J^T + l^2 I)^-1 J (tau -
    tau_0)``, damped least squares (``l``: ``damping``) so a singular pose gives a bounded
    estimate, not an explosion. ``tau_0`` is the bias (gravity, friction at rest) taken by the
    ``ForceTare`` command with the tool free. The GHC system measured instrument forces with
    strain gauges; robots with joint torque sensing (or a drive current model) use this path.
    ``effort_damping`` (per joint, N s/m or N m s/rad) takes the joints' viscous friction out
    of the efforts first (``tau - b qdot``), and ``effort_inertia`` (kg, kg m^2) their
    acceleration: with both, the efforts' mean since the last estimate minus the joints'
    momentum change and friction over that time (a discrete momentum observer; the drives
    must report efforts averaged over the stream period, e.g. ``sim``'s ``effort_average_ms``).
    Without them the joints' own dynamics read as a load: at a joint with a short lever to the
    tip (the OCC slave's yaw: 14-24 mm) its inertia reads as tens of kilograms at the tip, and
    fed back to the master that makes the loop oscillate. In simulation the tissue of
    occ/contact.py loads the ``sim`` drives, so this is a real estimate there too.
``tissue``
    Simulation only (a config with an ``environment``): the simulated tissue's own contact
    force, as a force sensor at the instrument would read it (the GHC's strain gauges on a
    simulated robot): exact, no noise, no lag.
``sensor``
    An OpenIGTLink SENSOR stream from a separate force sensor (the GHC's strain gauges): 3
    values (force) or 6 (force, torque), unit N (or none), in the ``sensor_frame`` (``patient``,
    the robot's ``base``, or the ``tip``: rotated by the measured tip orientation). A reading
    older than ``sensor_timeout_ms`` is not used (the source is unhealthy: the next source, or
    no force, and one ALERT); a reading that is not finite or not a force is refused and
    counted.

Loop thread only; one estimate per return sample (the stream rate), not per tick.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from igtl.messages.base import Message
from igtl.messages.sensor import SensorMessage

__all__ = ["SlaveForce"]

Vec3 = tuple[float, float, float]
ZERO: Vec3 = (0.0, 0.0, 0.0)
#: SENSOR units taken as a force, with their factor to N
FORCE_UNITS = {"": 1.0, "N": 1.0, "milliN": 1e-3, "kiloN": 1e3}


def sensor_force(msg: Message) -> tuple[Vec3 | None, str]:
    """The force a SENSOR message carries (N): ``(force, "")``, or ``(None, why not)`` for a
    message that is no SENSOR, not in newtons, of neither 3 nor 6 values, or not finite (in
    its unit or in N)."""
    if not isinstance(msg, SensorMessage):
        return None, f"{msg.message_type} is not a SENSOR"
    unit = str(msg.unit)
    factor = FORCE_UNITS.get(unit)
    values = msg.data
    if factor is None:
        return None, f"unit {unit!r} is not a force (N)"
    if len(values) not in (3, 6):
        return None, f"{len(values)} values (3: force, 6: force and torque)"
    if not all(math.isfinite(v) for v in values[:3]):
        return None, f"not a force: {values[:3]}"
    force = (values[0] * factor, values[1] * factor, values[2] * factor)
    if not all(math.isfinite(v) for v in force):  # 1e306 kiloN: finite, but no float in N
        return None, f"not a force: {values[:3]} {unit} is not finite in N"
    return force, ""


class SlaveForce:
    """The slave's tip force from its configured sources (see the module docstring)."""

    def __init__(
        self,
        sources: tuple[str, ...],
        *,
        sensor_interface: str | None = None,
        sensor_device: str = "ForceSensor",
        sensor_frame: str = "patient",
        sensor_timeout_s: float = 0.02,
        damping: float = 1e-4,
        effort_damping: tuple[float, ...] | None = None,
        effort_inertia: tuple[float, ...] | None = None,
        environment: Any = None,
        alert: Callable[[str, str, int], None] | None = None,
    ) -> None:
        if "tissue" in sources and environment is None:
            raise ValueError("force source 'tissue' needs a simulated environment")
        self.environment = environment
        self.effort_damping = effort_damping
        self.effort_inertia = effort_inertia
        self._prev: tuple[float, np.ndarray, np.ndarray] | None = None  # t, q, qdot
        self.sources = sources
        self.sensor_interface = sensor_interface
        self.sensor_device = sensor_device
        self.sensor_frame = sensor_frame
        self.sensor_timeout_s = sensor_timeout_s
        self.damping = damping
        self.alert = alert
        self.bias: list[float] | None = None
        #: the latest estimate of each source (N, patient frame), None when unhealthy
        self.estimates: dict[str, Vec3 | None] = {s: None for s in sources}
        #: what was sent: the first healthy source's estimate, and which source
        self.force_n: Vec3 = ZERO
        self.used: str | None = None
        self._sensor: Vec3 | None = None
        self._sensor_t = -math.inf
        self.sensor_samples = 0
        self.sensor_refused = 0
        self.sensor_last_error = ""
        self._sensor_alerted = False
        self.estimates_made = 0

    # ------------------------------------------------------------------ sensor
    def on_input(self, msg: Message, interface: str, now: float) -> bool:
        """A discrete input: a SENSOR reading, if it is the configured one: True when taken
        (the controller passes every input on; this is where a SENSOR is read)."""
        if (
            not isinstance(msg, SensorMessage)
            or interface != self.sensor_interface
            or msg.device_name != self.sensor_device
        ):
            return False
        force, error = sensor_force(msg)
        if force is None:
            self.sensor_refused += 1
            self.sensor_last_error = f"SENSOR {msg.device_name!r}: {error}"
            return False
        self._sensor = force
        self._sensor_t = now
        self.sensor_samples += 1
        if self._sensor_alerted:
            self._sensor_alerted = False
            self._tell("STREAM", f"force sensor {self.sensor_device!r} back", 1)
        return True

    # ------------------------------------------------------------------ estimates
    def tare(self, effort: list[float]) -> None:
        """``ForceTare``: the efforts now are the bias (the tool touches nothing)."""
        self.bias = list(effort)

    def estimate(
        self,
        now: float,
        frame: Any,
        q: list[float],
        qdot: list[float],
        effort: list[float],
        base: np.ndarray,
        tip_rotation: Callable[[], np.ndarray],
    ) -> Vec3:
        """The force to send now (N, patient frame; see the module docstring)."""
        self.estimates_made += 1
        used = None
        out = ZERO
        for src in self.sources:
            f: Vec3 | None
            if src == "effort":
                f = self._from_effort(now, frame, q, qdot, effort, base)
            elif src == "tissue":
                f = self.environment.force_n
            else:
                f = self._from_sensor(now, base, tip_rotation)
            self.estimates[src] = f
            if used is None and f is not None:
                used, out = src, f
        self.used = used
        self.force_n = out
        return out

    def _from_effort(
        self,
        now: float,
        frame: Any,
        q: list[float],
        qdot: list[float],
        effort: list[float],
        base: np.ndarray,
    ) -> Vec3 | None:
        tau = np.asarray(effort, dtype=float)
        qa, qda = np.asarray(q, dtype=float), np.asarray(qdot, dtype=float)
        prev, self._prev = self._prev, (now, qa, qda)
        if self.bias is not None:
            tau = tau - np.asarray(self.bias, dtype=float)
        dt = now - prev[0] if prev is not None else 0.0
        if self.effort_inertia is not None and dt > 0.0:
            # the joints' momentum balance since the last estimate (a discrete momentum
            # observer): what the efforts spent accelerating and against friction is no load
            assert prev is not None
            tau = tau - np.asarray(self.effort_inertia) * (qda - prev[2]) / dt
            if self.effort_damping is not None:
                # the drives' velocities, not position differences: an encoder's quantum over
                # 2 ms is a velocity that, at a 14 mm lever, reads as 0.2 N
                tau = tau - np.asarray(self.effort_damping) * 0.5 * (qda + prev[2])
        elif self.effort_damping is not None:
            tau = tau - np.asarray(self.effort_damping) * qda
        if not np.all(np.isfinite(tau)):
            return None
        jac = frame.jacobian(q)[:3]  # 3 x n, base frame
        lam = self.damping
        fb = -np.linalg.solve(jac @ jac.T + lam * lam * np.eye(3), jac @ tau)
        fp = base[:3, :3] @ fb
        return (float(fp[0]), float(fp[1]), float(fp[2]))

    def _from_sensor(
        self, now: float, base: np.ndarray, tip_rotation: Callable[[], np.ndarray]
    ) -> Vec3 | None:
        f = self._sensor
        if f is None:
            return None
        if now - self._sensor_t > self.sensor_timeout_s:
            if not self._sensor_alerted:
                self._sensor_alerted = True
                age = (now - self._sensor_t) * 1e3
                self._tell(
                    "ALERT",
                    f"force sensor {self.sensor_device!r} silent for {age:.0f} ms "
                    f"(timeout {self.sensor_timeout_s * 1e3:g} ms): its force is not used",
                    2,
                )
            return None
        if self.sensor_frame == "patient":
            return f
        rot = base[:3, :3] if self.sensor_frame == "base" else base[:3, :3] @ tip_rotation()
        v = rot @ np.array(f)
        return (float(v[0]), float(v[1]), float(v[2]))

    def _tell(self, name: str, text: str, code: int) -> None:
        if self.alert is not None:
            self.alert(name, text, code)

    def stats(self, now: float) -> dict[str, Any]:
        def rounded(v: Vec3 | None) -> list[float] | None:
            return None if v is None else [round(c, 4) for c in v]

        out: dict[str, Any] = {
            "sources": list(self.sources),
            "used": self.used,
            "force_n": rounded(self.force_n),
            "estimates_n": {k: rounded(v) for k, v in self.estimates.items()},
            "tared": self.bias is not None,
        }
        if "sensor" in self.sources:
            age = now - self._sensor_t
            out["sensor"] = {
                "samples": self.sensor_samples,
                "refused": self.sensor_refused,
                "age_ms": round(age * 1e3, 1) if math.isfinite(age) else None,
                "last_error": self.sensor_last_error,
            }
        return out
