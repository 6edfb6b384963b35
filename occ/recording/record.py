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
records, new records are dropped and counted (``dropped``), never blocking the loop. Where the
loop runs SCHED_FIFO the writer does too, two priorities below it (the interface threads are one
below): a writer at normal priority could be preempted by another process while it holds the
interpreter lock, and the loop would wait for the lock that long (measured: the loop's lateness
p99.9 with a recording 1.36x of without, 1.12x with the FIFO writer; docs/BENCHMARKS.md). Its
work is bounded (a flush every 50 ms of what was queued) and it yields the lock after every
record.

``occ-record`` (console script) exports a recording to CSV, to 3D Slicer's and PLUS's sequence
metafile (``--format seq``) or to a ROS 2 bag (``--format mcap``; occ/recording/export.py), replays
one into a peer, and plots one (``occ-record plot``: trajectories, tracking error, states with
causes, loop timing as a PNG; occ/recording/plot.py, matplotlib optional).

A recorder may also be started and stopped while the daemon runs (PLUS's ``StartRecording`` and
``StopRecording``: occ/recording/control.py); it is the same class, attached to the running robot.
"""

from __future__ import annotations

import csv
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Iterator
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
        self.errors = 0

    def start(self, *, exclusive: bool = False) -> Recorder:
        """Open the file and start the writer thread; ``exclusive``: refuse (FileExistsError)
        a file that exists, instead of replacing it (a recording started at run time)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "xb" if exclusive else "wb")  # noqa: SIM115 - close()
        self._thread = threading.Thread(target=self._writer, name="occ-recorder", daemon=True)
        self._thread.start()
        log.info("recording to %s (state at %g Hz)", self.path, self.rate_hz)
        return self

    # ------------------------------------------------------------------ loop thread
    def _put(self, item: tuple[Any, ...]) -> None:
        if len(self._q) >= self.max_backlog:
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
        if len(self._q) >= self.max_backlog:
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
            names = data.joint_names
            self._columns = ",".join(
                ["t", "state"]
                + [f"q.{n}" for n in names]
                + [f"sp.{n}" for n in names]
                + ["tip.x_mm", "tip.y_mm", "tip.z_mm"]
                + ([f"eff.{n}" for n in names] if data.effort_command is not None else [])
            )
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
            meta = dict(msg.metadata)
            meta["rec.dir"] = direction
            meta["rec.if"] = interface
            meta["rec.t"] = f"{now:.6f}"
            meta["rec.hv"] = str(msg.header_version)
            return bytes(msg.pack(2, metadata=meta))
        _, row, wall = item
        state = igtl.NDArrayMessage(
            array=np.asarray(row, dtype=np.float64),
            device_name=STATE_DEVICE,
            header_version=2,
            metadata={"columns": self._columns or "", "robot": self._robot},
            timestamp=wall,
        )
        return bytes(state.pack())

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
        while True:
            with self._cond:
                self._cond.wait(0.05)
                closed = self._closed
            self._flush()
            if closed:
                return

    def _flush(self) -> None:
        chunks = []
        sleep = time.sleep
        while self._q:
            try:
                item = self._q.popleft()
            except IndexError:  # pragma: no cover
                break
            try:
                chunks.append(self._encode(item))
            except (ValueError, TypeError, igtl.IGTLError):
                self.errors += 1
            # Hand the interpreter lock back after every record: a thread that wants it (the
            # loop, waking for its deadline) otherwise waits for the switch interval (5 ms by
            # default) while this thread packs a batch (measured: the slave's lateness p99.9
            # 1.8-3.0 ms with recording on vs 0.1 ms off).
            sleep(0)
        if chunks and self._file is not None:
            data = b"".join(chunks)
            try:
                self._file.write(data)
                self.bytes_written += len(data)
            except OSError:
                self.errors += 1
                log.exception("recorder: write failed")

    def close(self) -> None:
        """Stop the writer, write what is queued, close the file. Safe to call twice and from
        two threads (a recording stopped at run time while the daemon shuts down)."""
        with self._close_lock:
            self._close()

    def _close(self) -> None:
        if self._file is None:
            return
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._flush()
        self._file.close()
        self._file = None
        log.info(
            "recording closed: %d records, %d bytes, %d dropped",
            self.records + self.late_records,
            self.bytes_written,
            self.dropped + self.late_dropped,
        )

    def stats(self) -> dict[str, int | str]:
        return {
            "records": self.records + self.late_records,
            "bytes": self.bytes_written,
            "dropped": self.dropped + self.late_dropped,
            "errors": self.errors,
            "writer": self.thread_policy,
        }


def writer_priority(config: Any) -> int | None:
    """The priority of a daemon's threads that hold the interpreter lock for a while (the
    recorder's writer, the worker): SCHED_FIFO two below the loop (the interface threads are
    one below) when the loop runs SCHED_FIFO, else None."""
    prio = config.robot.realtime.fifo_priority
    return max(1, prio - 2) if prio else None


# ---------------------------------------------------------------------- reading
def iter_recording(path: str | Path) -> Iterator[Message]:
    """The messages of a recording one by one, read 1 MiB at a time (a 12-hour recording need
    not fit in memory); raises igtl.DecodeError on a damaged file."""
    dec = igtl.StreamDecoder()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            dec.feed(chunk)
            yield from dec
    dec.close()


def read_recording(path: str | Path) -> list[Message]:
    """All messages of a recording (raises igtl.DecodeError on a damaged file)."""
    return list(iter_recording(path))


def export_csv(path: str | Path, out_dir: str | Path) -> tuple[Path, Path]:
    """Write ``state.csv`` (the loop state rows) and ``messages.csv`` (one row per message)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    state_path, msg_path = out / "state.csv", out / "messages.csv"
    msgs = read_recording(path)
    with open(state_path, "w", newline="") as fs, open(msg_path, "w", newline="") as fm:
        ws, wm = csv.writer(fs), csv.writer(fm)
        header_written = False
        wm.writerow(
            ["t", "dir", "interface", "type", "device", "message_id", "timestamp", "content"]
        )
        for m in msgs:
            if m.message_type == "NDARRAY" and m.device_name == STATE_DEVICE:
                if not header_written:
                    ws.writerow(m.metadata.get("columns", "").split(","))
                    header_written = True
                row = [f"{v:.9g}" for v in np.asarray(m.array).ravel().tolist()]  # type: ignore[attr-defined]
                if len(row) > 1:  # the state column by its name, not its code (READY, RUNNING)
                    row[1] = STATE_NAMES.get(int(float(row[1])), row[1])
                ws.writerow(row)
                continue
            meta = m.metadata
            wm.writerow(
                [
                    meta.get("rec.t", ""),
                    meta.get("rec.dir", ""),
                    meta.get("rec.if", ""),
                    m.message_type,
                    m.device_name,
                    m.message_id,
                    f"{m.timestamp:.6f}",
                    _short(m),
                ]
            )
    return state_path, msg_path


def _short(m: Message) -> str:
    import json

    text = json.dumps(m.content_summary(), separators=(",", ":"), default=str)
    return text if len(text) <= 200 else text[:197] + "..."


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
