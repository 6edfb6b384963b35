"""The black box: the flight recorder every daemon keeps, and dumps when it matters.

Always on (``black_box:``, occ/config/blackbox.py). The loop writes, every tick, what it read
and what it did into rings preallocated at start, and a thread of its own writes a ring's
window to ``black_box.dir/<robot>-<time>-<cause>/`` (occ/recording/dump.py) when the robot
stops for a safety reason, faults, is emergency-stopped, or an operator asks
(``DumpBlackBox``). The alert that follows (a ``BLACKBOX`` STATUS to every operator and
viewer) says where.

What is kept, per tick (the *tick ring*, one float64 row a tick, ``array('d')`` written by
element assignment as the State Data Table is, occ/core/statetable.py):

- ``t``: the clock value the tick used (``now``), ``k``: its deadline index, ``state``: the
  state code the tick ended in (the recording's codes);
- ``pos.<joint>``: the position each joint believes (what the loop controlled from);
- what the loop wrote to the drives: ``sp.<joint>`` (position setpoints) and ``ew.<joint>``
  (efforts), NaN in a tick that wrote none;
- ``raw.pos|vel|eff.<joint>``: every drive's reading as its hook returned it, before the
  feedback checks (NaN in a tick that did not read it);
- ``to_wall``: the wall clock minus the loop's clock as the streams asked it this tick (the
  offset against which sample timestamps were judged; NaN when no sample needed it);
- with a simulated world (a config's ``environment``, occ/haptics/contact.py), what the drive's
  hook left in it and the controller reads as its tissue sensor: the contact force
  (``world.fx``, ``world.fy``, ``world.fz``, N, patient frame) and whether the tool touches
  (``world.contact``, 1 or 0).

And in the *event ring*, each with the index of the tick it happened in (the row it belongs
to): every input the loop consumed (a stream item as its wire bytes, reception time and peer;
an operator's request as the item the desk took; a cell member's heartbeat), the alerts and
replies sent, every state transition with its event and reason, each collision guard verdict
with the tick the loop first saw it, a driver hook's error, a controller's note of a worker's
result it took (a keyframe plan), the facts behind a stop (``note``), and the dump requests.
Events from other threads (a reply answered later, an alert from the supervisor's thread, a
verdict published off the loop) go to a small bounded deque beside the ring, stamped with the
tick under way. The periodic outputs (the tip to 3D Slicer, the stream to the slave) are not
kept: they are what the rows make of the state, and a replay makes them again.

Every :data:`CHECKPOINT_S` the loop, in the time a tick leaves before its next deadline
(:meth:`BlackBox.spare`; in simulated time at the end of the tick), takes a *checkpoint* of the
robot's state (occ/core/checkpoint.py); a dump's window starts at the last checkpoint at or
before its ``seconds``, so a deterministic replay (occ/core/replay.py) starts from the state
the robot had there and runs every tick of the window again.

Cost on the loop thread (docs/BENCHMARKS.md, "The black box"): element assignments into the
preallocated rings and a reference stored per input; no I/O, no lock, no container grows, and
no object kept per stream message (the collector never walks 30 s of them). What Python
allocates regardless are the integer and float temporaries of the arithmetic (as in the State
Data Table) and, at a transition or a dump request (rare, not per tick), a tuple and the
request handed to the writer; a checkpoint (once a second, in spare time) copies the state. A
dump costs the loop only that request: the writer thread copies the window out of the live
ring, oldest rows first, in chunks that hand the interpreter lock back, while the loop goes on
writing (the ring has a margin of :data:`MARGIN_S` plus :data:`CHECKPOINT_S` beyond
``seconds``, so the rows it copies are not overwritten meanwhile; rows it finds overwritten
after all are dropped and the dump says so). Nothing is swapped or stopped, so consecutive
dumps each hold their whole window. In simulated time the dump is written inline, at the end
of the tick that closes its window (exact, repeatable runs, as the collision guard checks
inline there); on the real clock always by the writer thread.

What a deterministic replay cannot reproduce, because no tick of the loop did it (reported as
a divergence where it mattered): another thread's change to the loop's state (the supervisor
catching a hung loop, a region defined from another thread), a drive's power-up on its own
thread, the tick a planner's result landed in (the planner thread hands it over between two
ticks: a replay lets it land before the tick after the request, as a simulated-time run that
waits for its planner does; to close it, the controller would note on the loop the tick it
first sees a result), and the samples the loop could not take in time (an overflowing stream
queue, judged without being recorded). A collision verdict from the worker thread is taken by
the loop at one point of its tick (``CollisionGuard.fresh``, at the start of
``after_control``) and recorded with that tick: a replay hands it over there. Inputs an
interface refused before the loop (authentication, ownership, a full queue) never reach the
loop and are counted by the interfaces: they cannot change what it does.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from array import array
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from occ.core.safety import RobotState
from occ.net.interfaces import rebuild_stream_item
from occ.recording.record import STATE_CODES

if TYPE_CHECKING:
    from occ.core.data import RobotData
    from occ.joint import Joint

log = logging.getLogger(__name__)

#: event kinds (the event ring's ``kind`` column)
IN, OUT, TRANSITION, VERDICT, NOTE, REQUEST, HOOK, CMD = 1, 2, 3, 4, 5, 6, 7, 8
#: a stream item kept as its wire bytes, reception time and peer (read back as IN)
_IN_WIRE = 9
KIND_NAMES = {
    IN: "in",
    OUT: "out",
    TRANSITION: "transition",
    VERDICT: "verdict",
    NOTE: "note",
    REQUEST: "dump",
    HOOK: "driver error",
    CMD: "in",  # a received item the operator desk took (IN: the streams and the cell)
}
#: seconds between two checkpoints of the robot's state (occ/core/checkpoint.py)
CHECKPOINT_S = 1.0
#: seconds of ring beyond ``black_box.seconds``: how late the writer may start copying a
#: window before its oldest rows are overwritten
MARGIN_S = 2.0
#: rows (events) copied between two hand-backs of the interpreter lock
CHUNK = 2048
#: dump requests waiting for the writer (a burst beyond is refused and counted)
QUEUE_DEPTH = 4
#: events from other threads kept beside the ring
OFF_LOOP_EVENTS = 4096
#: the simulated world's columns (a config's ``environment``), after ``to_wall``
WORLD_COLUMNS = ("world.fx", "world.fy", "world.fz", "world.contact")
#: states whose entry dumps the ring (STOPPED only for a safety reason: not an operator's Stop)
DUMPED_STATES = (RobotState.FAULT, RobotState.ESTOP, RobotState.STOPPED)
_STATE_CODE = {st: float(STATE_CODES.get(st.value, -1)) for st in RobotState}


def tick_columns(joint_names: Sequence[str], world: bool = False) -> list[str]:
    """The tick ring's columns, in order (module docstring); ``world``: with the simulated
    world's."""
    cols = ["t", "k", "state", *(f"pos.{j}" for j in joint_names)]
    cols += [f"sp.{j}" for j in joint_names] + [f"ew.{j}" for j in joint_names]
    for j in joint_names:
        cols += [f"raw.pos.{j}", f"raw.vel.{j}", f"raw.eff.{j}"]
    return [*cols, "to_wall", *(WORLD_COLUMNS if world else ())]


