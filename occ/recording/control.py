"""Recording started and stopped while the daemon runs, as PLUS servers do it.

Three operator commands, over COMMAND (answered by RTS_COMMAND) or a PLUS-style STRING
``CMD_<id>`` (answered by ``ACK_<id>``), from an operator interface:

- ``StartRecording`` (attribute ``OutputFilename``, optional): record to that file in the
  configured directory (``recording.directory``). The name is a bare file name (letters, digits,
  ``.``, ``_``, ``-``; no directory, not starting with ``.``); ``.igtl`` is added when it has no
  suffix of its own; an existing file is never replaced. Without a name:
  ``<robot>_<YYYYmmdd-HHMMSS>.igtl``. Refused while a recording runs (also one started with
  ``--record``). The reply comes once the file is open.
- ``StopRecording``: close the recording (any, ``--record``'s too); the reply, once every record
  is on disk, says how many records went to which file (PLUS: ``Recording N frames successful to
  file F``). ``OutputFilename`` renames the file on the way (never over an existing one).
- ``GetRecordingStatus``: ``recording=true; file=...; records=...; bytes=...; dropped=...``,
  ``recording=failed; file=...; cause=...; ...`` (below), ``recording=starting; file=...`` or
  ``recording=false`` (with ``last=`` the last file).

A recording that fails (a full disk, ``ENOSPC``; its file or directory removed; its writer
gone: occ/recording/record.py) is an ALERT to every operator once, with the cause (the robot's
alarms), and stays attached, marked failed, until StopRecording, whose answer (a FAIL: the
recording is not whole) says what is on disk and how many records were not written. Every
command is answered whatever the disk does: a job of the worker that raises answers its
command with the error.

The recorder is the one ``--record`` uses (occ/recording/record.py): the loop only appends to its
queue, its own thread writes. Opening the file and closing it (which waits for the writer to drain)
happen on the robot's worker thread, never on the loop: the loop hands the job over and the
reply is sent when the worker is done (a :class:`~occ.net.commands.Deferred`). The recorder is
attached by the worker (a reference the loop reads from its next tick) and detached by the loop
itself (StopRecording is handled on the loop thread), so the loop never loses it between a
check and a call.

Recordings are in the daemon's own format; ``occ-record export`` turns them into the sequence
metafile of 3D Slicer and PLUS or a ROS 2 bag (occ/recording/export.py). A name with such a suffix
(``.mha``, ``.nrrd``, ``.mcap`` ...) is refused with that advice: converting on the running
daemon would take the interpreter from the loop.
"""

from __future__ import annotations

import logging
import os
import re
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from occ.errors import CommandError
from occ.net.commands import Deferred, Request
from occ.recording.record import Recorder

if TYPE_CHECKING:
    from occ.core.ports import RecordingPort

log = logging.getLogger("occ.core.robot")

#: a bare file name: no directory, no leading dot, nothing a shell or another OS would mangle
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,199}")
#: suffixes of the export formats: a recording is not written in them (see the docstring)
EXPORT_SUFFIXES = (".mha", ".mhd", ".nrrd", ".nhdr", ".mcap", ".csv", ".db3", ".bag")


def _arg(req: Request, name: str) -> str:
    """An XML attribute, whatever its case (PLUS writes ``OutputFilename``)."""
    low = name.lower()
    for key, value in req.args.items():
        if key.lower() == low:
            return value.strip()
    return ""


