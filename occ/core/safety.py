"""Safety logic of the daemon: loop watchdog, robot state machine, packet-loss monitor.

Everything here is pure logic: no I/O, no threads, no clock of its own. The loop feeds it
times (seconds, from its :class:`~occ.clock.Clock`) and acts on what it returns or calls
back, so the same code runs in real time and in simulated time, and is tested exactly.

- :class:`Watchdog`: per-tick overrun detection -> alert callback, and a stop callback on a
  run of overruns or one long gap between ticks.
- :class:`RobotState`, :class:`StateMachine`: the robot lifecycle (OCC + dVRK +
  ros2_control), with latched FAULT and ESTOP.
- :class:`Supervisor`: from outside the loop thread, notices a loop that stopped ticking.
- :class:`LossMonitor`: loss versus lateness of a periodic stream: holds when it is overdue,
  resumes when it comes back in time, latches on proven loss (``max_consecutive + 1``
  consecutive sequence numbers), on silence past a grace, or on a run of samples refused for
  their timestamp; judges every sample (:class:`Verdict`).
"""

from __future__ import annotations

import enum
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from occ.errors import StateError

__all__ = [
    "EVENTS",
    "Supervisor",
    "Verdict",
    "TRANSITIONS",
    "LossEvent",
    "LossMonitor",
    "RobotState",
    "StateMachine",
    "Transition",
    "TransitionFailed",
    "Watchdog",
]

logger = logging.getLogger(__name__)

StopPolicy = Literal["hold", "fault"]


# --------------------------------------------------------------------------------------------
# Watchdog
# --------------------------------------------------------------------------------------------


class Watchdog:
    """Detects loop overruns and decides when they are bad enough to stop the robot.

    Fed once per tick with the tick's period (start - previous start; ``None`` for the first
    tick) and compute time (end - start), in seconds. A tick is an *overrun* when

    - its compute time exceeds ``budget_s``, or
    - its period exceeds ``period_limit_s`` (default ``2 * budget_s``: with the budget equal
      to the loop period, at least one deadline was missed).

    Then:

    - ``alert_run`` consecutive overruns -> ``on_alert(reason, overruns_total)``, at most once
      per ``alert_interval_s`` of loop time; suppressed alerts are counted and reported in the
      next message;
    - ``stop_run`` consecutive overruns, or a single period longer than ``hard_gap_s`` ->
      ``on_stop(reason, policy)`` once; latched until :meth:`reset`. ``policy`` (``"hold"``
      or ``"fault"``) tells the robot whether to stop-and-hold or to fault.

    Loop time for the rate limit is the sum of the periods fed, so no clock is needed.
    A loop that stops ticking altogether feeds nothing: that is the :class:`Supervisor`'s
    to see, from its own thread. Callbacks run on the thread that fed.
    """

    def __init__(
        self,
        budget_s: float,
        *,
        alert_run: int = 1,
        stop_run: int = 5,
        hard_gap_s: float = 0.010,
        policy: StopPolicy = "hold",
        on_alert: Callable[[str, int], None] | None = None,
        on_stop: Callable[[str, str], None] | None = None,
        period_limit_s: float | None = None,
        alert_interval_s: float = 1.0,
    ) -> None:
        if budget_s <= 0:
            raise ValueError(f"budget_s must be > 0, got {float(budget_s)}")
        if alert_run < 1 or stop_run < 1:
            raise ValueError("alert_run and stop_run must be >= 1")
        if policy not in ("hold", "fault"):
            raise ValueError(f"policy must be 'hold' or 'fault', got {policy!r}")
        self.budget_s = float(budget_s)
        self.period_limit_s = 2.0 * self.budget_s if period_limit_s is None else period_limit_s
        self.alert_run = alert_run
        self.stop_run = stop_run
        self.hard_gap_s = float(hard_gap_s)
        self.policy: StopPolicy = policy
        self.on_alert = on_alert
        self.on_stop = on_stop
        self.alert_interval_s = float(alert_interval_s)
        self._stop_lock = threading.Lock()
        self.overruns = 0
        self.max_consecutive = 0
        self.alerts = 0
        self.stops = 0
        self.reset()

    def reset(self) -> None:
        """Clear the stop latch and the current run (counters are kept)."""
        self.consecutive = 0
        self.stopped = False
        self.stop_reason: str | None = None
        self._elapsed = 0.0
        self._next_alert_at = -math.inf
        self._suppressed = 0

    def feed(self, period_s: float | None, compute_s: float) -> bool:
        """Account for one tick; return True when it was an overrun."""
        over = compute_s > self.budget_s
        if period_s is not None:
            self._elapsed += period_s
            if period_s > self.period_limit_s:
                over = True
            if period_s > self.hard_gap_s and not self.stopped:
                self._trigger_stop(
                    f"gap of {period_s * 1e3:.3f} ms between ticks "
                    f"(hard limit {self.hard_gap_s * 1e3:.3f} ms)"
                )
        if not over:
            self.consecutive = 0
            return False
        self.overruns += 1
        self.consecutive += 1
        self.max_consecutive = max(self.max_consecutive, self.consecutive)
        if self.consecutive >= self.alert_run:
            self._alert(period_s, compute_s)
        if self.consecutive >= self.stop_run and not self.stopped:
            self._trigger_stop(
                f"{self.consecutive} consecutive overruns "
                f"(budget {self.budget_s * 1e3:.3f} ms, last compute {compute_s * 1e3:.3f} ms)"
            )
        return True

    def _alert(self, period_s: float | None, compute_s: float) -> None:
        if self._elapsed < self._next_alert_at:
            self._suppressed += 1
            return
        if compute_s > self.budget_s:
            what = f"compute {compute_s * 1e3:.3f} ms > budget {self.budget_s * 1e3:.3f} ms"
        else:
            assert period_s is not None
            what = f"period {period_s * 1e3:.3f} ms > limit {self.period_limit_s * 1e3:.3f} ms"
        reason = f"overrun: {what} ({self.consecutive} consecutive, {self.overruns} total"
        if self._suppressed:
            reason += f", {self._suppressed} alerts suppressed"
        reason += ")"
        self._suppressed = 0
        self._next_alert_at = self._elapsed + self.alert_interval_s
        self.alerts += 1
        if self.on_alert is not None:
            self.on_alert(reason, self.overruns)

    def _trigger_stop(self, reason: str) -> None:
        with self._stop_lock:
            if self.stopped:
                return
            self.stopped = True
            self.stop_reason = reason
            self.stops += 1
        if self.on_stop is not None:
            self.on_stop(reason, self.policy)

    def counters(self) -> dict[str, Any]:
        return {
            "overruns": self.overruns,
            "max_consecutive": self.max_consecutive,
            "alerts": self.alerts,
            "stops": self.stops,
            "stopped": self.stopped,
        }


