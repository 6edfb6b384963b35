"""Recording: every message in and out plus the loop's state, in one file ``igtl dump`` reads.

File format: a plain concatenation of OpenIGTLink header-version-2 messages.

- Each message the daemon received or sent is stored with its content and metadata unchanged,
  plus three metadata entries: ``rec.dir`` (``in``/``out``), ``rec.if`` (interface name, ``*`` for
  a broadcast) and ``rec.t`` (daemon clock, seconds, 6 decimals). Its original header version is
  in ``rec.hv``.
- The loop state is an ``NDARRAY`` (float64) with device name ``OCCState`` written at
  ``rate_hz``: ``[t, state code, q..., setpoint..., tip x y z (mm)]``, then ``eff...`` (the
  efforts commanded, N or N m) on a robot whose controller commands efforts (a haptic master:
  the force it displays, next to the tool's position ``tip``); metadata ``columns`` names the
  columns and ``robot`` the robot.

The loop thread only appends references to a bounded in-memory queue; a writer thread adds the
recording metadata, packs and writes, handing the interpreter lock back after every record so
the loop never waits for it. If the writer falls behind by more than ``max_backlog``
records, new records are dropped and counted (``dropped``), never blocking the loop. A
backlog is written as it is packed (every MiB), and ``close`` waits for the writer as long as it
takes records from its queue; a writer that takes none for ``CLOSE_WAIT_S`` is stuck (a hung
disk) and given up, never raced by a second writer. Where the
loop runs SCHED_FIFO the writer does too, two priorities below it (the interface threads are one
below): a writer at normal priority could be preempted by another process while it holds the
interpreter lock, and the loop would wait for the lock that long (measured: the loop's lateness
p99.9 with a recording 1.36x of without, 1.12x with the FIFO writer; docs/BENCHMARKS.md). Its
work is bounded (a flush every 50 ms of what was queued) and it yields the lock after every
record.

A recording that cannot be written (a full disk: ``ENOSPC``; its file removed, e.g. with its
directory; the writer thread ended by an error) *fails*, once: the writer stops writing, the
file is cut back to its last whole record (where the file system allows), the cause is logged
once and handed to the recorder's failure callback (the robot's alarms: an ALERT to every
operator, occ/core/alarms.py), and from then on every record is counted as not written instead
of being packed. ``close`` never raises: what it cannot do is part of the failure. The robot
keeps running; GetRecordingStatus says ``recording=failed`` with the cause.

``occ-record`` (console script) exports a recording to CSV, to 3D Slicer's and PLUS's sequence
metafile (``--format seq``) or to a ROS 2 bag (``--format mcap``; occ/recording/export.py), replays
one into a peer, and plots one (``occ-record plot``: trajectories, tracking error, states with
causes, loop timing as a PNG; occ/recording/plot.py, matplotlib optional).

A recorder may also be started and stopped while the daemon runs (PLUS's ``StartRecording`` and
``StopRecording``: occ/recording/control.py); it is the same class, attached to the running robot.
"""

from __future__ import annotations

import errno
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

import igtl
from igtl.messages.base import Message
from igtl.transport.common import name_native_thread

if TYPE_CHECKING:
    from occ.core.data import RobotData

log = logging.getLogger(__name__)

STATE_DEVICE = "OCCState"
STATE_CODES = {
    "INIT": 0,
    "READY": 1,
    "ENABLED": 2,
    "RUNNING": 3,
    "STOPPED": 4,
    "FAULT": 5,
    "ESTOP": 6,
    "SHUTDOWN": 7,
}
STATE_NAMES = {code: name for name, code in STATE_CODES.items()}
#: bytes packed before they are written (a backlog is written as it is packed)
WRITE_BATCH = 1 << 20
#: how long close waits for a writer that takes nothing from its queue (a hung disk)
CLOSE_WAIT_S = 5.0


