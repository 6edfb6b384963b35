"""Deterministic replay of a black box dump: ``occ-record replay --deterministic DIR``.

The robot is rebuilt from the dump's ``config.yaml`` (every interface on an in-process
channel: nothing is sent or bound; the cell's heartbeats are not sent), in simulated time, and
put in the state its checkpoint holds (occ/core/checkpoint.py): the state of every part before
the window's first tick. Then each recorded tick runs again through :meth:`Robot.tick
<occ.core.robot.Robot.tick>`, the robot's own code, with what that tick had:

- the clock value it read, and the wall-clock offset the streams asked for;
- every drive's reading as its hook returned it (the drivers keep their lifecycle and their
  feedback checks; only the hooks that touch hardware are the replay's), and a hook's error
  raised again where one was raised;
- with a simulated world, what the drive's hook left in it (the contact force the tissue
  sensor reads, and whether the tool touches): the hook that computed it is the replay's;
- every item the streams took, in order, with its reception time; every request the
  operator desk took (queued before the tick, as the interface thread did); every heartbeat
  the cell took.

After each tick its row (the replayed robot's own black box writes one) is compared with the
recorded row, bit for bit as float64: the state, every position setpoint and effort written,
and every joint's believed reading; and the tick's state transitions with theirs. The first
difference is reported (tick, field, recorded, replayed); none means the replay is exact.

``config`` replaces the dump's configuration (what-if: a changed gain); the replay then says
where its outputs first differ.

A controller's worker (the keyframe planner) runs what a tick asked of it (a plan, from the
request and the keyframes: recorded inputs) and the replay waits for it before the next tick,
so its result lands between the two ticks, as in a simulated-time run that waits for its
workers (each test and tool does).

Not replayed, and reported as a divergence where it mattered: what another thread did to the
loop's state (a hung loop's supervisor, a collision verdict that a worker thread delivered on
the real clock: in simulated time the guard checks inline and the replay recomputes it; a
planner's result that landed ticks later on the real clock), a drive's power-up on a thread
of its own, samples the loop could not take in time (an overflowing queue).
"""

from __future__ import annotations

import io
import json
import math
import pickle
import sys
import tempfile
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from occ.clock import SimClock
from occ.config import DaemonConfig
from occ.core.checkpoint import build_readings, restore
from occ.core.loader import load_config
from occ.core.robot import Robot, build_robot
from occ.core.wiring import checkpointer
from occ.errors import DriverError
from occ.recording.blackbox import CMD, HOOK, IN, TRANSITION, VERDICT
from occ.recording.dump import REPLAY, read_manifest

#: how long a replay waits for a controller's worker (a plan) after each tick
WORKER_WAIT_S = 60.0
#: the row fields compared, by column prefix (the rest are inputs)
COMPARED = ("state", "sp.", "ew.", "pos.")


@dataclass
class Divergence:
    """The first difference between the recorded run and the replay."""

    tick: int
    t: float
    field: str
    recorded: Any
    replayed: Any

    def describe(self) -> str:
        return (
            f"tick {self.tick} (t={self.t:.6f} s): {self.field}: recorded {self.recorded!r}, "
            f"replayed {self.replayed!r}"
        )


