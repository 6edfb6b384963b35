"""A black box dump on disk: what the dump writer thread writes (occ/recording/blackbox.py).

``black_box.dir/<robot>-<UTC time>-<cause>/`` holds:

- ``manifest.json``: the format (``occ-black-box`` 1), the robot, the causes (each with its
  reason), the trigger (tick index, the loop's time and deadline index, the wall time), the
  window (first tick index, rows, events, from which tick the events are whole, rows lost),
  the software (``occ`` version, Python, the hot path's build), the SHA-256 of the URDF, of
  every plugin's source file (drivers and controllers) and of ``config.yaml``, the tick
  columns, whether the dump replays (``replay``: from which tick, or why not) and what a
  dump does not hold;
- ``config.yaml``: the daemon's whole configuration as it ran (the validated model: it loads
  again with :class:`~occ.config.DaemonConfig`);
- ``ticks.npy``: the tick rows as the loop wrote them (float64, bit for bit; columns in the
  manifest): the clock each tick used, its deadline index, its state, every joint's
  believed position, what was written to the drives, every drive's raw reading;
- ``recording.igtl``: the window in the recording format (occ/recording/record.py), so
  ``occ-record export DIR`` (CSV, ``.seq.mha``, ``.mcap``), ``plot`` and ``replay`` read a dump
  as any recording: every message in and out with ``rec.t`` the tick's time and ``rec.tick``
  its tick index (alerts and replies out; the periodic outputs are not kept), then that
  tick's ``OCCState`` row (the tip by forward kinematics on the writer's own model; ``sp``
  the last position setpoint written);
- ``events.jsonl``: the events that are not messages, one JSON object a line with their tick:
  state transitions with their reasons, collision verdicts, controllers' notes, dump requests;
- ``replay.pkl``: what ``occ-record replay --deterministic`` reads (occ/core/replay.py): the
  robot's state at the window's first tick (a checkpoint: the slots changed since the robot
  was built, every part by its path) and every input with its tick, pickled; loaded with only
  this project's classes, numpy's and a few builtins allowed (occ/core/checkpoint.py).

A dump is written into ``.<name>.partial`` and renamed when whole, so a directory with a
manifest is complete. Then the dumps of this robot in ``dir`` are bounded: the oldest go
beyond ``max_dumps`` or ``max_mb`` (the newest is always kept), and stale partial ones too.
A dump that cannot be written (a full disk) is removed and told (``BLACKBOX`` alert).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import pickle
import select
import shutil
import signal
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, fields, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np

from occ.recording.blackbox import (
    CMD,
    HOOK,
    IN,
    KIND_NAMES,
    OUT,
    REQUEST,
    TRANSITION,
    VERDICT,
    BlackBox,
    DumpRequest,
    Window,
)
from occ.recording.record import (
    DUMP_RECORDING,
    os_cause,
    pack_message_record,
    pack_state_record,
    state_columns,
)

log = logging.getLogger(__name__)

FORMAT = "occ-black-box"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
#: what a deterministic replay reads (occ/core/replay.py)
REPLAY = "replay.pkl"
#: records packed before they are written
BATCH = 256
#: how long a dump's child process may take before it is killed (s)
FORK_TIMEOUT_S = 120.0
#: inputs pickled in one piece of replay.pkl (about 0.3 ms of the writer's work)
INPUTS_PIECE = 16

#: what a dump does not hold (the module docstring of blackbox.py says why)
NOT_RECORDED = [
    "another thread's change to the loop's state (the supervisor catching a hung loop, a "
    "region defined from another thread)",
    "a drive's power-up on a thread of its own",
    "stream samples the loop could not take in time (an overflowing queue)",
    "the periodic outputs (a replay makes them again from the state)",
    "the tick a planner's result landed in (a replay lets it land before the tick after its "
    "request)",
    "a simulated world's depth in each shape (only a refused ForceTare's words name it)",
    "inputs the interfaces refused before the loop (counted by the interfaces)",
]


@dataclass(frozen=True)
class DumpContext:
    """What the writer needs besides the rings: fixed at build, off the loop."""

    #: the daemon's configuration, as YAML text
    config_yaml: str
    #: software version, build, hashes of the URDF and plugins (occ/core/provenance.py)
    provenance: dict[str, Any]
    #: the tip position (mm, base frame) of joint positions, on the writer's own model
    tip_mm: Callable[[list[float]], tuple[float, float, float]]
    max_dumps: int
    max_bytes: int
    #: ``tell(text, ok)``: the alert that says where the dump went (or why it did not)
    tell: Callable[[str, bool], None]


def write_dump(box: BlackBox, req: DumpRequest, ctx: DumpContext) -> Path | None:
    """Copy ``req``'s window out of ``box`` and write it (module docstring); the alert told
    either way. Returns the dump's directory, None when it could not be written."""
    path, text, ok = make_dump(box, req, ctx)
    ctx.tell(text, ok)
    return path