@dataclass
class DumpRequest:
    """One dump to write: where, why, and the window's end (exclusive: the rows and events
    of the trigger's tick are in it)."""

    name: str
    path: Path
    causes: list[tuple[str, str]]
    #: rows written when the window closed (the trigger's tick is row ``end - 1``)
    end: int
    #: events written then
    events_end: int
    #: the trigger: the loop's time, its deadline index, the wall time
    t: float
    k: int
    wall: float


@dataclass
class Window:
    """What the writer copied out of the rings for one dump (oldest first)."""

    rows: np.ndarray
    first_row: int  #: the ring index of ``rows[0]``
    #: (tick index, kind, where, object), in order
    events: list[tuple[int, int, Any, Any]] = field(default_factory=list)
    #: the first tick whose events are all in the window (events overwritten before it)
    events_whole_from: int = 0
    #: rows of the promised window lost to a writer that started too late
    rows_lost: int = 0
    #: the robot's state before ``rows[0]`` was ticked (a replay's start), None: none kept
    checkpoint: list[Any] | None = None
    #: the loop thread's own events from the checkpoint on (what a replay feeds and expects)
    loop_events: list[tuple[int, int, Any, Any]] = field(default_factory=list)


class BlackBox:
    """The rings and the loop's taps (module docstring). One per robot; the loop thread
    writes, the dump writer thread (:class:`DumpWriter`) reads."""

    def __init__(
        self,
        name: str,
        joint_names: Sequence[str],
        rate_hz: float,
        seconds: float,
        events_per_s: int,
        *,
        enabled: bool = True,
        world: bool = False,
    ) -> None:
        """``world``: the robot has a simulated world (its columns, bound by :meth:`bind`)."""
        self.name = name
        self.enabled = enabled
        self.joint_names = tuple(joint_names)
        self.columns = tick_columns(self.joint_names, world)
        n = len(self.joint_names)
        self.width = len(self.columns)
        self._sp_at = 3 + n  # the written columns' offset in a row
        self._ew_at = self._sp_at + n
        self._raw_at = self._ew_at + n  # the drives' own readings
        self._wall_at = self._raw_at + 3 * n
        self._world_at = self._wall_at + 1
        self._world: Any = None  # the simulated world (bind), None: no world columns
        self.rate_hz = float(rate_hz)
        self.seconds = float(seconds) if enabled else 0.0
        #: rows a dump holds (seconds x rate); the ring has a margin beyond them
        self.capacity = max(1, math.ceil(self.seconds * rate_hz))
        margin = MARGIN_S + CHECKPOINT_S  # a window starts at a checkpoint before its seconds
        self._slots = self.capacity + math.ceil(margin * rate_hz) if enabled else 1
        self._buf = array("d", bytes(8 * self._slots * self.width))
        self._view = np.frombuffer(self._buf, dtype=np.float64).reshape(self._slots, self.width)
        self._end = self._slots * self.width
        self._pos = 0
        self._nan = array("d", [math.nan] * (2 * n))
        self._raw_nan = array("d", [math.nan] * (3 * n))
        self._buf[self._sp_at : self._sp_at + 2 * n] = self._nan
        self._buf[self._raw_at : self._raw_at + 3 * n] = self._raw_nan
        #: simulated time: checkpoints taken at the end of the tick (no loop calls spare())
        self.inline_checkpoints = False
        #: what the dump's writer calls between pieces of its work: on the real clock the
        #: loop's ``yield_to_loop`` (it works only while the loop is idle), else a hand-back
        #: of the interpreter lock
        self.pace: Callable[[], None] = _hand_back
        #: what builds the robot's checkpointer at activation (occ/core/wiring.py)
        self.make_checkpointer: Callable[[], Any] | None = None
        #: rows written since start (the tick under way writes row ``count``)
        self.count = 0
        self.ev_capacity = max(16, math.ceil(self.seconds * events_per_s))
        self._ev_slots = self.ev_capacity + math.ceil(margin * events_per_s) if enabled else 1
        self._ev_rings = event_rings(self._ev_slots)
        self._ev_tick, self._ev_kind, self._ev_where, self._ev_obj = self._ev_rings[:4]
        self._ev_t, self._ev_peer = self._ev_rings[4:]  # a stream item's (_IN_WIRE) t_rx, peer
        #: rows (events) at the ring's old end the writer leaves to the loop while it copies: a
        #: chunk, or what the loop writes in MARGIN_S if fewer (else a small ring copies none)
        self._copy_margin = min(CHUNK, math.ceil(MARGIN_S * rate_hz))
        self._ev_copy_margin = min(CHUNK, math.ceil(MARGIN_S * events_per_s))
        #: events written since start
        self.ev_count = 0
        self._off_loop: deque[tuple[int, int, Any, Any]] = deque(maxlen=OFF_LOOP_EVENTS)
        self._loop_ident: int | None = None
        self._data: RobotData | None = None
        self._joints: Sequence[Joint] = ()
        #: (driver, the row offsets of its joints' raw columns)
        self._drives: tuple[tuple[Any, tuple[int, ...]], ...] = ()
        self._streams: Any = None
        #: the robot's state every CHECKPOINT_S (a replay starts from one); None: not taken
        self.checkpoints: Checkpoints | None = None
        self.checkpointer: Any = None
        self._guard: Any = None
        self._verdict: Any = None
        self._state_code = -1.0
        self._pending: DumpRequest | None = None
        self._names: set[str] = set()
        self.writer: DumpWriter | None = None
        self.dir = Path(".")
        self.requested = 0
        self.refused = 0

    def bind(
        self,
        data: RobotData,
        joints: Sequence[Joint],
        guard: Any | None,
        writer: DumpWriter | None,
        directory: Path,
        drives: Sequence[tuple[Any, Sequence[int]]] = (),
        streams: Any = None,
        world: Any = None,
    ) -> None:
        """What the loop's row reads (the robot's data and joints, each driver with the
        indices of its joints, the streams' wall offset, the simulated world when the box was
        made with its columns, the collision guard whose ``verdict`` it watches), and who
        writes the dumps where."""
        if (world is not None) != (self.width > self._world_at):
            raise ValueError("a simulated world needs a black box made with world=True")
        self._world = world
        self._data = data
        self._joints = tuple(joints)
        self._drives = tuple((d, tuple(self._raw_at + 3 * i for i in idx)) for d, idx in drives)
        self._streams = streams
        self._guard = guard
        self._state_code = _STATE_CODE[data.state]
        self.writer = writer
        self.dir = Path(directory)

    def start(self) -> None:
        """The writer thread and the first checkpoint (the robot's activation)."""
        if self.writer is not None:
            self.writer.start()
        if self.enabled and self.make_checkpointer is not None and self.checkpoints is None:
            keep = math.ceil((self.seconds + MARGIN_S) / CHECKPOINT_S) + 2
            cp = self.make_checkpointer()
            self.checkpointer = cp
            self.checkpoints = Checkpoints(cp.take, self.rate_hz, keep)
        cps = self.checkpoints
        if cps is not None:
            if cps.baseline is None and self._data is not None:
                cps.built_at = self._data.clock.now()
            if self.inline_checkpoints:
                cps.take(self.count, self.ev_count)
            # on the real clock the loop takes the first one just before its first tick
            # (ControlLoop calls spare() then): after what occd --start asked of that tick

    def spare(self, roomy: bool = True) -> bool:
        """After a tick, on the loop thread (between two ticks: a consistent state): a
        checkpoint when one is due and the tick left room (``roomy``), or, on a machine so
        loaded that no tick has left room for a whole interval since it was due, after this
        tick anyway (a late tick at worst, rather than a window whose start cannot be
        replayed). True when one was taken."""
        cps = self.checkpoints
        if cps is not None and self.count >= cps.due and (roomy or self.count >= cps.late):
            cps.take(self.count, self.ev_count)
            return True
        return False

    def stop(self) -> None:
        """The dumps under way written (up to 10 s), the writer ended (the robot's shutdown)."""
        if self.writer is not None:
            self.writer.stop()

    def outputs_tap(self, recorder: Any | None) -> Callable[[Any, str, float], None] | None:
        """What the output scheduler calls with each message it sent: the recorder's
        ``record_message`` when one is attached. The black box keeps none of the periodic
        outputs (a replay makes them again from the state; 30 s of them alive would cost every
        collection, docs/BENCHMARKS.md); alerts and replies it keeps (:meth:`sent`)."""
        if recorder is None:
            return None
        record = recorder.record_message
        return lambda m, iface, at: record(m, "out", iface, at)

    # ------------------------------------------------------------------ loop thread
    def resync(self) -> None:
        """The state code from the robot's state again (a checkpoint restored under it)."""
        assert self._data is not None
        self._state_code = _STATE_CODE[self._data.state]

    def on_loop(self) -> None:
        """The calling thread is the loop's (its first tick): its events go to the ring."""
        self._loop_ident = threading.get_ident()

    def _put(self, kind: int, where: Any, obj: Any) -> None:
        if not self.enabled:
            return
        if threading.get_ident() != self._loop_ident:
            self._off_loop.append((self.count, kind, where, obj))  # atomic; bounded
            return
        i = self.ev_count % self._ev_slots
        self._ev_tick[i] = self.count
        self._ev_kind[i] = kind
        self._ev_where[i] = where
        self._ev_obj[i] = obj
        self.ev_count += 1  # after the event: a reader never takes half of one

    def took(self, item: Any, interface: str) -> None:
        """An input the streams took (a received message as the loop saw it:
        :class:`~occ.net.interfaces.Inbound`) or the cell (a member's heartbeat,
        ``interface`` ``cell``). A received stream message is kept as its wire bytes, its
        reception time and its peer, no object of its own (the collector never walks 30 s of
        messages), and rebuilt as the interface built it when a dump reads it."""
        msg = getattr(item, "msg", None)
        wire = None if msg is None else msg._wire
        if wire is None or not self.enabled or threading.get_ident() != self._loop_ident:
            self._put(IN, interface, item)
            return
        i = self.ev_count % self._ev_slots
        self._ev_tick[i] = self.count
        self._ev_kind[i] = _IN_WIRE
        self._ev_where[i] = interface
        self._ev_obj[i] = wire
        self._ev_t[i] = item.t_rx
        self._ev_peer[i] = item.peer
        self.ev_count += 1

    def took_request(self, item: Any, interface: str) -> None:
        """A received item the operator desk took (a request, a discrete input)."""
        self._put(CMD, interface, item)

    def hook_failed(self, driver: str, action: str, err: BaseException) -> None:
        """A driver's hook raised (its ``_read`` or ``_write``): what a replay raises again."""
        cls = type(err)
        self._put(HOOK, (driver, action), (cls.__module__, cls.__qualname__, str(err), repr(err)))

    def sent(self, msg: Any, interface: str, now: float = 0.0) -> None:
        """A message the robot sent (``*``: to every operator and viewer); any thread."""
        self._put(OUT, interface, msg)

    def note(self, what: str, obj: Any) -> None:
        """A worker's result the loop took (a controller's plan), or anything a part wants in
        the record; any thread."""
        self._put(NOTE, what, obj)

    def wrote(self, values: Sequence[float], effort: bool) -> None:
        """What the loop wrote to the drives this tick (positions or efforts): one per joint;
        a longer list (which the drives refuse) keeps its first, never spilling into the next
        columns."""
        if not self.enabled:
            return
        if len(values) > len(self.joint_names):  # refused by the drives: its first ones
            values = values[: len(self.joint_names)]
        buf = self._buf
        i = self._pos + (self._ew_at if effort else self._sp_at)
        for v in values:
            buf[i] = v
            i += 1

    def end_tick(self, now: float, k: int) -> None:
        """The tick's row (the loop, last thing in the tick): element assignments."""
        if not self.enabled:
            return
        guard = self._guard
        if guard is not None:
            v = guard.verdict
            if v is not self._verdict:  # a new verdict: the tick the loop first saw it
                self._verdict = v
                self._put(VERDICT, None, v)
        buf = self._buf
        i = self._pos
        buf[i] = now
        buf[i + 1] = k
        buf[i + 2] = self._state_code
        i += 3
        for jt in self._joints:  # the position each joint believes (its checks passed)
            buf[i] = jt.position
            i += 1
        at = self._pos
        for d, cols in self._drives:  # each drive's reading as its hook returned it
            if d.raw_now == now:
                p, v, e = d.raw
                n = 0
                for c in cols:
                    c += at
                    buf[c] = p[n]
                    buf[c + 1] = v[n]
                    buf[c + 2] = e[n]
                    n += 1
            else:  # not read in this tick (powering up, unconfigured)
                for c in cols:
                    c += at
                    buf[c] = buf[c + 1] = buf[c + 2] = math.nan
        streams = self._streams
        if streams is not None:
            w = streams._to_wall
            buf[at + self._wall_at] = math.nan if w is None else w
        world = self._world
        if world is not None:  # what the drive's hook left in the simulated world
            c = at + self._world_at
            f = world.force_n
            buf[c] = f[0]
            buf[c + 1] = f[1]
            buf[c + 2] = f[2]
            buf[c + 3] = 1.0 if world.in_contact else 0.0
        nxt = self._pos + self.width
        if nxt >= self._end:
            nxt = 0
        at = nxt + self._sp_at
        buf[at : at + len(self._nan)] = self._nan  # the next tick wrote nothing yet
        self._pos = nxt
        self.count += 1  # after the row: a reader never takes a half-written one
        if self.inline_checkpoints:
            self.spare()
        pending = self._pending
        if pending is not None:
            self._pending = None
            pending.end, pending.events_end = self.count, self.ev_count
            self._submit(pending)

    def on_transition(
        self, old: RobotState, new: RobotState, event: str, reason: str, t: float
    ) -> None:
        """The state machine's listener: the transition recorded, and a dump requested on
        entering FAULT or ESTOP, or STOPPED for anything but an operator's Stop."""
        self._state_code = _STATE_CODE[new]
        self._put(TRANSITION, None, (old.value, new.value, event, reason))
        if new in DUMPED_STATES and not (
            new is RobotState.STOPPED and reason.startswith("operator ")
        ):
            self.request(new.value.lower(), reason)

    def request(self, cause: str, why: str) -> str:
        """Dump the ring for ``cause`` (a word: ``fault``, ``operator``...) and ``why``. On the
        loop thread the window closes at the end of this tick (several requests in one tick
        are one dump); from another thread at once. Returns the directory it goes to, or
        why not."""
        if not self.enabled or self.writer is None:
            return "no black box (black_box.enabled is false)"
        self.requested += 1
        pending = self._pending
        on_loop = threading.get_ident() == self._loop_ident
        if pending is not None and on_loop:
            pending.causes.append((cause, why))
            return str(pending.path)
        req = self._new_request(cause, why)
        self._put(REQUEST, cause, why)
        if on_loop:
            self._pending = req
        else:
            req.end, req.events_end = self.count, self.ev_count
            self._submit(req)
        return str(req.path)

    def _new_request(self, cause: str, why: str) -> DumpRequest:
        assert self._data is not None
        clock = self._data.clock
        wall = clock.wall_time()
        name = dump_name(self.name, cause, wall, self._names)
        k = self.count  # the tick under way (its deadline index is in its row)
        return DumpRequest(name, self.dir / name, [(cause, why)], -1, -1, clock.now(), k, wall)

    def _submit(self, req: DumpRequest) -> None:
        writer = self.writer
        if writer is None or not writer.submit(req):
            self.refused += 1
            log.error(
                "black box: dump %s refused (%d waiting for the writer)", req.name, QUEUE_DEPTH
            )

    # ------------------------------------------------------------------ the writer's side
    def window(self, req: DumpRequest) -> Window:
        """The rows and events of ``req``'s window, copied out of the live rings (oldest
        first, in chunks that hand the interpreter lock back); what was overwritten before
        it was copied is dropped and counted."""
        end = req.end
        first = max(0, end - self.capacity)
        checkpoint, cp_events = None, 0
        if self.checkpoints is not None:  # start at the checkpoint before the window's seconds
            # not overwritten meanwhile
            oldest = max(0, self.count + 1 - self._slots + self._copy_margin)
            found = self.checkpoints.start(first, oldest, end)
            if found is not None:
                first, cp_events, checkpoint = found
        rows = np.empty((end - first, self.width), dtype=np.float64)
        slots = self._slots
        r = first
        while r < end:
            s = r % slots
            m = min(end - r, slots - s, CHUNK)
            rows[r - first : r - first + m] = self._view[s : s + m]
            r += m
            self.pace()
        gone = (self.count + 1 - slots) - first  # rows the loop may have written over
        lost = max(0, gone)
        if lost:
            rows, first = rows[lost:], first + lost
        if lost:
            checkpoint = None  # its rows are gone: the replay could not start there
        events, loop_events, whole_from = self._events(req.events_end, first, end, cp_events)
        return Window(rows, first, events, whole_from, lost, checkpoint, loop_events)

    def _events(
        self, end: int, first_row: int, end_row: int, cp_events: int = 0
    ) -> tuple[list[tuple[int, int, Any, Any]], list[tuple[int, int, Any, Any]], int]:
        """The window's events, oldest first (the loop's and, merged by tick, the other
        threads'); the loop's own from event ``cp_events`` on (taken after the checkpoint);
        the first tick whose events are all there."""
        slots = self._ev_slots
        start = max(0, end - self._ev_slots + self._ev_copy_margin)
        cols: list[list[Any]] = [[] for _ in self._ev_rings]  # each ring's, in its order
        e = start
        while e < end:
            s = e % slots
            m = min(end - e, slots - s, CHUNK)
            for col, ring in zip(cols, self._ev_rings, strict=True):
                col.extend(ring[s : s + m])
            e += m
            self.pace()
        gone = max(0, (self.ev_count + 1 - slots) - start)
        for col in cols:
            del col[:gone]
        ticks, kinds, wheres, objs, rx, peers = cols
        rebuilt = 0
        for n, kind in enumerate(kinds):  # stream items kept as bytes: rebuilt
            if kind == _IN_WIRE:
                kinds[n] = IN
                if ticks[n] < first_row:
                    continue  # before the window: dropped below
                objs[n] = rebuild_stream_item(wheres[n], peers[n], objs[n], rx[n])
                rebuilt += 1
                if rebuilt & 7 == 0:
                    self.pace()
        # events overwritten before the window's first tick: the first tick kept may have
        # lost some, the next ones are whole (none when the loop wrote over every one)
        if start + gone <= 0:
            whole_from = first_row
        elif ticks:
            whole_from = max(first_row, ticks[0] + 1)
        else:
            whole_from = end_row
        base = start + gone  # the index of ticks[0] among every event written
        out: list[tuple[int, int, Any, Any]] = []
        since_cp: list[tuple[int, int, Any, Any]] = []
        for n, ev in enumerate(zip(ticks, kinds, wheres, objs, strict=True)):
            if first_row <= ev[0] < end_row:
                out.append(ev)
                if base + n >= cp_events:
                    since_cp.append(ev)
        off = [ev for ev in list(self._off_loop) if first_row <= ev[0] < end_row]
        merged = sorted(out + off, key=lambda ev: ev[0]) if off else out  # stable: loop's first
        return merged, since_cp, whole_from

    def wait_idle(self, timeout: float = 10.0) -> bool:
        """Wait until every dump requested so far is written (tests, tools, shutdown)."""
        return self.writer is None or self.writer.wait_idle(timeout)

    def stats(self) -> dict[str, Any]:
        w = self.writer
        return {
            "enabled": self.enabled,
            "seconds": self.seconds,
            "ticks": min(self.count, self.capacity),
            "events": min(self.ev_count, self.ev_capacity),
            "requested": self.requested,
            "refused": self.refused,
            "checkpoints": self.checkpoints.taken if self.checkpoints is not None else 0,
            "checkpoint_max_ms": (
                round(self.checkpoints.cost_max_s * 1e3, 3) if self.checkpoints is not None else 0.0
            ),
            "dir": str(self.dir),
            **(w.stats() if w is not None else {}),
        }


