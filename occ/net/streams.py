"""The robot's stream inputs: the sockets the loop polls, the stream queues, the loss monitors,
and which master's stream moves the robot.

Every sample of every stream is judged by its loss monitor, in arrival order; only accepted
samples of the stream in control reach the controllers. With ``collaboration`` each master has
its own monitor and only the owner's acts on the robot; :meth:`StreamInputs.handover` moves
control (occ/net/collab.py decides who may ask).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from typing import Any

from igtl.messages.base import Message
from igtl.transport import Peer, UDPEndpoint
from occ.config import LossConfig
from occ.core.assembly import build_loss_monitors
from occ.core.safety import LossEvent, LossMonitor, Verdict
from occ.errors import CommandError
from occ.net.collab import Collaboration
from occ.net.interfaces import Inbound, Interface, InterfaceManager, StreamItem, StreamQueue
from occ.samples import PoseSample

log = logging.getLogger(__name__)

#: Datagrams a tick reads from each UDP stream socket (a 500 Hz stream brings one every other
#: tick); beyond that a flood waits in the socket buffer, which overflows: the tick's cost stays
#: bounded, and a master drowned in a flood is a failed link (hold, then the latched stop).
POLL_LIMIT = 4


def judge(
    monitor: LossMonitor, sample: PoseSample, now: float, to_wall: float, since: float = -math.inf
) -> Verdict:
    """The loss monitor's verdict on one stream sample.

    ``since`` is the previous tick's start: a sample taken in this tick arrived after it, or
    was stamped when read (a polled socket), so its earliest arrival for the timestamp
    check is ``min(t_rx, since)``: a stall of our own loop never makes samples stale."""
    rx = sample.t_rx
    return monitor.on_packet(
        sample.seq, sample.t_sample, now, rx + to_wall, (rx if rx < since else since) + to_wall
    )


OnSample = Callable[[PoseSample, float], Any]
OnInput = Callable[[Any, float], Any]  # an input event (occ/events.py)
Refuse = Callable[[Inbound, CommandError], None]


class StreamInputs:
    """The stream side of one robot (see the module docstring)."""

    def __init__(
        self,
        interfaces: InterfaceManager,
        loss: LossConfig,
        collab: Collaboration | None,
        wall_time: Callable[[], float],
    ) -> None:
        #: the wall clock of the loop's clock, for the timestamp check
        self._wall_time = wall_time
        self.collab = collab
        masters = collab.masters if collab is not None else ()
        #: every watched stream's monitor (one per master when collaborating)
        self.monitors: dict[str, LossMonitor] = build_loss_monitors(
            loss, masters if collab is not None else None
        )
        self._monitor_list = list(self.monitors.items())
        #: the interface whose stream moves the robot (the owner's) and its monitor
        self.input: str | None = collab.owner if collab is not None else loss.input
        self.monitor: LossMonitor | None = self.monitors.get(self.input or "")
        if self.monitor is None:
            self.input = None
        self.policy = loss.policy
        #: (interface, queue, its loss monitor or None, a master's stream), looked up once
        self._queues = [
            (iface.name, q, self.monitors.get(iface.name), iface.name in masters)
            for iface in interfaces.interfaces.values()
            for q in iface.streams.values()
        ]
        # UDP stream sockets are read by the loop itself, at most POLL_LIMIT datagrams a tick:
        # a 500 Hz stream then costs no thread wake-up per datagram, and a flood costs the
        # tick a bounded amount (the socket buffer overflows instead). What the loop reads
        # there goes straight to this tick (routed by its interface, judged, followed): no
        # queue, no lock, no other thread in between.
        self._pollers = [
            (
                iface.transport.poll,
                self._direct(
                    iface.name, iface, self.monitors.get(iface.name), iface.name in masters
                ),
            )
            for iface in interfaces.interfaces.values()
            if isinstance(iface.transport, UDPEndpoint) and iface.transport.polled
        ]
        #: stream items that failed to route (a bug, logged): counted as the I/O thread's
        #: callback errors are, the tick goes on
        self.route_errors = 0
        self._prev_tick = -math.inf  # the previous tick's start (earliest arrival of samples)
        # this tick's context, set by drain() for the items handled in it
        self._now = 0.0
        self._since = -math.inf
        self._to_wall: float | None = None
        self._on_sample: OnSample = _unbound
        self._on_input: OnInput = _unbound
        self._refuse: Refuse = _unbound
        self._recorder: Any | None = None
        #: ``tap(item, interface)``: each item the loop takes (the black box), or None
        self.tap: Callable[[StreamItem, str], None] | None = None

    @property
    def holding(self) -> bool:
        """The stream in control is overdue (or latched): the robot must not follow it."""
        monitor = self.monitor
        return monitor is not None and monitor.holding

    def bind(self, on_sample: OnSample, on_input: OnInput, refuse: Refuse) -> None:
        """Where the stream items go (the controllers), and who answers a refused input (the
        operator desk): set once, before the first :meth:`drain`."""
        self._on_sample = on_sample
        self._on_input = on_input
        self._refuse = refuse

    def drain(self, now: float, recorder: Any | None) -> None:
        """Every stream item, in order: each pose sample judged by its loss monitor, the
        accepted ones of the stream in control (and of streams no master sends) to
        ``on_sample``; the discrete inputs that share a stream (fixture definitions,
        keyframes) to ``on_input`` (:meth:`bind`). Polled UDP sockets are read first, at most
        ``POLL_LIMIT`` datagrams each, each item handled as it is read; then the queues the
        interface threads filled."""
        self._begin(now, recorder)
        for poll, direct in self._pollers:
            poll(POLL_LIMIT, direct)
        for name, q, monitor, master in self._queues:
            if q.pending or q.evicted:  # most ticks nothing arrived (checked without a call)
                self._drain_queue(name, q, monitor, master)

    def _begin(self, now: float, recorder: Any | None) -> None:
        self._since = self._prev_tick
        self._prev_tick = self._now = now
        self._to_wall = None
        self._recorder = recorder

    def replay(
        self, now: float, recorder: Any | None, items: Sequence[tuple[str, StreamItem]]
    ) -> None:
        """:meth:`drain` of the items a recorded tick took, in their order (a deterministic
        replay, occ/core/replay.py: every interface on its queue)."""
        self._begin(now, recorder)
        routes = {name: (monitor, master) for name, _q, monitor, master in self._queues}
        for name, item in items:
            monitor, master = routes[name]
            self._handle(name, monitor, master, item)

    def _drain_queue(
        self, name: str, q: StreamQueue, monitor: LossMonitor | None, master: bool
    ) -> None:
        """What an interface thread queued for this tick, in order."""
        if q.evicted and monitor is not None:
            # samples the loop could not take in time: seen, never called lost
            now, since, to_wall = self._now, self._since, self._wall()
            for old in q.drain_overflow():
                event = old.event
                if isinstance(event, PoseSample):
                    judge(monitor, event, now, to_wall, since)
        elif q.evicted:
            q.drain_overflow()
        handle = self._handle
        for item in q.drain():
            handle(name, monitor, master, item)

    def to_wall(self) -> float:
        """Wall time minus loop time this tick, read once a tick (the controllers' too: the
        black box records it, so a replay reads the same)."""
        return self._wall()

    def _wall(self) -> float:
        """Wall time minus loop time this tick (reception times on the wall clock, to compare
        with header timestamps), asked once a tick and only when a sample needs it."""
        to_wall = self._to_wall
        if to_wall is None:
            to_wall = self._to_wall = self._wall_time() - self._now
        return to_wall

    def _direct(
        self, name: str, iface: Interface, monitor: LossMonitor | None, master: bool
    ) -> Callable[[Peer, Message], None]:
        """The handler of what the loop reads from ``iface``'s socket: routed by the interface
        (every check of the I/O thread's path), then handled at once. A routing error is
        counted and logged as the transport's guard does it (the datagram is dropped, the
        tick goes on); the handling's own errors reach the tick, as a queued item's do."""
        route = iface.route
        handle = self._handle
        streams = iface.streams
        only = next(iter(streams.values())) if len(streams) == 1 else None  # e.g. POSITION

        def direct(peer: Peer, msg: Message) -> None:
            try:
                item = route(peer, msg)
            except Exception:  # noqa: BLE001 - as the I/O thread's CallbackGuard
                self.route_errors += 1
                log.exception("%s: routing a polled %s raised", name, msg.message_type)
                return
            if item is not None:
                (only if only is not None else streams[msg.message_type]).received += 1
                handle(name, monitor, master, item)

        return direct

    def _handle(
        self, name: str, monitor: LossMonitor | None, master: bool, item: StreamItem
    ) -> None:
        """One stream item of interface ``name`` in this tick: a pose judged by the stream's
        monitor, followed if accepted and of the stream in control (a master not in control
        is judged and counted, and moves nothing); a discrete input to the controllers."""
        now = self._now
        recorder = self._recorder
        if recorder is not None:
            recorder.record_message(item.msg, "in", name, now)
        tap = self.tap
        if tap is not None:
            tap(item, name)
        follow = not master or name == self.input
        event = item.event
        if isinstance(event, PoseSample):
            if monitor is not None:
                rx = event.t_rx
                since = self._since
                to_wall = self._to_wall
                if to_wall is None:  # once a tick, and only when a sample needs it
                    to_wall = self._to_wall = self._wall_time() - now
                verdict = monitor.on_packet(
                    event.seq,
                    event.t_sample,
                    now,
                    rx + to_wall,
                    (rx if rx < since else since) + to_wall,
                )
                if verdict is not Verdict.ACCEPT:
                    return
            if follow:
                try:
                    self._on_sample(event, now)
                except CommandError as err:  # a TRANSFORM fixture refused
                    self._refuse(item, err)
        elif follow:
            try:
                self._on_input(event, now)
            except CommandError as err:
                # a discrete input on a stream queue (a VFIXTURE) that the controller
                # refused: an answer to its sender, not a FAULT
                self._refuse(item, err)

    def events(self, now: float) -> Sequence[tuple[str, LossMonitor, LossEvent]]:
        """This tick's loss events: (interface, its monitor, the event), for every monitor
        (most ticks none: an empty tuple, nothing built)."""
        found: list[tuple[str, LossMonitor, LossEvent]] | None = None
        for name, mon in self._monitor_list:
            event = mon.check(now)
            if event is not None:
                if found is None:
                    found = []
                found.append((name, mon, event))
        return () if found is None else found

    def reset(self) -> None:
        """Every monitor cleared, armed by its next packet (entering RUNNING, Reset)."""
        for monitor in self.monitors.values():
            monitor.reset(None)

    def handover(self, to: str, interface: str, now: float, running: bool) -> tuple[str, str]:
        """Give control to master ``to`` (an operator's ``Handover`` that arrived on
        ``interface``): the collaboration policy checked, and while RUNNING the new owner's
        stream live (not latched, not late, heard since Run); its monitor is the one acted on
        from now on. Returns (old owner, who authorised it); CommandError when refused
        (nothing changes)."""
        co = self.collab
        if co is None:
            raise CommandError("Handover: no collaboration configured (this slave has one master)")
        try:
            if not to:
                raise CommandError('Handover needs To="MASTER INTERFACE"')
            by = co.authorize(interface, to)
            if to == co.owner:
                return to, by
            monitor = self.monitors.get(to)
            if running and monitor is not None:
                if monitor.tripped or monitor.holding or monitor.last_good is None:
                    why = (
                        "latched lost"
                        if monitor.tripped
                        else "late"
                        if monitor.holding
                        else "silent since Run"
                    )
                    raise CommandError(
                        f"{to}'s stream is not live ({why}): control stays with {co.owner}"
                    )
        except CommandError:
            co.refused += 1
            raise
        old = co.switch(to, by, now)
        self.input = to
        self.monitor = monitor
        return old, by


def _unbound(*args: Any) -> None:
    """Before :meth:`StreamInputs.bind`: a stream item has nowhere to go."""
    raise RuntimeError("StreamInputs.bind was not called: stream items have nowhere to go")
