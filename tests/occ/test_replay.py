"""Deterministic replay of black box dumps (occ/core/replay.py; issue 41, item 4).

Every shipped config runs in simulated time past a checkpoint in mid-run (``black_box.seconds``
1: the window starts at the checkpoint of tick 1000 or later), is dumped by a safety stop or an
operator's emergency stop, and ``replay_dump`` rebuilds it from the dump alone: every setpoint,
effort, state, reading and transition equal bit for bit, nothing left unrestored. Then what the
replay must tell apart: a changed parameter diverges at the first tick it matters, naming the
field; a recorded value one ulp off is caught where it is; a dump whose replay file is missing
or damaged is refused with the reason (the CLI exits 1), and the CLI's exits 0 and 4.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from occ.config import DaemonConfig
from occ.core.checkpoint import Checkpointer, restore
from occ.core.loader import parse_config
from occ.core.replay import replay_dump
from occ.core.safety import RobotState
from occ.recording.cli import main as occ_record
from occ.recording.dump import REPLAY, read_manifest
from occ_testkit import CONFIGS
from occ_testkit.rigs import SimMaster, SlaveRig
from occ_testkit.testing import SimPair, SimRobot
from tests.occ.test_collab import Collab, handover, ok
from tests.occ.test_collision import CEILING, command, ur5
from tests.occ.test_haptic_master import forbidden_at

pytestmark = pytest.mark.req("SR-BOX-6")

#: a dump, and the state its replayed transitions must end in (the stop that dumped it)
Dumped = tuple[Path, str]


def _config(
    tmp_path: Path, name: str, raw: dict[str, Any] | None = None, **edits: Any
) -> DaemonConfig:
    """configs/``name`` (or ``raw``, read from it and edited) with a black box of 1 s in
    ``tmp_path``; ``edits``: controller parameters changed."""
    data = raw if raw is not None else yaml.safe_load((CONFIGS / name).read_text())
    data["black_box"] = {"dir": str(tmp_path / "bb" / name.replace("/", "-")), "seconds": 1}
    data["controller"]["params"].update(edits)
    return parse_config(yaml.safe_dump(data), source=str(CONFIGS / name))


def _dumps(robot: Any) -> list[Path]:
    box = robot.black_box
    assert box.wait_idle(30.0)
    return sorted(p for p in box.dir.iterdir() if not p.name.startswith("."))


def _xml(name: str, **args: Any) -> str:
    return f'<Command Name="{name}"' + "".join(f' {k}="{v}"' for k, v in args.items()) + "/>"


# ------------------------------------------------------------------ one run per shipped config
def _teleop_loss(tmp_path: Path, name: str, step_mm: float, **rig: Any) -> list[Dumped]:
    """A slave following a moving stream for 2.5 s, then three numbers lost: a loss stop."""
    r = SlaveRig(_config(tmp_path, name), **rig)
    try:
        r.running()
        for _ in range(2500):
            r.target[0] += step_mm
            r.step(1)
        r.seq += 3
        r.step(20)
        assert r.robot.state is RobotState.STOPPED
        (path,) = _dumps(r.robot)
    finally:
        r.close()
    return [(path, "STOPPED")]


def slave(tmp_path: Path) -> list[Dumped]:
    return _teleop_loss(tmp_path, "slave.yaml", 0.01)


def servo(tmp_path: Path) -> list[Dumped]:
    """configs/servo.yaml: absolute targets (a CRTK servo stream), 1 mm/s."""
    return _teleop_loss(tmp_path, "servo.yaml", 0.001, stream="servo", device="ServoCP")


def master(tmp_path: Path) -> list[Dumped]:
    """The haptic master (its hand simulated) with a forbidden sphere defined inside the
    window: the force it displays is written to the drives' efforts."""
    m = SimMaster(_config(tmp_path, "master.yaml"), feed=True)
    try:
        m.run()
        m.step(1200 - m.k)
        t = m.feed.handle_mm()
        m.op.send(forbidden_at(m.feed.patient((t[0] + 4.0, t[1], t[2])), k=0.5))
        m.step(2600 - m.k)
        assert m.command("EStop").metadata["Status"] == "SUCCESS"
        (path,) = _dumps(m.robot)
    finally:
        m.close()
    rows, cols = _rows(path)
    ew = rows[:, cols.index("ew.x") : cols.index("ew.x") + 3]
    assert (np.abs(ew[np.isfinite(ew)]) > 0.5).any()  # the fixture's force, displayed
    return [(path, "ESTOP")]


