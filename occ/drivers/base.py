"""The driver base class: lifecycle, state checks and limit checks for every backend.

Modelled on python-can's ``BusABC`` (the base does the generic work; a backend overrides only
narrow private hooks) and on the ros2_control hardware lifecycle::

    UNCONFIGURED --configure()--> INACTIVE --activate()--> ACTIVE
         ^                          |   ^                    |
         |                          |   +---deactivate()-----+
         |                          |
         +--(reset, never configured)--- FAULT <--(hook error, limit with on_limit='fault')
                                         |
                                         +--reset()--> INACTIVE
    any state --shutdown()--> SHUTDOWN   (idempotent; also via the context manager)

* INACTIVE: states are readable (``read``), commands are refused.
* ACTIVE: commands are accepted (``write``).
* FAULT: latched until :meth:`Driver.reset`; entering it from ACTIVE calls the backend's
  ``_deactivate`` hook (best effort) so the hardware stops following commands.

Every command goes through :meth:`Driver.write`, which checks position limits and the
velocity limit (step from the previous accepted setpoint divided by the elapsed time) for
every joint. Policy ``on_limit='clamp'`` clamps and counts (``limit_events``);
``on_limit='fault'`` latches FAULT and raises :class:`~occ.errors.LimitError`. A non-finite
setpoint always faults: there is nothing sensible to clamp it to.

Backends implement::

    _configure()                       open the hardware / allocate the model
    _activate()                        enable power stages; hold the current position
    _deactivate()                      stop following commands (brakes/hold)
    _shutdown()                        release the hardware; must tolerate partial setup
    _read(now) -> (pos, vel, eff)      sequences of floats, one per joint, SI units
    _write(values, now)                position setpoints or efforts, by command_interface

Two more duties, because the loop itself can fail (see docs/ARCHITECTURE.md, "Safety"):

- **Device-side heartbeat.** Every driver takes the parameter ``heartbeat_ms`` (default 50;
  0 or null = off). From its first command on, the *device* must stop itself (hold, brakes
  on) when it has not been commanded for that long while ACTIVE, as dVRK's FPGA watchdog
  and a CANopen heartbeat consumer do, and report it: the next ``read`` raises
  :class:`~occ.errors.DriverError` ("heartbeat lost"), which latches FAULT. This is what
  still protects the patient when the whole process is frozen. ``sim`` and the CAN drive
  simulator implement it; a backend for hardware that cannot must say so in its
  documentation.
- **Safe stop from another thread.** :meth:`Driver.safe_stop` is called by the supervisor
  while the loop thread may be hung inside a tick. It calls the ``_safe_stop`` hook (default:
  ``_deactivate``), which must put the hardware in its safe state at once and be safe to call
  while the loop thread is inside ``_read`` or ``_write``; the driver then latches FAULT, so a
  ``write`` from the resumed loop is refused until :meth:`Driver.reset`.

Feedback checks (every ``read``, in the base, so every backend has them): a joint's position
is its feedback, and feedback can fail while the drive still answers.

- **Lost**: a non-finite position (NaN, inf) from a joint that has been measured latches
  FAULT ("feedback lost"). Before the first measurement NaN means "not reported yet": the
  joint stays unmeasured, and Enable is refused until it is measured.
- **Jump**: a step larger than ``feedback_jump`` (default 10) times the joint's velocity limit
  over the time since its last reading (at least one ``period``) latches FAULT: no healthy
  joint moves that fast; a slipped encoder or a corrupted frame does. (The velocity limit
  bounds the commands, not the motion: a servo catching up after a stall of the loop moves
  faster for a moment; 3 x tripped on a busy machine after a 50 ms stall.) 0 = off.
- **Frozen**: while ACTIVE on position commands, a joint whose reported position has not
  changed at all for ``frozen_feedback_ms`` (default 50) while its command is further than
  ``FROZEN_AWAY`` from it (5 mrad, 0.5 mm) latches FAULT: the drive answers, the heartbeat
  lives, but the encoder is stuck. 0 = off.

The hooks receive ``now`` (seconds on the loop's clock) because a simulated driver integrates
its dynamics over exactly those times, which makes a simulated-clock run reproducible.
``values`` passed to ``_write`` is a buffer the base reuses every tick: copy it if needed.
"""

from __future__ import annotations

import enum
import logging
import math
import threading
from collections.abc import Mapping, Sequence
from types import TracebackType
from typing import Any, ClassVar, Literal