@dataclass
class ReplayResult:
    """What a replay found."""

    first_tick: int
    ticks: int = 0
    #: (tick, from, to, event, reason) of every transition replayed
    transitions: list[tuple[int, str, str, str, str]] = field(default_factory=list)
    divergence: Divergence | None = None
    #: slots of the checkpoint that could not be restored (named)
    problems: list[str] = field(default_factory=list)
    #: slots that the replayed robot's build made differently from the recorded robot's
    #: (a changed configuration: kept as built here, not restored)
    built_differently: list[str] = field(default_factory=list)

    @property
    def exact(self) -> bool:
        return self.divergence is None

    def report(self) -> dict[str, Any]:
        """For ``--json``."""
        d = self.divergence
        return {
            "exact": self.exact,
            "first_tick": self.first_tick,
            "ticks": self.ticks,
            "divergence": None if d is None else vars(d),
            "transitions": [
                dict(zip(("tick", "from", "to", "event", "reason"), t, strict=True))
                for t in self.transitions
            ],
            "not_restored": self.problems,
            "built_differently": self.built_differently,
        }

    def describe(self, path: str | Path) -> str:
        """For the terminal."""
        last = self.first_tick + self.ticks - 1
        lines = [f"{path}: ticks {self.first_tick}..{last} replayed ({self.ticks})"]
        for tick, old, new, event, reason in self.transitions:
            lines.append(f"  tick {tick}: {old} -> {new} ({event}): {reason}")
        if self.built_differently:
            lines.append(
                "  built differently here (the configuration given): "
                + ", ".join(self.built_differently[:8])
                + (" ..." if len(self.built_differently) > 8 else "")
            )
        for p in self.problems:
            lines.append(f"  NOT RESTORED: {p}")
        if self.divergence is None:
            lines.append("EXACT: every setpoint, effort, state and reading equal bit for bit")
        else:
            lines.append(f"DIVERGED at {self.divergence.describe()}")
        return "\n".join(lines)


class ReplayClock(SimClock):
    """Simulated time that reads, as its wall clock, the offset the recorded tick had."""

    __slots__ = ("to_wall",)

    def __init__(self, start: float, to_wall: float) -> None:
        super().__init__(start)
        self.to_wall = to_wall

    def wall_time(self) -> float:
        return self._t + self.to_wall


class _Replayed(Exception):
    """A hook's error raised again: the same words (``repr`` and ``str``) as recorded."""

    def __init__(self, text: str, rep: str) -> None:
        super().__init__(text)
        self._rep = rep

    def __repr__(self) -> str:
        return self._rep


def _error(cls: tuple[str, str, str, str]) -> Exception:
    module, name, text, rep = cls
    if module.startswith("occ.") and name.endswith("Error"):
        return DriverError(text)  # an OCCError passes through the driver as it is
    return _Replayed(text, rep)


class _Drives:
    """The drivers' hardware hooks, answered from the recorded rows."""

    def __init__(
        self, robot: Robot, columns: Sequence[str], built: dict[str, Any], paths: dict[int, str]
    ) -> None:
        """``built``: the drivers' slots as the recorded build left them; ``paths``: the
        parts' paths (a checkpointer's), the drivers' among them."""
        self.row: np.ndarray | None = None
        self.errors: dict[tuple[str, str], Exception] = {}
        #: each driver's reading when the recorded robot was configured
        self.built = {d.name: built.get(f"{paths.get(id(d))}.raw") for d in robot.hardware.drivers}
        col = {c: i for i, c in enumerate(columns)}
        for d, idx in robot.hardware.pairs:
            names = [robot.joints[i].name for i in idx]
            cols = [(col[f"raw.pos.{j}"], col[f"raw.vel.{j}"], col[f"raw.eff.{j}"]) for j in names]
            d._read = self._reader(d.name, cols)  # type: ignore[method-assign]
            d._write = self._writer(d.name)  # type: ignore[method-assign]
            for hook in ("_configure", "_activate", "_deactivate", "_shutdown", "_safe_stop"):
                setattr(d, hook, _nothing)
            d.activation_waits = False  # type: ignore[misc]

    def _reader(self, name: str, cols: list[tuple[int, int, int]]) -> Any:
        def read(now: float) -> Any:
            err = self.errors.pop((name, "read"), None)
            if err is not None:
                raise err
            row = self.row
            if row is None:  # configuring: what the recorded robot read then (a drive it
                # never read holds the driver's empty reading: not one, as none)
                got = self.built.get(name)
                return got if got is not None and len(got[0]) == len(cols) else _unread(len(cols))
            return (
                [float(row[p]) for p, _, _ in cols],
                [float(row[v]) for _, v, _ in cols],
                [float(row[e]) for _, _, e in cols],
            )

        return read

    def _writer(self, name: str) -> Any:
        def write(values: Sequence[float], now: float) -> None:
            err = self.errors.pop((name, "write"), None)
            if err is not None:
                raise err

        return write