class Recorder:
    """Writes a recording; call :meth:`start` before the loop, :meth:`close` after.

    The loop thread only appends references to a queue (messages are immutable, the state row
    is a fresh list); the writer thread adds the recording metadata, packs and writes. So the
    loop never packs, never touches the file, and the two threads share no counter.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        rate_hz: float = 100.0,
        include_messages: bool = True,
        max_backlog: int = 200_000,
        fifo_priority: int | None = None,
    ) -> None:
        self.path = Path(path)
        #: SCHED_FIFO priority of the writer thread (below the loop's and the interface
        #: threads'), where permitted: a writer holding the interpreter lock must not be
        #: preempted by other processes while the loop waits for the lock
        self.fifo_priority = fifo_priority
        self.thread_policy = "SCHED_OTHER"
        self.rate_hz = float(rate_hz)
        self.include_messages = include_messages
        self.max_backlog = max_backlog  # records waiting for the writer
        self._q: deque[tuple[Any, ...]] = deque()
        self._next_state = 0.0
        self._cond = threading.Condition()
        self._close_lock = threading.Lock()
        self._closed = False
        self._thread: threading.Thread | None = None
        self._file: Any = None
        self._columns: str | None = None
        self._robot = ""
        # loop thread only
        self.records = 0
        self.dropped = 0
        # other threads (answers that come later): their own counters, under a lock the loop
        # never takes
        self._late_lock = threading.Lock()
        self.late_records = 0
        self.late_dropped = 0
        # writer thread only
        self.bytes_written = 0
        self.written = 0  # records on disk
        self.errors = 0  # records that could not be packed (each counted, the rest goes on)
        self.lost = 0  # records queued but never written: the recording had failed
        self.progress = 0  # records taken from the queue (close waits while it grows)
        #: why the recording failed ("No space left on device (ENOSPC)"); None while it has
        #: not. Set once, by the writer (or by close), read by anyone.
        self.failure: str | None = None
        self._fail_lock = threading.Lock()
        self._on_failure: Callable[[str], None] | None = None
        self._failure_told = False

    def start(self, *, exclusive: bool = False) -> Recorder:
        """Open the file and start the writer thread; ``exclusive``: refuse (FileExistsError)
        a file that exists, instead of replacing it (a recording started at run time)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # unbuffered: every write is one system call whose result is known, so a full disk
        # is seen at the record it cuts, and the file can be cut back to the last whole one
        mode = "xb" if exclusive else "wb"
        self._file = open(self.path, mode, buffering=0)  # noqa: SIM115 - close()
        self._thread = threading.Thread(target=self._writer, name="occ-recorder", daemon=True)
        self._thread.start()
        log.info("recording to %s (state at %g Hz)", self.path, self.rate_hz)
        return self

    # ------------------------------------------------------------------ loop thread
    def on_failure(self, callback: Callable[[str], None]) -> None:
        """``callback(text)`` once when the recording fails (:meth:`describe_failure`), from
        the thread that saw it; at once if it has failed already. Told once per recorder,
        however often a callback is set (a recorder detached and attached again)."""
        with self._fail_lock:
            self._on_failure = callback
            tell = self.failure is not None and not self._failure_told
            self._failure_told = self._failure_told or tell
        if tell:
            self._tell(callback)

    def _put(self, item: tuple[Any, ...]) -> None:
        # a failed recording takes nothing more (its writer may be gone: the queue would grow)
        if len(self._q) >= self.max_backlog or self.failure is not None:
            self.dropped += 1
            return
        self._q.append(item)
        self.records += 1

    def record_message(self, msg: Message, direction: str, interface: str, now: float) -> None:
        if self.include_messages and self._file is not None:
            self._put(("msg", msg, direction, interface, now))

    def record_message_late(self, msg: Message, direction: str, interface: str, now: float) -> None:
        """:meth:`record_message` for a thread other than the loop's (the answer to a
        command that finished later, on a planner thread): the queue's append is atomic, and
        its counters are its own, so nothing the loop holds is taken."""
        if not (self.include_messages and self._file is not None):
            return
        if len(self._q) >= self.max_backlog or self.failure is not None:
            with self._late_lock:
                self.late_dropped += 1
            return
        self._q.append(("msg", msg, direction, interface, now))
        with self._late_lock:
            self.late_records += 1

    def record_state(self, data: RobotData, now: float) -> None:
        if self._file is None or now < self._next_state:
            return
        self._next_state = now + 1.0 / self.rate_hz
        if self._columns is None:
            self._robot = data.name
            self._columns = state_columns(data.joint_names, data.effort_command is not None)
        tip = data.tip
        row = [
            now,
            float(STATE_CODES.get(data.state.value, -1)),
            *data.q,
            *data.commanded(),
            tip[0, 3] * 1000.0,
            tip[1, 3] * 1000.0,
            tip[2, 3] * 1000.0,
        ]
        if data.effort_command is not None:
            row.extend(data.effort_command)  # a haptic master: the force it displays
        self._put(("state", row, data.clock.wall_time()))

    # ------------------------------------------------------------------ writer thread
    def _encode(self, item: tuple[Any, ...]) -> bytes:
        if item[0] == "msg":
            _, msg, direction, interface, now = item
            return pack_message_record(msg, direction, interface, now)
        _, row, wall = item
        return pack_state_record(row, self._columns or "", self._robot, wall)

    def _writer(self) -> None:
        name_native_thread("recorder")
        if self.fifo_priority is not None:
            try:
                os.sched_setscheduler(
                    threading.get_native_id(), os.SCHED_FIFO, os.sched_param(self.fifo_priority)
                )
                self.thread_policy = f"SCHED_FIFO {self.fifo_priority}"
            except (OSError, AttributeError) as err:  # EPERM, or no SCHED_FIFO here
                self.thread_policy = f"SCHED_OTHER (SCHED_FIFO refused: {err})"
        try:
            while True:
                with self._cond:
                    self._cond.wait(0.05)
                    closed = self._closed
                self._flush()
                if closed:
                    return
        except Exception as err:  # noqa: BLE001 - a dead writer must not record in silence
            self._fail(f"the writer thread ended: {type(err).__name__}: {err}", err)

    def _flush(self) -> None:
        if self.failure is not None:
            self._discard()
            return
        chunks: list[bytes] = []
        size = 0
        sleep = time.sleep
        while self._q:
            if size >= WRITE_BATCH:  # a backlog goes out as it is packed: progress shows
                self._write(chunks)
                chunks, size = [], 0
                if self.failure is not None:
                    self._discard()
                    return
            try:
                item = self._q.popleft()
            except IndexError:  # pragma: no cover
                break
            self.progress += 1
            try:
                chunk = self._encode(item)
                chunks.append(chunk)
                size += len(chunk)
            except (ValueError, TypeError, igtl.IGTLError) as err:
                self.errors += 1
                if self.errors <= 3:  # one bad record is not a failure; its kind is told
                    log.warning("recorder: a record could not be packed (%s); skipped", err)
            # Hand the interpreter lock back after every record: a thread that wants it (the
            # loop, waking for its deadline) otherwise waits for the switch interval (5 ms by
            # default) while this thread packs a batch (measured: the slave's lateness p99.9
            # 1.8-3.0 ms with recording on vs 0.1 ms off).
            sleep(0)
        if chunks:
            self._write(chunks)
        if self.failure is None:
            self._check_file()

    def _write(self, chunks: list[bytes]) -> None:
        """Write whole records; on an error, cut the file back to the last whole record and
        fail with the cause."""
        if self._file is None:  # closed under a writer given up for stuck
            self.lost += len(chunks)
            return
        data = memoryview(b"".join(chunks))
        done = 0
        try:
            while done < len(data):
                n = self._file.write(data[done:])
                if not n:  # a raw write that wrote nothing and raised nothing
                    raise OSError(errno.EIO, "the file took no bytes")
                done += n
        except OSError as err:
            whole = n_whole = 0
            for chunk in chunks:
                if whole + len(chunk) > done:
                    break
                whole += len(chunk)
                n_whole += 1
            self.bytes_written += whole
            self.written += n_whole
            self.lost += len(chunks) - n_whole
            if done > whole:  # a record cut: the file back to the last whole one
                self._cut_back()
            self._fail(os_cause(err))
            return
        self.bytes_written += len(data)
        self.written += len(chunks)

    def _cut_back(self) -> None:
        """The file back to its last whole record (a regular file; a device cannot be cut)."""
        try:
            os.ftruncate(self._file.fileno(), self.bytes_written)
        except (OSError, ValueError):
            pass

    def _check_file(self) -> None:
        """A file removed while it is written (its directory deleted) takes every byte with
        it when it is closed: a failure, said now rather than found later."""
        if self._file is None:
            return
        try:
            gone = os.fstat(self._file.fileno()).st_nlink == 0
        except (OSError, ValueError) as err:
            self._fail(f"the file cannot be checked: {err}")
            return
        if gone:
            self._fail("the file was removed while recording (its directory deleted?)")

    def _discard(self) -> None:
        """After a failure: what is queued is counted, not packed."""
        q = self._q
        while q:
            try:
                q.popleft()
            except IndexError:  # pragma: no cover
                break
            self.lost += 1
            self.progress += 1

    def _fail(self, cause: str, err: BaseException | None = None) -> None:
        """The recording failed: said once in the log (with ``err``'s traceback: a bug's) and
        once to the failure callback."""
        with self._fail_lock:
            if self.failure is not None:
                return
            self.failure = cause
            callback = None if self._failure_told else self._on_failure
            self._failure_told = self._failure_told or callback is not None
        log.error(
            "%s; the robot goes on, nothing more is recorded", self.describe_failure(), exc_info=err
        )
        if callback is not None:
            self._tell(callback)

    def _tell(self, callback: Callable[[str], None]) -> None:
        try:
            callback(self.describe_failure())
        except Exception:  # noqa: BLE001 - the writer must outlive a failing alert
            log.exception("recorder: telling the failure failed")

    def describe_failure(self) -> str:
        """What failed, why, and what the file holds (empty while nothing failed)."""
        if self.failure is None:
            return ""
        return (
            f"recording {self.path} failed: {self.failure}; {self.written} records "
            f"({self.bytes_written} bytes) on disk, {self.not_written()} not written"
        )

    def not_written(self) -> int:
        """Records taken and not on disk (queued, dropped, lost, unpackable): 0 once a healthy
        recording is closed."""
        taken = self.records + self.late_records
        return max(0, taken - self.written) + self.dropped + self.late_dropped

    def close(self) -> None:
        """Stop the writer, write what is queued, close the file. Safe to call twice and from
        two threads (a recording stopped at run time while the daemon shuts down); never
        raises: what it cannot do is the recording's failure (:attr:`failure`)."""
        with self._close_lock:
            self._close()

    def _close(self) -> None:
        if self._file is None:
            return
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        thread = self._thread
        seen = -1
        # as long as the writer drains a backlog it is waited for; a writer that takes
        # nothing for CLOSE_WAIT_S is stuck (a hung disk): given up, never raced
        while thread is not None and thread.is_alive() and self.progress != seen:
            seen = self.progress
            thread.join(timeout=CLOSE_WAIT_S)
        if thread is not None and thread.is_alive():
            self._fail(f"the writer made no progress for {CLOSE_WAIT_S:g} s (a hung disk?)")
        else:
            self._flush()
        try:
            self._file.close()
        except OSError as err:
            self._fail(f"closing the file: {os_cause(err)}")
        self._file = None
        log.info(
            "recording closed: %d records, %d bytes, %d dropped%s",
            self.records + self.late_records,
            self.bytes_written,
            self.dropped + self.late_dropped,
            f"; FAILED: {self.failure}" if self.failure is not None else "",
        )

    def stats(self) -> dict[str, int | str | None]:
        return {
            "records": self.records + self.late_records,
            "written": self.written,
            "bytes": self.bytes_written,
            "dropped": self.dropped + self.late_dropped,
            "errors": self.errors,
            "lost": self.lost,
            "failure": self.failure,
            "writer": self.thread_policy,
        }