from mypy_extensions import mypyc_attr

from occ.errors import DriverError, LimitError, OCCError, StateError, caused
from occ.joint import Joint

__all__ = ["Driver", "DriverState", "CommandInterface", "LimitPolicy"]

logger = logging.getLogger(__name__)

CommandInterface = Literal["position", "effort"]
LimitPolicy = Literal["clamp", "fault"]
_INTERFACES = ("position", "effort")
_POLICIES = ("clamp", "fault")

#: Parameters every driver takes (the base reads them), whatever its own DEFAULT_PARAMS say:
#: the device heartbeat, and the feedback checks (see "Feedback checks" in the docstring).
BASE_PARAMS: dict[str, Any] = {
    "heartbeat_ms": 50.0,
    "feedback_jump": 10.0,
    "frozen_feedback_ms": 50.0,
}

#: How far (rad, m) the command must be from a joint that has not moved at all for
#: ``frozen_feedback_ms`` before its feedback is called frozen: far beyond the tracking lag of
#: a healthy servo at the velocity limits, so a joint holding still never trips it.
FROZEN_AWAY = {"revolute": 0.005, "prismatic": 0.0005}

# Relative slack on the velocity check, so that a setpoint moving at exactly the limit is not
# flagged because of float rounding in (x - prev) / dt.
_VEL_SLACK = 1e-9


class DriverState(enum.Enum):
    """Lifecycle state of a driver (ros2_control names plus FAULT and SHUTDOWN)."""

    UNCONFIGURED = "unconfigured"
    INACTIVE = "inactive"
    ACTIVE = "active"
    FAULT = "fault"
    SHUTDOWN = "shutdown"