def wall(tmp_path: Path) -> list[Dumped]:
    """The wall pair (configs/master.yaml and configs/wall.yaml): the slave's tool presses into
    the simulated tissue, its force goes back to the master's hand; both emergency-stopped."""
    p = SimPair(_config(tmp_path, "master.yaml"), _config(tmp_path, "wall.yaml"))
    try:
        p.start()
        p.run_for(2.6)
        p.s_op.send_command("EStop")
        p.m_op.send_command("EStop")
        p.step(1)
        (m_path,) = _dumps(p.master.robot)
        (s_path,) = _dumps(p.slave.robot)
    finally:
        p.close()
    rows, cols = _rows(s_path)
    assert (rows[:, cols.index("world.contact")] == 1.0).sum() > 100  # in the tissue a while
    return [(s_path, "ESTOP"), (m_path, "ESTOP")]


def keyframes(tmp_path: Path) -> list[Dumped]:
    """configs/keyframe.yaml: the demo file planned and acknowledged inside the window (the
    planner's thread: a recorded request), its trajectory running when the robot is
    emergency-stopped. The robot rests at home until then: its drives as built count."""
    sim = SimRobot(_config(tmp_path, "keyframe.yaml"))
    op = sim.peer("slicer")
    kf: Any = sim.robot.controller.controllers[0]

    def ask(name: str, **args: Any) -> str:
        cid = op.send_command(name, _xml(name, **args))
        sim.step(1)
        assert kf.wait_idle(30.0)
        sim.step(1)
        reply = op.reply_to(cid)
        assert reply is not None and reply.metadata["Status"] == "SUCCESS", name
        return str(reply.metadata["Message"])

    try:
        ask("Enable")
        ask("Run")
        sim.step(1200 - sim.k)
        plan = ask("KeyframePlan").split(":")[0].split()[1]
        sim.step(150)  # the preview goes out
        ask("KeyframeAck", Plan=plan)
        sim.step(1000)
        assert kf.active is not None  # running
        op.send_command("EStop", _xml("EStop"))
        sim.step(1)
        (path,) = _dumps(sim.robot)
    finally:
        sim.close()
    return [(path, "ESTOP")]


def ur5_collision(tmp_path: Path) -> list[Dumped]:
    """configs/ur5.yaml teleoperated up into a ceiling (as tests/occ/test_collision.py): the
    collision guard stops it, its wrist inside the margin."""
    raw = ur5({"margin_mm": 10.0, "regions": [CEILING]})
    sim = SimRobot(_config(tmp_path, "ur5.yaml", raw))
    try:
        link = sim.peer("master")
        command(sim, "Enable")
        command(sim, "Run")
        for k in range(8000):
            if k % 2 == 0:  # the tool raised at 50 mm/s
                n = k // 2 + 1
                link.send_position((0.0, 0.0, 0.2 * n), seq=n, timestamp=sim.clock.wall_time())
            sim.step(1)
            if sim.robot.state is not RobotState.RUNNING:
                break
        assert sim.robot.state is RobotState.STOPPED and sim.k > 2000
        assert sim.robot.collision is not None and sim.robot.collision.stops == 1
        (path,) = _dumps(sim.robot)
    finally:
        sim.close()
    return [(path, "STOPPED")]


def collaborative(tmp_path: Path) -> list[Dumped]:
    """configs/collab/slave.yaml: two masters, control handed from the mentor to the trainee
    inside the window, then three of the trainee's numbers lost: a loss stop."""
    c = Collab(_config(tmp_path, "collab/slave.yaml"))
    try:
        c.running()
        c.step_ms(1200 - c.k)
        assert ok(c.command(c.desks["mentor"], "Handover", handover("trainee")))
        assert c.robot.collab is not None and c.robot.collab.owner == "trainee"
        c.step_ms(1400)
        c.drops["trainee"] |= {c.seq["trainee"] + i for i in (1, 2, 3)}
        c.step_ms(20)
        assert c.robot.state is RobotState.STOPPED
        (path,) = _dumps(c.robot)
    finally:
        c.close()
    return [(path, "STOPPED")]


SHIPPED: list[Callable[[Path], list[Dumped]]] = [
    slave,
    servo,
    master,
    wall,
    keyframes,
    ur5_collision,
    collaborative,
]