class Supervisor:
    """Notices, from outside the loop thread, a loop that stopped ticking.

    The loop calls :meth:`beat` at the start and the end of every tick (one attribute store);
    a supervisor thread calls :meth:`check` a few times per ``timeout_s``. A loop that has
    not beaten for more than ``timeout_s`` while armed (a hung tick, a call that blocks, a
    tick stuck on the interpreter lock) trips it once: :meth:`check` returns the reason and
    ``on_trip(reason)`` runs on the checking thread. Latched until :meth:`reset`. Pure logic:
    the same code runs in simulated time, where a test calls :meth:`check` itself.
    """

    __slots__ = (
        "timeout_s",
        "on_trip",
        "last_beat",
        "armed",
        "tripped",
        "reason",
        "trips",
        "_last_check",
        "_window_from",
        "starved",
    )

    def __init__(
        self, timeout_s: float = 0.020, on_trip: Callable[[str], None] | None = None
    ) -> None:
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be > 0, got {float(timeout_s)}")
        self.timeout_s = float(timeout_s)
        self.on_trip = on_trip
        self.last_beat: float | None = None
        self.armed = False
        self.tripped = False
        self.reason = ""
        self.trips = 0
        self._last_check: float | None = None
        self._window_from = -math.inf
        #: checks that found the supervisor itself frozen (the whole process or machine paused)
        self.starved = 0

    def beat(self, now: float) -> None:
        self.last_beat = now

    def arm(self, now: float) -> None:
        """Start watching (the loop starts); the first beat is due within the timeout."""
        self.last_beat = now
        self._last_check = now
        self.armed = True

    def disarm(self) -> None:
        """Stop watching (the loop ended on purpose)."""
        self.armed = False

    def reset(self) -> None:
        self.tripped = False
        self.reason = ""

    def check(self, now: float) -> str | None:
        """Trip if the loop has been silent too long; returns the reason on the trip only.

        Silence is counted only while the supervisor itself was awake: when its own previous
        check is more than ``timeout_s`` ago, the whole process (or machine) was paused (a VM
        hiccup, SIGSTOP) and the loop had no chance to tick either; the window then starts
        again now (counted in ``starved``), so a paused machine is not a hung loop, while a
        loop that stays silent after the pause is caught one timeout later.
        """
        last_check = self._last_check
        self._last_check = now
        last = self.last_beat
        if not self.armed or self.tripped or last is None:
            return None
        if last_check is not None and now - last_check > self.timeout_s:
            self.starved += 1
            self._window_from = now
            return None
        silent = now - max(last, self._window_from)
        if silent <= self.timeout_s:
            return None
        self.tripped = True
        self.trips += 1
        self.reason = (
            f"control loop did not tick for {(now - last) * 1e3:.1f} ms "
            f"(supervisor limit {self.timeout_s * 1e3:.1f} ms)"
        )
        if self.on_trip is not None:
            self.on_trip(self.reason)
        return self.reason


# --------------------------------------------------------------------------------------------
# Robot state machine
# --------------------------------------------------------------------------------------------


