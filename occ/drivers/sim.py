"""A simulated driver with real joint dynamics: the default driver everywhere.

Each joint is a rigid body on a viscous bearing, ``J * a = u - b * v``, so that tracking
error, settling time and saturation mean something in tests and demos. What drives it
depends on the command interface:

* ``position`` (default): an internal drive servo, evaluated at every integration substep
  (like a drive's fast inner loop), places the closed-loop poles at the configured bandwidth
  ``wn = 2*pi*bandwidth_hz`` and damping ratio ``zeta``:
  ``u = J*wn**2 * (r - x) - (2*zeta*wn*J - b) * v``, which gives
  ``x'' + 2*zeta*wn*x' + wn**2*x = wn**2*r``. The effort is clamped to the joint's
  ``limits.effort`` (a large step saturates, as on real hardware).
* ``effort``: the effort computed by the driver base with each joint's PID is applied
  directly, held constant between writes (zero-order hold).

Time is whatever ``now`` the loop passes to ``read``/``write``: the model advances from the
previous ``now`` to the new one. A servoed joint whose effort stays inside its limit is a
linear system, advanced in one exact step (its 2x2 transition matrix for that interval,
cached per interval length to 1 ns: the loop's period repeats). Where the effort would saturate or
the joint reach an end stop within the interval, and in the effort interface, the model
integrates with semi-implicit (symplectic) Euler instead, splitting the interval into equal
substeps no longer than ``max_substep`` (and short enough for the servo poles). The same
sequence of ``now`` values therefore gives bit-identical results under a real or a
simulated clock. A joint at rest with no effort is skipped.

Measurement: position gets optional Gaussian noise (``noise_std``, from a seeded
``random.Random``, so runs are deterministic) and is then quantised to ``encoder_resolution``;
velocity and effort are reported exactly (a drive reports its filtered estimates).

When not ACTIVE the servo is off; with ``brakes`` (default) the joints are locked, otherwise
they coast on their damping. Joints stop hard (velocity zeroed) at their position limits,
which stand in for the mechanical end stops.

Parameters (``params``; each per-joint value may be a scalar, a list in joint order, or a
mapping ``{joint_name: value}``):

====================  ==========================  ==========================================
key                   default                     meaning
====================  ==========================  ==========================================
command_interface     ``"position"``              ``"position"`` or ``"effort"``
inertia               0.01                        kg*m^2 (revolute) or kg (prismatic)
damping               0.1                         viscous, N*m*s/rad or N*s/m
bandwidth_hz          10.0                        internal servo natural frequency (position)
damping_ratio         1.0                         internal servo damping ratio (position)
encoder_resolution    2*pi/2**17 rad; 1e-6 m      quantum of measured position; 0 = exact
noise_std             0.0                         Gaussian noise on measured position
seed                  0                           noise seed (one stream per driver)
initial_positions     each joint's ``home``       where the joints start at ``configure``
max_substep           0.0005                      s, longest integration substep
brakes                True                        lock joints while not ACTIVE
effort_average_ms     0                           the reported effort is the mean over the
                                                  last intervals spanning this long (a drive's
                                                  filtered current); 0 = the effort at the end
                                                  of the last interval
faults                []                          hardware faults from the start: kinds of
                                                  :meth:`SimDriver.inject`, ``kind`` or
                                                  ``kind:joint`` (e.g. ``[activate]``, ``[nan:2]``)
period                0.001                       s, nominal loop period (driver base)
heartbeat_ms          50                          the simulated drive stops itself (brakes)
                                                  when not commanded for this long (base)
====================  ==========================  ==========================================

Heartbeat: the model is the drive. When the time between two commands (``write``) exceeds
``heartbeat_ms`` while ACTIVE, the drive follows the old command only up to the heartbeat
deadline, then brakes (velocity 0, position held) and latches "heartbeat lost", which the next
``read`` reports as a :class:`~occ.errors.DriverError` (FAULT in the base), exactly what a
frozen host would find when it comes back. ``reset`` clears it.

Hardware faults, injected (:meth:`SimDriver.inject`, for fault tests and operator training):
the simulated drive misbehaves as real drives do, and the base and the robot must catch it.

==============  ===============================================================================
kind            what the drive does
==============  ===============================================================================
configure       the next ``configure`` fails (the drive does not answer)
activate        every ``activate`` fails (the power stage does not come up)
hook            ``read`` raises an exception of no driver type (a bug in a hook)
write           every ``write`` fails (the command does not reach the drive)
heartbeat       commands stop reaching the drive: it stops itself at its heartbeat deadline
nan             joint ``joint`` reports NaN (from the start: a joint never measured)
frozen          every position stays where it was at injection (the model moves on)
jump            joint ``joint`` reports 20 % of its range further than it is
drift           joint ``joint``'s reading runs away from the truth at ``amount`` per second
                (default 0.1: 0.1 mm a tick on a prismatic joint) while the drive servos its
                true position: a runaway encoder whose drive still answers
slip            joint ``joint``'s reading is ``amount`` (default 0.5 mm or mrad) off the truth
                from now on: an encoder that slipped once
==============  ===============================================================================

A spec in ``faults`` is ``kind``, ``kind:joint`` or ``kind:joint:amount`` (``drift:2:0.5``).

:meth:`SimDriver.clear_faults` repairs the drive. Until then its ``reset`` fails naming the
fault, as a drive's fault reset does while the cause persists; once repaired it succeeds.
"""