def write_dump_forked(
    box: BlackBox, req: DumpRequest, ctx: DumpContext, timeout_s: float = FORK_TIMEOUT_S
) -> Path | None:
    """:func:`write_dump` in a child process (the real clock): ``fork()`` right after a tick
    gives the child a copy-on-write snapshot of the rings as they are, and the child copies,
    packs and writes the window with an interpreter lock of its own, so a dump never keeps
    the loop waiting for the lock (a thread of the loop's process that works for a second
    does, measured: ticks late by 5-10 ms while it wrote; the fork itself costs the process
    a few milliseconds once). The child touches none of the parent's I/O: it writes the
    files, says on a pipe what it wrote and exits; the alert is told here, by the parent.
    A child that has not answered within ``timeout_s`` is killed, and told as a failure."""
    r, w = os.pipe()
    box.pace()  # the fork's few milliseconds in the time the ticks leave
    pid = os.fork()
    if pid == 0:  # the child
        code = 1
        try:
            os.close(r)
            box.pace = _no_pace
            path, text, ok = make_dump(box, req, ctx)
            os.write(
                w,
                json.dumps({"path": str(path) if path else None, "text": text, "ok": ok}).encode(
                    "utf-8"
                ),
            )
            code = 0
        except BaseException as err:  # noqa: BLE001 - told to the parent, then the child ends
            with contextlib.suppress(Exception):
                text = f"black box of {_causes(req)} NOT written: {err!r}"
                os.write(w, json.dumps({"path": None, "text": text, "ok": False}).encode())
        finally:
            os._exit(code)
    os.close(w)
    answer = _child_answer(r, pid, timeout_s)
    ok = bool(answer.get("ok"))
    text = str(answer.get("text") or f"black box of {_causes(req)} NOT written: no answer")
    ctx.tell(text, ok)
    return Path(answer["path"]) if ok and answer.get("path") else None


def _child_answer(r: int, pid: int, timeout_s: float) -> dict[str, Any]:
    """What the dump's child said on its pipe (``{}`` when nothing, or killed after
    ``timeout_s``); the child reaped either way."""
    chunks: list[bytes] = []
    deadline = time.monotonic() + timeout_s
    try:
        while True:
            left = deadline - time.monotonic()
            if left <= 0.0:
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGKILL)
                log.error("black box: the dump's child %d did not answer in %.0f s", pid, timeout_s)
                break
            ready, _, _ = select.select([r], [], [], min(left, 1.0))
            if ready:
                data = os.read(r, 65536)
                if not data:
                    break
                chunks.append(data)
    finally:
        os.close(r)
        with contextlib.suppress(ChildProcessError):
            os.waitpid(pid, 0)
    try:
        answer: dict[str, Any] = json.loads(b"".join(chunks).decode("utf-8"))
    except ValueError:
        return {}
    return answer


def _no_pace() -> None:
    return None