def _rows(path: Path) -> tuple[np.ndarray, list[str]]:
    return np.load(path / "ticks.npy"), read_manifest(path)["tick_columns"]


@pytest.mark.parametrize("run", SHIPPED, ids=[f.__name__ for f in SHIPPED])
def test_every_shipped_config_replays_exactly(
    run: Callable[[Path], list[Dumped]], tmp_path: Path
) -> None:
    for path, stop in run(tmp_path):
        m = read_manifest(path)
        first = m["window"]["first_tick"]
        # the window starts at a checkpoint taken in mid-run, not at the robot's build
        assert first >= 1000 and first % 1000 == 0 and m["replay"]["from_tick"] == first
        result = replay_dump(path)
        assert result.exact, result.divergence and result.divergence.describe()
        assert result.problems == [] and result.built_differently == []
        assert result.first_tick == first and result.ticks == m["window"]["ticks"]
        tick, _, to, _, _ = result.transitions[-1]
        assert (tick, to) == (m["trigger"]["tick"], stop)


# ------------------------------------------------------------------ what the replay tells apart
@pytest.fixture(scope="module")
def slave_dump(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A slave whose master holds still for the window's first 0.5 s, then moves; a loss
    stop at tick 2500."""
    r = SlaveRig(_config(tmp_path_factory.mktemp("slave"), "slave.yaml"))
    try:
        r.running()
        r.step(1500 - r.sim.k)
        for _ in range(1000):  # from tick 1500 on: 10 mm/s
            r.target[0] += 0.01
            r.step(1)
        r.seq += 3
        r.step(20)
        assert r.robot.state is RobotState.STOPPED
        (path,) = _dumps(r.robot)
    finally:
        r.close()
    return path


def _edited(path: Path, out: Path, edit: Callable[[dict[str, Any]], None]) -> Path:
    """The dump's own config.yaml, edited, written to ``out``."""
    raw = yaml.safe_load((path / "config.yaml").read_text())
    edit(raw)
    out.write_text(yaml.safe_dump(raw))
    return out


def _scale(raw: dict[str, Any]) -> None:
    raw["controller"]["params"]["scale"] *= 1.01


def _tolerant(raw: dict[str, Any]) -> None:
    raw["safety"]["loss"]["max_consecutive"] = 3  # three in a row no longer stop it


@pytest.mark.parametrize(
    ("edit", "tick", "field", "built"),
    [
        # the master moves from tick 1500: the scale matters from the first sample that moved
        (_scale, 1500, "sp.", "robot.controller.controllers[0].scale"),
        # the loss monitor's bound matters only where the loss is judged: the stop's tick
        (_tolerant, 2500, "state", "robot.streams.monitors['master'].max_consecutive"),
    ],
    ids=["gain", "loss-bound"],
)
def test_a_changed_parameter_diverges_at_the_first_tick_it_matters(
    slave_dump: Path,
    tmp_path: Path,
    edit: Callable[[dict[str, Any]], None],
    tick: int,
    field: str,
    built: str,
) -> None:
    what = _edited(slave_dump, tmp_path / "what.yaml", edit)
    result = replay_dump(slave_dump, parse_config(what.read_text(), source=str(what)))
    d = result.divergence
    assert d is not None and (d.tick, result.ticks) == (tick, tick - 1000 + 1)
    assert d.field.startswith(field) and d.recorded != d.replayed
    assert built in result.built_differently and result.problems == []
    # until there, every tick was equal: the replay of the dump's own config is exact
    assert replay_dump(slave_dump).exact


def test_a_recorded_value_one_ulp_off_is_caught_at_its_tick(
    slave_dump: Path, tmp_path: Path
) -> None:
    """Bit for bit: a setpoint of the record moved by the smallest step a float64 takes is
    the divergence, at its tick and field, with both values."""
    rows, cols = _rows(slave_dump)
    r, c = 1800 - 1000, cols.index("sp.pitch")
    true = float(rows[r, c])
    rows[r, c] = np.nextafter(rows[r, c], np.inf)
    np.save(slave_dump / "ticks.npy", rows)
    try:
        d = replay_dump(slave_dump).divergence
    finally:
        rows[r, c] = true
        np.save(slave_dump / "ticks.npy", rows)
    assert d is not None and (d.tick, d.field) == (1800, "sp.pitch")
    assert (d.recorded, d.replayed) == (np.nextafter(true, np.inf), true)


@pytest.mark.parametrize(
    ("damage", "words"),
    [
        (lambda p: p.unlink(), f"{REPLAY} is missing"),
        (lambda p: p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2]), "is damaged"),
        (lambda p: p.write_bytes(b"\x80\x05not a pickle at all"), "is damaged"),
        (lambda p: p.write_bytes(json.dumps({"checkpoint": 1}).encode()), "is damaged"),
    ],
    ids=["missing", "cut", "garbage", "not-ours"],
)
def test_a_missing_or_damaged_replay_file_is_refused_with_the_reason(
    slave_dump: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    damage: Callable[[Path], None],
    words: str,
) -> None:
    copy = tmp_path / slave_dump.name
    copy.mkdir()
    for f in slave_dump.iterdir():
        (copy / f.name).write_bytes(f.read_bytes())
    damage(copy / REPLAY)
    with pytest.raises(ValueError, match=f"{copy}: cannot be replayed: .*{words}"):
        replay_dump(copy)
    assert occ_record(["replay", "--deterministic", str(copy)]) == 1
    out, err = capsys.readouterr()
    assert out == "" and words in err and "Traceback" not in err


