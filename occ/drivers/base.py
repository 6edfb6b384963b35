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
    "feedback_jump": 2.0,
    "frozen_feedback_ms": 50.0,
    "feedback_noise": None,
    "limit_margin": None,
    "following_error": {},
}

#: ``following_error``'s keys and defaults (None: by joint type, or from the backend)
FOLLOWING_DEFAULTS: dict[str, Any] = {
    "window": None,
    "time_ms": 3.0,
    "lag_ms": None,
    "stiffness": None,
}
#: the following-error window's default: far beyond a healthy servo's error at rest
FOLLOWING_WINDOW = {"revolute": 0.005, "prismatic": 0.0005}
#: how far a joint may be measured outside its limits before its feedback is not believed
LIMIT_MARGIN = {"revolute": 0.02, "prismatic": 0.002}
#: a healthy servo's lag behind a moving command, when the backend does not know its own
DEFAULT_LAG_S = 0.020

#: How far (rad, m) the command must be from a joint that has not moved at all for
#: ``frozen_feedback_ms`` before its feedback is called frozen: far beyond the tracking lag of
#: a healthy servo at the velocity limits, so a joint holding still never trips it.
FROZEN_AWAY = {"revolute": 0.005, "prismatic": 0.0005}

# Relative slack on the velocity check, so that a setpoint moving at exactly the limit is not
# flagged because of float rounding in (x - prev) / dt.
_VEL_SLACK = 1e-9


def _number(name: str, key: str, raw: Any, *, positive: bool = False) -> float:
    try:
        value = float(raw)
    except (TypeError, ValueError):
        value = math.nan
    if not (value > 0.0 if positive else value >= 0.0) or value == math.inf:
        want = "> 0" if positive else ">= 0"
        raise ValueError(f"driver {name!r}: {key} must be a finite number {want}, got {raw!r}")
    return value


def _per_joint_param(
    name: str, key: str, raw: Any, joints: Sequence[Joint], *, positive: bool = False
) -> list[float] | None:
    """``raw`` as one value per joint: None (the default applies), one number for every
    joint, or ``{joint: number}`` naming every joint. ValueError naming the key otherwise."""
    if raw is None:
        return None
    if isinstance(raw, Mapping):
        names = [j.name for j in joints]
        unknown = sorted(set(map(str, raw)) - set(names))
        missing = [n for n in names if n not in raw]
        if unknown or missing:
            raise ValueError(
                f"driver {name!r}: {key} names joints {sorted(map(str, raw))}; its joints are "
                f"{names}"
                + (f" (unknown: {unknown})" if unknown else "")
                + (f" (missing: {missing})" if missing else "")
            )
        return [_number(name, f"{key}.{n}", raw[n], positive=positive) for n in names]
    if isinstance(raw, (bool, str)) or not isinstance(raw, (int, float)):
        raise ValueError(
            f"driver {name!r}: {key} must be a number or {{joint: number}}, got {raw!r}"
        )
    value = _number(name, key, raw, positive=positive)
    return [value] * len(joints)