def make_dump(box: BlackBox, req: DumpRequest, ctx: DumpContext) -> tuple[Path | None, str, bool]:
    """Copy ``req``'s window out of ``box`` and write it; (its directory or None, the alert's
    words, whether it was written). Tells nobody (:func:`write_dump` does)."""
    window = box.window(req)
    if req.path.exists():  # another daemon of this robot's name, in this millisecond
        req.path = req.path.with_name(f"{req.name}-{os.getpid()}")
    tmp = req.path.parent / f".{req.name}.partial"
    try:
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir(parents=True)
        size = _write_files(tmp, box, req, window, ctx)
        os.replace(tmp, req.path)
    except OSError as err:
        shutil.rmtree(tmp, ignore_errors=True)
        text = f"black box of {_causes(req)} NOT written to {req.path}: {os_cause(err)}"
        log.error("%s", text)
        return None, text, False
    removed = prune(req.path.parent, box.name, ctx.max_dumps, ctx.max_bytes, keep=req.path)
    secs = len(window.rows) / box.rate_hz
    text = (
        f"black box of {_causes(req)} written to {req.path} ({len(window.rows)} ticks, "
        f"{secs:.1f} s, {len(window.events)} events, {size / 1e6:.1f} MB)"
        + (f"; {len(removed)} older dump(s) removed" if removed else "")
    )
    log.warning("%s", text)
    return req.path, text, True


def _causes(req: DumpRequest) -> str:
    return "; ".join(f"{c} ({why})" if why else c for c, why in req.causes)


def _write_files(
    tmp: Path, box: BlackBox, req: DumpRequest, window: Window, ctx: DumpContext
) -> int:
    """Every file of the dump into ``tmp``; the bytes written."""
    np.save(tmp / "ticks.npy", window.rows)
    (tmp / "config.yaml").write_text(ctx.config_yaml, encoding="utf-8")
    n_msgs = _write_recording(tmp / DUMP_RECORDING, box, req, window, ctx)
    n_other = _write_events(tmp / "events.jsonl", window)
    replayable = _write_replay(tmp / REPLAY, box, window)
    rows = window.rows
    manifest = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "robot": box.name,
        "causes": [{"cause": c, "reason": why} for c, why in req.causes],
        "trigger": {"tick": req.end - 1, "t": req.t, "wall": req.wall},
        "window": {
            "first_tick": window.first_row,
            "ticks": len(rows),
            "seconds": len(rows) / box.rate_hz,
            "t_first": float(rows[0, 0]) if len(rows) else None,
            "t_last": float(rows[-1, 0]) if len(rows) else None,
            "rows_lost": window.rows_lost,
            "messages": n_msgs,
            "events": n_other,
            "events_whole_from_tick": window.events_whole_from,
        },
        "rate_hz": box.rate_hz,
        # on the real clock collision verdicts came from a worker thread: a replay feeds them
        "clock": "simulated" if box.inline_checkpoints else "real",
        "joints": list(box.joint_names),
        "tick_columns": box.columns,
        **ctx.provenance,
        "config_sha256": hashlib.sha256(ctx.config_yaml.encode("utf-8")).hexdigest(),
        "replay": replayable,
        "not_recorded": NOT_RECORDED,
        "files": [
            "manifest.json",
            "config.yaml",
            "ticks.npy",
            DUMP_RECORDING,
            "events.jsonl",
            *([REPLAY] if "from_tick" in replayable else []),  # written only with a checkpoint
        ],
    }
    (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1, default=str), encoding="utf-8")
    return sum(p.stat().st_size for p in tmp.iterdir())


