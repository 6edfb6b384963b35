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

**Activation that waits.** A backend whose ``_activate`` waits for the hardware (several bus
round trips: a CiA 402 state machine) sets the class attribute ``activation_waits = True``: the
robot then calls :meth:`Driver.activate` on a thread of its own while the loop goes on ticking,
and touches the driver (read, write, deactivate, reset) only once it has returned
(occ/core/powerup.py). Such a hook looks at :attr:`~DriverLifecycle.activation_cancelled`
between its steps: when another thread asked for a safe stop (:meth:`~DriverLifecycle.safe_stop`:
the drive ends FAULT, switched off) or a cancel (:meth:`~DriverLifecycle.cancel_activation`: it
ends INACTIVE, switched off, and ``activate`` raises StateError), it switches its power stages
off and returns at once.

Feedback checks (every ``read``, in the base, so every backend has them): a joint's position
is its feedback, and feedback can fail while the drive still answers. The robot never trusts
what it cannot check (issue 36); each failed check latches FAULT naming the drive, the joint,
the figures and the rule, and the base powers the drive off in the same call.

- **Lost**: a non-finite position (NaN, inf) from a joint that has been measured latches
  FAULT ("feedback lost"). Before the first measurement NaN means "not reported yet": the
  joint stays unmeasured, and Enable is refused until it is measured.
- **Out of range**: a measured position outside the joint's limits by more than
  ``limit_margin`` (default 0.02 rad, 2 mm; per joint or one number) latches FAULT: commands
  are clamped to the limits, so a healthy joint is never measured far outside them. Checked in
  every state (a joint outside its range at power-up is not enabled).
- **Jump**: while ACTIVE, a step larger than ``feedback_jump`` (default 2) times the speed
  the joint may have (its velocity limit, or the commanded speed while a command catches up
  after a stall) over the time since its last reading (at least one ``period``), or than
  ``feedback_jump`` times the last commanded step (a late tick's step shows in the next
  reading, however soon it comes), plus twice the encoder's noise (``feedback_noise``),
  latches FAULT: no healthy joint moves that fast; a slipped encoder or a corrupted frame
  does. 0 = off.
- **Following error** (``following_error: {window, time_ms, lag_ms, stiffness}``, the CiA 402
  way: object 0x6065 *following error window*, 0x6066 *time out*): while ACTIVE on position
  commands, a joint measured further from its command than the window for longer than
  ``time_ms`` (default 3) latches FAULT. The window is ``window`` (default 5 mrad, 0.5 mm)
  plus what a healthy servo lags: ``lag_ms`` times the commanded speed averaged over the lag
  (so a step after a stall of the loop widens it by the step, as much as the error it makes),
  plus the measured effort over the servo's ``stiffness`` (a position servo pushed by tissue
  or a load gives way by effort/stiffness; None leaves that term out). A backend that knows its
  servo supplies both (``sim``: from its bandwidth and gains); the defaults are 20 ms and
  None. An encoder that runs away while the drive still answers and the heartbeat lives is
  caught here, before the joint is measured outside its limits. ``following_error: null``
  (or ``false``) = off.
- **Frozen**: while ACTIVE on position commands, a joint whose reported position has not
  moved by more than ``feedback_noise`` for ``frozen_feedback_ms`` (default 50) while its
  command is further than ``FROZEN_AWAY`` from it (5 mrad, 0.5 mm) latches FAULT: the drive
  answers, the heartbeat lives, but the encoder is stuck (a stale value that dithers by a
  count is still stuck). 0 = off.
- ``feedback_noise`` (rad or m, per joint or one number): what a healthy encoder's reading
  may wander at rest, its quantum included; default from the backend (``sim``: its encoder
  resolution plus four standard deviations of its noise; ``can``: one count), else 0.