@mypyc_attr(allow_interpreted_subclasses=True)  # mypyc: plugins and tests subclass it
class Driver:
    """Base class of all joint drivers (see the module docstring for the contract).

    ``params`` is the backend's free-form parameter mapping from the config; the base reads
    only ``command_interface`` (if the ``command_interface`` argument is None) and ``period``
    (the nominal loop period in seconds, default 0.001, used for the velocity check and the
    servo ``dt`` of the first write after activation, when no previous write exists).
    """

    #: What the hardware takes: position setpoints, or efforts computed by the joints' PIDs.
    command_interface: CommandInterface = "position"
    #: The interfaces a backend can accept; a subclass narrows this if it must.
    supported_interfaces: ClassVar[tuple[str, ...]] = ("position",)
    #: A backend's parameters and their defaults. When set, the base refuses unknown keys
    #: (a typo in the YAML must not be silently ignored) and ``self.params`` holds the defaults
    #: merged with the configured values.
    DEFAULT_PARAMS: ClassVar[Mapping[str, Any] | None] = None

    def __init__(
        self,
        name: str,
        joints: Sequence[Joint],
        params: Mapping[str, Any] | None = None,
        on_limit: LimitPolicy = "clamp",
        command_interface: CommandInterface | None = None,
    ) -> None:
        if not joints:
            raise ValueError(f"driver {name!r}: needs at least one joint")
        if on_limit not in _POLICIES:
            raise ValueError(f"driver {name!r}: on_limit must be one of {_POLICIES}")
        params = dict(params or {})
        if self.DEFAULT_PARAMS is not None:
            known = set(self.DEFAULT_PARAMS) | set(BASE_PARAMS)
            unknown = set(params) - known
            if unknown:
                raise ValueError(
                    f"driver {name!r} ({type(self).__name__}): unknown params "
                    f"{sorted(unknown)}; known: {sorted(known)}"
                )
            params = {**BASE_PARAMS, **self.DEFAULT_PARAMS, **params}
        else:
            params = {**BASE_PARAMS, **params}
        heartbeat = params["heartbeat_ms"]
        try:
            heartbeat_s = 0.0 if heartbeat is None else float(heartbeat) * 1e-3
        except (TypeError, ValueError):
            heartbeat_s = math.nan
        if not heartbeat_s >= 0.0:
            raise ValueError(
                f"driver {name!r}: heartbeat_ms must be a number >= 0 (0 = off), got {heartbeat!r}"
            )
        checks: list[float] = []
        for key in ("feedback_jump", "frozen_feedback_ms"):
            raw = params[key]
            try:
                value = 0.0 if raw is None else float(raw)
            except (TypeError, ValueError):
                value = math.nan
            if not value >= 0.0:
                raise ValueError(
                    f"driver {name!r}: {key} must be a number >= 0 (0 = off), got {raw!r}"
                )
            checks.append(value)
        interface = command_interface or params.get("command_interface") or self.command_interface
        if interface not in _INTERFACES or interface not in self.supported_interfaces:
            raise ValueError(
                f"driver {name!r} ({type(self).__name__}): command_interface {interface!r} not "
                f"supported; choose one of {self.supported_interfaces}"
            )
        period = float(params.get("period", 0.001))
        if not period > 0.0:
            raise ValueError(f"driver {name!r}: period must be > 0, got {period}")
        names = [j.name for j in joints]
        if len(set(names)) != len(names):
            raise ValueError(f"driver {name!r}: duplicate joint names {names}")
        #: joints whose effort would come from a PID without gains: position setpoints
        #: (:meth:`write`) are refused for them; direct efforts (:meth:`write_effort`, a haptic
        #: master's force) need none
        self.missing_gains: list[str] = (
            [j.name for j in joints if j.gains is None] if interface == "effort" else []
        )

        self.name: str = name
        self.joints: list[Joint] = list(joints)
        self.params: dict[str, Any] = params
        self.on_limit: LimitPolicy = on_limit
        self.command_interface = interface  # instance attribute shadows the class default
        self.period: float = period
        #: the device stops itself when not commanded for this long while ACTIVE (0 = off)
        self.heartbeat_s: float = heartbeat_s
        # feedback checks: per joint (max speed for a plausible step, distance for "frozen")
        self._jump_speed = [checks[0] * j.limits.velocity for j in joints]
        self._frozen_s = checks[1] * 1e-3
        self._frozen_away = [FROZEN_AWAY.get(j.type, 0.005) for j in joints]
        self._changed_at = [math.nan] * len(joints)
        self._safe_lock = threading.Lock()
        self._safe_stops = 0
        self._state: DriverState = DriverState.UNCONFIGURED
        self._configured: bool = False
        self._fault_reason: str | None = None
        n = len(self.joints)
        # Preallocated per-tick buffers: write() never allocates lists.
        self._values: list[float] = [0.0] * n
        self._limit_table: list[tuple[Joint, float, float, float]] = []
        self._prev_setpoint: list[float] = [0.0] * n
        self._prev_write_time: float = math.nan
        self._reads: int = 0
        self._writes: int = 0
        self._limit_events: int = 0
        self._errors: int = 0

    # ------------------------------------------------------------------ properties
    @property
    def state(self) -> DriverState:
        """The current lifecycle state."""
        return self._state

    @property
    def fault_reason(self) -> str | None:
        """Why the driver is in FAULT (None otherwise)."""
        return self._fault_reason if self._state is DriverState.FAULT else None

    @property
    def joint_names(self) -> list[str]:
        """Joint names in command/measurement order."""
        return [j.name for j in self.joints]

    def stats(self) -> dict[str, int]:
        """Counters since construction: reads, writes, limit_events, errors, safe_stops."""
        return {
            "reads": self._reads,
            "writes": self._writes,
            "limit_events": self._limit_events,
            "errors": self._errors,
            "safe_stops": self._safe_stops,
        }

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}({self.name!r}, joints={self.joint_names}, "
            f"state={self._state.value}, interface={self.command_interface})"
        )

    # ------------------------------------------------------------------ lifecycle
    def configure(self) -> None:
        """UNCONFIGURED -> INACTIVE: open the hardware; states become readable."""
        self._require((DriverState.UNCONFIGURED,), "configure")
        self._call_hook(self._configure, "configure")
        self._configured = True
        self._transition(DriverState.INACTIVE)

    def activate(self) -> None:
        """INACTIVE -> ACTIVE: commands are accepted from now on.

        Servo memories and the previous setpoint are cleared, so the first write after
        activation is velocity-checked against the *measured* position (if any) over one
        nominal period: activation never becomes a jump.
        """
        self._require((DriverState.INACTIVE,), "activate")
        for joint in self.joints:
            joint.reset_servo()
        self._prev_write_time = math.nan
        self._changed_at = [math.nan] * len(self.joints)  # frozen: watched from the next read
        # the limits as plain floats, read by every write (fewer look-ups on the loop)
        self._limit_table = [
            (j, j.limits.min, j.limits.max, j.limits.velocity * (1.0 + _VEL_SLACK))
            for j in self.joints
        ]
        self._call_hook(self._activate, "activate")
        self._transition(DriverState.ACTIVE)

    def deactivate(self) -> None:
        """ACTIVE -> INACTIVE: stop accepting commands; states stay readable."""
        self._require((DriverState.ACTIVE,), "deactivate")
        self._call_hook(self._deactivate, "deactivate")
        self._transition(DriverState.INACTIVE)

    def reset(self) -> None:
        """Clear a latched FAULT: back to INACTIVE (or UNCONFIGURED if never configured)."""
        self._require((DriverState.FAULT,), "reset")
        self._call_hook(self._reset, "reset")
        for joint in self.joints:
            joint.reset_servo()
        self._prev_write_time = math.nan
        logger.info("driver %s: fault reset (was: %s)", self.name, self._fault_reason)
        self._fault_reason = None
        self._transition(DriverState.INACTIVE if self._configured else DriverState.UNCONFIGURED)

    def safe_stop(self, reason: str) -> None:
        """From any thread, at once: the hardware to its safe state, the driver latched FAULT.

        For a supervisor that found the loop thread hung (possibly inside this driver's
        ``read`` or ``write``). Idempotent; never raises (a failing hook is logged and
        counted: the driver is latched FAULT anyway). Only an ACTIVE driver has anything to
        stop: an INACTIVE one is already holding with its power stages off.
        """
        with self._safe_lock:
            if self._state is not DriverState.ACTIVE:
                return
            self._safe_stops += 1
            try:
                self._safe_stop()
            except Exception:  # noqa: BLE001 - the caller is a supervisor: it must go on
                self._errors += 1
                logger.exception("driver %s: safe stop failed", self.name)
            self._fault_reason = f"safe stop: {reason}"
            logger.error("driver %s: FAULT: %s", self.name, self._fault_reason)
            self._transition(DriverState.FAULT)

    def shutdown(self) -> None:
        """Release the hardware from any state; safe to call twice.

        Hook errors are counted and re-raised as one :class:`DriverError` after the state
        has become SHUTDOWN, so a failing shutdown never leaves the driver half alive.
        """
        if self._state is DriverState.SHUTDOWN:
            return
        first_error: BaseException | None = None
        if self._state is DriverState.ACTIVE:
            try:
                self._deactivate()
            except Exception as err:  # noqa: BLE001 - keep shutting down
                self._errors += 1
                first_error = err
        if self._configured:
            try:
                self._shutdown()
            except Exception as err:  # noqa: BLE001
                self._errors += 1
                first_error = first_error or err
        self._transition(DriverState.SHUTDOWN)
        if first_error is not None:
            failed = DriverError(f"driver {self.name!r}: shutdown failed: {first_error}")
            raise caused(failed, first_error) from first_error

    def __enter__(self) -> Driver:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.shutdown()

    def __del__(self) -> None:
        # Like python-can's leaked-bus warning: a configured driver nobody shut down may still
        # hold hardware. getattr because __init__ may have failed half way.
        if getattr(self, "_configured", False) and getattr(self, "_state", None) not in (
            DriverState.SHUTDOWN,
            None,
        ):
            logger.warning("driver %s was not shut down properly", getattr(self, "name", "?"))

    # ------------------------------------------------------------------ I/O
    def read(self, now: float) -> None:
        """Update every joint's measured state from the hardware (INACTIVE, ACTIVE or FAULT).

        Reading is allowed in FAULT when the driver was configured, so operators still see
        where the robot is; a hook error latches FAULT and raises :class:`DriverError`.
        """
        state = self._state
        if state is not DriverState.ACTIVE and state is not DriverState.INACTIVE:
            if not (state is DriverState.FAULT and self._configured):
                raise StateError(f"driver {self.name!r}: cannot read in state {state.value}")
        try:
            positions, velocities, efforts = self._read(now)
        except Exception as err:
            raise self._hook_failed("read", err) from err
        jump = self._jump_speed
        changed = self._changed_at
        period = self.period
        frozen_s = self._frozen_s if state is DriverState.ACTIVE else 0.0
        if self.command_interface == "effort":
            frozen_s = 0.0  # the hand, not a servo, moves an effort-driven joint
        for i, joint in enumerate(self.joints):
            x = positions[i]
            if x - x != 0.0:  # NaN or inf (math.isfinite without a call)
                if joint.measured:
                    self._feedback_fault(f"joint {joint.name}: feedback lost (position {x})")
                continue  # not reported yet: the joint stays unmeasured
            if joint.measured:
                prev = joint.position
                if x != prev:
                    changed[i] = now
                    step = x - prev if x > prev else prev - x
                    dt = now - joint.stamp
                    if dt < period:
                        dt = period
                    if jump[i] > 0.0 and step > jump[i] * dt:
                        self._feedback_fault(
                            f"joint {joint.name}: feedback jump of {step:.6g} in "
                            f"{dt * 1e3:.3g} ms (at most {jump[i] * dt:.6g}: "
                            f"{self.params['feedback_jump']} x the velocity limit)"
                        )
                elif frozen_s > 0.0:
                    since = changed[i]
                    if since != since:
                        changed[i] = now
                    elif now - since > frozen_s:
                        away = joint.command_position - x
                        if away > self._frozen_away[i] or -away > self._frozen_away[i]:
                            self._feedback_fault(
                                f"joint {joint.name}: feedback frozen at {x:.6g} for "
                                f"{(now - since) * 1e3:.0f} ms while commanded {away:+.6g} away"
                            )
            # Joint.set_measured, inlined: this runs for every joint every tick
            joint.position = x
            joint.velocity = velocities[i]
            joint.effort = efforts[i]
            joint.measured = True
            joint.stamp = now
        self._reads += 1

    def write(self, setpoints: Sequence[float], now: float) -> None:
        """Command one position setpoint per joint (ACTIVE only), limit-checked.

        The velocity limit applies to the step from the previous accepted setpoint over
        ``now - previous now`` (a second write at the same ``now`` may not move). On the first
        write after activation the reference is the measured position over one ``period``.
        """
        if self._state is not DriverState.ACTIVE:
            raise StateError(f"driver {self.name!r}: commands refused in state {self._state.value}")
        if self.missing_gains:
            raise ValueError(
                f"driver {self.name!r}: effort interface needs PID gains on joints "
                f"{self.missing_gains} to take position setpoints"
            )
        joints = self.joints
        n = len(joints)
        if len(setpoints) != n:
            raise ValueError(f"driver {self.name!r}: expected {n} setpoints, got {len(setpoints)}")
        prev_time = self._prev_write_time
        first = prev_time != prev_time  # NaN: no write since activation
        dt = self.period if first else now - prev_time
        if dt < 0.0:
            dt = 0.0
        prev = self._prev_setpoint
        values = self._values
        effort = self.command_interface == "effort"
        clamp = self.on_limit == "clamp"
        for i, (joint, lo, hi, vmax) in enumerate(self._limit_table):
            x = float(setpoints[i])
            if x - x != 0.0:  # inf or NaN (math.isfinite without a call: every joint, every tick)
                self._fault(LimitError(f"driver {self.name!r}: joint {joint.name}: setpoint {x}"))
            if x < lo or x > hi:
                if not clamp:
                    self._fault(
                        LimitError(
                            f"driver {self.name!r}: joint {joint.name}: position {x:.6g} outside "
                            f"limits [{lo:.6g}, {hi:.6g}]"
                        )
                    )
                x = lo if x < lo else hi
                self._limit_events += 1
            if first:
                ref = joint.position if joint.measured else math.nan
            else:
                ref = prev[i]
            if ref == ref:
                step = x - ref
                reach = vmax * dt
                if step > reach or -step > reach:
                    if not clamp:
                        speed = abs(step) / dt if dt > 0.0 else math.inf
                        self._fault(
                            LimitError(
                                f"driver {self.name!r}: joint {joint.name}: velocity {speed:.6g} "
                                f"exceeds limit {joint.limits.velocity:.6g} (setpoint {x:.6g})"
                            )
                        )
                    max_step = joint.limits.velocity * dt
                    x = ref + max_step if step > 0.0 else ref - max_step
                    self._limit_events += 1
            prev[i] = x
            joint.command_position = x
            values[i] = joint.servo(x, dt) if effort else x
        self._prev_write_time = now
        try:
            self._write(values, now)
        except Exception as err:
            raise self._hook_failed("write", err) from err
        self._writes += 1

    def write_effort(self, efforts: Sequence[float], now: float) -> None:
        """Command one effort per joint directly (N for prismatic joints, N m for revolute
        ones; ACTIVE only, ``command_interface`` effort): the effort command interface of a
        haptic master, whose controller computes the force to display. Each effort is clamped
        to its joint's effort limit (counted in ``limit_events``); a non-finite one faults.
        No PID and no position checks: the hand, not the drive, decides where the joint goes.
        """
        if self._state is not DriverState.ACTIVE:
            raise StateError(f"driver {self.name!r}: commands refused in state {self._state.value}")
        if self.command_interface != "effort":
            raise StateError(
                f"driver {self.name!r}: takes {self.command_interface} commands, not efforts"
            )
        joints = self.joints
        n = len(joints)
        if len(efforts) != n:
            raise ValueError(f"driver {self.name!r}: expected {n} efforts, got {len(efforts)}")
        values = self._values
        for i, joint in enumerate(joints):
            u = float(efforts[i])
            if not math.isfinite(u):
                self._fault(LimitError(f"driver {self.name!r}: joint {joint.name}: effort {u}"))
            lim = joint.limits.effort
            if u > lim or u < -lim:
                u = lim if u > 0.0 else -lim
                self._limit_events += 1
            joint.command_effort = u
            values[i] = u
        # the hand moved the joints: the next position setpoint is checked against where they
        # are measured (as after activation), not against the setpoint before these efforts
        self._prev_write_time = math.nan
        try:
            self._write(values, now)
        except Exception as err:
            raise self._hook_failed("write", err) from err
        self._writes += 1

    # ------------------------------------------------------------------ hooks
    def _configure(self) -> None:
        """Open the hardware (override)."""

    def _activate(self) -> None:
        """Enable the power stages and hold the current position (override)."""

    def _deactivate(self) -> None:
        """Stop following commands; brake or hold (override)."""

    def _reset(self) -> None:
        """Clear a hardware fault if the backend can (override; default does nothing)."""

    def _safe_stop(self) -> None:
        """Put the hardware in its safe state now, from another thread (override if
        ``_deactivate`` is not safe to call while the loop thread is inside a hook)."""
        self._deactivate()

    def _shutdown(self) -> None:
        """Release the hardware (override)."""

    def _read(self, now: float) -> tuple[Sequence[float], Sequence[float], Sequence[float]]:
        """Return (positions, velocities, efforts), one float per joint, SI units."""
        raise NotImplementedError

    def _write(self, values: Sequence[float], now: float) -> None:
        """Send position setpoints or efforts (by ``command_interface``) to the hardware."""
        raise NotImplementedError

    # ------------------------------------------------------------------ internals
    def _require(self, allowed: tuple[DriverState, ...], action: str) -> None:
        if self._state not in allowed:
            raise StateError(
                f"driver {self.name!r}: cannot {action} in state {self._state.value}"
                + (f" ({self._fault_reason}); reset() first" if self._fault_reason else "")
            )

    def _transition(self, new: DriverState) -> None:
        old = self._state
        self._state = new
        logger.info("driver %s: %s -> %s", self.name, old.value, new.value)

    def _call_hook(self, hook: Any, action: str) -> None:
        try:
            hook()
        except Exception as err:
            raise self._hook_failed(action, err) from err

    def _hook_failed(self, action: str, err: Exception) -> OCCError:
        """Count, latch FAULT and return the error to raise (DriverErrors pass through)."""
        self._errors += 1
        wrapped: OCCError
        if isinstance(err, OCCError):
            wrapped = err
        else:
            wrapped = caused(DriverError(f"driver {self.name!r}: {action} failed: {err!r}"), err)
        self._enter_fault(str(wrapped))
        return wrapped

    def _feedback_fault(self, what: str) -> None:
        """Latch FAULT for feedback that cannot be trusted and raise it."""
        self._errors += 1
        err = DriverError(f"driver {self.name!r}: {what}")
        self._enter_fault(str(err))
        raise err

    def _fault(self, err: LimitError) -> None:
        """Latch FAULT for a limit violation and raise it."""
        self._enter_fault(str(err))
        raise err

    def _enter_fault(self, reason: str) -> None:
        if self._state is DriverState.SHUTDOWN:
            return
        was_active = self._state is DriverState.ACTIVE
        if self._state is not DriverState.FAULT:
            self._fault_reason = reason
            logger.error("driver %s: FAULT: %s", self.name, reason)
            self._transition(DriverState.FAULT)
        if was_active:
            try:
                self._deactivate()
            except Exception:  # noqa: BLE001 - already faulted; keep the first reason
                self._errors += 1
                logger.exception("driver %s: deactivate after fault failed", self.name)