def _write_recording(
    path: Path, box: BlackBox, req: DumpRequest, window: Window, ctx: DumpContext
) -> int:
    """The window as a recording: each tick's messages, then its OCCState row. Returns the
    messages written."""
    rows, events, n = window.rows, window.events, len(box.joint_names)
    sp_at, ew_at = 3 + n, 3 + 2 * n
    # a robot that commands efforts (a haptic master): its rows end with them, as recorded
    efforts = bool(len(rows)) and not np.isnan(rows[:, ew_at : ew_at + n]).all()
    columns = state_columns(box.joint_names, efforts)
    to_wall = req.wall - req.t
    last_sp = [math.nan] * n
    last_ew = [0.0] * n
    e, written = 0, 0
    chunks: list[bytes] = []
    with open(path, "wb") as f:
        for r in range(len(rows)):
            row = rows[r]
            tick = window.first_row + r
            t = float(row[0])
            while e < len(events) and events[e][0] <= tick:
                ev_tick, kind, where, obj = events[e]
                e += 1
                if kind == IN or kind == OUT or kind == CMD:
                    extra = {"rec.tick": str(ev_tick)}
                    direction = "out" if kind == OUT else "in"
                    if kind != OUT:
                        obj = getattr(obj, "msg", None)  # a received item: its message
                        if obj is None:
                            continue  # a cell member's heartbeat: in replay.pkl only
                    try:
                        chunks.append(pack_message_record(obj, direction, where, t, extra))
                        written += 1
                    except Exception as err:  # noqa: BLE001 - one message, not the dump
                        log.warning("black box: a %s message could not be packed: %s", kind, err)
            sp = row[sp_at : sp_at + n]
            if not math.isnan(sp[0]):
                last_sp = sp.tolist()
            ew = row[ew_at : ew_at + n]
            if not math.isnan(ew[0]):
                last_ew = ew.tolist()
            q = row[3 : 3 + n].tolist()
            tip = ctx.tip_mm(q)
            state = [t, float(row[2]), *q, *last_sp, *tip, *(last_ew if efforts else ())]
            chunks.append(pack_state_record(state, columns, box.name, t + to_wall))
            if r & 7 == 7:
                # out of the loop's way every 8 ticks packed (~0.1 ms of work): on the real
                # clock only in the time the ticks leave (ControlLoop.yield_to_loop)
                box.pace()
            if len(chunks) >= BATCH:
                f.write(b"".join(chunks))
                chunks.clear()
        f.write(b"".join(chunks))
    return written


def _write_replay(path: Path, box: BlackBox, window: Window) -> dict[str, Any]:
    """What a deterministic replay needs beside the ticks (occ/core/replay.py): the
    robot's state before the window's first tick (its checkpoint, every part by its path),
    the clock when it was built, and every input of the window with its tick: the received
    items as the loop took them (their reception times and the requests parsed), the cell's
    heartbeats, the collision verdicts, the drivers' hook errors. Returns the manifest's
    ``replay`` entry."""
    cp = box.checkpointer
    if window.checkpoint is None or cp is None or box.checkpoints is None:
        why = "no checkpoint of the robot's state in the window"
        return {"possible": False, "why": why}
    first = window.first_row
    whole = window.events_whole_from <= first
    inputs = [
        (tick, kind, where, obj)
        for tick, kind, where, obj in window.loop_events
        if kind == IN or kind == CMD or kind == VERDICT or kind == HOOK or kind == TRANSITION
    ]
    try:
        checkpoint = cp.dumps(window.checkpoint, box.checkpoints.baseline, box.pace)
        pieces = []  # a few inputs a piece: the writer is out of the loop's way between
        for i in range(0, len(inputs), INPUTS_PIECE):
            pieces.append(cp.dumps_values(inputs[i : i + INPUTS_PIECE]))
            box.pace()
        blob = pickle.dumps(
            {"checkpoint": checkpoint, "inputs": pieces, "built_at": box.checkpoints.built_at},
            protocol=pickle.HIGHEST_PROTOCOL,
        )
    except Exception as err:  # noqa: BLE001 - the dump is still a record: say why not
        log.exception("black box: the replay inputs could not be written")
        return {"possible": False, "why": f"inputs could not be written: {err!r}"}
    path.write_bytes(blob)
    entry: dict[str, Any] = {"possible": whole, "from_tick": first, "inputs": len(inputs)}
    if not whole:
        entry["why"] = f"inputs before tick {window.events_whole_from} were overwritten"
    return entry


