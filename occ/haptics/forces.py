"""Forces at the slave: what the instrument feels, from the drives' efforts or a force sensor.

The slave (``teleop-slave`` with ``force``) sends its tip force to the master on the return
channel (occ/haptics/returnlink.py, metadata ``force_n``, N in the patient frame). Two sources, used
in the configured order of preference (the first one healthy is sent; every one is in the
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
    occ/haptics/contact.py loads the ``sim`` drives, so this is a real estimate there too.
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
    counted. Six values are a 6-axis F/T sensor's wrench: the torques (N m, about the
    sensor's origin, scaled by the same prefix as the force: ``milliN`` gives mN m) are kept
    and rotated like the force (:attr:`SlaveForce.torque_nm`, ``torque_nm`` on the return
    channel).

The sensor as the German Heart Center used it (issue 37):

Weight compensation
    What hangs beyond the sensor (the instrument, its drive, the gripper: ``tool_mass_kg`` at
    ``tool_com_mm`` in the sensor's axes, the ``tip`` frame's) weighs on it at every pose. Each
    reading has that weight removed at the pose of the tick it arrives in: gravity
    (``gravity_mps2``, the robot's base frame) rotated into the sensor's frame by the robot's
    forward kinematics, ``F -= m g_s`` and, for a 6-axis sensor, ``T -= c x (m g_s)`` (the
    weight's moment about the sensor's origin).
Tare (``ForceTare``)
    The sensor's zero drifts (temperature, the strain gauges' creep), so its offset is taken at
    rest: the mean of the readings of the last ``tare_window_ms``, *after* the weight is
    removed, so that re-orienting the tool after a tare shows no phantom force (the weight is
    the model's, the offset is the sensor's). It is subtracted from every later reading. A tare
    is refused, with the reason, and nothing changes (the drives' bias neither), when the
    instrument is not at rest or could be touching something, because a tare in contact would
    hide a real force from then on: the tip moving faster than ``tare_max_speed_mm_s`` now or
    on average over the window; the simulated tissue touching it (simulation); the readings
    varying by more than ``tare_max_spread_n`` over the window (a force that changes is no
    offset); more than ``tare_max_offset_n`` left once the weight is removed (a load, or a
    wrong tool model, not a zero); too few readings (under 5, or over less than half the
    window: a silent sensor). The same command takes the drives' effort bias (``effort``).

Loop thread only; one estimate per return sample (the stream rate), not per tick.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from occ.events import Event, ForceReading

__all__ = ["SlaveForce", "TareRefused", "gravity_wrench", "sensor_wrench"]

Vec3 = tuple[float, float, float]
ZERO: Vec3 = (0.0, 0.0, 0.0)
#: SENSOR units taken as a force, with their factor to N
FORCE_UNITS = {"": 1.0, "N": 1.0, "milliN": 1e-3, "kiloN": 1e3}


class TareRefused(ValueError):
    """A tare that cannot be taken now: its text says why (the operator's reply)."""


def sensor_wrench(reading: Event) -> tuple[Vec3 | None, Vec3 | None, str]:
    """The wrench a SENSOR reading (occ/events.py) carries: ``(force N, torque N m or None,
    "")`` (torque None for 3 values), or ``(None, None, why not)`` as :func:`sensor_force`
    refuses; a torque that is not finite refuses the reading too (a 6-axis reading is one
    measurement)."""
    force, error = sensor_force(reading)
    if force is None:
        return None, None, error
    assert isinstance(reading, ForceReading)
    values = reading.values
    if len(values) != 6:
        return force, None, ""
    factor = FORCE_UNITS[reading.unit]
    torque = (values[3] * factor, values[4] * factor, values[5] * factor)
    if not all(math.isfinite(v) for v in torque):
        return None, None, f"not a torque: {tuple(values[3:6])}"
    return force, torque, ""


def gravity_wrench(
    mass_kg: float,
    com_m: Vec3,
    gravity: Vec3,
    frame: str,
    tip_rotation: np.ndarray,
    base_rotation: np.ndarray,
) -> tuple[Vec3, Vec3]:
    """The weight of what hangs beyond the sensor as the sensor reads it, in its reporting
    ``frame`` (``tip``, ``base`` or ``patient``): force ``m g_s`` and its moment about the
    sensor's origin ``c_s x m g_s``. ``com_m`` is in the tip's axes, ``gravity`` (m/s^2) in the
    robot's base frame, ``tip_rotation`` the tip's orientation in the base frame,
    ``base_rotation`` the base's in the patient frame."""
    g = np.asarray(gravity, dtype=float)
    c = np.asarray(com_m, dtype=float)
    if frame == "tip":
        gs, cs = tip_rotation.T @ g, c
    elif frame == "base":
        gs, cs = g, tip_rotation @ c
    else:
        gs, cs = base_rotation @ g, base_rotation @ (tip_rotation @ c)
    f = mass_kg * gs
    t = np.cross(cs, f)
    return (float(f[0]), float(f[1]), float(f[2])), (float(t[0]), float(t[1]), float(t[2]))


def _sub(a: Vec3, b: Vec3) -> Vec3:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def sensor_force(reading: Event) -> tuple[Vec3 | None, str]:
    """The force a SENSOR reading carries (N): ``(force, "")``, or ``(None, why not)`` for an
    input that is no SENSOR, not in newtons, of neither 3 nor 6 values, or not finite (in
    its unit or in N)."""
    if not isinstance(reading, ForceReading):
        return None, f"{reading.kind} is not a SENSOR"
    unit = reading.unit
    factor = FORCE_UNITS.get(unit)
    values = reading.values
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
        pose: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None,
        tool_mass_kg: float = 0.0,
        tool_com_m: Vec3 = ZERO,
        gravity: Vec3 = (0.0, 0.0, -9.81),
        tare_window_s: float = 0.1,
        tare_max_speed: float = 0.5e-3,
        tare_max_spread_n: float = 0.05,
        tare_max_offset_n: float = 1.0,
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
        #: the tip's pose in the base frame and the base's in the patient frame, now (the
        #: robot's forward kinematics): the weight is removed at the pose of each reading
        self._pose = pose
        self.tool_mass_kg = tool_mass_kg
        self.tool_com_m = tool_com_m
        self.gravity = gravity
        self.tare_window_s = tare_window_s
        self.tare_max_speed = tare_max_speed
        self.tare_max_spread_n = tare_max_spread_n
        self.tare_max_offset_n = tare_max_offset_n
        #: the last reading's torque with the weight removed (N m, sensor frame; None: 3 axes)
        self._sensor_torque: Vec3 | None = None
        #: the sensor's offset (its frame: force N, torque N m), taken by the last tare
        self.offset_n: Vec3 = ZERO
        self.offset_nm: Vec3 = ZERO
        #: the readings of the last tare window: (t, force, torque, tip position in m)
        self._window: deque[tuple[float, Vec3, Vec3 | None, Vec3]] = deque()
        #: the torque sent with the force (N m, patient frame, about the sensor's origin);
        #: None when the source used has none (3 axes, the effort estimate, the tissue)
        self.torque_nm: Vec3 | None = None
        self._torque: Vec3 | None = None
        self.tares = 0
        self.tares_refused = 0
        self.tare_last = ""
        self.tare_t: float | None = None
        self.tare_readings = 0

    # ------------------------------------------------------------------ sensor
    def on_input(self, event: Event, now: float) -> bool:
        """A discrete input: a SENSOR reading, if it is the configured one: True when taken
        (the controller passes every input on; this is where a SENSOR is read)."""
        if (
            not isinstance(event, ForceReading)
            or event.interface != self.sensor_interface
            or event.device != self.sensor_device
        ):
            return False
        force, torque, error = sensor_wrench(event)
        if force is None:
            self.sensor_refused += 1
            self.sensor_last_error = f"SENSOR {event.device!r}: {error}"
            return False
        tip, base = self._pose() if self._pose is not None else (np.eye(4), np.eye(4))
        if self.tool_mass_kg > 0.0:
            rt, rb = tip[:3, :3], base[:3, :3]
            m, c, g = self.tool_mass_kg, self.tool_com_m, self.gravity
            gf, gt = gravity_wrench(m, c, g, self.sensor_frame, rt, rb)
            force = _sub(force, gf)
            if torque is not None:
                torque = _sub(torque, gt)
        self._sensor = force
        self._sensor_torque = torque
        self._sensor_t = now
        window = self._window
        window.append((now, force, torque, (float(tip[0, 3]), float(tip[1, 3]), float(tip[2, 3]))))
        while window and window[0][0] < now - self.tare_window_s:
            window.popleft()
        self.sensor_samples += 1
        if self._sensor_alerted:
            self._sensor_alerted = False
            self._tell("STREAM", f"force sensor {self.sensor_device!r} back", 1)
        return True

    # ------------------------------------------------------------------ estimates
    def tare(self, effort: list[float]) -> None:
        """The efforts now are the bias (the tool touches nothing): :meth:`tare_all` checks
        that first."""
        self.bias = list(effort)

    def tare_all(
        self, now: float, effort: list[float], tip_speed: float, contact: str | None = None
    ) -> str:
        """``ForceTare``: the drives' bias and the sensor's offset (module docstring), or
        :class:`TareRefused` with the reason and nothing changed. ``tip_speed`` (m/s) is the
        tip's speed now, ``contact`` what touches the tool when something is known to (the
        simulated tissue), else None. Returns what was taken (the operator's reply)."""
        try:
            offset = self._check_tare(now, tip_speed, contact)
        except TareRefused as err:
            self.tares_refused += 1
            self.tare_last = str(err)
            raise
        parts = []
        if "effort" in self.sources:
            self.tare(effort)
            parts.append("effort bias [" + ", ".join(f"{v:.4g}" for v in effort) + "]")
        if offset is not None:
            (self.offset_n, torque, n) = offset
            self.offset_nm = torque if torque is not None else ZERO
            self.tare_readings = n
            text = "sensor offset [" + ", ".join(f"{v:.4f}" for v in self.offset_n) + "] N"
            if torque is not None:
                text += " [" + ", ".join(f"{v:.5f}" for v in torque) + "] N m"
            text += f" from {n} readings"
            if self.tool_mass_kg > 0.0:
                text += f", the tool's weight ({self.tool_mass_kg:g} kg) removed"
            parts.append(text)
        self.tares += 1
        self.tare_t = now
        self.tare_last = "taken: " + "; ".join(parts or ["nothing to tare"])
        return "force tare " + self.tare_last

    def _check_tare(
        self, now: float, tip_speed: float, contact: str | None
    ) -> tuple[Vec3, Vec3 | None, int] | None:
        """The sensor's offset a tare would take (None without a sensor source), or
        :class:`TareRefused`."""
        limit = self.tare_max_speed
        if not tip_speed <= limit:
            raise TareRefused(
                f"force tare refused: the instrument is moving (tip {tip_speed * 1e3:.2f} mm/s, "
                f"limit {limit * 1e3:g} mm/s)"
            )
        if contact is not None:
            raise TareRefused(
                f"force tare refused: the instrument is in contact ({contact}): a tare now "
                "would hide that force"
            )
        if "sensor" not in self.sources:
            return None
        span_s = self.tare_window_s
        readings = [r for r in self._window if r[0] >= now - span_s]
        n = len(readings)
        span = readings[-1][0] - readings[0][0] if readings else 0.0
        if n < 5 or span < 0.5 * span_s:
            raise TareRefused(
                f"force tare refused: the sensor {self.sensor_device!r} gave {n} readings over "
                f"{span * 1e3:.0f} ms of the last {span_s * 1e3:g} ms (at least 5, over half "
                "of it): it must be heard at rest"
            )
        first = np.array(readings[0][3])
        moved = max(float(np.linalg.norm(np.array(r[3]) - first)) for r in readings)
        if moved > limit * span_s:
            raise TareRefused(
                f"force tare refused: the instrument moved {moved * 1e3:.3f} mm in the last "
                f"{span_s * 1e3:g} ms (limit {limit * span_s * 1e3:.3g} mm: "
                f"{limit * 1e3:g} mm/s)"
            )
        forces = np.array([r[1] for r in readings])
        mean = forces.mean(axis=0)
        spread = float(np.linalg.norm(forces - mean, axis=1).max())
        if spread > self.tare_max_spread_n:
            raise TareRefused(
                f"force tare refused: the sensor's reading varied by {spread:.3f} N over the "
                f"last {span_s * 1e3:g} ms (limit {self.tare_max_spread_n:g} N): not at rest "
                "(a contact, a vibration)"
            )
        size = float(np.linalg.norm(mean))
        if size > self.tare_max_offset_n:
            weight = " once the tool's weight is removed" if self.tool_mass_kg > 0.0 else ""
            raise TareRefused(
                f"force tare refused: {size:.3f} N left{weight} (limit "
                f"{self.tare_max_offset_n:g} N): a load on the instrument, or a wrong tool "
                "model (mass, centre of mass), not the sensor's zero"
            )
        torque: Vec3 | None = None
        if all(r[2] is not None for r in readings):
            t = np.array([r[2] for r in readings]).mean(axis=0)
            torque = (float(t[0]), float(t[1]), float(t[2]))
        return (float(mean[0]), float(mean[1]), float(mean[2])), torque, n

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
        self.torque_nm = self._torque if used == "sensor" else None
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
        self._torque = None
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
        f = _sub(f, self.offset_n)
        t = self._sensor_torque
        if t is not None:
            t = _sub(t, self.offset_nm)
        if self.sensor_frame == "patient":
            self._torque = t
            return f
        rot = base[:3, :3] if self.sensor_frame == "base" else base[:3, :3] @ tip_rotation()
        v = rot @ np.array(f)
        if t is not None:
            w = rot @ np.array(t)
            self._torque = (float(w[0]), float(w[1]), float(w[2]))
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
            "tared": self.bias is not None or self.tares > 0,
            "torque_nm": rounded(self.torque_nm),
            "tare": {
                "taken": self.tares,
                "refused": self.tares_refused,
                "last": self.tare_last,
                "t": self.tare_t,
                "readings": self.tare_readings,
                "offset_n": rounded(self.offset_n),
                "offset_nm": rounded(self.offset_nm),
            },
        }
        if "sensor" in self.sources:
            age = now - self._sensor_t
            out["sensor"] = {
                "samples": self.sensor_samples,
                "refused": self.sensor_refused,
                "age_ms": round(age * 1e3, 1) if math.isfinite(age) else None,
                "last_error": self.sensor_last_error,
            }
            if self.tool_mass_kg > 0.0:
                out["tool"] = {
                    "mass_kg": self.tool_mass_kg,
                    "com_mm": [round(v * 1e3, 3) for v in self.tool_com_m],
                }
        return out