The hooks receive ``now`` (seconds on the loop's clock) because a simulated driver integrates
its dynamics over exactly those times, which makes a simulated-clock run reproducible.
``values`` passed to ``_write`` is a buffer the base reuses every tick: copy it if needed.
"""

from __future__ import annotations

import enum
import logging
import math
import threading
from collections.abc import Callable, Mapping, Sequence
from types import TracebackType
from typing import Any, ClassVar, Literal, cast

from mypy_extensions import mypyc_attr

from occ.drivers.checks import FeedbackChecks
from occ.drivers.params import driver_params
from occ.errors import DriverError, LimitError, OCCError, StateError, caused
from occ.joint import Joint

__all__ = ["Driver", "DriverState", "CommandInterface", "LimitPolicy"]

logger = logging.getLogger(__name__)

CommandInterface = Literal["position", "effort"]
LimitPolicy = Literal["clamp", "fault"]
_POLICIES = ("clamp", "fault")

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


@mypyc_attr(allow_interpreted_subclasses=True)  # mypyc: Driver and its plugins subclass it
class DriverLifecycle:
    """The lifecycle of a driver: the state machine of the module docstring, the safe stop
    from another thread, the hooks' errors latched as FAULT. :class:`Driver` adds the joints'
    commands and readings; a backend subclasses Driver, never this class alone."""

    #: The backend's ``_activate`` waits for the hardware (a CiA 402 state machine: several
    #: bus round trips, up to a timeout): the robot runs it on a thread of its own while the
    #: loop goes on ticking, and touches the drive again only once it has ended
    #: (occ/core/powerup.py). False (the default): ``activate`` is quick and runs in the tick.
    activation_waits: ClassVar[bool] = False

    def __init__(self, name: str, joints: Sequence[Joint]) -> None:
        self.name: str = name
        self.joints: list[Joint] = list(joints)
        #: a safe stop asked for while an activation was under way (supervisor): the
        #: activation must not leave the drive powered (see :meth:`activate`)
        self._stop_asked: str | None = None
        #: the activation under way on another thread is to end switched off, not faulted
        #: (a Disable while powering up): see :meth:`cancel_activation`
        self._cancel_asked: str | None = None
        self._activating = False
        #: a switch-off (deactivate, safe stop) raised and no later one succeeded: the power
        #: stage may still be on whatever the state says (never counted safe; issue 36)
        self.stop_failed: str | None = None
        self._safe_lock = threading.Lock()
        self._safe_stops = 0
        self._state: DriverState = DriverState.UNCONFIGURED
        self._configured: bool = False
        self._fault_reason: str | None = None
        self._errors: int = 0
        #: ``tap(driver, action, error)`` of every hook that raised (the black box), or None
        self.hook_tap: Callable[[str, str, BaseException], None] | None = None

    @property
    def state(self) -> DriverState:
        """The current lifecycle state."""
        return self._state

    @property
    def fault_reason(self) -> str | None:
        """Why the driver is in FAULT (None otherwise)."""
        return self._fault_reason if self._state is DriverState.FAULT else None

    # ------------------------------------------------------------------ lifecycle
    def configure(self) -> None:
        """UNCONFIGURED -> INACTIVE: open the hardware; states become readable."""
        self._require((DriverState.UNCONFIGURED,), "configure")
        self._call_hook(self._configure, "configure")
        self._configured = True
        self._setup_checks(backend=True)
        self._transition(DriverState.INACTIVE)

    def activate(self) -> None:
        """INACTIVE -> ACTIVE: commands are accepted from now on.

        Servo memories and the previous setpoint are cleared, so the first write after
        activation is velocity-checked against the *measured* position (if any) over one
        nominal period: activation never becomes a jump. A safe stop asked for from another
        thread while the power stage was coming up (:meth:`safe_stop`) is honoured when it is
        up: the drive is switched off again and latched FAULT, and this raises.
        """
        self._require((DriverState.INACTIVE,), "activate")
        self._start_commands()
        with self._safe_lock:
            self._stop_asked = None
            self._cancel_asked = None
            self._activating = True
        try:
            self._call_hook(self._activate, "activate")
        finally:
            with self._safe_lock:
                self._activating = False
                asked = self._stop_asked
                cancel = self._cancel_asked
                self._stop_asked = self._cancel_asked = None
        if asked is not None:
            # the supervisor found the loop hung while the power stage came up: it must not
            # stay up (issue 36: a slow power-up left one drive powered after the trip)
            self._state = DriverState.ACTIVE  # so _enter_fault switches it off again
            err = DriverError(
                f"driver {self.name!r}: safe stop while powering up: {asked}; switched off"
            )
            self._errors += 1
            self._enter_fault(str(err))
            raise err
        if cancel is not None:
            # not wanted any more (a Disable while it came up): off again, not faulted
            self._state = DriverState.ACTIVE  # so deactivate switches it off
            self.deactivate()
            raise StateError(
                f"driver {self.name!r}: activation cancelled: {cancel}; switched off again"
            )
        self._transition(DriverState.ACTIVE)

    def cancel_activation(self, reason: str) -> bool:
        """From any thread: the activation under way on another thread (a driver whose
        :attr:`activation_waits`) is not wanted any more. It ends switched off again, INACTIVE
        (not FAULT), and :meth:`activate` raises :class:`~occ.errors.StateError`; a backend that
        waits looks at :attr:`activation_cancelled` between its steps and gives up early. True
        when an activation was under way (else nothing to do)."""
        with self._safe_lock:
            if not self._activating:
                return False
            if self._cancel_asked is None:
                self._cancel_asked = reason
            return True

    @property
    def activating(self) -> bool:
        """An activation is under way (on whichever thread runs it)."""
        return self._activating

    @property
    def activation_cancelled(self) -> bool:
        """For a backend's ``_activate`` that waits: a safe stop (:meth:`safe_stop`) or a
        cancel (:meth:`cancel_activation`) was asked while it runs. The hook then switches its
        power stages off and returns at once; the base does the rest (FAULT after a safe stop,
        INACTIVE after a cancel)."""
        return self._activating and (self._stop_asked is not None or self._cancel_asked is not None)

    def deactivate(self) -> None:
        """ACTIVE -> INACTIVE: stop accepting commands; states stay readable. A switch-off
        that fails latches FAULT and is remembered in :attr:`stop_failed` (the power stage may
        still be on) until a later switch-off succeeds."""
        self._require((DriverState.ACTIVE,), "deactivate")
        self._call_hook(self._deactivate, "deactivate")
        self.stop_failed = None
        self._transition(DriverState.INACTIVE)

    def reset(self) -> None:
        """Clear a latched FAULT: back to INACTIVE (or UNCONFIGURED if never configured).

        A drive whose switch-off failed is switched off first (a reset never leaves a power
        stage on that nobody commands); the backend's ``_reset`` then clears the hardware's
        fault and must raise when it cannot (the cause persists). Whether the drive is healthy
        again is the robot's question: it reads every drive afresh before it leaves FAULT
        (:meth:`occ.core.hardware.HardwareSet.reset`).
        """
        self._require((DriverState.FAULT,), "reset")
        if self.stop_failed is not None:
            self._call_hook(self._deactivate, "reset (switch-off)")
            self.stop_failed = None
        self._call_hook(self._reset, "reset")
        self._forget_commands()
        logger.info("driver %s: fault reset (was: %s)", self.name, self._fault_reason)
        self._fault_reason = None
        self._transition(DriverState.INACTIVE if self._configured else DriverState.UNCONFIGURED)

    def safe_stop(self, reason: str) -> None:
        """From any thread, at once: the hardware to its safe state, the driver latched FAULT.

        For a supervisor that found the loop thread hung (possibly inside this driver's
        ``read`` or ``write``). Idempotent; never raises (a failing hook is logged, counted and
        kept in :attr:`stop_failed`: the driver is latched FAULT anyway, but not counted
        safe). An INACTIVE driver is already holding with its power stages off, unless its
        activation is under way on another thread: then the stop is remembered and the
        activation switches it off again when the power stage is up (:meth:`activate`).
        """
        with self._safe_lock:
            if self._state is not DriverState.ACTIVE:
                if self._activating:
                    self._stop_asked = reason
                return
            self._safe_stops += 1
            try:
                self._safe_stop()
            except Exception as err:  # noqa: BLE001 - the caller is a supervisor: it must go on
                self._errors += 1
                self.stop_failed = f"safe stop failed: {err!r}"
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

    def __del__(self) -> None:
        # Like python-can's leaked-bus warning: a configured driver nobody shut down may still
        # hold hardware. getattr because __init__ may have failed half way.
        if getattr(self, "_configured", False) and getattr(self, "_state", None) not in (
            DriverState.SHUTDOWN,
            None,
        ):
            logger.warning("driver %s was not shut down properly", getattr(self, "name", "?"))

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

    def _setup_checks(self, backend: bool = False) -> None:
        """The feedback checks' figures, once the backend is configured (:class:`Driver`)."""

    def _start_commands(self) -> None:
        """At activation, before the power stage comes up: commands start afresh
        (:class:`Driver`)."""

    def _forget_commands(self) -> None:
        """At a fault's reset, once the hardware's is cleared (:class:`Driver`)."""

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
        tap = self.hook_tap
        if tap is not None:  # the black box: what a replay raises again
            tap(self.name, action, err)
        wrapped: OCCError
        if isinstance(err, OCCError):
            wrapped = err
        else:
            wrapped = caused(DriverError(f"driver {self.name!r}: {action} failed: {err!r}"), err)
        self._enter_fault(str(wrapped))
        return wrapped

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
            except Exception as err:  # noqa: BLE001 - already faulted; keep the first reason
                self._errors += 1
                self.stop_failed = f"switch-off failed: {err!r}"
                logger.exception("driver %s: deactivate after fault failed", self.name)
            else:
                self.stop_failed = None


@mypyc_attr(allow_interpreted_subclasses=True)  # mypyc: plugins and tests subclass it
class Driver(DriverLifecycle):
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
        p = driver_params(
            name,
            type(self).__name__,
            joints,
            params,
            self.DEFAULT_PARAMS,
            command_interface,
            self.command_interface,
            self.supported_interfaces,
        )
        interface = p.interface
        #: joints whose effort would come from a PID without gains: position setpoints
        #: (:meth:`write`) are refused for them; direct efforts (:meth:`write_effort`, a haptic
        #: master's force) need none
        self.missing_gains: list[str] = (
            [j.name for j in joints if j.gains is None] if interface == "effort" else []
        )

        super().__init__(name, joints)
        self.params: dict[str, Any] = p.values
        self.on_limit: LimitPolicy = on_limit
        self.command_interface = cast(CommandInterface, interface)  # shadows the class's
        self.period: float = p.period
        #: the device stops itself when not commanded for this long while ACTIVE (0 = off)
        self.heartbeat_s: float = p.heartbeat_s
        #: the feedback checks, run by every read (see "Feedback checks" above)
        self._checks = FeedbackChecks(
            joints, p.jump, p.frozen_ms, p.noise, p.margin, p.following, p.period
        )
        self._setup_checks()
        n = len(self.joints)
        # Preallocated per-tick buffers: write() never allocates lists.
        self._values: list[float] = [0.0] * n
        self._limit_table: list[tuple[Joint, float, float, float]] = []
        self._prev_setpoint: list[float] = [0.0] * n
        self._prev_write_time: float = math.nan
        self._reads: int = 0
        #: the last reading as ``_read`` returned it, and the ``now`` of its read (the black
        #: box keeps it: what a replay gives the checks again, occ/core/replay.py): a copy in
        #: buffers of its own, since a hook may return its own buffers and change them later
        #: in the tick (a simulated drive switched off zeroes its velocities)
        self.raw: tuple[Sequence[float], Sequence[float], Sequence[float]] = ((), (), ())
        self._raw_copy: tuple[list[float], list[float], list[float]] = ([], [], [])
        self.raw_now = math.nan
        self._writes: int = 0
        self._limit_events: int = 0

    # ------------------------------------------------------------------ properties
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

    def __enter__(self) -> Driver:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.shutdown()

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
            raw = self._read(now)
        except Exception as err:
            raise self._hook_failed("read", err) from err
        positions, velocities, efforts = raw
        copy = self._raw_copy
        copy[0][:] = positions  # element copies: nothing allocated for a hook's lists
        copy[1][:] = velocities
        copy[2][:] = efforts
        self.raw, self.raw_now = copy, now
        # in FAULT the drive is off and its last reading may be the one that was not
        # believed: positions are still read (operators see where the robot is), lost and
        # out-of-range readings still reported, the rest judged again after a reset
        bad = self._checks.apply(
            positions,
            velocities,
            efforts,
            now,
            state is DriverState.ACTIVE,
            state is not DriverState.FAULT,
            self.command_interface == "effort",
        )
        self._reads += 1
        if bad is not None:
            self._feedback_fault(bad)

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
        checks = self._checks
        cmd_speed = checks.cmd_speed
        last_step = checks.last_step
        fade = checks.fade
        for i, (joint, lo, hi, vmax) in enumerate(self._limit_table):
            x = float(setpoints[i])
            if x - x != 0.0:  # inf or NaN (math.isfinite without a call: every joint, every tick)
                self._fault(LimitError(f"driver {self.name!r}: joint {joint.name}: setpoint {x}"))
            if x < lo or x > hi:
                if not clamp:
                    self._fault(self._outside(joint, x, lo, hi))
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
                        self._fault(self._too_fast(joint, step, dt, x))
                    max_step = joint.limits.velocity * dt
                    x = ref + max_step if step > 0.0 else ref - max_step
                    self._limit_events += 1
            if ref == ref:
                # the commanded speed: each step over one nominal period (a step after a stall
                # counts as fast: the servo catches up), averaged over the servo's lag (an
                # exponential average: a step S raises lag x speed by S, as the error it
                # makes, which then decays with the servo's own time)
                moved = x - ref if x > ref else ref - x
                last_step[i] = moved
                gain = dt * fade[i]
                if gain > 1.0:
                    gain = 1.0
                cmd_speed[i] += (moved / self.period - cmd_speed[i]) * gain
            prev[i] = x
            joint.command_position = x
            values[i] = joint.servo(x, dt) if effort else x
        checks.commanded = True
        self._prev_write_time = now
        try:
            self._write(values, now)
        except Exception as err:
            raise self._hook_failed("write", err) from err
        self._writes += 1

    def _outside(self, joint: Joint, x: float, lo: float, hi: float) -> LimitError:
        """The error of a setpoint ``x`` outside ``joint``'s limits ``[lo, hi]``."""
        return LimitError(
            f"driver {self.name!r}: joint {joint.name}: position {x:.6g} outside "
            f"limits [{lo:.6g}, {hi:.6g}]"
        )

    def _too_fast(self, joint: Joint, step: float, dt: float, x: float) -> LimitError:
        """The error of a setpoint ``x`` a ``step`` away from the last in ``dt``: too fast."""
        speed = abs(step) / dt if dt > 0.0 else math.inf
        return LimitError(
            f"driver {self.name!r}: joint {joint.name}: velocity {speed:.6g} "
            f"exceeds limit {joint.limits.velocity:.6g} (setpoint {x:.6g})"
        )

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

    def _following_model(self) -> tuple[Sequence[float], Sequence[float | None]] | None:
        """What the backend knows of its servo, per joint: (the lag behind a moving command,
        s; the stiffness against a load, N/m or N m/rad, None if unknown), for the following
        error's window; None (the default) when it knows nothing. Called at configure."""
        return None

    def _default_noise(self) -> Sequence[float] | None:
        """The encoders' noise at rest, per joint (rad or m, the quantum included), when the
        backend knows it and ``feedback_noise`` is not configured; None = 0."""
        return None

    def _read(self, now: float) -> tuple[Sequence[float], Sequence[float], Sequence[float]]:
        """Return (positions, velocities, efforts), one float per joint, SI units."""
        raise NotImplementedError

    def _write(self, values: Sequence[float], now: float) -> None:
        """Send position setpoints or efforts (by ``command_interface``) to the hardware."""
        raise NotImplementedError

    # ------------------------------------------------------------------ internals
    def _setup_checks(self, backend: bool = False) -> None:
        """The per-joint figures of the feedback checks, from the parameters and, once the
        backend is configured (``backend``), from what it knows of its encoders and servo."""
        checks = self._checks
        noise = self._default_noise() if backend and checks.noise_cfg is None else None
        checks.setup(noise, self._following_model() if backend else None)

    def _start_commands(self) -> None:
        # servo memories and the previous setpoint cleared: the first write is checked
        # against the measured position (see activate)
        for joint in self.joints:
            joint.reset_servo()
        self._prev_write_time = math.nan
        self._checks.restart()
        # the limits as plain floats, read by every write (fewer look-ups on the loop)
        self._limit_table = [
            (j, j.limits.min, j.limits.max, j.limits.velocity * (1.0 + _VEL_SLACK))
            for j in self.joints
        ]

    def _forget_commands(self) -> None:
        for joint in self.joints:
            joint.reset_servo()
        self._prev_write_time = math.nan
        self._checks.forget()

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