def _write_events(path: Path, window: Window) -> int:
    """The events that are not messages (JSON lines). Returns how many."""
    rows, first = window.rows, window.first_row
    n = 0
    with open(path, "w", encoding="utf-8") as f:
        for tick, kind, where, obj in window.events:
            if kind == IN or kind == OUT or kind == HOOK or kind == CMD:
                continue
            r = tick - first
            t = float(rows[r, 0]) if 0 <= r < len(rows) else None
            rec: dict[str, Any] = {"tick": tick, "t": t, "kind": KIND_NAMES.get(kind, kind)}
            if kind == TRANSITION:
                rec.update(zip(("from", "to", "event", "reason"), obj, strict=True))
            elif kind == REQUEST:
                rec.update({"cause": where, "reason": obj})
            else:
                if where is not None:
                    rec["what"] = where
                rec["value"] = jsonable(obj)
            f.write(json.dumps(rec, default=str) + "\n")
            n += 1
    return n


def jsonable(obj: Any, depth: int = 0) -> Any:
    """A verdict, a plan or a note as JSON can hold it: dataclasses by their fields, arrays
    as lists, infinities as text, a named part by its name, anything else by its repr."""
    if obj is None or isinstance(obj, bool | int | str):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else str(obj)
    if depth > 4:
        return repr(obj)[:200]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist(), depth + 1)
    if isinstance(obj, list | tuple):
        return [jsonable(v, depth + 1) for v in obj]
    if isinstance(obj, dict):
        return {str(k): jsonable(v, depth + 1) for k, v in obj.items()}
    describe = getattr(obj, "describe", None)
    if callable(describe) and not is_dataclass(obj):
        return str(describe())
    if is_dataclass(obj):
        out = {f.name: jsonable(getattr(obj, f.name), depth + 1) for f in fields(obj)}
        if callable(describe):
            out["text"] = str(describe())
        return out
    name = getattr(obj, "name", None)
    if isinstance(name, str):
        return name
    return repr(obj)[:200]


# ---------------------------------------------------------------------- bounds
def dumps_of(directory: Path, robot: str) -> Iterator[Path]:
    """The complete dumps of ``robot`` in ``directory`` (a manifest of this format)."""
    if not directory.is_dir():
        return
    for p in directory.iterdir():
        if p.is_dir() and p.name.startswith(f"{robot}-") and (p / MANIFEST).is_file():
            yield p


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def prune(directory: Path, robot: str, max_dumps: int, max_bytes: int, keep: Path) -> list[Path]:
    """Remove ``robot``'s oldest dumps beyond ``max_dumps`` or ``max_bytes`` (never ``keep``,
    the newest), and its partial dumps left by a crash. Returns what was removed. Only this
    robot's: daemons of other robots may share the directory."""
    for p in directory.glob(f".{robot}-*.partial"):
        shutil.rmtree(p, ignore_errors=True)
    dumps = sorted(dumps_of(directory, robot), key=lambda p: (p.stat().st_mtime, p.name))
    sizes = {p: _size(p) for p in dumps}
    total, left = sum(sizes.values()), len(dumps)
    gone: list[Path] = []
    for p in dumps:  # oldest first
        if left <= max_dumps and total <= max_bytes:
            break
        if p == keep:
            continue
        shutil.rmtree(p, ignore_errors=True)
        gone.append(p)
        total, left = total - sizes[p], left - 1
    return gone


def read_manifest(path: str | Path) -> dict[str, Any]:
    """A dump's manifest (ValueError when ``path`` is not a dump of this format)."""
    p = Path(path) / MANIFEST
    try:
        manifest: dict[str, Any] = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        raise ValueError(f"{path}: not a black box dump ({err})") from err
    if manifest.get("format") != FORMAT:
        raise ValueError(f"{path}: not a black box dump (format {manifest.get('format')!r})")
    return manifest