class _World:
    """The simulated world's state from the recorded rows (``world.*`` columns, when the
    robot has one): set before each tick, as the drive's hook set it in the tick's read."""

    def __init__(self, robot: Robot, columns: Sequence[str]) -> None:
        self.env = robot.hardware.environment
        self.at = columns.index("world.fx") if "world.fx" in columns else -1
        if (self.env is None) != (self.at < 0):
            has = "has no" if self.at < 0 else "has a"
            raise ValueError(
                f"the dump {has} simulated world (environment) and the configuration replayed "
                "the other way round"
            )

    def set(self, row: np.ndarray) -> None:
        if self.env is None:
            return
        i = self.at
        self.env.force_n = (float(row[i]), float(row[i + 1]), float(row[i + 2]))
        self.env.in_contact = bool(row[i + 3] == 1.0)


def _nothing(*_args: Any) -> None:
    return None


def _unread(n: int) -> tuple[list[float], list[float], list[float]]:
    nan = [math.nan] * n
    return nan, nan, nan


class Damaged(ValueError):
    """A dump whose files cannot be read back (missing, cut, changed): it cannot be replayed."""


def load_dump(path: str | Path) -> tuple[dict[str, Any], DaemonConfig, np.ndarray, bytes]:
    """A dump's manifest, configuration, rows and replay file (ValueError when it has none,
    :class:`Damaged` when one of them cannot be read)."""
    p = Path(path)
    manifest = read_manifest(p)
    entry = manifest.get("replay") or {}
    if not entry.get("possible"):
        why = entry.get("why", "a dump of a version without replay")
        raise ValueError(f"{p}: cannot be replayed: {why}")
    name = "config.yaml"
    try:
        raw = yaml.safe_load((p / name).read_text(encoding="utf-8"))
        config = DaemonConfig.model_validate(raw, context={"base_dir": p})
        name = "ticks.npy"
        rows = np.load(p / name, allow_pickle=False)
        name = REPLAY
        blob = (p / name).read_bytes()
    except FileNotFoundError as err:
        raise Damaged(f"{p}: cannot be replayed: {name} is missing") from err
    except (OSError, ValueError, yaml.YAMLError) as err:
        raise Damaged(f"{p}: cannot be replayed: {name} is damaged ({err})") from err
    return manifest, config, rows, blob


def for_replay(config: DaemonConfig, scratch: Path) -> DaemonConfig:
    """``config`` rebuilt where nothing leaves the process: every interface in-process, the
    black box's own dumps in ``scratch`` (never written: the replay compares its rows)."""
    interfaces = tuple(
        itf.model_copy(
            update={"transport": "inproc", "channel": f"replay-{id(scratch)}-{itf.name}"}
        )
        for itf in config.interfaces
    )
    box = config.black_box.model_copy(update={"enabled": True, "dir": scratch})
    return config.model_copy(update={"interfaces": interfaces, "black_box": box})


def replay_dump(path: str | Path, config: DaemonConfig | None = None) -> ReplayResult:
    """Replay the dump at ``path`` (module docstring), with ``config`` instead of its own when
    given. ValueError when it cannot be replayed (no checkpoint, inputs overwritten)."""
    manifest, recorded_config, rows, blob = load_dump(path)
    columns: list[str] = manifest["tick_columns"]
    with tempfile.TemporaryDirectory(prefix="occ-replay-") as scratch:
        cfg = for_replay(config or recorded_config, Path(scratch))
        try:
            return _run(cfg, manifest, columns, rows, blob, config is None)
        except Damaged as err:
            raise Damaged(f"{path}: cannot be replayed: {REPLAY} is damaged ({err})") from err