class RecordingControl:
    """StartRecording, StopRecording and GetRecordingStatus of one robot (module docstring)."""

    def __init__(self, port: RecordingPort) -> None:
        self.port = port
        #: the file a start is opening on the worker (None when none is)
        self._pending: Path | None = None
        #: recorders started or stopped here that may still need closing (at shutdown)
        self._open: set[Recorder] = set()
        self._lock = threading.Lock()  # _open, _closed: the loop, the worker, shutdown
        self._closed = False
        self.last_path: Path | None = None
        self.started = 0
        self.stopped = 0
        self.failed = 0

    # ------------------------------------------------------------------ loop thread
    def directory(self) -> Path:
        return Path(self.port.config.directory)

    def file_name(self, text: str, command: str) -> str:
        """``text`` as a recording's file name in the directory, or CommandError saying why."""
        if not NAME_PATTERN.fullmatch(text):
            raise CommandError(
                f"{command}: OutputFilename must be a bare file name (letters, digits, '.', "
                f"'_', '-'; at most 200; no directory, not starting with '.'), got {text!r}"
            )
        lower = text.lower()
        if lower.endswith(EXPORT_SUFFIXES):
            raise CommandError(
                f"{command}: {text!r}: the daemon records in its own format (.igtl); record to "
                "NAME.igtl, then occ-record export NAME.igtl OUT.seq.mha (or OUT.mcap)"
            )
        return text if lower.endswith(".igtl") else text + ".igtl"

    def start(self, req: Request) -> Deferred:
        """StartRecording (module docstring)."""
        r = self.port
        current = r.recorder()
        if current is not None:
            raise CommandError(
                f"StartRecording: already recording to {current.path}; send StopRecording first"
            )
        if self._pending is not None:
            raise CommandError(f"StartRecording: already starting a recording ({self._pending})")
        if self._closed:
            raise CommandError("StartRecording: the daemon is shutting down")
        text = _arg(req, "OutputFilename")
        if not text:
            text = f"{r.name}_{time.strftime('%Y%m%d-%H%M%S')}.igtl"
        path = self.directory() / self.file_name(text, "StartRecording")
        done = Deferred()
        self._pending = path
        if not r.worker.start().submit(lambda: self._open_file(path, done)):
            self._pending = None
            raise CommandError("StartRecording: busy (the worker's queue is full); try again")
        return done

    def stop(self, req: Request) -> Deferred:
        """StopRecording (module docstring)."""
        r = self.port
        rec = r.recorder()
        if rec is None:
            if self._pending is not None:
                raise CommandError(
                    f"StopRecording: the recording {self._pending} is still being opened; try again"
                )
            raise CommandError("StopRecording: not recording")
        text = _arg(req, "OutputFilename")
        target = rec.path
        if text:
            target = self.directory() / self.file_name(text, "StopRecording")
        with self._lock:
            self._open.add(rec)
        r.set_recorder(None)  # the loop thread: nothing is recorded from here on
        done = Deferred()
        if not r.worker.start().submit(lambda: self._close_file(rec, target, done)):
            r.set_recorder(rec)
            raise CommandError("StopRecording: busy (the worker's queue is full); try again")
        return done

    def describe(self) -> str:
        """GetRecordingStatus's answer."""
        rec = self.port.recorder()
        if rec is not None and rec.failure is not None:
            s = rec.stats()
            return (
                f"recording=failed; file={rec.path}; cause={rec.failure}; "
                f"records={s['records']}; written={s['written']}; bytes={s['bytes']}; "
                f"not_written={rec.not_written()}"
            )
        if rec is not None:
            s = rec.stats()
            return (
                f"recording=true; file={rec.path}; records={s['records']}; bytes={s['bytes']}; "
                f"dropped={s['dropped']}; errors={s['errors']}"
            )
        pending = self._pending
        if pending is not None:
            return f"recording=starting; file={pending}"
        last = f"; last={self.last_path}" if self.last_path is not None else ""
        return f"recording=false{last}"

    def stats(self) -> dict[str, Any]:
        """For GetStats."""
        rec = self.port.recorder()
        return {
            "active": rec is not None,
            "file": str(rec.path) if rec is not None else None,
            "recorder": rec.stats() if rec is not None else None,
            "started": self.started,
            "stopped": self.stopped,
            "failed": self.failed,
            "last": str(self.last_path) if self.last_path is not None else None,
        }

    # ------------------------------------------------------------------ worker thread
    def _open_file(self, path: Path, done: Deferred) -> None:
        try:
            self._start_file(path, done)
        except Exception as err:  # noqa: BLE001 - the command is answered whatever happened
            log.exception("StartRecording: %s", path)
            self._fail(done, f"StartRecording: cannot record to {path}: {err}")

    def _start_file(self, path: Path, done: Deferred) -> None:
        cfg = self.port.config
        rec = Recorder(
            path,
            rate_hz=cfg.rate_hz,
            include_messages=cfg.include_messages,
            fifo_priority=self.port.fifo_priority,
        )
        try:
            # its own step: a FileExistsError here is the directory's name taken by a file,
            # not the recording's file existing
            path.parent.mkdir(parents=True, exist_ok=True)
        except FileExistsError:
            self._fail(
                done, f"StartRecording: cannot write {path}: {path.parent} is not a directory"
            )
            return
        except OSError as err:
            self._fail(done, f"StartRecording: cannot write {path}: {err.strerror or err}")
            return
        try:
            rec.start(exclusive=True)
        except FileExistsError:
            self._fail(done, f"StartRecording: {path} exists; not overwriting")
            return
        except OSError as err:
            self._fail(done, f"StartRecording: cannot write {path}: {err.strerror or err}")
            return
        with self._lock:
            closed = self._closed
            if not closed:
                self._open.add(rec)
        if closed:  # the daemon stopped while the file was being opened
            rec.close()
            self._fail(done, "StartRecording: the daemon is shutting down")
            return
        self.port.set_recorder(rec)
        self._pending = None
        self.started += 1
        log.info("recording started at run time: %s", path)
        done.resolve(f"recording to {path}")

    def _fail(self, done: Deferred, text: str) -> None:
        self._pending = None
        self.failed += 1
        log.warning("%s", text)
        done.fail(text)

    def _close_file(self, rec: Recorder, target: Path, done: Deferred) -> None:
        try:
            self._stop_file(rec, target, done)
        except Exception as err:  # noqa: BLE001 - the command is answered whatever happened
            log.exception("StopRecording: %s", rec.path)
            self.failed += 1
            done.fail(f"StopRecording: recording stopped; closing {rec.path} failed: {err}")

    def _stop_file(self, rec: Recorder, target: Path, done: Deferred) -> None:
        rec.close()  # never raises: what it could not do is the recording's failure
        with self._lock:
            self._open.discard(rec)
        s = rec.stats()
        self.stopped += 1
        path = rec.path
        summary = f"{s['records']} records ({s['bytes']} bytes, {s['dropped']} dropped)"
        if target != path:
            try:
                # a hard link then an unlink: never over an existing file (os.rename would)
                os.link(path, target)
                os.unlink(path)
                path = target
            except OSError as err:
                self.last_path = path
                self.failed += 1
                done.fail(
                    f"StopRecording: recording stopped, {summary} in {path}; cannot name it "
                    f"{target.name}: {err.strerror or err}"
                    + (f"; it had FAILED: {rec.failure}" if rec.failure is not None else "")
                )
                return
        self.last_path = path
        if rec.failure is not None:  # stopped, but not whole: the operator must know
            self.failed += 1
            done.fail(
                f"StopRecording: recording stopped; it had FAILED: {rec.failure}; "
                f"{s['written']} records ({s['bytes']} bytes) in {path} up to the failure, "
                f"{rec.not_written()} records not written"
            )
            return
        log.info("recording stopped: %s in %s", summary, path)
        done.resolve(f"Recording {summary} successful to file {path}")

    # ------------------------------------------------------------------ shutdown
    def close_all(self) -> None:
        """Close every recording started or stopped here (the daemon's shutdown; a recording
        ``--record`` started and nobody stopped is its caller's to close)."""
        with self._lock:
            self._closed = True
            recs = list(self._open)
            self._open.clear()
        for rec in recs:
            rec.close()