def pack_message_record(
    msg: Message, direction: str, interface: str, now: float, extra: dict[str, str] | None = None
) -> bytes:
    """One message as a recording stores it (module docstring): its own metadata and the
    recording's (``rec.dir``, ``rec.if``, ``rec.t``, ``rec.hv``, and ``extra``), header v2."""
    meta = dict(msg.metadata)
    meta["rec.dir"] = direction
    meta["rec.if"] = interface
    meta["rec.t"] = f"{now:.6f}"
    meta["rec.hv"] = str(msg.header_version)
    if extra:
        meta.update(extra)
    return bytes(msg.pack(2, metadata=meta))


def pack_state_record(row: Any, columns: str, robot: str, wall: float) -> bytes:
    """One ``OCCState`` row as a recording stores it (an NDARRAY of float64)."""
    state = igtl.NDArrayMessage(
        array=np.asarray(row, dtype=np.float64),
        device_name=STATE_DEVICE,
        header_version=2,
        metadata={"columns": columns, "robot": robot},
        timestamp=wall,
    )
    return bytes(state.pack())


def state_columns(names: Any, efforts: bool) -> str:
    """The ``columns`` of a robot's ``OCCState`` rows (joint ``names``; ``efforts``: a robot
    that commands efforts, whose rows end with them)."""
    return ",".join(
        ["t", "state"]
        + [f"q.{n}" for n in names]
        + [f"sp.{n}" for n in names]
        + ["tip.x_mm", "tip.y_mm", "tip.z_mm"]
        + ([f"eff.{n}" for n in names] if efforts else [])
    )


