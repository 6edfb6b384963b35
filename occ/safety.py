"""Safety logic of the daemon: loop watchdog, robot state machine, packet-loss monitor.

Everything here is pure logic: no I/O, no threads, no clock of its own. The loop feeds it
times (seconds, from its :class:`~occ.clock.Clock`) and acts on what it returns or calls
back, so the same code runs in real time and in simulated time, and is tested exactly.

- :class:`Watchdog`: per-tick overrun detection -> alert callback, and a stop callback on a
  run of overruns or one long gap between ticks.
- :class:`RobotState`, :class:`StateMachine`: the robot lifecycle (OCC + dVRK +
  ros2_control), with latched FAULT and ESTOP.
- :class:`LossMonitor`: lost packets of a periodic stream, by sequence number, by timestamp
  (v1 peers) and by deadline (silent peer); trips on ``max_consecutive + 1`` consecutive
  losses.
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
    "TRANSITIONS",
    "LossEvent",
    "LossMonitor",
    "RobotState",
    "StateMachine",
    "Transition",
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
    :meth:`check` lets a supervisor thread detect a loop that stopped ticking altogether; it
    needs ``now`` passed to :meth:`feed`. Callbacks run on the thread that fed or checked.
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
            raise ValueError(f"budget_s must be > 0, got {budget_s}")
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
        self._last_feed_now: float | None = None

    def feed(self, period_s: float | None, compute_s: float, now: float | None = None) -> bool:
        """Account for one tick; return True when it was an overrun."""
        if now is not None:
            self._last_feed_now = now
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

    def check(self, now: float) -> bool:
        """From a supervisor: stop if no tick was fed for more than ``hard_gap_s``.

        Returns True when the watchdog is (now) stopped.
        """
        last = self._last_feed_now
        if last is not None and not self.stopped and now - last > self.hard_gap_s:
            self._trigger_stop(
                f"no tick for {(now - last) * 1e3:.3f} ms "
                f"(hard limit {self.hard_gap_s * 1e3:.3f} ms)"
            )
        return self.stopped

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

    Threading: transitions are meant to happen on the loop thread (commands from interface
    threads are queued to it). A lock makes the check-and-set atomic anyway, so a stray call
    from another thread cannot corrupt the state; :attr:`state` may be read from any thread.
    Listeners ``(old, new, event, reason, time)`` run after the change, outside the lock, on
    the requesting thread; a listener that raises is logged and does not stop the others or
    undo the transition. ``time`` is ``clock.wall_time()`` (Unix seconds, for IGTL STATUS).
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
        self.last_reason = ""

    @property
    def state(self) -> RobotState:
        return self._state

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
        """Apply ``event``; raise :class:`StateError` (state unchanged) if refused."""
        name = self._normalise(event)
        with self._lock:
            old = self._state
            new = TRANSITIONS.get((old, name))
            if new is None:
                allowed = ", ".join(self.allowed_events(old)) or "nothing"
                raise StateError(
                    f"{name!r} refused in state {old.value}; allowed from {old.value}: {allowed}"
                )
            self._state = new
            if new is not old:
                self.last_reason = reason
        transition = Transition(old, new, name, reason, self._now())
        if transition.changed:
            for listener in list(self._listeners):
                try:
                    listener(old, new, name, reason, transition.time)
                except Exception:
                    logger.exception("state listener %r failed on %s -> %s", listener, old, new)
        return transition

    def try_request(self, event: str, reason: str = "") -> Transition | None:
        """Like :meth:`request` but return None instead of raising when refused."""
        try:
            return self.request(event, reason)
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


@dataclass(frozen=True, slots=True)
class LossEvent:
    """A loss-monitor trip: ``kind`` is "sequence", "timestamp" or "deadline"."""

    cause: str
    kind: str
    run: int
    time: float
    since_last_good_s: float


class LossMonitor:
    """Counts lost packets of a periodic stream and trips on too many in a row.

    Three ways to notice a loss:

    (a) sequence numbers (IGTL v2 message ID, uint32, wrap-around handled): a jump of ``d``
        means ``d - 1`` packets lost. A repeated number is a *duplicate*; an older one that
        was missing is *reordered* (late) and taken back out of ``lost_total``; neither
        counts as a loss nor refreshes the deadline. The last 64 numbers are remembered.
    (b) the deadline since the last good packet: expected packet ``i`` is due at
        ``last_good + i * period_s`` and *overdue* once ``now`` passes that plus
        ``tolerance_s`` (default ``period_s / 4``). Each overdue packet counts as lost, so a
        silent peer is noticed without any packet arriving. Once a packet arrives, its
        sequence number (or timestamp) corrects the count.
    (c) v1 peers without sequence numbers: by sender timestamp gaps,
        ``round(gap / period_s) - 1`` missing.

    Up to ``max_consecutive`` consecutive losses are tolerated; ``max_consecutive + 1`` trips.
    :meth:`check` returns the :class:`LossEvent` once and the monitor stays tripped (latched)
    until :meth:`reset`.

    Timing contract (OCC, Arata et al. 2010: 500 Hz positions, 2 lost tolerated, 3 lost
    stop within 7 ms): pass the *loop's tick time* as ``now`` both to :meth:`on_packet`
    (when the tick drains the packet) and to :meth:`check` (after draining, every tick). The
    default deadline is ``period_s * (max_consecutive + 1) + tolerance_s`` = 6.5 ms, so a
    1 kHz loop trips at the tick exactly 7 ms after the tick that took the last good packet
    -- the first tick at which the third packet (due at +6 ms) is overdue -- while a packet
    delayed by up to one tick still arrives in time. ``check`` is O(1) and allocates nothing
    except when it trips.

    Not thread-safe: call from the loop thread.
    """

    def __init__(
        self,
        period_s: float = 0.002,
        max_consecutive: int = 2,
        deadline_s: float | None = None,
        *,
        tolerance_s: float | None = None,
    ) -> None:
        if period_s <= 0:
            raise ValueError(f"period_s must be > 0, got {period_s}")
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
        # the first elapsed time at which anything can be overdue: skip the maths before it
        self._quiet_s = min(self.period_s + self.tolerance_s, self.deadline_s)
        self.received = 0
        self.lost_total = 0
        self.max_run = 0
        self.duplicates = 0
        self.reordered = 0
        self.trips = 0
        self._reset_stream(None)

    def _reset_stream(self, now: float | None) -> None:
        self._last_seq: int | None = None
        self._window = 0
        self._last_ts: float | None = None
        self._last_good: float | None = now
        self._silent = 0  # losses already counted by the deadline since the last good packet
        self._tripped = False
        self._pending: LossEvent | None = None

    def reset(self, now: float | None = None) -> None:
        """Clear the latch and forget the stream position (counters are kept).

        With ``now``, the deadline is armed from ``now``; otherwise it is armed by the next
        packet.
        """
        self._reset_stream(now)

    def arm(self, now: float) -> None:
        """Start the deadline at ``now`` without a packet (e.g. on entering RUNNING)."""
        self._last_good = now
        self._silent = 0

    @property
    def tripped(self) -> bool:
        return self._tripped

    @property
    def last_good(self) -> float | None:
        return self._last_good

    def on_packet(self, seq: int | None, timestamp: float | None, now: float) -> None:
        """Account for one received packet (seq preferred, else timestamp, else arrival)."""
        self.received += 1
        if seq is not None:
            seq &= _MASK32
            last = self._last_seq
            if last is None:
                gap = 0
                self._window = 1
            else:
                d = (seq - last) & _MASK32
                if d == 0:
                    self.duplicates += 1
                    return
                if d >= _HALF32:  # behind the newest: duplicate or late
                    back = (last - seq) & _MASK32
                    if back < _WINDOW:
                        bit = 1 << back
                        if self._window & bit:
                            self.duplicates += 1
                            return
                        self._window |= bit
                        if self.lost_total > 0:
                            self.lost_total -= 1
                    self.reordered += 1
                    return
                gap = d - 1
                self._window = ((self._window << d) | 1) & _WINDOW_MASK if d < _WINDOW else 1
            self._last_seq = seq
            if gap > self.max_consecutive:
                first = (seq - gap) & _MASK32
                last_lost = (seq - 1) & _MASK32
                where = f"seq {first}-{last_lost}"
                self._good(gap, now, "sequence", where)
            else:
                self._good(gap, now, "sequence", "")
            return
        if timestamp is not None:
            last_ts = self._last_ts
            if last_ts is None:
                gap = 0
            else:
                dt = timestamp - last_ts
                if dt == 0.0:
                    self.duplicates += 1
                    return
                if dt < 0.0:
                    self.reordered += 1
                    return
                gap = max(0, round(dt / self.period_s) - 1)
            self._last_ts = timestamp
            where = ""
            if gap > self.max_consecutive and last_ts is not None:
                where = f"timestamp gap {(timestamp - last_ts) * 1e3:.1f} ms"
            self._good(gap, now, "timestamp", where)
            return
        self._good(self._silent, now, "deadline", "")

    def _good(self, gap: int, now: float, kind: str, where: str) -> None:
        # ``gap`` is authoritative; correct what the deadline already counted as lost.
        self.lost_total = max(0, self.lost_total + gap - self._silent)
        self.max_run = max(self.max_run, gap)
        since = now - self._last_good if self._last_good is not None else 0.0
        self._last_good = now
        self._silent = 0
        if gap > self.max_consecutive and not self._tripped:
            where = where or f"{since * 1e3:.1f} ms without a packet"
            self._trip(f"{gap} consecutive packets lost ({where})", kind, gap, now, since)

    def check(self, now: float) -> LossEvent | None:
        """Call every tick after draining packets; returns a :class:`LossEvent` once on trip."""
        pending = self._pending
        if pending is not None:
            self._pending = None
            return pending
        last = self._last_good
        if last is None or self._tripped:
            return None
        elapsed = now - last
        if elapsed <= self._quiet_s:
            return None
        overdue = math.ceil((elapsed - self.tolerance_s) / self.period_s) - 1
        if overdue > self._silent:
            self.lost_total += overdue - self._silent
            self._silent = overdue
            self.max_run = max(self.max_run, overdue)
        if elapsed > self.deadline_s:
            self._trip(
                f"no packet for {elapsed * 1e3:.1f} ms ({overdue} periods)",
                "deadline",
                overdue,
                now,
                elapsed,
            )
            event = self._pending
            self._pending = None
            return event
        return None

    def _trip(self, cause: str, kind: str, run: int, now: float, since: float) -> None:
        self._tripped = True
        self.trips += 1
        self._pending = LossEvent(cause, kind, run, now, since)

    def counters(self) -> dict[str, Any]:
        """Counters for the stats snapshot (``LoopStats.interfaces``)."""
        return {
            "received": self.received,
            "lost_total": self.lost_total,
            "max_run": self.max_run,
            "duplicates": self.duplicates,
            "reordered": self.reordered,
            "trips": self.trips,
            "tripped": self._tripped,
        }