def event_rings(slots: int) -> tuple[Any, ...]:
    """The event ring's columns, preallocated: tick, kind, where, object, and a stream
    item's reception time and peer."""
    return (
        array("q", bytes(8 * slots)),
        array("b", bytes(slots)),
        [None] * slots,
        [None] * slots,
        array("d", bytes(8 * slots)),
        [None] * slots,
    )


def dump_name(robot: str, cause: str, wall: float, taken: set[str]) -> str:
    """A dump's directory name, ``<robot>-<UTC time>-<cause>``, made unique among ``taken``
    (and added to it) with a counter: no file system call on the loop (the writer checks)."""
    stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime(wall))
    ms = int(wall * 1000.0) % 1000
    slug = "".join(c if c.isalnum() else "-" for c in cause.lower())[:32] or "dump"
    name = f"{robot}-{stamp}.{ms:03d}Z-{slug}"
    base, n = name, 1
    while name in taken:
        n += 1
        name = f"{base}-{n}"
    taken.add(name)
    return name


def _hand_back() -> None:
    time.sleep(0)


class Checkpoints:
    """The robot's state every :data:`CHECKPOINT_S` (a :class:`~occ.core.checkpoint.Checkpointer`'s
    ``take``), the last ``keep`` kept, each with the row it was taken before."""

    def __init__(self, take: Callable[[], list[Any]], rate_hz: float, keep: int) -> None:
        self._take = take
        self.every = max(1, round(CHECKPOINT_S * rate_hz))
        #: the row count at which the next one is due, and when it is taken without room
        self.due = 0
        self.late = 0
        #: (row, events written by then, the state)
        self._ring: deque[tuple[int, int, list[Any]]] = deque(maxlen=keep)
        self.taken = 0
        self.cost_max_s = 0.0
        #: the first one: the robot as built, before its first tick
        self.baseline: list[Any] | None = None
        #: the clock when it was taken (the activation; in simulated time the configure's
        #: time as well): a replay configures its robot then
        self.built_at = math.nan

    def take(self, row: int, events: int) -> None:
        """The state now, before row ``row`` is ticked and after ``events`` events (the loop
        thread, between ticks)."""
        t0 = time.perf_counter()
        values = self._take()
        self._ring.append((row, events, values))  # atomic: the writer reads all or nothing
        self.late = row + 2 * self.every  # due at row + every, overdue one interval later
        if self.baseline is None:
            self.baseline = values
        self.due = row + self.every
        self.taken += 1
        self.cost_max_s = max(self.cost_max_s, time.perf_counter() - t0)

    def start(self, first: int, oldest: int, end: int) -> tuple[int, int, list[Any]] | None:
        """Where a window that should start at row ``first`` starts: the last checkpoint at
        or before it whose rows are still in the ring (from ``oldest``), else the first after
        it before ``end``; None when there is none."""
        kept = [c for c in list(self._ring) if oldest <= c[0] < end]
        before = [c for c in kept if c[0] <= first]
        if before:
            return before[-1]
        return kept[0] if kept else None