class RobotState(enum.Enum):
    """Robot lifecycle states."""

    INIT = "INIT"  # created, not configured
    READY = "READY"  # configured, servos off
    ENABLED = "ENABLED"  # servos on, holding position
    RUNNING = "RUNNING"  # following commands (teleoperation, trajectory)
    STOPPED = "STOPPED"  # holding the last safe position, refusing new motion
    FAULT = "FAULT"  # latched until reset
    ESTOP = "ESTOP"  # emergency stop, latched until reset
    SHUTDOWN = "SHUTDOWN"  # final


#: Request names accepted by :meth:`StateMachine.request` (lower case; case-insensitive).
EVENTS: tuple[str, ...] = (
    "configure",
    "enable",
    "run",
    "hold",
    "stop",
    "disable",
    "fault",
    "estop",
    "reset",
    "shutdown",
)


def _build_table() -> dict[tuple[RobotState, str], RobotState]:
    s = RobotState
    t: dict[tuple[RobotState, str], RobotState] = {
        (s.INIT, "configure"): s.READY,
        (s.READY, "enable"): s.ENABLED,
        (s.ENABLED, "run"): s.RUNNING,
        (s.RUNNING, "hold"): s.ENABLED,
        (s.ENABLED, "stop"): s.STOPPED,
        (s.RUNNING, "stop"): s.STOPPED,
        (s.STOPPED, "stop"): s.STOPPED,
        (s.STOPPED, "run"): s.RUNNING,
        (s.STOPPED, "enable"): s.ENABLED,
        (s.ENABLED, "disable"): s.READY,
        (s.RUNNING, "disable"): s.READY,
        (s.STOPPED, "disable"): s.READY,
        (s.FAULT, "reset"): s.READY,
        (s.ESTOP, "reset"): s.READY,
    }
    for state in s:
        if state is not s.SHUTDOWN:
            # E-stop outranks a fault: a fault during ESTOP leaves it in ESTOP.
            t[(state, "fault")] = s.ESTOP if state is s.ESTOP else s.FAULT
            t[(state, "estop")] = s.ESTOP
        t[(state, "shutdown")] = s.SHUTDOWN
    return t


#: (state, event) -> new state; a pair not in the table is refused.
TRANSITIONS: dict[tuple[RobotState, str], RobotState] = _build_table()


@dataclass(frozen=True, slots=True)
class Transition:
    """The result of an accepted request. ``changed`` is False for an idempotent request
    (e.g. ``stop`` while STOPPED, ``fault`` while FAULT): accepted, nothing to do, listeners
    not called."""

    old: RobotState
    new: RobotState
    event: str
    reason: str
    time: float

    @property
    def changed(self) -> bool:
        return self.old is not self.new


Listener = Callable[[RobotState, RobotState, str, str, float], None]


#: states a failure cannot make worse (a fault there stays where it is)
_LATCHED = frozenset({RobotState.FAULT, RobotState.ESTOP, RobotState.SHUTDOWN})


class TransitionFailed(StateError):
    """A transition whose effector (the hardware) or a listener failed: the robot latched
    FAULT (or stayed where it was), and the message says why."""