def _run(
    cfg: DaemonConfig,
    manifest: dict[str, Any],
    columns: list[str],
    rows: np.ndarray,
    blob: bytes,
    same_config: bool = True,
) -> ReplayResult:
    wall_at = columns.index("to_wall")
    first = int(manifest["window"]["first_tick"])
    outer = _unpickled(_loads, blob)
    built_at = float(outer.get("built_at", math.nan))  # configured when the recorded one was
    start = built_at if math.isfinite(built_at) else float(rows[0, 0])
    clock = ReplayClock(start, _first_finite(rows[:, wall_at]))
    robot = build_robot(cfg, clock=clock)
    try:
        built = checkpointer(robot)  # the parts as built: the drivers' paths, the plugins
        readings = _unpickled(lambda b: build_readings(b, built.roots), outer["checkpoint"])
        drives = _Drives(robot, columns, readings, built.paths)
        robot.black_box.writer = None  # its rows are compared, its dumps never written
        robot.configure()
        if robot.cell is not None:
            robot.cell.link.send = lambda beat: len(robot.cell.link.peers)  # type: ignore[union-attr,method-assign]
        cp = checkpointer(robot)
        result = ReplayResult(first)
        same = same_config
        restored = _unpickled(lambda b: restore(cp, b, same), outer["checkpoint"])
        result.problems, result.built_differently = restored
        robot.black_box.resync()
        inputs = [ev for piece in outer["inputs"] for ev in _unpickled(cp.loads, piece)]
        verdicts = _verdicts(robot, manifest)
        _replay_ticks(robot, clock, drives, columns, rows, inputs, result, verdicts)
        return result
    finally:
        robot.shutdown()


def _unpickled(load: Any, blob: Any) -> Any:
    """``load(blob)``, any error of a cut or changed pickle :class:`Damaged` (a pickle that
    is not this format's can raise almost anything while it is read)."""
    try:
        return load(blob)
    except Exception as err:  # noqa: BLE001 - told as the file's damage, with its words
        raise Damaged(f"{type(err).__name__}: {err}") from err


def _loads(blob: bytes) -> dict[str, Any]:
    """The replay file's outer layer: a dict of two byte strings and the build's clock (no
    class may load)."""

    class _Plain(pickle.Unpickler):
        def find_class(self, module: str, name: str) -> Any:
            raise pickle.UnpicklingError(f"replay.pkl may not load {module}.{name}")

    out = _Plain(io.BytesIO(blob)).load()
    if not isinstance(out, dict) or not isinstance(out.get("checkpoint"), bytes):
        raise ValueError("not a replay file")
    pieces = out.get("inputs")
    if not isinstance(pieces, list) or not all(isinstance(p, bytes) for p in pieces):
        raise ValueError("not a replay file (inputs)")
    if not isinstance(out.get("built_at", 0.0), float):
        raise ValueError("not a replay file (built_at)")
    return out


def _first_finite(values: np.ndarray) -> float:
    ok = values[np.isfinite(values)]
    return float(ok[0]) if len(ok) else 1_700_000_000.0


def _verdicts(robot: Robot, manifest: dict[str, Any]) -> Any:
    """Where a recorded collision verdict goes: on the real clock the worker's verdicts came
    when they came, so the replay checks nothing and hands each one to the guard at the tick
    that took it (``CollisionGuard.fresh``, taken at the start of ``after_control``); in
    simulated time the guard checked inline and checks again (None)."""
    guard = robot.collision
    if guard is None or manifest.get("clock") != "real":
        return None
    guard.publish = lambda q, base, now=None: None  # type: ignore[method-assign]

    def give(verdict: Any) -> None:
        guard.fresh = verdict

    return give