def recording_file(path: str | Path) -> Path:
    """The recording at ``path``: the file itself, or a black box dump's (a directory with
    ``recording.igtl``, occ/recording/blackbox.py), so every reader takes both."""
    p = Path(path)
    if p.is_dir() and (p / DUMP_RECORDING).is_file():
        return p / DUMP_RECORDING
    return p


#: the recording inside a black box dump's directory
DUMP_RECORDING = "recording.igtl"


def os_cause(err: OSError) -> str:
    """An OS error as an operator reads it: ``No space left on device (ENOSPC)``."""
    name = errno.errorcode.get(err.errno or 0)
    text = err.strerror or str(err)
    return f"{text} ({name})" if name else text


def writer_priority(config: Any) -> int | None:
    """The priority of a daemon's threads that hold the interpreter lock for a while (the
    recorder's writer, the worker): SCHED_FIFO two below the loop (the interface threads are
    one below) when the loop runs SCHED_FIFO, else None."""
    prio = config.robot.realtime.fifo_priority
    return max(1, prio - 2) if prio else None


# ---------------------------------------------------------------------- reading
#: damaged messages a salvage names one by one (the others are only counted)
NAMED_SKIPS = 10


@dataclass
class ReadReport:
    """How far a reading of a recording got (:func:`iter_recording` with a report): to its
    end, or salvaged up to damage. A recording cut mid-message (a crash, an interrupted copy)
    or with a header that makes no sense stops the reading there (``stop``); a message whose
    framing is sound but whose body is damaged (a CRC error) is passed over and counted
    (``skipped``), the reading goes on."""

    path: str = ""
    size: int = 0  #: bytes in the file
    messages: int = 0  #: messages read
    end: int = 0  #: byte offset just after the last message read
    last_t: float | None = None  #: the last message's ``rec.t`` (the daemon's clock, s)
    last_wall: float | None = None  #: its header timestamp (the wall clock, s)
    skipped: int = 0  #: damaged messages passed over (framing intact)
    skips: list[tuple[int, str]] = field(default_factory=list)  #: the first ones: offset, why
    stop: tuple[int, str] | None = None  #: where the reading stopped short, and why

    @property
    def complete(self) -> bool:
        """Every byte of the file read as a message."""
        return self.stop is None and self.skipped == 0

    def took(self, msg: Message, end: int) -> None:
        self.messages += 1
        self.end = end
        try:
            self.last_t = float(msg.metadata.get("rec.t", ""))
        except ValueError:
            pass
        if msg.timestamp > 0.0:
            self.last_wall = float(msg.timestamp)

    def skip(self, offset: int, why: str) -> None:
        self.skipped += 1
        if len(self.skips) < NAMED_SKIPS:
            self.skips.append((offset, why))

    def where(self) -> str:
        """The last message read: its number, its end and its times."""
        when = []
        if self.last_t is not None:
            when.append(f"t={self.last_t:.6f} s on the daemon's clock")
        if self.last_wall is not None:
            ms = int(round(self.last_wall * 1000.0)) % 1000
            wall = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(self.last_wall))
            when.append(f"{wall}.{ms:03d} UTC")
        return f"message {self.messages} ending at byte {self.end}" + (
            f" ({', '.join(when)})" if when else ""
        )

    def describe(self) -> str:
        """One paragraph for the person who exports: complete, or what was salvaged."""
        if self.complete:
            return f"{self.path}: complete, {self.messages} messages, {self.size} bytes"
        parts = [f"{self.path}: DAMAGED; salvaged {self.messages} messages up to {self.where()}"]
        if self.stop is not None:
            offset, why = self.stop
            parts.append(
                f"stopped at byte {offset} of {self.size} ({why}); the "
                f"{self.size - offset} bytes from there are not exported"
            )
        if self.skipped:
            named = ", ".join(f"byte {o}: {w}" for o, w in self.skips)
            rest = self.skipped - len(self.skips)
            more = f" and {rest} more" if rest else ""
            parts.append(f"{self.skipped} damaged messages skipped ({named}{more})")
        return "; ".join(parts)