class StateMachine:
    """Robot lifecycle with latched FAULT and ESTOP.

    Transitions (rows: current state; columns: event; cell: new state; ``.`` = refused with
    :class:`~occ.errors.StateError`, nothing changes; ``=`` = accepted, no change)::

                  configure enable  run      hold     stop     disable fault  estop  reset  shutdown
        INIT      READY     .       .        .        .        .       FAULT  ESTOP  .      SHUTDOWN
        READY     .         ENABLED .        .        .        .       FAULT  ESTOP  .      SHUTDOWN
        ENABLED   .         .       RUNNING  .        STOPPED  READY   FAULT  ESTOP  .      SHUTDOWN
        RUNNING   .         .       .        ENABLED  STOPPED  READY   FAULT  ESTOP  .      SHUTDOWN
        STOPPED   .         ENABLED RUNNING  .        =        READY   FAULT  ESTOP  .      SHUTDOWN
        FAULT     .         .       .        .        .        .       =      ESTOP  READY  SHUTDOWN
        ESTOP     .         .       .        .        .        .       =(1)   =      READY  SHUTDOWN
        SHUTDOWN  .         .       .        .        .        .       .      .      .      =

    (1) E-stop outranks a fault: ``fault`` while ESTOP is accepted and stays ESTOP.

    ``stop`` is both the operator's Stop and the safety stop (packet loss, watchdog with
    policy "hold"): hold the last safe position and refuse new motion. FAULT and ESTOP latch:
    only ``reset`` leaves them (to READY, servos off). Safety code that must not raise can use
    :meth:`try_request`.

    The *effector* (:meth:`set_effector`, the robot's hardware) carries a transition out
    before it is committed: ``effector(old, new, event)`` returns '' when done, or why it could
    not be done. A failed power-up (``enable``, or ``run`` from STOPPED) or a failed ``reset``
    is vetoed: the state does not become the new one; instead the robot latches FAULT (or
    stays FAULT) with that reason, and :class:`TransitionFailed` tells the requester. A
    power-down cannot be refused: its effector does what it can and reports the rest itself.

    Threading: transitions are meant to happen on the loop thread (commands from interface
    threads are queued to it). A lock makes the check-and-set atomic anyway, so a stray call
    from another thread cannot corrupt the state; :attr:`state` may be read from any thread.
    Listeners ``(old, new, event, reason, time)`` run after the change, outside the lock, on
    the requesting thread. A listener that raises does not stop the others, and is not
    swallowed: the robot latches FAULT naming it (unless already FAULT, ESTOP or SHUTDOWN) and
    the requester gets :class:`TransitionFailed`. ``time`` is ``clock.wall_time()`` (Unix
    seconds, for IGTL STATUS).
    """

    def __init__(
        self,
        initial: RobotState = RobotState.INIT,
        *,
        clock: Any | None = None,
    ) -> None:
        self._state = initial
        self._clock = clock
        self._lock = threading.Lock()
        self._listeners: list[Listener] = []
        self._guards: list[Callable[[RobotState, str], str]] = []
        self._effector: Callable[[RobotState, RobotState, str], str] | None = None
        self.last_reason = ""

    @property
    def state(self) -> RobotState:
        return self._state

    def add_guard(self, guard: Callable[[RobotState, str], str]) -> None:
        """``guard(state, event)`` returns why the event must be refused now ('' to allow):
        e.g. no enabling while a joint has never been measured."""
        self._guards.append(guard)

    def set_effector(self, effector: Callable[[RobotState, RobotState, str], str]) -> None:
        """``effector(old, new, event)`` carries out a transition before it is committed and
        returns why it could not ('' when done); see the class docstring."""
        self._effector = effector

    def add_listener(self, listener: Listener) -> None:
        self._listeners.append(listener)

    def remove_listener(self, listener: Listener) -> None:
        self._listeners.remove(listener)

    @staticmethod
    def _normalise(event: str) -> str:
        name = event.strip().lower().replace("-", "").replace("_", "")
        if name not in EVENTS:
            raise ValueError(f"unknown event {event!r}; events are: {', '.join(EVENTS)}")
        return name

    def allowed_events(self, state: RobotState | None = None) -> list[str]:
        """Events accepted from ``state`` (default: the current state), in EVENTS order."""
        state = self._state if state is None else state
        return [e for e in EVENTS if (state, e) in TRANSITIONS]

    def can(self, event: str) -> bool:
        return (self._state, self._normalise(event)) in TRANSITIONS

    def _now(self) -> float:
        if self._clock is not None:
            return float(self._clock.wall_time())
        return time.time()

    def request(self, event: str, reason: str = "") -> Transition:
        """Apply ``event``; raise :class:`StateError` (state unchanged) if refused, or
        :class:`TransitionFailed` when the effector or a listener failed (see the class
        docstring)."""
        name = self._normalise(event)
        with self._lock:
            old = self._state
            new = self._admit(old, name)
            failed = ""
            if new is not old and self._effector is not None:
                failed = self._effector(old, new, name)
            if not failed:
                self._state = new
                if new is not old:
                    self.last_reason = reason
        if failed:
            # vetoed: latch FAULT with the reason (its effector powers everything off)
            if TRANSITIONS.get((old, "fault"), old) is not old:
                self.request("fault", f"{name} failed: {failed}")
            raise TransitionFailed(
                f"{name!r} failed in state {old.value}: {failed}; the robot is {self._state.value}"
            )
        transition = Transition(old, new, name, reason, self._now())
        if transition.changed:
            errors = []
            for listener in list(self._listeners):
                try:
                    listener(old, new, name, reason, transition.time)
                except Exception as err:  # noqa: BLE001 - every listener runs; see below
                    logger.exception("state listener %r failed on %s -> %s", listener, old, new)
                    errors.append(f"state listener raised {type(err).__name__}: {err}")
            if errors:
                text = "; ".join(errors)
                if new not in _LATCHED:
                    self.request("fault", text)
                raise TransitionFailed(f"{name!r}: {text}; the robot is {self._state.value}")
        return transition

    def check(self, event: str) -> RobotState:
        """The state ``event`` would lead to now, or the :class:`StateError` :meth:`request`
        would raise (its table and its guards); nothing is carried out (a power-up off the
        loop thread asks first, occ/core/powerup.py)."""
        name = self._normalise(event)
        with self._lock:
            return self._admit(self._state, name)

    def _admit(self, old: RobotState, name: str) -> RobotState:
        new = TRANSITIONS.get((old, name))
        if new is None:
            allowed = ", ".join(self.allowed_events(old)) or "nothing"
            raise StateError(
                f"{name!r} refused in state {old.value}; allowed from {old.value}: {allowed}"
            )
        for guard in self._guards:
            why = guard(old, name)
            if why:
                raise StateError(f"{name!r} refused in state {old.value}: {why}")
        return new

    def try_request(self, event: str, reason: str = "") -> Transition | None:
        """Like :meth:`request` but return None instead of raising when refused (for safety
        code that must go on). A failed transition has latched FAULT already; it is logged."""
        try:
            return self.request(event, reason)
        except TransitionFailed as err:
            logger.error("%s", err)
            return None
        except StateError:
            return None

    def __repr__(self) -> str:
        return f"StateMachine(state={self._state.value})"