def _replay_ticks(
    robot: Robot,
    clock: ReplayClock,
    drives: _Drives,
    columns: list[str],
    rows: np.ndarray,
    inputs: list[tuple[int, int, Any, Any]],
    result: ReplayResult,
    verdicts: Any = None,
) -> None:
    by_tick: dict[int, list[tuple[int, Any, Any]]] = defaultdict(list)
    for tick, kind, where, obj in inputs:
        by_tick[tick].append((kind, where, obj))
    compared = [i for i, c in enumerate(columns) if c.startswith(COMPARED)]
    wall_at = columns.index("to_wall")
    world = _World(robot, columns)
    waits = (getattr(c, "wait_idle", None) for c in robot.controller.controllers)
    workers = [w for w in waits if callable(w)]  # the controllers' threads (a keyframe planner)
    box = robot.black_box
    streams, cell = robot.streams, robot.cell
    pending: list[tuple[str, Any]] = []
    robot.streams.drain = lambda now, recorder: streams.replay(now, recorder, pending)  # type: ignore[method-assign]
    beats: list[Any] = []
    if cell is not None:
        cell.link.take = lambda: list(beats)  # type: ignore[method-assign]
    transitions: list[tuple[int, str, str, str, str]] = []
    here = [0]
    robot.state_machine.add_listener(
        lambda old, new, event, reason, t: transitions.append(
            (here[0], old.value, new.value, event, reason)
        )
    )
    for r in range(len(rows)):
        row = rows[r]
        tick = result.first_tick + r
        here[0] = tick
        t, k = float(row[0]), int(row[1])
        if math.isfinite(row[wall_at]):
            clock.to_wall = float(row[wall_at])
        clock.set(t)
        drives.row = row
        world.set(row)
        pending.clear()
        beats.clear()
        expected: list[tuple[int, str, str, str, str]] = []
        for kind, where, obj in by_tick.get(tick, ()):
            if kind == IN and where == "cell":
                beats.append(obj)
            elif kind == IN:
                pending.append((where, obj))
            elif kind == CMD:
                robot.interfaces.commands.put(obj)
            elif kind == HOOK:
                drives.errors[tuple(where)] = _error(obj)
            elif kind == TRANSITION:
                expected.append((tick, *obj))
            elif kind == VERDICT and verdicts is not None:
                verdicts(obj)
        robot.tick(t, k)
        for idle in workers:  # what the tick asked of them lands before the next one
            idle(WORKER_WAIT_S)
        result.ticks += 1
        got = box._view[(box.count - 1) % box._slots]
        diff = _first_difference(row, got, compared, columns)
        if diff is None and transitions != expected:
            diff = ("transitions", expected, list(transitions))
        result.transitions.extend(transitions)
        transitions.clear()
        if diff is not None:
            result.divergence = Divergence(tick, t, *diff)
            return


def _first_difference(
    recorded: np.ndarray, replayed: np.ndarray, compared: list[int], columns: list[str]
) -> tuple[str, Any, Any] | None:
    a = recorded[compared].view(np.uint64)
    b = replayed[compared].view(np.uint64)
    if np.array_equal(a, b):
        return None
    i = int(np.flatnonzero(a != b)[0])
    c = compared[i]
    return columns[c], float(recorded[c]), float(replayed[c])


#: exit status of a replay that diverged from the recorded run
DIVERGED = 4


def main_deterministic(path: Path, config: Path | None, *, as_json: bool = False) -> int:
    """``occ-record replay --deterministic DIR [--config FILE] [--json]``: 0 exact, 4
    diverged, 1 when it cannot be replayed."""
    try:
        cfg = load_config(config) if config is not None else None
        result = replay_dump(path, cfg)
    except (ValueError, OSError) as err:
        print(f"occ-record: {err}", file=sys.stderr)
        return 1
    if as_json:
        print(json.dumps(result.report(), indent=1, default=str))
    else:
        print(result.describe(path))
    return 0 if result.exact else DIVERGED