def _following_params(name: str, raw: Any, joints: Sequence[Joint]) -> dict[str, Any] | None:
    """``following_error`` checked: None when off (null, false), else its keys with their
    defaults merged (``FOLLOWING_DEFAULTS``); ValueError naming what is wrong."""
    if raw is None or raw is False:
        return None
    if not isinstance(raw, Mapping):
        raise ValueError(
            f"driver {name!r}: following_error must be a mapping {{window, time_ms, lag_ms, "
            f"stiffness}} or null (off), got {raw!r}"
        )
    unknown = sorted(set(map(str, raw)) - set(FOLLOWING_DEFAULTS))
    if unknown:
        raise ValueError(
            f"driver {name!r}: following_error: unknown keys {unknown}; known: "
            f"{sorted(FOLLOWING_DEFAULTS)}"
        )
    cfg = {**FOLLOWING_DEFAULTS, **raw}
    return {
        "window": _per_joint_param(
            name, "following_error.window", cfg["window"], joints, positive=True
        ),
        "time_s": _number(name, "following_error.time_ms", cfg["time_ms"]) * 1e-3,
        "lag": None
        if cfg["lag_ms"] is None
        else [
            v * 1e-3
            for v in _per_joint_param(name, "following_error.lag_ms", cfg["lag_ms"], joints) or ()
        ],
        "stiffness": _per_joint_param(
            name, "following_error.stiffness", cfg["stiffness"], joints, positive=True
        ),
    }


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
        noise_cfg = _per_joint_param(name, "feedback_noise", params["feedback_noise"], joints)
        margin_cfg = _per_joint_param(name, "limit_margin", params["limit_margin"], joints)
        self._following = _following_params(name, params["following_error"], joints)
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
        self._jump = checks[0]
        self._jump_speed = [checks[0] * j.limits.velocity for j in joints]
        self._frozen_s = checks[1] * 1e-3
        self._frozen_away = [FROZEN_AWAY.get(j.type, 0.005) for j in joints]
        self._changed_at = [math.nan] * len(joints)
        #: where each joint was when its reading last moved by more than its noise
        self._anchor = [math.nan] * len(joints)
        self._noise_cfg = noise_cfg
        self._fb_noise = [0.0] * len(joints)  # set by _setup_checks (the backend may know it)
        margins = margin_cfg or [LIMIT_MARGIN.get(j.type, 0.02) for j in joints]
        #: the measured range each joint must stay in: its limits widened by its margin
        self._range = [
            (j.limits.min - m, j.limits.max + m, m) for j, m in zip(joints, margins, strict=True)
        ]
        # following error (per joint): window, lag (s), 1 / stiffness (0: no load term), the
        # average of the commanded speed, since when the error is outside the window
        self._fe_window = [0.0] * len(joints)
        self._fe_lag = [0.0] * len(joints)
        self._fe_compliance = [0.0] * len(joints)
        self._fe_time = 0.0
        self._cmd_speed = [0.0] * len(joints)
        #: each joint's last commanded step (the next reading may show it whole)
        self._last_step = [0.0] * len(joints)
        self._fe_since = [math.nan] * len(joints)
        self._commanded = False
        #: a safe stop asked for while an activation was under way (supervisor): the
        #: activation must not leave the drive powered (see :meth:`activate`)
        self._stop_asked: str | None = None
        self._activating = False
        #: a switch-off (deactivate, safe stop) raised and no later one succeeded: the power
        #: stage may still be on whatever the state says (never counted safe; issue 36)
        self.stop_failed: str | None = None
        self._setup_checks()
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
        for joint in self.joints:
            joint.reset_servo()
        self._prev_write_time = math.nan
        self._changed_at = [math.nan] * len(self.joints)  # frozen: watched from the next read
        self._fe_since = [math.nan] * len(self.joints)
        self._cmd_speed = [0.0] * len(self.joints)
        self._last_step = [0.0] * len(self.joints)
        self._commanded = False
        # the limits as plain floats, read by every write (fewer look-ups on the loop)
        self._limit_table = [
            (j, j.limits.min, j.limits.max, j.limits.velocity * (1.0 + _VEL_SLACK))
            for j in self.joints
        ]
        with self._safe_lock:
            self._stop_asked = None
            self._activating = True
        try:
            self._call_hook(self._activate, "activate")
        finally:
            with self._safe_lock:
                self._activating = False
                asked = self._stop_asked
                self._stop_asked = None
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
        self._transition(DriverState.ACTIVE)

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
        (:meth:`occ.hardware.HardwareSet.reset`).
        """
        self._require((DriverState.FAULT,), "reset")
        if self.stop_failed is not None:
            self._call_hook(self._deactivate, "reset (switch-off)")
            self.stop_failed = None
        self._call_hook(self._reset, "reset")
        for joint in self.joints:
            joint.reset_servo()
        self._prev_write_time = math.nan
        self._anchor = [math.nan] * len(self.joints)
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
        cmd_speed = self._cmd_speed
        last_step = self._last_step
        jump_factor = self._jump
        noise = self._fb_noise
        changed = self._changed_at
        anchor = self._anchor
        ranges = self._range
        period = self.period
        frozen_s = self._frozen_s if state is DriverState.ACTIVE else 0.0
        # the following error: only for a drive that is servoing our commands
        following = state is DriverState.ACTIVE and self._commanded and self._following is not None
        if self.command_interface == "effort":
            frozen_s = 0.0  # the hand, not a servo, moves an effort-driven joint
            following = False
        # in FAULT the drive is off and its last reading may be the one that was not
        # believed: positions are still read (operators see where the robot is), lost and
        # out-of-range readings still reported, the rest judged again after a reset
        judged = state is not DriverState.FAULT
        # a jump is judged on a powered drive: powered off, a joint moved by hand goes as fast
        # as the hand (the velocity limit bounds commands), and Enable holds a fresh reading
        active = state is DriverState.ACTIVE and jump_factor > 0.0
        bad: str | None = None  # the first failed check: raised once every joint is read
        for i, joint in enumerate(self.joints):
            x = positions[i]
            if x - x != 0.0:  # NaN or inf (math.isfinite without a call)
                if joint.measured and bad is None:
                    bad = f"joint {joint.name}: feedback lost (position {x})"
                continue  # not reported yet: the joint stays unmeasured
            lo, hi, margin = ranges[i]
            if x < lo or x > hi:
                if bad is None:
                    bad = (
                        f"joint {joint.name}: measured position {x:.6g} outside its limits "
                        f"[{joint.limits.min:.6g}, {joint.limits.max:.6g}] by more than "
                        f"{margin:.6g} (limit_margin)"
                    )
                continue  # not believed: the joint keeps its last reading
            why = ""
            if joint.measured and judged:
                prev = joint.position
                if x != prev and active:
                    step = x - prev if x > prev else prev - x
                    dt = now - joint.stamp
                    if dt < period:
                        dt = period
                    # the speed this joint may have: its limit, or faster while a command
                    # catches up after a stall of the loop (the servo follows a step)
                    speed = jump[i]
                    catching_up = jump_factor * cmd_speed[i]
                    if catching_up > speed:
                        speed = catching_up
                    # a reading shows the step commanded over the previous write's interval,
                    # which a late tick made longer than this reading's: that step is plausible
                    reach = speed * dt
                    stepped = jump_factor * last_step[i]
                    if stepped > reach:
                        reach = stepped
                    reach += 2.0 * noise[i]
                    if step > reach:
                        why = (
                            f"joint {joint.name}: feedback jump of {step:.6g} in "
                            f"{dt * 1e3:.3g} ms (at most {reach:.6g}: feedback_jump "
                            f"{jump_factor:g} x {speed / jump_factor:.6g}/s, the speed it may "
                            f"have, plus twice the noise {noise[i]:.3g})"
                        )
                ref = anchor[i]
                if ref != ref or x - ref > noise[i] or ref - x > noise[i]:
                    anchor[i] = x  # moved beyond the encoder's noise: not frozen
                    changed[i] = now
                elif frozen_s > 0.0:
                    since = changed[i]
                    if since != since:
                        changed[i] = now
                    elif now - since > frozen_s:
                        away = joint.command_position - x
                        if away > self._frozen_away[i] or -away > self._frozen_away[i]:
                            why = (
                                f"joint {joint.name}: feedback frozen at {x:.6g} for "
                                f"{(now - since) * 1e3:.0f} ms while commanded {away:+.6g} "
                                f"away (no move beyond its noise, {noise[i]:.3g})"
                            )
            else:
                anchor[i] = x
                changed[i] = now
            if following and not why:
                why = self._following_error(i, joint, x, efforts[i], now)
            if why:
                if bad is None:
                    bad = why
                continue  # not believed: the joint keeps its last reading
            # Joint.set_measured, inlined: this runs for every joint every tick
            joint.position = x
            joint.velocity = velocities[i]
            joint.effort = efforts[i]
            joint.measured = True
            joint.stamp = now
        self._reads += 1
        if bad is not None:
            self._feedback_fault(bad)

    def _following_error(self, i: int, joint: Joint, x: float, effort: float, now: float) -> str:
        """The following error of joint ``i`` (see "Following error" in the module doc): ''
        while within its window, or the fault's words once outside it for ``time_ms``."""
        error = joint.command_position - x
        if error < 0.0:
            error = -error
        load = effort if effort >= 0.0 else -effort
        window = (
            self._fe_window[i]
            + self._fe_lag[i] * self._cmd_speed[i]
            + load * self._fe_compliance[i]
        )
        if error <= window:
            self._fe_since[i] = math.nan
            return ""
        since = self._fe_since[i]
        if since != since:
            self._fe_since[i] = since = now
        if now - since < self._fe_time:
            return ""
        return (
            f"joint {joint.name}: following error {error:.6g} beyond its window "
            f"{window:.6g} for {(now - since) * 1e3:.3g} ms (following_error: measured "
            f"{x:.6g}, commanded {joint.command_position:.6g}, time_ms {self._fe_time * 1e3:g})"
        )

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
        cmd_speed = self._cmd_speed
        fade = self._fade
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
            if ref == ref:
                # the commanded speed: each step over one nominal period (a step after a stall
                # counts as fast: the servo catches up), averaged over the servo's lag (an
                # exponential average: a step S raises lag x speed by S, as the error it
                # makes, which then decays with the servo's own time)
                moved = x - ref if x > ref else ref - x
                self._last_step[i] = moved
                gain = dt * fade[i]
                if gain > 1.0:
                    gain = 1.0
                cmd_speed[i] += (moved / self.period - cmd_speed[i]) * gain
            prev[i] = x
            joint.command_position = x
            values[i] = joint.servo(x, dt) if effort else x
        self._commanded = True
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

    def _following_model(self) -> tuple[Sequence[float], Sequence[float | None]] | None:
        """What the backend knows of its servo, per joint: (the lag behind a moving command,
        s; the stiffness against a load, N/m or N m/rad, None if unknown), for the following
        error's window; None (the default) when it knows nothing. Called at configure."""
        return None

    def _default_noise(self) -> Sequence[float] | None:
        """The encoders' noise at rest, per joint (rad or m, the quantum included), when the
        backend knows it and ``feedback_noise`` is not configured; None = 0."""
        return None

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
    def _setup_checks(self, backend: bool = False) -> None:
        """The per-joint figures of the feedback checks, from the parameters and, once the
        backend is configured (``backend``), from what it knows of its encoders and servo."""
        n = len(self.joints)
        noise = self._noise_cfg
        if noise is None and backend:
            noise = list(self._default_noise() or ())
        self._fb_noise = list(noise) if noise and len(noise) == n else [0.0] * n
        model = self._following_model() if backend else None
        fe = self._following
        lags: list[float] = [DEFAULT_LAG_S] * n
        stiff: list[float | None] = [None] * n
        if model is not None:
            lags = [float(v) for v in model[0]]
            stiff = list(model[1])
        if fe is not None:
            if fe["lag"] is not None:
                lags = list(fe["lag"])
            if fe["stiffness"] is not None:
                stiff = list(fe["stiffness"])
            window = fe["window"] or [FOLLOWING_WINDOW.get(j.type, 0.005) for j in self.joints]
            # the encoder's own noise never counts as an error
            self._fe_window = [w + 2.0 * e for w, e in zip(window, self._fb_noise, strict=True)]
            self._fe_time = float(fe["time_s"])
        self._fe_lag = lags
        self._fe_compliance = [0.0 if k is None else 1.0 / k for k in stiff]
        self._fade = [1.0 / max(lag, self.period) for lag in lags]

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
            except Exception as err:  # noqa: BLE001 - already faulted; keep the first reason
                self._errors += 1
                self.stop_failed = f"switch-off failed: {err!r}"
                logger.exception("driver %s: deactivate after fault failed", self.name)
            else:
                self.stop_failed = None