# --------------------------------------------------------------------------------------------
# Packet-loss monitor
# --------------------------------------------------------------------------------------------

_MASK32 = 0xFFFFFFFF
_HALF32 = 0x80000000
_WINDOW = 64  # sequence numbers remembered behind the newest, to tell duplicates from late ones
_WINDOW_MASK = (1 << _WINDOW) - 1


class Verdict(enum.IntEnum):
    """What :meth:`LossMonitor.on_packet` decided about one sample. Only ``ACCEPT`` may move
    the robot; every other verdict is counted under its own name."""

    ACCEPT = 0
    DUPLICATE = 1  # a sequence number (or timestamp) already seen
    LATE = 2  # an older, missing sequence number that arrived after a newer one (reordered)
    IMPLAUSIBLE = 3  # a sequence number that cannot be right: too far ahead, or far behind
    STALE = 4  # header timestamp older than the peer's clock offset allows
    FUTURE = 5  # header timestamp newer than the peer's clock offset allows
    UNSEQUENCED = 6  # no sequence number on a stream that carries them (a v1 peer)


_VERDICT_COUNTER = {
    Verdict.DUPLICATE: "duplicates",
    Verdict.LATE: "reordered",
    Verdict.IMPLAUSIBLE: "implausible_seq",
    Verdict.STALE: "stale",
    Verdict.FUTURE: "future",
    Verdict.UNSEQUENCED: "unsequenced",
}


@dataclass(frozen=True, slots=True)
class LossEvent:
    """Something the robot must act on (see :class:`LossMonitor`).

    ``kind``: ``"hold"`` (the stream is overdue: stop moving, not latched), ``"resume"`` (it
    came back in time: follow again), ``"latch"`` (a real failure: latched stop with an
    alert), ``"refused"`` (samples refused as implausible: alert, keep following).
    ``source`` says how it was noticed: ``"sequence"``, ``"timestamp"``, ``"deadline"``,
    ``"grace"`` or ``"check"``.
    """

    kind: str
    cause: str
    source: str
    run: int
    time: float
    since_last_good_s: float
    #: the first and last sequence numbers judged lost (a latch proven by a gap in the
    #: numbers), None otherwise: what ``occ-record why`` names from a black box dump
    lost: tuple[int, int] | None = None

    @property
    def latched(self) -> bool:
        return self.kind == "latch"


_PRIORITY = {"refused": 0, "hold": 1, "resume": 2, "latch": 3}


