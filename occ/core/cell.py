"""The cell: several daemons around one patient, one safety (issue 40; the German Heart Center's
arms, whose collision detection stops every arm).

Each member heartbeats every other over its cell link (occ/net/celllink.py: OpenIGTLink over
UDP, sequence-numbered, signed when keyed) at least every ``cell.period_ms`` and at once when
its state or its stop changes: its state, its *stop* (why it left RUNNING for a safety reason,
and the member that stop comes from), its joint positions, its base and its chain's hash.

A member's stop
    Set when it enters FAULT or ESTOP (any cause, operator's EStop included), when it is held
    by a safety stop (the loss monitor's latch, the watchdog, a collision: Alarms'
    ``safety_stop``; never an operator's plain Stop or Disable), when its supervisor finds the
    loop hung (announced from the supervisor's thread, since the loop cannot), and when the
    cell holds it for another member (a *relay*: the origin is that member). It stands until
    the member is RUNNING again.

What the others do (``policy: stop-all``)
    A member with a stop of its own or relayed (its origin not this daemon), a member silent
    past ``grace_ms`` after it was heard, or one that shut down, is an *origin*: this daemon is
    held (RUNNING or ENABLED -> STOPPED, the drives holding) in the tick that sees it, with a
    ``CELL`` alert to every operator naming the origin and its cause. The origin stays latched
    here: ``Run`` is refused, naming it, until the origin is heard RUNNING, or its own stop is
    only a relay of one that started here (two members that lost each other), or it left the
    cell (``CellLeave`` on it, or ``CellForget <member>`` here for one that is gone). A relay
    whose origin is not in this daemon's member list (the members' files disagree) holds too,
    until no member relays it: its recovery cannot be seen from here. A member
    not heard since this daemon started refuses ``Run`` too (the cell is incomplete), without
    a latch. A member whose chain hash differs from its configured URDF's refuses Run and holds
    (where its arm is cannot be checked). ``alert-only``: the alerts without the hold.

Members that left
    ``CellLeave`` makes this member leave: its heartbeats say so and go on (its arm is still
    where it is: the others keep checking against it), its stops stop no one, and the cell's
    stop it no more; ``CellJoin`` comes back. A member that left is judged again when it joins.

Timing: a member's stop reaches the others in the heartbeat sent in the tick it happened, and
holds them in the tick they read it (1 ms loops: a few ms; measured by tools/cell_faults.py,
docs/BENCHMARKS.md). A member killed or frozen is noticed by its silence: ``grace_ms`` plus a
tick. Each hold records its propagation: the hold's wall time minus the origin's stop's (the
same host's clock, or clocks agreeing as the auth freshness needs).
"""

from __future__ import annotations

import logging
import math
import socket
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from occ.clock import RealClock
from occ.core.safety import RobotState
from occ.net.celllink import Beat, CellLink

if TYPE_CHECKING:
    from occ.clock import Clock
    from occ.config import CellConfig
    from occ.core.alarms import Alarms
    from occ.core.data import RobotData
    from occ.core.safety import StateMachine

__all__ = ["Cell", "Member"]

log = logging.getLogger(__name__)

#: the STATUS code of a ``CELL`` alert (OpenIGTLink's DISABLED: this arm is held)
CELL_STATUS_CODE = 15
_STOPPED = (RobotState.FAULT, RobotState.ESTOP)
_POWERED = (RobotState.RUNNING, RobotState.ENABLED)
#: a heartbeat is due this much before its period ends: a tick's time on a grid of 1 ms
#: (k * 1e-3) is often a hair before the last send's time plus 5 ms, and that tick must send
#: (it waited for the next, 6 ms after the last, in 15 % of the periods)
_SEND_SLACK_S = 1e-6


@dataclass
class Member:
    """What this daemon knows of one other member."""

    name: str
    address: tuple[str, int]
    #: the chain hash its configured URDF gives (None: no geometry configured)
    chain: str | None
    heard: float | None = None
    boot: int = 0
    seq: int = 0
    state: str = ""
    cause: str = ""
    origin: str = ""
    stop_wall: float = 0.0
    #: the sender's wall clock on the last heartbeat taken (0: none yet)
    sent_wall: float = 0.0
    their_chain: str = ""
    #: it left (its own command, announced), or was forgotten here (an operator's command)
    left: bool = False
    forgotten: bool = False
    lost: int = 0
    stale: int = 0
    restarts: int = 0

    def row(self, now: float) -> dict[str, Any]:
        return {
            "state": self.state or None,
            "heard_ms_ago": None if self.heard is None else round((now - self.heard) * 1e3, 1),
            "cause": self.cause,
            "origin": self.origin,
            "left": self.left or self.forgotten,
            "chain_ok": None if self.chain is None or not self.their_chain else self.chain_ok,
            "lost": self.lost,
            "stale": self.stale,
            "restarts": self.restarts,
        }

    @property
    def chain_ok(self) -> bool:
        return self.chain is None or not self.their_chain or self.their_chain == self.chain

    @property
    def out(self) -> bool:
        return self.left or self.forgotten