def iter_recording(path: str | Path, report: ReadReport | None = None) -> Iterator[Message]:
    """The messages of a recording one by one, read 1 MiB at a time (a 12-hour recording need
    not fit in memory). Without ``report`` a damaged file raises igtl.DecodeError; with one it
    is salvaged (:class:`ReadReport`): the messages up to the damage, and where it is."""
    path = recording_file(path)  # a black box dump: its recording
    dec = igtl.StreamDecoder()
    if report is not None:
        report.path, report.size = str(path), os.path.getsize(path)
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            dec.feed(chunk)
            if report is None:
                yield from dec
                continue
            while True:
                at = dec.offset
                try:
                    msg = dec.next_message()
                except igtl.DecodeError as err:
                    if err.recoverable:  # the framing holds: the next message is sound
                        report.skip(at, str(err))
                        continue
                    report.stop = (at, str(err))
                    return
                if msg is None:
                    break
                report.took(msg, dec.offset)
                yield msg
    if report is None:
        dec.close()
    elif dec.buffered:
        report.stop = (dec.offset, f"the file ends inside a message, {dec.buffered} bytes of it")


def read_recording(path: str | Path) -> list[Message]:
    """All messages of a recording (raises igtl.DecodeError on a damaged file)."""
    return list(iter_recording(path))