from __future__ import annotations

import math
import random
from collections.abc import Mapping, Sequence
from typing import Any

from mypy_extensions import mypyc_attr

from occ.drivers.base import CommandInterface, Driver, LimitPolicy
from occ.drivers.sim_faults import FAULT_AMOUNTS, SIM_FAULTS, SimFaults, fault_specs
from occ.drivers.sim_model import (
    SIM_DEFAULTS,
    average_effort,
    distinct_poles,
    effort_substeps,
    exact_steps,
    position_substeps,
    sim_params,
)
from occ.errors import DriverError
from occ.joint import Joint

__all__ = ["SimDriver", "SIM_DEFAULTS", "SIM_FAULTS", "FAULT_AMOUNTS"]


@mypyc_attr(allow_interpreted_subclasses=True)  # mypyc: plugins extend built-ins
class SimDriver(Driver):
    """Simulated joints (see the module docstring for the model and the parameters)."""

    supported_interfaces = ("position", "effort")
    DEFAULT_PARAMS = SIM_DEFAULTS

    def __init__(
        self,
        name: str,
        joints: Sequence[Joint],
        params: Mapping[str, Any] | None = None,
        on_limit: LimitPolicy = "clamp",
        command_interface: CommandInterface | None = None,
    ) -> None:
        super().__init__(name, joints, params, on_limit, command_interface)
        p = self.params  # defaults merged, unknown keys refused by the base
        js = self.joints
        model = sim_params(p, js, self.command_interface)
        self._inertia = model.inertia
        self._damping = model.damping
        self._initial = model.initial
        self._kp = model.kp
        self._kd = model.kd
        self._substep = model.substep
        self._resolution = resolution = model.resolution
        self._encoders = list(enumerate(resolution))
        self._noise = noise = model.noise
        self._brakes = bool(p["brakes"])
        self._seed = p["seed"]
        self._rng = random.Random(self._seed)
        self._effort_limit = [j.limits.effort for j in js]
        self._lo = [j.limits.min for j in js]
        self._hi = [j.limits.max for j in js]
        # one tuple per joint, read by the integrator every tick (fewer look-ups on the loop)
        self._model = [
            (
                1.0 / self._inertia[i],
                self._damping[i],
                self._lo[i],
                self._hi[i],
                self._kp[i],
                self._kd[i],
                self._effort_limit[i],
            )
            for i in range(len(js))
        ]
        # the servoed joints' exact step, per joint (see _servo_steps)
        self._servoed = self.command_interface == "position"
        # ... with each joint's encoder quantum (0: exact), read in the same pass
        self._servo_model = [
            (self._kp[i], self._kd[i], self._effort_limit[i], self._lo[i], self._hi[i], res)
            for i, res in enumerate(resolution)
        ]
        self._exact_encoder = not any(noise) and not any(resolution)
        self._noisy = any(n > 0.0 for n in noise)
        # the common read: a servoed drive, no averaging, a noiseless encoder (see _read)
        self._plain = self._servoed and not self._noisy
        # exact steps of the servoed joints: e = x - r obeys e'' + c e' + k e = 0 while the
        # effort stays inside its limit (k = kp/J, c = (kd + b)/J)
        self._servo_poles = [
            (self._kp[i] / self._inertia[i], (self._kd[i] + self._damping[i]) / self._inertia[i])
            for i in range(len(js))
        ]
        self._set_poles(self._servo_poles)
        self._step_h = math.nan
        self._step: list[tuple[float, float, float, float]] = []
        self._avg_window = model.avg_window
        self._init_state()
        self._init_faults(p["faults"])

    def _init_state(self) -> None:
        """The model's state at construction: at its initial positions, off, no load."""
        n = len(self.joints)
        self._x = list(self._initial)
        self._v = [0.0] * n
        self._u = [0.0] * n  # applied effort
        self._cmd = [0.0] * n  # position target or effort command
        self._t = math.nan
        self._enabled = False
        #: the simulated world (occ/haptics/contact.py ``Environment``): ``efforts(q, qd)``, the
        #: joint efforts the tissue applies (None: none); set by the robot's assembly
        self.environment: Any = None
        #: the efforts it applied over the last interval
        self.external_effort = [0.0] * n
        #: the last intervals: (length, per joint the integral of the effort over it)
        self._effort_hist: list[tuple[float, list[float]]] = []
        self._effort_avg = [0.0] * n
        self._measured = [0.0] * n

    def _init_faults(self, faults: Any) -> None:
        """The drive's own heartbeat state and its hardware faults from the start (the
        ``faults`` parameter)."""
        self._last_cmd_t = math.nan  # model time of the last command (heartbeat)
        self._heartbeat_lost: str | None = None
        self._heartbeat_reported = False
        self.heartbeat_trips = 0
        self._fault_set = SimFaults(self.joints)
        #: injected faults: kind -> joint index (see :meth:`inject`); empty when healthy
        self._faults = self._fault_set.kinds
        for spec in fault_specs(faults):
            kind, _, rest = spec.partition(":")
            joint, _, amount = rest.partition(":")
            try:
                self.inject(kind, int(joint) if joint else 0, float(amount) if amount else None)
            except ValueError as err:
                raise ValueError(f"sim param 'faults': {err}") from None

    # ------------------------------------------------------------------ inspection
    @property
    def true_positions(self) -> list[float]:
        """The model's exact positions (not what the encoder reports); for tests and plots."""
        return list(self._x)

    @property
    def substep(self) -> float:
        """The integration substep actually used (s)."""
        return self._substep

    # ------------------------------------------------------------------ injected faults
    def inject(self, kind: str, joint: int = 0, amount: float | None = None) -> None:
        """Make the simulated drive fail as ``kind`` (``SIM_FAULTS``, the module docstring)
        from now on; ``joint`` (an index in this driver's joints) for nan, jump, drift and
        slip; ``amount`` for drift (per second) and slip (``FAULT_AMOUNTS`` by default)."""
        self._fault_set.inject(kind, joint, amount, self.name, self._measured, self._t)

    def clear_faults(self) -> None:
        """Repair the drive: no injected fault from now on."""
        self._faults.clear()

    def _injected(self, out: Sequence[float]) -> Sequence[float]:
        return self._fault_set.reading(out, self._t)

    # ------------------------------------------------------------------ hooks
    def _configure(self) -> None:
        if "configure" in self._faults:
            raise DriverError(f"sim driver {self.name!r}: simulated fault: no answer at configure")
        n = len(self.joints)
        self._x = list(self._initial)
        self._v = [0.0] * n
        self._u = [0.0] * n
        self._cmd = [0.0] * n
        self._t = math.nan
        self._enabled = False
        self._rng = random.Random(self._seed)

    def _activate(self) -> None:
        if "activate" in self._faults:
            raise DriverError(
                f"sim driver {self.name!r}: simulated fault: the power stage did not come up"
            )
        # Hold where we are: position target = current position, zero effort.
        if self.command_interface == "position":
            self._cmd[:] = self._x
        else:
            self._cmd[:] = [0.0] * len(self._cmd)
        # the heartbeat is watched from the first command on (as a CANopen consumer starts
        # with the first heartbeat it receives): activation may precede the loop's start
        self._last_cmd_t = math.nan
        self._enabled = True

    def _deactivate(self) -> None:
        self._enabled = False
        for i in range(len(self._u)):
            self._u[i] = 0.0
            if self._brakes:
                self._v[i] = 0.0

    def _safe_stop(self) -> None:
        # Another thread may be inside _advance: flags only, the model brakes from its
        # next step on.
        self._enabled = False

    def _following_model(self) -> tuple[Sequence[float], Sequence[float | None]] | None:
        # a PD servo trails a ramp by v (kd + b) / kp and gives way to a load by f / kp; half
        # as much again and one period of margin, for the zero-order hold between commands
        if self.command_interface != "position":
            return None
        lags = [
            1.5 * (self._kd[i] + self._damping[i]) / self._kp[i] + self.period
            for i in range(len(self.joints))
        ]
        return lags, list(self._kp)

    def _default_noise(self) -> Sequence[float] | None:
        return [r + 4.0 * s for r, s in zip(self._resolution, self._noise, strict=True)]

    def _reset(self) -> None:
        # a drive's fault reset does not clear while its cause persists (CiA 402: the fault
        # reset is refused while the fault condition remains): the simulated drive's own
        # diagnosis reports an injected fault until it is repaired (clear_faults)
        if self._faults:
            raise DriverError(
                f"sim driver {self.name!r}: fault persists ({', '.join(sorted(self._faults))})"
            )
        self._deactivate()
        self._heartbeat_lost = None
        self._heartbeat_reported = False

    def stats(self) -> dict[str, int]:
        out = super().stats()
        out["heartbeat_trips"] = self.heartbeat_trips
        return out

    def _shutdown(self) -> None:
        self._enabled = False

    def _read(self, now: float) -> tuple[Sequence[float], Sequence[float], Sequence[float]]:
        dt = now - self._t  # NaN before the first step
        if (
            self._plain
            and dt > 0.0
            and self._enabled
            and self.environment is None
            and not self._avg_window > 0.0
            and not now - self._last_cmd_t > self.heartbeat_s > 0.0
            and self._heartbeat_lost is None
        ):
            # the common interval (a servoed drive commanded within its heartbeat, no load, no
            # averaging, a noiseless encoder): what _advance and _integrate would choose, and
            # _servo_steps fills the encoders' reading as it steps
            self._t = now
            self._servo_steps(dt)
            if self._faults:
                return self._injected(self._measured), self._v, self._u
            return self._measured, self._v, self._u
        self._advance(now)
        if self._heartbeat_lost is not None and not self._heartbeat_reported:
            self._heartbeat_reported = True  # once: then positions are readable again
            raise DriverError(f"sim driver {self.name!r}: {self._heartbeat_lost}")
        out = self._measured
        effort = self._effort_avg if self._avg_window > 0.0 else self._u
        if self._exact_encoder:
            out[:] = self._x
        elif not self._noisy:  # the encoders' counts only (the shipped drives)
            x_all = self._x
            for i, res in self._encoders:
                x = x_all[i]
                out[i] = math.floor(x / res + 0.5) * res if res > 0.0 else x
        else:
            rng = self._rng
            for i, x in enumerate(self._x):
                sigma = self._noise[i]
                if sigma > 0.0:
                    x += rng.gauss(0.0, sigma)
                res = self._resolution[i]
                if res > 0.0:
                    x = math.floor(x / res + 0.5) * res
                out[i] = x
        if self._faults:
            return self._injected(out), self._v, effort
        return out, self._v, effort

    def _write(self, values: Sequence[float], now: float) -> None:
        if now != self._t:  # (a read at this now has advanced the model already)
            self._advance(now)  # the previous command acts until now (zero-order hold)
        if self._heartbeat_lost is not None:
            raise DriverError(f"sim driver {self.name!r}: {self._heartbeat_lost}")
        if self._faults:
            if "write" in self._faults:
                raise DriverError(f"sim driver {self.name!r}: simulated fault: write failed")
            if "heartbeat" in self._faults:
                return  # lost on the way: the drive's heartbeat deadline runs on
        cmd = self._cmd
        for i in range(len(cmd)):
            cmd[i] = values[i]
        self._last_cmd_t = now

    # ------------------------------------------------------------------ model
    def _advance(self, now: float) -> None:
        hb = self.heartbeat_s
        last = self._last_cmd_t
        if self._enabled and hb > 0.0 and last == last and now - last > hb:
            # the drive's own watchdog: the old command acts until the heartbeat deadline,
            # then the drive brakes and reports it
            stop_at = last + hb
            self._integrate(stop_at)
            self._deactivate()
            self.heartbeat_trips += 1
            self._heartbeat_lost = (
                f"heartbeat lost: no command for {(now - last) * 1e3:.1f} ms (limit "
                f"{hb * 1e3:.1f} ms); the drive stopped itself"
            )
        self._integrate(now)

    def _exact_steps(self, h: float) -> list[tuple[float, float, float, float]]:
        """Per joint, the transition matrix over ``h`` of its exact step
        (:func:`~occ.drivers.sim_model.exact_steps`). Cached for the last ``h``."""
        out = exact_steps(self._servo_distinct, h)
        # joints with the same poles share one step (one computed for all: the shipped arms)
        out = out * self._n if self._one_pole else [out[j] for j in self._servo_which]
        self._step_h = h
        self._step = out
        return out

    def _set_poles(self, poles: Sequence[tuple[float, float]]) -> None:
        """The poles ``(k, c)`` of each joint's exact step (``e'' + c e' + k e = 0``): what of
        the step does not depend on its length, computed once per distinct pair
        (:meth:`_exact_steps` then computes one step per distinct pair)."""
        self._servo_which, self._servo_distinct = distinct_poles(poles)
        self._one_pole = len(self._servo_distinct) == 1
        self._n = len(poles)

    def _integrate(self, now: float) -> None:
        t = self._t
        if t != t:  # first call: the model starts at this instant
            self._t = now
            return
        dt = now - t
        if dt <= 0.0:
            return  # a repeated (or backwards) time does not move the model
        self._t = now
        if (
            self._enabled
            and self._servoed
            and self.environment is None
            and not self._avg_window > 0.0
        ):
            self._servo_steps(dt)
        else:
            self._integrate_joints(dt, range(len(self._x)))

    def _servo_steps(self, dt: float) -> None:
        """The common interval: a servoed drive, no load, no averaging. Each joint takes one
        exact step when its effort stays inside the limit and no end stop is reached, else
        :meth:`_integrate_joints` integrates that joint (the joints are independent). The
        noiseless encoders' reading of the new positions goes to ``_measured`` on the way
        (what :meth:`_read` reports; a noisy encoder's is drawn there instead)."""
        step = self._step if -1e-9 < dt - self._step_h < 1e-9 else self._exact_steps(dt)
        x_all, v_all, u_all, cmd, out = self._x, self._v, self._u, self._cmd, self._measured
        for i, (kp, kd, ulim, lo, hi, res) in enumerate(self._servo_model):
            r = cmd[i]
            e = x_all[i] - r
            v = v_all[i]
            u = -kp * e - kd * v
            if -ulim <= u <= ulim:
                a11, a12, a21, a22 = step[i]
                e1 = a11 * e + a12 * v
                v1 = a21 * e + a22 * v
                u1 = -kp * e1 - kd * v1
                x1 = r + e1
                if -ulim <= u1 <= ulim and lo <= x1 <= hi:
                    x_all[i] = x1
                    v_all[i] = v1
                    u_all[i] = u1
                    out[i] = math.floor(x1 / res + 0.5) * res if res > 0.0 else x1
                    continue
            self._integrate_joints(dt, (i,))
            x1 = x_all[i]
            out[i] = math.floor(x1 / res + 0.5) * res if res > 0.0 else x1

    def _load(self) -> Any:
        """The world's load on the joints now (None: no world), held over the interval
        (zero-order hold, as the commands) and shown in ``external_effort``."""
        env = self.environment
        ext = self.external_effort
        tau = env.efforts(self._x, self._v) if env is not None else None
        if tau is not None:
            ext[:] = tau
        elif env is not None:
            for i in range(len(ext)):
                ext[i] = 0.0
        return tau

    def _integrate_joints(self, dt: float, joints: Sequence[int]) -> None:
        """Every case, for ``joints``: a load, averaging, saturation, end stops, the effort
        interface, a drive off (the exact step where it holds, substeps otherwise)."""
        # at least one: an interval shorter than 1e-9 substeps (the heartbeat deadline a
        # rounding error after the last step) once divided by zero here
        steps = max(1, math.ceil(dt / self._substep - 1e-9))
        h = dt / steps
        enabled = self._enabled
        position_mode = self.command_interface == "position"
        brakes = self._brakes
        x_all, v_all, u_all, cmd = self._x, self._v, self._u, self._cmd
        step_h = self._step_h
        step = self._step
        tau = self._load()
        averaging = self._avg_window > 0.0
        integral = [0.0] * len(x_all) if averaging else x_all  # (unused when not averaging)
        model = self._model
        for i in joints:
            inv_j, b, lo, hi, kp, kd, ulim = model[i]
            x = x_all[i]
            v = v_all[i]
            te = tau[i] if tau is not None else 0.0
            if averaging:
                # the effort's integral over the interval from the momentum balance
                # (J dv = (u + te - b v) dt): exact whichever branch integrates it
                x0, v0 = x, v
            if not enabled:
                u_all[i] = 0.0
                if brakes or (v == 0.0 and te == 0.0):
                    v_all[i] = 0.0
                    continue
            if enabled and position_mode:
                r = cmd[i]
                # a constant load moves the servo's equilibrium by te / kp: the exact step is
                # taken about it, the motor's effort still about the command
                r_eq = r + te / kp
                e = x - r_eq
                u = -kp * (x - r) - kd * v
                if -ulim <= u <= ulim:
                    # the linear regime: one exact step, kept when the effort stays inside
                    # its limit at the end and no end stop is reached
                    if not -1e-9 < dt - step_h < 1e-9:  # 1 ns: summed float time jitters
                        step_h = dt
                        step = self._exact_steps(dt)
                    a11, a12, a21, a22 = step[i]
                    e1 = a11 * e + a12 * v
                    v1 = a21 * e + a22 * v
                    x1 = r_eq + e1
                    u1 = -kp * (x1 - r) - kd * v1
                    if -ulim <= u1 <= ulim and lo <= x1 <= hi:
                        x_all[i] = x1
                        v_all[i] = v1
                        u_all[i] = u1
                        if averaging:
                            integral[i] = (v1 - v0) / inv_j + b * (x1 - x0) - te * dt
                        continue
                x, v, u = position_substeps(model[i], x, v, r, te, steps, h)
            else:
                u = cmd[i] if enabled else 0.0
                x, v = effort_substeps(model[i], x, v, u, te, steps, h)
            if averaging:
                # an end stop zeroes v: the stop's impulse is not the motor's, so the balance
                # is taken only without one; the stop's interval reports its last effort
                stopped = x <= lo or x >= hi
                if enabled and not stopped:
                    integral[i] = (v - v0) / inv_j + b * (x - x0) - te * dt
                else:
                    integral[i] = u * dt if enabled else 0.0
            x_all[i] = x
            v_all[i] = v
            u_all[i] = u
        if averaging:
            average_effort(self._effort_hist, self._avg_window, dt, integral, self._effort_avg)