@dataclass
class LastStop:
    origin: str
    cause: str
    wall: float
    propagation_ms: float | None
    #: the wall time the origin sent the last heartbeat this daemon took from it (None: never
    #: heard): for a silent origin, the hold's ``wall`` is at least ``grace_ms`` after it
    origin_sent_wall: float | None = None


@dataclass
class _Own:
    """This member's stop, as its heartbeats announce it."""

    cause: str = ""
    origin: str = ""
    stop_wall: float = 0.0
    leaving: bool = False
    #: the cell holds this robot for ``origin`` right now (its listener sees the transition)
    holding_for: tuple[str, str, float] | None = None
    propagations: deque[float] = field(default_factory=lambda: deque(maxlen=1000))


class Cell:
    """One member's side of the cell (module docstring)."""

    def __init__(
        self,
        cfg: CellConfig,
        me: str,
        link: CellLink,
        members: Sequence[Member],
        *,
        states: StateMachine,
        alarms: Alarms,
        data: RobotData,
        clock: Clock,
        chain: str,
        on_peer: Callable[[str, tuple[float, ...], tuple[float, ...], float], None] | None = None,
        on_peer_gone: Callable[[str], None] | None = None,
    ) -> None:
        self.cfg, self.name, self.me = cfg, cfg.name, me
        self.link = link
        self.members = {m.name: m for m in members}
        self.states, self.alarms, self.data, self.clock = states, alarms, data, clock
        self.chain = chain
        self.on_peer, self.on_peer_gone = on_peer, on_peer_gone
        #: ``tap(beat, "cell")``: each heartbeat the loop takes (the black box), or None
        self.tap: Callable[[Beat, str], None] | None = None
        self.stop_all = cfg.policy == "stop-all"
        self.period_s = cfg.period_ms * 1e-3
        self.grace_s = cfg.grace_ms * 1e-3
        self.boot = time.time_ns()
        self.own = _Own()
        #: origin -> why, latched until it runs again, left, or relays only this daemon
        self.latched: dict[str, str] = {}
        self.last_stop: LastStop | None = None
        self.holds = 0
        self.alerts = 0
        self._told: dict[str, str] = {}
        self._next_send = 0.0
        self._due = True
        self._start_told = ""
        #: judge again though nothing came (an operator's command changed the members)
        self._dirty = True
        #: when the member heard longest ago falls silent (the next judgement due without news)
        self._silence_due = 0.0

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self.link.start()
        states = self.states
        states.add_listener(self.on_transition)
        states.add_guard(self.may_run)
        self.alarms.on_supervisor_trip = self.announce_hung

    def stop(self) -> None:
        """The last heartbeat (SHUTDOWN: the others hold, as for a silent member) and the
        link closed."""
        try:
            self._send(self.clock.now())
        finally:
            self.link.stop()

    # ------------------------------------------------------------------ this member's stop
    def on_transition(
        self, old: RobotState, new: RobotState, event: str, reason: str, t: float
    ) -> None:
        """The state machine's listener: what this member's heartbeats say of its stop."""
        try:
            self._on_transition(old, new, reason, t)
        finally:
            # at once, from whichever thread changed the state: the others hold in their
            # next tick rather than after this loop's
            self._send(self.clock.now())

    def _on_transition(self, old: RobotState, new: RobotState, reason: str, t: float) -> None:
        own = self.own
        if new is RobotState.RUNNING:
            own.cause, own.origin, own.stop_wall = "", "", 0.0
        elif new in _STOPPED:
            own.cause, own.origin, own.stop_wall = f"{new.value}: {reason}", self.me, t
        elif new is RobotState.SHUTDOWN:
            own.cause, own.origin, own.stop_wall = "shut down", self.me, t
        elif new is RobotState.STOPPED and old in _POWERED:
            if own.holding_for is not None:
                origin, why, stop_wall = own.holding_for
                own.cause, own.origin, own.stop_wall = why, origin, stop_wall
            elif self.alarms.safety_stopping:
                own.cause, own.origin, own.stop_wall = reason, self.me, t

    def announce_stop(self, cause: str) -> None:
        """A controller's word (ControllerContext.cell_stop): this member stops the cell for
        ``cause`` (a plan run by the whole cell dropped here), as a safety stop would: the
        others hold until this member runs again. A stop already announced stands: a relay
        keeps its origin (two members each naming itself would wait for each other), a fault
        its cause."""
        own = self.own
        if not own.cause:
            own.cause, own.origin, own.stop_wall = cause, self.me, self.clock.wall_time()
        self._send(self.clock.now())

    def announce_hung(self, reason: str) -> None:
        """On the supervisor's thread: the loop is hung, so tell the others now (the loop
        would send nothing until it comes back)."""
        if self.states.state not in (*_POWERED, RobotState.STOPPED):
            return  # nothing of this arm is powered: its loop comes back to an alert only
        own = self.own
        own.cause, own.origin = f"hung loop: {reason}", self.me
        own.stop_wall = self.clock.wall_time()
        self._send(self.clock.now())

    # ------------------------------------------------------------------ the tick
    def tick(self, now: float) -> None:
        """On the loop thread, before the controllers: the heartbeats received, the members
        judged (a hold in this tick), this member's heartbeat when due."""
        beats = self.link.take()
        tap = self.tap
        for beat in beats:
            if tap is not None:
                tap(beat, "cell")
            self._on_beat(beat)
        if beats or self._dirty or now > self._silence_due:
            self._judge(now)
        if self._due or now >= self._next_send - _SEND_SLACK_S:
            self._send(now)

    def _on_beat(self, beat: Beat) -> None:
        m = self.members.get(beat.member)
        if m is None:  # the link takes members only; a cell renamed under it
            return
        if beat.boot < m.boot:
            m.stale += 1
            return
        if beat.boot > m.boot:
            if m.boot:
                m.restarts += 1
                log.warning("cell: %s restarted", m.name)
            m.boot = beat.boot
        else:
            step = (beat.seq - m.seq) & 0xFFFFFFFF
            if step == 0 or step >= 1 << 31:  # a duplicate, or older: a replay or reordered
                m.stale += 1
                return
            m.lost += step - 1
        m.seq = beat.seq
        m.heard, m.sent_wall = beat.t_rx, beat.sent_wall
        m.state, m.cause, m.origin, m.stop_wall = (
            beat.state,
            beat.cause,
            beat.origin,
            beat.stop_wall,
        )
        m.their_chain = beat.chain
        if beat.leaving != m.left:
            m.left = beat.leaving
            log.warning("cell: %s %s the cell", m.name, "left" if m.left else "joined")
        if not beat.leaving:
            m.forgotten = False  # a member heard in the cell is in it again
        if self.on_peer is not None and m.chain is not None and m.chain_ok:
            self.on_peer(m.name, beat.q, beat.base, beat.t_rx)

    def _origins(self, now: float) -> dict[str, tuple[str, float]]:
        """Every member that stops this one now: origin -> (why, the origin's stop time)."""
        out: dict[str, tuple[str, float]] = {}
        grace = self.grace_s
        for m in self.members.values():
            if m.out:
                continue
            if m.heard is None:
                continue  # incomplete, not stopped: may_run says so
            silent = now - m.heard
            if silent > grace:
                out[m.name] = (f"{m.name} silent (nothing for over {grace * 1e3:g} ms)", 0.0)
            elif not m.chain_ok:
                out[m.name] = (
                    f"{m.name}'s kinematic chain {m.their_chain} is not its URDF's {m.chain}",
                    0.0,
                )
            elif m.cause and m.origin and m.origin != self.me:
                origin = m.origin
                if origin != m.name and self._recovered(origin, now):
                    continue  # a relay of a stop this daemon sees is over
                # a member's own stop says what happened to it; a relay names its origin, and
                # an origin this daemon's cell list lacks (the members' files disagree) is held
                # for all the same: its recovery cannot be seen here, only the relay's end
                if origin == m.name:
                    why = f"{origin} {m.cause}"
                elif origin in self.members:
                    why = f"{m.cause} (via {m.name})"
                else:
                    why = f"{m.cause} (via {m.name}; {origin} is not in this member's cell list)"
                out.setdefault(origin, (why, m.stop_wall))
        return out

    def _recovered(self, origin: str, now: float) -> bool:
        """``origin`` is heard here, running with no stop of its own, or is out of the cell.
        An origin not in this daemon's list is never seen to recover: its relay stands."""
        m = self.members.get(origin)
        if m is None:
            return False
        if m.out:
            return True
        return (
            m.heard is not None
            and now - m.heard <= self.grace_s
            and m.state == RobotState.RUNNING.value
            and not m.cause
        )

    def _judge(self, now: float) -> None:
        self._dirty = False
        heard = [m.heard for m in self.members.values() if m.heard is not None and not m.out]
        self._silence_due = min(heard) + self.grace_s if heard else math.inf
        if self.own.leaving:
            return
        origins = self._origins(now)
        for origin, (why, stop_wall) in origins.items():
            if self.latched.get(origin) != why:
                self.latched[origin] = why
                self._alert(origin, why, stop_wall)
        for origin in [o for o in self.latched if o not in origins and self._cleared(o)]:
            del self.latched[origin]
            self._told.pop(origin, None)
            log.warning("cell: %s no longer stops %s", origin, self.me)

    def _cleared(self, origin: str) -> bool:
        """A latched origin is cleared once it runs again, left the cell, or its only stop is
        a relay of one that started here."""
        m = self.members.get(origin)
        if m is None or m.out:
            return True
        return m.heard is not None and (
            (m.state == RobotState.RUNNING.value and not m.cause) or m.origin == self.me
        )

    def _alert(self, origin: str, why: str, stop_wall: float) -> None:
        """A new stop from ``origin``: told to every operator; held with ``stop-all``."""
        wall = self.clock.wall_time()
        prop = (wall - stop_wall) * 1e3 if stop_wall > 0.0 else None
        m = self.members.get(origin)
        sent = m.sent_wall if m is not None and m.sent_wall > 0.0 else None
        self.last_stop = LastStop(origin, why, wall, prop, sent)
        state = self.states.state
        hold = self.stop_all and state in _POWERED
        text = f"cell {self.name}: {why}" + ("; holding" if hold else "")
        if self._told.get(origin) != why:
            self._told[origin] = why
            self.alerts += 1
            log.error("CELL: %s", text)
            self.alarms.last_alert = text
            self.alarms.broadcast("CELL", text, CELL_STATUS_CODE)
        if hold:
            self.holds += 1
            if prop is not None:
                self.own.propagations.append(prop)
            self.own.holding_for = (origin, why, stop_wall or wall)
            try:
                self.states.try_request("stop", f"cell: {why}")
            finally:
                self.own.holding_for = None

    def may_run(self, state: RobotState, event: str) -> str:
        """The state machine's guard: no Run while the cell stops this member (``stop-all``),
        or while a member has not been heard since this daemon started."""
        if event != "run" or not self.stop_all or self.own.leaving:
            return ""
        if self.latched:
            origin, why = next(iter(self.latched.items()))
            if origin not in self.members:
                return (
                    f"cell {self.name}: {why}; Run once no member relays {origin}'s stop "
                    "(the members' cell lists should agree)"
                )
            return (
                f"cell {self.name}: {why}; Run once {origin} runs again or leaves the cell "
                f"(CellLeave there, or CellForget {origin} here)"
            )
        unheard = self._unheard()
        return f"cell {self.name}: not heard yet from {unheard}" if unheard else ""

    def _unheard(self) -> str:
        """The members in the cell not heard since this daemon started, named ('' none)."""
        return ", ".join(m.name for m in self.members.values() if m.heard is None and not m.out)

    def start_wait(self, event: str) -> str:
        """``occd --start``'s gate: its Run waits (ticks on, ENABLED) until every member has
        been heard (members start one by one); why, told once, or '' to go. A latched stop
        does not wait: the Run is refused as an operator's would be."""
        if event != "run" or not self.stop_all or self.own.leaving or self.latched:
            return ""
        unheard = self._unheard()
        if not unheard:
            return ""
        why = f"--start: Run waits for cell {self.name}: not heard yet from {unheard}"
        if why != self._start_told:
            self._start_told = why
            log.warning("%s", why)
        return why

    # ------------------------------------------------------------------ heartbeats
    def _send(self, now: float) -> None:
        self._due = False
        self._next_send = now + self.period_s
        own, data = self.own, self.data
        b = data.base
        base = (*(float(v) for v in b[:3, :3].ravel()), *(float(v) for v in b[:3, 3]))
        self.link.send(
            Beat(
                cell=self.name,
                member=self.me,
                boot=self.boot,
                seq=0,
                state=self.states.state.value,
                cause=own.cause,
                origin=own.origin,
                stop_wall=own.stop_wall,
                chain=self.chain,
                q=tuple(float(v) for v in data.q),
                base=base,
                leaving=own.leaving,
            )
        )

    # ------------------------------------------------------------------ operators
    def command(self, name: str, args: dict[str, str]) -> str:
        """``CellLeave``, ``CellJoin``, ``CellForget Member=<name>``: the reply text;
        ValueError saying why it is refused."""
        key = name.lower()
        self._dirty = True
        if key == "cellleave":
            self.own.leaving, self._due = True, True
            self.latched.clear()
            return (
                f"{self.me} left cell {self.name}: its stops stop no one, the cell's stop it "
                "no more"
            )
        if key == "celljoin":
            self.own.leaving, self._due = False, True
            return f"{self.me} joined cell {self.name}"
        if key == "cellforget":
            who = args.get("Member", args.get("member", "")).strip()
            m = self.members.get(who)
            if m is None:
                known = ", ".join(sorted(self.members)) or "none"
                raise ValueError(f"no member {who!r} in cell {self.name} (members: {known})")
            m.forgotten = True
            self.latched.pop(who, None)
            self._told.pop(who, None)
            if self.on_peer_gone is not None:
                self.on_peer_gone(who)
            return f"{who} forgotten by {self.me} until it is heard in the cell again"
        raise ValueError(f"unknown cell command {name!r}")

    def stats(self) -> dict[str, Any]:
        now = self.clock.now()
        props = sorted(self.own.propagations)
        last = self.last_stop
        return {
            "name": self.name,
            "me": self.me,
            "policy": self.cfg.policy,
            "left": self.own.leaving,
            "cause": self.own.cause,
            "origin": self.own.origin,
            "members": {n: m.row(now) for n, m in self.members.items()},
            "latched": dict(self.latched),
            "holds": self.holds,
            "alerts": self.alerts,
            "last_stop": None
            if last is None
            else {
                "origin": last.origin,
                "cause": last.cause,
                "wall": last.wall,
                "propagation_ms": last.propagation_ms,
                "origin_sent_wall": last.origin_sent_wall,
            },
            "propagation_ms": {
                "n": len(props),
                "p50": props[len(props) // 2] if props else None,
                "max": props[-1] if props else None,
            },
            "link": self.link.stats(),
        }


def build_cell(
    cfg: CellConfig,
    robot_name: str,
    *,
    states: StateMachine,
    alarms: Alarms,
    data: RobotData,
    clock: Clock,
    chain: str,
    chains: Mapping[str, str | None],
    arms: tuple[Any, Any] | None = None,
) -> Cell:
    """The cell of ``cfg`` for this robot: its link bound to its own entry's address, the other
    members by their addresses (host names resolved once, here: a heartbeat is recognised by
    the address it comes from); ``chains`` the chain hash of each member's configured URDF."""
    me = cfg.me(robot_name)
    own = _address(cfg.entry(me).address)
    members = [
        Member(m.name, _address(m.address), chains.get(m.name)) for m in cfg.members if m.name != me
    ]
    key = cfg.auth_key_file.read_text(encoding="utf-8") if cfg.auth_key_file else None
    link = CellLink(
        cfg.name,
        me,
        own,
        {m.name: m.address for m in members},
        key_text=key,
        now=clock.now,
        wall=clock.wall_time,
        polled=not isinstance(clock, RealClock),  # simulated time: deterministic turns
    )
    on_peer, on_gone = arms if arms is not None else (None, None)
    return Cell(
        cfg,
        me,
        link,
        members,
        states=states,
        alarms=alarms,
        data=data,
        clock=clock,
        chain=chain,
        on_peer=on_peer,
        on_peer_gone=on_gone,
    )


def _address(text: str) -> tuple[str, int]:
    host, port = text.rsplit(":", 1)
    host = host.strip("[]")
    try:
        host = socket.gethostbyname(host)
    except OSError:
        pass  # an IPv6 literal, or unknown: used as written (the bind says so if it is wrong)
    return host, int(port)