class LossMonitor:
    """Loss versus lateness of a periodic stream (the OCC rule, Arata et al. 2010, plus what a
    real deployment needs).

    Lateness (the deadline, not latched): expected packet ``i`` is due at
    ``last_good + i * period_s``; when the stream is overdue by ``max_consecutive + 1``
    periods plus ``tolerance_s`` (default 2 ms x 3 + 0.5 ms = 6.5 ms, so a 1 kHz loop notices
    at the tick exactly 7 ms after the last good packet) the monitor *holds*: the robot keeps
    its last safe setpoint. A stream that comes back before ``grace_s`` with no gap of
    ``max_consecutive + 1`` sequence numbers *resumes* by itself (counted, with an event).

    Loss (latched until :meth:`reset`):

    - ``max_consecutive + 1`` or more consecutive sequence numbers missing (IGTL v2 message
      ID, uint32, wrap-around handled), proven by the first packet after the gap; for v1
      peers without IDs, the same gap told by the sender timestamps (``round(gap/period) - 1``
      missing);
    - silence past ``grace_s`` (default 100 ms: a dead master);
    - with ``strict=True`` (the paper's rule word for word) the deadline itself latches.

    Samples are judged, not just counted: :meth:`on_packet` returns a :class:`Verdict` and only
    ``ACCEPT`` may be applied. Duplicates and late (reordered) numbers are not applied and
    do not refresh the deadline. A number further ahead than the elapsed time allows
    (``elapsed / period + seq_slack``) or further behind than the 64-number window is
    *implausible*: refused without a loss (an alert event, rate-limited), so a stray datagram
    cannot stop teleoperation and cannot steer it either. Once a stream has carried sequence
    numbers, a sample without one (a v1 peer) is refused: it cannot refresh the deadline.

    Timestamps (``timestamp_tolerance_s``, None = off): each sample's age
    ``rx_time - timestamp`` is compared with the peer's clock offset (the two clocks differ
    and drift; a constant offset between the receiver's monotonic clock and the sender's wall
    clock cancels out). Older than the offset by more than the tolerance: STALE; newer:
    FUTURE. The offset is the *smallest* age seen (an age is the offset plus a transit or
    queueing delay, never less): an accepted younger sample sets it at once, an older one
    moves it up by 1 % (drift). Tracking by 1 % both ways, as before, let the samples that
    queue up before the loop's first tick (the socket is bound before the loop starts) teach
    an offset tens of ms too old, and the fresh samples after them were refused as "in the
    future" until the robot stopped. A refused sample still arrived: its sequence number is
    accounted for (never a loss), but it is not applied and does not refresh the deadline, so
    a stream of late samples holds at the deadline, resumes by itself when fresh samples come
    back, and latches only at the grace, like a silent one. (Three refused in a row used to
    latch as a loss: on a busy 2-core machine a starved master stamps its samples and sends
    them 60-80 ms later, and the slave stopped with no packet missing.)

    ``lost_total`` counts only proven losses: gaps between accepted sequence numbers, minus
    late arrivals that filled them. Samples the daemon itself could not take in time (its
    stream queue overflowed) must still be passed to :meth:`on_packet` so that the sequence
    accounting sees every number that arrived.

    Timing contract: pass the loop's tick time as ``now`` to :meth:`on_packet` (when the tick
    drains the packet) and to :meth:`check` (after draining, every tick). :meth:`check` is
    O(1) and allocates nothing except when it returns an event. Not thread-safe: loop thread.
    """

    def __init__(
        self,
        period_s: float = 0.002,
        max_consecutive: int = 2,
        deadline_s: float | None = None,
        *,
        tolerance_s: float | None = None,
        grace_s: float = 0.100,
        strict: bool = False,
        timestamp_tolerance_s: float | None = None,
        seq_slack: int = 10,
        alert_interval_s: float = 1.0,
    ) -> None:
        if period_s <= 0:
            raise ValueError(f"period_s must be > 0, got {float(period_s)}")
        if max_consecutive < 0:
            raise ValueError(f"max_consecutive must be >= 0, got {max_consecutive}")
        self.period_s = float(period_s)
        self.max_consecutive = int(max_consecutive)
        self.tolerance_s = self.period_s / 4.0 if tolerance_s is None else float(tolerance_s)
        self.deadline_s = (
            self.period_s * (self.max_consecutive + 1) + self.tolerance_s
            if deadline_s is None
            else float(deadline_s)
        )
        if grace_s < self.deadline_s:
            raise ValueError(f"grace_s ({grace_s}) must be >= the deadline ({self.deadline_s})")
        self.grace_s = float(grace_s)
        self.strict = bool(strict)
        self.timestamp_tolerance_s = (
            None if timestamp_tolerance_s is None else float(timestamp_tolerance_s)
        )
        self.seq_slack = int(seq_slack)
        self.alert_interval_s = float(alert_interval_s)
        self.received = 0
        self.accepted = 0
        self.lost_total = 0
        self.max_run = 0
        self.duplicates = 0
        self.reordered = 0
        self.implausible_seq = 0
        self.stale = 0
        self.future = 0
        self.unsequenced = 0
        self.holds = 0
        self.resumes = 0
        self.trips = 0
        self.offset_s: float | None = None
        self._reset_stream(None)

    # -------------------------------------------------------------- state
    def _reset_stream(self, now: float | None) -> None:
        self._last_seq: int | None = None
        self._window = 0
        self._last_ts: float | None = None
        self._last_good: float | None = now
        self._holding = False
        self._tripped = False
        self._pending: LossEvent | None = None
        self._refused_since_good = 0
        self._next_refused_alert = -math.inf
        self.offset_s = None
        self.trip_event: LossEvent | None = None

    def reset(self, now: float | None = None) -> None:
        """Clear the latch and the hold and forget the stream position and the peer's clock
        offset (counters are kept). With ``now`` the deadline is armed from ``now``;
        otherwise by the next accepted packet."""
        self._reset_stream(now)

    def arm(self, now: float) -> None:
        """Start the deadline at ``now`` without a packet (e.g. on entering RUNNING)."""
        self._last_good = now

    @property
    def tripped(self) -> bool:
        """Latched (a real loss): stays True until :meth:`reset`."""
        return self._tripped

    @property
    def holding(self) -> bool:
        """The stream is overdue (or latched): the robot must not follow it."""
        return self._holding or self._tripped

    @property
    def last_good(self) -> float | None:
        return self._last_good

    # -------------------------------------------------------------- samples
    def on_packet(
        self,
        seq: int | None,
        timestamp: float | None,
        now: float,
        rx_time: float | None = None,
        rx_earliest: float | None = None,
    ) -> Verdict:
        """Judge one received sample (see the class docstring); ``rx_time`` is when it was
        received (default ``now``), for the timestamp check. ``rx_earliest`` (default
        ``rx_time``) is the earliest it can have arrived: a receiver that reads its socket once
        a tick knows only that a datagram came after its previous read. A sample is refused as
        stale only when it is too old even for that earliest arrival, so the receiver's own
        stall (a 70 ms VM pause of the slave) is never taken for old samples; it is refused as
        from the future only when it is too young even for ``rx_time``."""
        self.received += 1
        rx = now if rx_time is None else rx_time
        verdict = self._judge(seq, timestamp, now, rx, rx if rx_earliest is None else rx_earliest)
        if verdict is not Verdict.ACCEPT:
            name = _VERDICT_COUNTER[verdict]
            setattr(self, name, getattr(self, name) + 1)
        return verdict

    def _judge(
        self, seq: int | None, ts: float | None, now: float, rx: float, rx_lo: float
    ) -> Verdict:
        """The verdict on one sample, in three steps: what its sequence number (or, without
        one, its timestamp) says was lost before it (:meth:`_by_sequence`,
        :meth:`_by_timestamp`, counted by :meth:`_count_gap`); whether its timestamp fits the
        peer's clock (:meth:`_check_clock`); accepted (:meth:`_accept`)."""
        # 1. the sequence number: every plausible new number is accounted for, whatever its
        # timestamp (a late sample arrived: it is not lost), so only gaps prove a loss
        found: Verdict | tuple[int, str]
        if seq is not None:
            source = "sequence"
            found = self._by_sequence(seq & _MASK32, now)
        elif self._last_seq is not None:
            return Verdict.UNSEQUENCED
        elif ts is not None and ts > 0.0:
            source = "timestamp"
            found = self._by_timestamp(ts)
        else:
            source, found = "deadline", (0, "")
        if isinstance(found, Verdict):
            return found
        gap, where = found
        self._count_gap(gap, where, source, now)
        # 2. the timestamp, against the peer's learned clock offset
        refused = self._check_clock(ts, rx, rx_lo)
        if refused is not None:
            return refused
        # 3. accepted: resume after a hold
        return self._accept(gap, source, now)

    def _by_sequence(self, seq: int, now: float) -> Verdict | tuple[int, str]:
        """A sequenced sample (``seq`` masked to 32 bits): its verdict when it ends here
        (duplicate, late, implausible), else the packets missing before it and, when they are
        more than ``max_consecutive``, which."""
        gap = 0
        where = ""
        last = self._last_seq
        if last is None:
            self._window = 1
        else:
            d = (seq - last) & _MASK32
            if d == 0:
                return Verdict.DUPLICATE
            if d >= _HALF32:  # behind the newest
                return self._behind(seq, last, now)
            lg = self._last_good
            allowed = self.seq_slack + (0 if lg is None else int((now - lg) / self.period_s) + 1)
            if d > allowed:
                why = f"seq {seq} is {d} ahead of {last} (at most {allowed} possible)"
                return self._implausible(why, now)
            gap = d - 1
            self._window = ((self._window << d) | 1) & _WINDOW_MASK if d < _WINDOW else 1
            if gap > self.max_consecutive:
                where = f"seq {(last + 1) & _MASK32}-{(seq - 1) & _MASK32} missing"
        self._last_seq = seq
        return gap, where

    def _behind(self, seq: int, last: int, now: float) -> Verdict:
        """A number behind the newest: late when it is in the window and not seen yet (no
        longer lost), a duplicate when seen, implausible when further back."""
        back = (last - seq) & _MASK32
        if back >= _WINDOW:
            return self._implausible(f"seq {seq} is {back} behind {last}", now)
        bit = 1 << back
        if self._window & bit:
            return Verdict.DUPLICATE
        self._window |= bit
        if self.lost_total > 0:
            self.lost_total -= 1
        return Verdict.LATE

    def _by_timestamp(self, ts: float) -> Verdict | tuple[int, str]:
        """An unsequenced sample with a timestamp: its verdict when it ends here (duplicate,
        late), else the periods missing before it and, past ``max_consecutive``, how long the
        gap was."""
        gap = 0
        where = ""
        last_ts = self._last_ts
        if last_ts is not None:
            dt = ts - last_ts
            if dt == 0.0:
                return Verdict.DUPLICATE
            if dt < 0.0:
                return Verdict.LATE
            gap = max(0, round(dt / self.period_s) - 1)
            if gap > self.max_consecutive:
                where = f"timestamp gap {dt * 1e3:.1f} ms"
        self._last_ts = ts
        return gap, where

    def _count_gap(self, gap: int, where: str, source: str, now: float) -> None:
        """The packets missing before a sample counted; more than ``max_consecutive`` trips
        the latch (once)."""
        self.lost_total += gap
        if gap > self.max_run:
            self.max_run = gap
        if gap > self.max_consecutive and not self._tripped:
            lg = self._last_good
            since = now - lg if lg is not None else 0.0
            seq = self._last_seq  # the number that proved the gap (sequenced streams)
            lost = None
            if source == "sequence" and seq is not None:
                lost = ((seq - gap) & _MASK32, (seq - 1) & _MASK32)
            cause = f"{gap} consecutive packets lost ({where})"
            self._trip(cause, source, gap, now, since, lost)

    def _check_clock(self, ts: float | None, rx: float, rx_lo: float) -> Verdict | None:
        """The timestamp against the peer's learned clock offset: a sample too old (or from
        the future) is not applied and does not refresh the deadline, so a late stream holds
        and a silent one latches at the grace, as any late stream does; it is never called
        lost by itself (a busy sender stamps, then sends late). None: it fits (the offset
        learned from it)."""
        tol = self.timestamp_tolerance_s
        if tol is not None and ts is not None and ts > 0.0:
            age = rx - ts
            offset = self.offset_s
            if offset is not None and (rx_lo - ts - offset > tol or offset - age > tol):
                self._refused_since_good += 1
                return Verdict.FUTURE if age < offset else Verdict.STALE
            if offset is None or age < offset:
                self.offset_s = age  # a younger sample: the smallest age is the offset
            else:
                # slow tracking upward (drift), bounded per sample
                self.offset_s = offset + 0.01 * (age - offset)
        return None

    def _accept(self, gap: int, source: str, now: float) -> Verdict:
        """Accepted: the deadline refreshed, and a stream that was held resumes."""
        self.accepted += 1
        lg = self._last_good
        since = now - lg if lg is not None else 0.0
        self._last_good = now
        refused = self._refused_since_good
        self._refused_since_good = 0
        if self._holding and not self._tripped:
            self._holding = False
            self.resumes += 1
            extra = f", {refused} refused meanwhile" if refused else ""
            self._post(
                LossEvent(
                    "resume",
                    f"stream back after {since * 1e3:.1f} ms (gap {gap}{extra}); following again",
                    source,
                    gap,
                    now,
                    since,
                )
            )
        return Verdict.ACCEPT

    def _implausible(self, what: str, now: float) -> Verdict:
        if now >= self._next_refused_alert:
            self._next_refused_alert = now + self.alert_interval_s
            self._post(
                LossEvent(
                    "refused",
                    f"refused an implausible sequence number: {what} "
                    f"({self.implausible_seq + 1} so far)",
                    "sequence",
                    0,
                    now,
                    0.0,
                )
            )
        self._refused_since_good += 1
        return Verdict.IMPLAUSIBLE

    # -------------------------------------------------------------- every tick
    def check(self, now: float) -> LossEvent | None:
        """Call every tick after draining packets; returns at most one event (the most
        important one since the last call)."""
        last = self._last_good
        if last is not None and not self._tripped:
            elapsed = now - last
            if elapsed > self.deadline_s:
                if elapsed > self.grace_s or self.strict:
                    refused = self._refused_since_good
                    extra = f"; {refused} samples refused meanwhile" if refused else ""
                    what = "grace" if elapsed > self.grace_s else "deadline"
                    limit = self.grace_s if what == "grace" else self.deadline_s
                    self._trip(
                        f"no packet for {elapsed * 1e3:.2f} ms (limit {limit * 1e3:.1f} ms"
                        f"{', strict' if what == 'deadline' else ''}){extra}",
                        what,
                        int((elapsed - self.tolerance_s) / self.period_s),
                        now,
                        elapsed,
                    )
                elif not self._holding:
                    self._holding = True
                    self.holds += 1
                    self._post(
                        LossEvent(
                            "hold",
                            f"no packet for {elapsed * 1e3:.1f} ms: holding",
                            "deadline",
                            int((elapsed - self.tolerance_s) / self.period_s),
                            now,
                            elapsed,
                        )
                    )
        pending = self._pending
        if pending is not None:
            self._pending = None
        return pending

    def _post(self, event: LossEvent) -> None:
        p = self._pending
        if p is None or _PRIORITY[event.kind] >= _PRIORITY[p.kind]:
            self._pending = event

    def _trip(
        self,
        cause: str,
        source: str,
        run: int,
        now: float,
        since: float = 0.0,
        lost: tuple[int, int] | None = None,
    ) -> None:
        self._tripped = True
        self._holding = False
        self.trips += 1
        event = LossEvent("latch", cause, source, run, now, since, lost)
        self.trip_event = event
        self._post(event)

    def counters(self) -> dict[str, Any]:
        """Counters for the stats snapshot."""
        return {
            "received": self.received,
            "accepted": self.accepted,
            "lost_total": self.lost_total,
            "max_run": self.max_run,
            "duplicates": self.duplicates,
            "reordered": self.reordered,
            "implausible_seq": self.implausible_seq,
            "stale": self.stale,
            "future": self.future,
            "unsequenced": self.unsequenced,
            "holds": self.holds,
            "resumes": self.resumes,
            "trips": self.trips,
            "holding": self.holding,
            "tripped": self._tripped,
            "clock_offset_ms": None if self.offset_s is None else round(self.offset_s * 1e3, 3),
        }