def original(m: Message) -> Message:
    """A recorded message as it was on the wire (recording metadata removed)."""
    meta = {k: v for k, v in m.metadata.items() if not k.startswith("rec.")}
    hv = int(m.metadata.get("rec.hv", m.header_version))
    return m.replace(
        metadata=meta if hv == 2 else {},
        header_version=hv,
        message_id=m.message_id if hv == 2 else 0,
    )


def replay(
    path: str | Path,
    target: tuple[str, int],
    *,
    udp: bool = False,
    speed: float = 1.0,
    direction: str = "in",
    interface: str | None = None,
    types: set[str] | None = None,
) -> int:
    """Send the recorded messages of one direction to a peer with their original timing."""
    from igtl.transport import TCPClient, UDPEndpoint

    msgs = [
        m
        for m in read_recording(path)
        if m.metadata.get("rec.dir") == direction
        and (interface is None or m.metadata.get("rec.if") == interface)
        and (types is None or m.message_type in types)
    ]
    if not msgs:
        return 0
    ep: UDPEndpoint | TCPClient
    if udp:
        ep = UDPEndpoint("127.0.0.1", 0, remote=target).start()
    else:
        cl = TCPClient(target[0], target[1], reconnect=False).start()
        if not cl.wait_connected(5.0):
            cl.stop()
            raise ConnectionError(f"cannot connect to {target[0]}:{target[1]}")
        ep = cl
    try:
        t0 = float(msgs[0].metadata.get("rec.t", 0.0))
        start = time.perf_counter()
        sent = 0
        for m in msgs:
            due = (float(m.metadata.get("rec.t", t0)) - t0) / speed
            delay = start + due - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            if ep.send(original(m)):
                sent += 1
        return sent
    finally:
        ep.stop()