def test_the_cli_exits_0_when_exact_and_4_when_diverged(
    slave_dump: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert occ_record(["replay", "--deterministic", str(slave_dump)]) == 0
    out = capsys.readouterr().out
    assert "ticks 1000..2500 replayed (1501)" in out
    assert "tick 2500: RUNNING -> STOPPED (stop): packet loss on master" in out
    assert out.rstrip().endswith(
        "EXACT: every setpoint, effort, state and reading equal bit for bit"
    )
    assert occ_record(["replay", "--deterministic", str(slave_dump), "--json"]) == 0
    x = json.loads(capsys.readouterr().out)
    assert x["exact"] and x["divergence"] is None and x["ticks"] == 1501
    assert x["not_restored"] == [] and x["built_differently"] == []
    assert x["transitions"][-1]["tick"] == 2500 and x["transitions"][-1]["to"] == "STOPPED"
    what = str(_edited(slave_dump, tmp_path / "what.yaml", _scale))
    assert occ_record(["replay", "--deterministic", str(slave_dump), "--config", what]) == 4
    out = capsys.readouterr().out
    assert "DIVERGED at tick 1500 (t=1.500000 s): sp." in out
    assert "built differently here (the configuration given)" in out
    args = ["replay", "--deterministic", str(slave_dump), "--config", what, "--json"]
    assert occ_record(args) == 4
    x = json.loads(capsys.readouterr().out)
    assert not x["exact"] and x["divergence"]["tick"] == 1500
    assert x["divergence"]["field"].startswith("sp.") and x["ticks"] == 501


# ------------------------------------------------------------------ the checkpoint's edges
class _Part:
    """A part of a robot in miniature (this project's module): its attributes are slots."""

    def __init__(self) -> None:
        self.gain = 1.0
        self.history: list[Any] = [0.0]
        self.scratch = [Fraction(1, 2), Fraction(1, 4)]  # a foreign library's scratch only


def test_a_slot_no_replay_can_read_is_named_and_scratch_is_no_slot() -> None:
    part = _Part()
    cp = Checkpointer(part)
    assert [p for _, _, p in cp.slots] == ["robot.gain", "robot.history"]
    base = cp.take()
    part.gain = 2.0
    part.history.append(Fraction(1, 3))  # a foreign object made at run time: no replay reads it
    blob = cp.dumps(cp.take(), base)  # written whole: the one slot marked, not the rest lost
    again = _Part()
    problems, built = restore(Checkpointer(again), blob)
    assert again.gain == 2.0 and built == []
    (why,) = problems
    assert why.startswith("robot.history: cannot be written: UnpicklingError")
    assert "may not load fractions.Fraction" in why


# ------------------------------------------------------------------ the replay's pieces alone
def test_a_result_reports_and_describes_what_the_replay_found() -> None:
    from occ.core.replay import Divergence, ReplayResult

    r = ReplayResult(10, ticks=3)
    r.transitions = [(11, "RUNNING", "STOPPED", "stop", "why")]
    r.problems = ["robot.a: gone"]
    r.built_differently = [f"robot.s{i}" for i in range(9)]
    assert r.exact
    assert r.report() == {
        "exact": True,
        "first_tick": 10,
        "ticks": 3,
        "divergence": None,
        "transitions": [
            {"tick": 11, "from": "RUNNING", "to": "STOPPED", "event": "stop", "reason": "why"}
        ],
        "not_restored": ["robot.a: gone"],
        "built_differently": r.built_differently,
    }
    eight = ", ".join(f"robot.s{i}" for i in range(8))
    assert r.describe("D").splitlines() == [
        "D: ticks 10..12 replayed (3)",
        "  tick 11: RUNNING -> STOPPED (stop): why",
        f"  built differently here (the configuration given): {eight} ...",
        "  NOT RESTORED: robot.a: gone",
        "EXACT: every setpoint, effort, state and reading equal bit for bit",
    ]
    r.built_differently = r.built_differently[:8]
    r.divergence = Divergence(12, 0.0125, "sp.j", 1.0, 2.0)
    assert not r.exact
    assert r.report()["divergence"] == {
        "tick": 12,
        "t": 0.0125,
        "field": "sp.j",
        "recorded": 1.0,
        "replayed": 2.0,
    }
    assert r.describe("D").splitlines()[2:] == [
        f"  built differently here (the configuration given): {eight}",
        "  NOT RESTORED: robot.a: gone",
        "DIVERGED at tick 12 (t=0.012500 s): sp.j: recorded 1.0, replayed 2.0",
    ]


def test_a_hooks_error_is_raised_again_with_its_recorded_words() -> None:
    from occ.core.replay import ReplayClock, _error, _first_difference, _first_finite
    from occ.errors import DriverError

    err = _error(("occ.errors", "DriverError", "joint 1: lost", "DriverError('joint 1: lost')"))
    assert type(err) is DriverError and str(err) == "joint 1: lost"
    for cls in (
        ("occ.errors", "Warning", "t", "r"),
        ("can", "BusError", "t", "r"),
        ("xocc.errors", "DriverError", "t", "r"),
    ):
        other = _error(cls)
        assert type(other) is not DriverError and (str(other), repr(other)) == ("t", "r")
    clock = ReplayClock(2.0, 100.0)
    assert clock.wall_time() == 102.0
    clock.to_wall = 50.0
    clock.set(3.0)
    assert clock.wall_time() == 53.0
    assert _first_finite(np.array([np.nan, np.inf, 5.0, 6.0])) == 5.0
    assert _first_finite(np.array([np.nan])) == 1_700_000_000.0
    cols = ["t", "state", "sp.a", "x"]
    a = np.array([0.0, 1.0, 2.0, 3.0])
    assert _first_difference(a, a.copy(), [1, 2], cols) is None
    b = a.copy()
    b[3] = 9.0  # not compared
    assert _first_difference(a, b, [1, 2], cols) is None
    b[2] = -0.0 if a[2] == 0.0 else np.nextafter(a[2], 0.0)
    assert _first_difference(a, b, [1, 2], cols) == ("sp.a", 2.0, float(b[2]))
    zero, minus = np.array([0.0, 0.0]), np.array([0.0, -0.0])  # equal, not the same bits
    assert _first_difference(zero, minus, [0, 1], ["state", "sp.b"]) == ("sp.b", 0.0, -0.0)


@pytest.mark.parametrize(
    ("outer", "words"),
    [
        ([1, 2], "not a replay file"),
        ({"checkpoint": "text"}, "not a replay file"),
        ({"checkpoint": b"", "inputs": (b"",)}, "not a replay file (inputs)"),
        ({"checkpoint": b"", "inputs": [b"", "x"]}, "not a replay file (inputs)"),
        ({"checkpoint": b"", "inputs": [], "built_at": 1}, "not a replay file (built_at)"),
    ],
)
def test_the_replay_files_outer_layer_is_plain_data(outer: Any, words: str) -> None:
    import pickle

    from occ.core.replay import _loads

    with pytest.raises(ValueError, match=f"^{re.escape(words)}$"):
        _loads(pickle.dumps(outer))
    ok = {"checkpoint": b"c", "inputs": [b"i"], "built_at": 0.5}
    assert _loads(pickle.dumps(ok)) == ok
    assert _loads(pickle.dumps({"checkpoint": b"c", "inputs": []}))["inputs"] == []
    # no class at all: not even a harmless one
    with pytest.raises(pickle.UnpicklingError, match="^replay.pkl may not load builtins.complex$"):
        _loads(pickle.dumps({"checkpoint": b"", "inputs": [], "x": 1j}))


def test_a_dump_without_a_replay_says_why(tmp_path: Path) -> None:
    from occ.core.replay import load_dump

    (tmp_path / "manifest.json").write_text(json.dumps({"format": "occ-black-box"}))
    with pytest.raises(ValueError, match="cannot be replayed: a dump of a version without replay$"):
        load_dump(tmp_path)
    (tmp_path / "manifest.json").write_text(
        json.dumps({"format": "occ-black-box", "replay": {"possible": False, "why": "no room"}})
    )
    with pytest.raises(
        ValueError, match=f"^{re.escape(str(tmp_path))}: cannot be replayed: no room$"
    ):
        load_dump(tmp_path)
    (tmp_path / "manifest.json").write_text(
        json.dumps({"format": "occ-black-box", "replay": {"possible": True}})
    )
    with pytest.raises(ValueError, match="cannot be replayed: config.yaml is missing$"):
        load_dump(tmp_path)


def test_a_dumps_rows_holding_pickles_are_refused(slave_dump: Path, tmp_path: Path) -> None:
    """ticks.npy is read without pickles: an object array (code on load) is damage."""
    copy = tmp_path / slave_dump.name
    copy.mkdir()
    for f in slave_dump.iterdir():
        (copy / f.name).write_bytes(f.read_bytes())
    np.save(copy / "ticks.npy", np.array([[object()]], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match="ticks.npy is damaged .*allow_pickle=False"):
        replay_dump(copy)


def test_each_outputs_sequence_is_a_slot_and_the_schedule_built_from_the_config_is_not() -> None:
    """The output scheduler's tables derived from the config are ``checkpoint_fixed`` (no
    checkpoint copies them again each second); the outputs they point to are still parts, so
    a replay numbers its messages on from where the recorded robot was."""
    from occ.core.wiring import checkpointer

    sim = SimRobot(CONFIGS / "slave.yaml")
    try:
        paths = [p for _, _, p in checkpointer(sim.robot).slots]
    finally:
        sim.close()
    assert "robot.outputs.outputs[0].seq" in paths
    assert not any("_schedule" in p or "_due" in p for p in paths if p.startswith("robot.outputs"))
    assert not any(p.startswith("robot.operators.port.stats._entries") for p in paths)


def test_a_drive_the_recorded_build_never_read_answers_unread_not_empty_lists() -> None:
    """A drive the recorded robot had not read when it was built holds the driver's empty
    reading ``((), (), ())`` (truthy: a tuple of three): the replay's configure-time read
    answers NaN for each joint, as for a drive with no recorded reading at all, never lists of
    the wrong length. A read or write the recorded robot saw fail fails again, once."""
    from occ.core.replay import _Drives
    from occ.errors import DriverError
    from occ.recording.blackbox import tick_columns

    sim = SimRobot(CONFIGS / "slave.yaml")
    try:
        robot = sim.robot
        (drive, idx), *_ = robot.hardware.pairs
        names = [robot.joints[i].name for i in idx]
        paths = {id(drive): "robot.drive"}
        columns = tick_columns(names)
        for built in ({"robot.drive.raw": ((), (), ())}, {}):
            _Drives(robot, columns, built, paths)
            got = drive._read(0.0)
            assert [len(x) for x in got] == [len(names)] * 3
            assert all(math.isnan(v) for x in got for v in x)
        recorded = ([0.1] * len(names), [0.0] * len(names), [0.0] * len(names))
        drives = _Drives(robot, columns, {"robot.drive.raw": recorded}, paths)
        assert drive._read(0.0) == recorded  # a real recorded reading is answered as it was
        # a read the recorded robot saw fail fails again, once, with its error; a recorded
        # write failure is the write's, never the read's
        drives.errors[(drive.name, "write")] = DriverError("bus off")
        assert drive._read(0.0) == recorded
        drives.errors[(drive.name, "read")] = DriverError("encoder lost")
        with pytest.raises(DriverError, match="encoder lost"):
            drive._read(0.0)
        assert drive._read(0.0) == recorded and (drive.name, "read") not in drives.errors
        with pytest.raises(DriverError, match="bus off"):
            drive._write([0.0] * len(names), 0.0)
    finally:
        sim.close()
