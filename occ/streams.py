"""The robot's stream inputs: the sockets the loop polls, the stream queues, the loss monitors,
and which master's stream moves the robot.

Every sample of every stream is judged by its loss monitor, in arrival order; only accepted
samples of the stream in control reach the controllers. With ``collaboration`` each master has
its own monitor and only the owner's acts on the robot; :meth:`StreamInputs.handover` moves
control (occ/collab.py decides who may ask).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Any

from igtl.transport import UDPEndpoint

from .assembly import build_loss_monitors
from .collab import Collaboration
from .config import LossConfig
from .errors import CommandError
from .interfaces import Inbound, InterfaceManager
from .safety import LossEvent, LossMonitor, Verdict
from .samples import PoseSample

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


class StreamInputs:
    """The stream side of one robot (see the module docstring)."""

    def __init__(
        self,
        interfaces: InterfaceManager,
        loss: LossConfig,
        collab: Collaboration | None,
        wall_offset: Callable[[float], float],
    ) -> None:
        #: ``wall_offset(now)``: wall time minus loop time, for the timestamp check
        self._wall_offset = wall_offset
        self.collab = collab
        # UDP stream sockets are read by the loop itself, at most POLL_LIMIT datagrams a tick:
        # a 500 Hz stream then costs no thread wake-up per datagram, and a flood costs the
        # tick a bounded amount (the socket buffer overflows instead)
        self._pollers = [
            iface.transport.poll
            for iface in interfaces.interfaces.values()
            if isinstance(iface.transport, UDPEndpoint) and iface.transport.polled
        ]
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
        self._prev_tick = -math.inf  # the previous tick's start (earliest arrival of samples)

    @property
    def holding(self) -> bool:
        """The stream in control is overdue (or latched): the robot must not follow it."""
        monitor = self.monitor
        return monitor is not None and monitor.holding

    def drain(
        self,
        now: float,
        on_sample: Callable[[PoseSample, float], Any],
        on_input: Callable[[Inbound, float], Any],
        refuse: Callable[[Inbound, CommandError], None],
        recorder: Any | None,
    ) -> None:
        """Every stream item, in order: each pose sample judged by its loss monitor, the
        accepted ones of the stream in control (and of streams no master sends) to
        ``on_sample``; the discrete inputs that share a stream (fixture definitions,
        keyframes) to ``on_input``. Polled UDP sockets are read first, at most ``POLL_LIMIT``
        datagrams each."""
        for poll in self._pollers:
            poll(POLL_LIMIT)
        since = self._prev_tick
        self._prev_tick = now
        to_wall = 0.0
        walled = False
        for name, q, monitor, master in self._queues:
            if not q.pending and not q.evicted:
                continue  # most ticks: nothing arrived (checked without a call)
            if monitor is not None:
                if not walled:
                    walled = True
                    # reception times on the wall clock, to compare with header timestamps
                    to_wall = self._wall_offset(now)
                if q.evicted:
                    # samples the loop could not take in time: seen, never called lost
                    for old in q.drain_overflow():
                        if isinstance(old, PoseSample):
                            judge(monitor, old, now, to_wall, since)
            # a master not in control is judged and counted, and moves nothing
            follow = not master or name == self.input
            for item in q.drain():
                if recorder is not None:
                    recorder.record_message(item.msg, "in", name, now)
                if isinstance(item, PoseSample):
                    if monitor is not None:
                        if judge(monitor, item, now, to_wall, since) is not Verdict.ACCEPT:
                            continue
                    if follow:
                        try:
                            on_sample(item, now)
                        except CommandError as err:  # a TRANSFORM fixture refused
                            refuse(Inbound(item.interface, item.peer, item.msg, item.t_rx), err)
                elif follow:
                    try:
                        on_input(item, now)
                    except CommandError as err:
                        # a discrete input on a stream queue (a VFIXTURE) that the controller
                        # refused: an answer to its sender, not a FAULT
                        refuse(item, err)

    def events(self, now: float) -> Iterator[tuple[str, LossMonitor, LossEvent]]:
        """This tick's loss events: (interface, its monitor, the event), for every monitor."""
        for name, mon in self._monitor_list:
            event = mon.check(now)
            if event is not None:
                yield name, mon, event

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