class DumpWriter:
    """The thread that writes dumps (``write(request)`` does the work: occ/recording/dump.py);
    a bounded queue, never blocking the loop. ``inline``: in simulated time, each dump is
    written when it is submitted, in the tick that closes its window (exact, repeatable runs,
    as the collision guard checks inline there); never on the real clock. The thread runs at
    normal priority, never SCHED_FIFO: on the real clock it forks a child that writes
    (occ/recording/dump.py), which would inherit the policy, and a second of busy real-time
    work exhausts the kernel's real-time budget (sched_rt_runtime_us), throttling every
    real-time thread of the CPU, the loop's too."""

    def __init__(
        self, write: Callable[[DumpRequest], object], name: str, *, inline: bool = False
    ) -> None:
        self._write = write
        self.inline = inline
        self._q: queue.Queue[DumpRequest | None] = queue.Queue(QUEUE_DEPTH)
        self._thread = threading.Thread(target=self._main, name=name, daemon=True)
        self._started = False
        self._idle = threading.Condition()
        self._outstanding = 0
        self.written = 0
        self.failed = 0
        self.last = ""

    def start(self) -> None:
        if not self._started and not self.inline:
            self._started = True
            self._thread.start()

    def submit(self, req: DumpRequest) -> bool:
        with self._idle:
            self._outstanding += 1
        if self.inline:
            self._run(req)
            return True
        try:
            self._q.put_nowait(req)
        except queue.Full:
            self._done()
            return False
        return True

    def _done(self) -> None:
        with self._idle:
            self._outstanding -= 1
            self._idle.notify_all()

    def wait_idle(self, timeout: float) -> bool:
        """True once every dump submitted is written (False after ``timeout``, or at once
        when the thread was never started: the robot was never activated)."""
        if not self._started or self.inline:
            return self._outstanding == 0
        with self._idle:
            return self._idle.wait_for(lambda: self._outstanding == 0, timeout)

    def stop(self, timeout: float = 10.0) -> None:
        """Write what is queued (up to ``timeout``), then end the thread."""
        if self._started and not self.inline:
            self.wait_idle(timeout)
            try:
                self._q.put_nowait(None)
            except queue.Full:
                return
            self._thread.join(1.0)

    def _main(self) -> None:
        while True:
            req = self._q.get()
            if req is None:
                return
            self._run(req)

    def _run(self, req: DumpRequest) -> None:
        try:
            self._write(req)
            self.written += 1
            self.last = str(req.path)
        except Exception:  # noqa: BLE001 - a failed dump is told by write; the thread lives
            self.failed += 1
            log.exception("black box: writing %s failed", req.path)
        finally:
            self._done()

    def stats(self) -> dict[str, Any]:
        return {"written": self.written, "failed": self.failed, "last": self.last}
