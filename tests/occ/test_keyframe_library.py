"""The trajectory library through the daemon (issue 28, item 5): KeyframeSave, KeyframeLibrary,
KeyframeLoad Set=..., KeyframeDelete on configs/keyframe.yaml.

In simulated time (occ_testkit.testing.SimRobot, every setpoint the drivers were told), and over
real processes: ``occd`` saves a plan, is killed, starts again, loads it by name and runs it to the
same keyframes. The database itself is tested in tests/occ/test_trajlib.py.
"""

from __future__ import annotations

import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from occ.controllers.keyframe import KeyframeController
from occ.errors import ConfigError
from occ.kinematics.frame import robots_dir
from occ.core.loader import load_config, parse_config
from occ.core.safety import RobotState
from occ_testkit.testing import SimPeer, SimRobot

from .test_keyframe import Session, xml

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"
sys.path.insert(0, str(ROOT / "tools"))

from loopback import free_port, stop_processes, wait_port, write_yaml  # noqa: E402
from slicer_standin import SlicerStandIn  # noqa: E402

HOME = [0.0, 0.35, 0.05]
PERIOD = 1e-3
#: the shipped demo set (configs/keyframes/demo.yaml), loaded at start-up
DEMO = [(2.0, [0.30, 0.35, 0.05]), (4.0, [0.30, 0.50, 0.08]), (6.5, [-0.20, 0.45, 0.08])]
DEMO_END = 8.5


def keyframe_config(library: Path | None, **robot: Any) -> dict[str, Any]:
    """configs/keyframe.yaml as data, its files absolute, the library at ``library``."""
    data = yaml.safe_load((CONFIGS / "keyframe.yaml").read_text())
    params = data["controller"]["params"]
    params["file"] = str(CONFIGS / "keyframes" / "demo.yaml")
    params["keyframe_dir"] = str(CONFIGS / "keyframes")
    if library is not None:
        params["library"] = str(library)
    data["robot"].update(robot)
    return data


class Daemon(Session):
    """A keyframe robot in simulated time and its Slicer console (an operator): test_keyframe's
    session on a robot built from this module's config."""

    def __init__(self, library: Path | None, **robot: Any) -> None:
        cfg = parse_config(
            yaml.safe_dump(keyframe_config(library, **robot)), source="kf.yaml", base_dir=CONFIGS
        )
        self.sim = SimRobot(cfg)
        self.robot = self.sim.robot
        (kf,) = self.robot.controller.controllers
        assert isinstance(kf, KeyframeController)
        self.kf = kf
        self.slicer: SimPeer = self.sim.peer("slicer")
        self.setpoints: list[list[float]] = []

    def plan_and_ack(self, **args: Any) -> str:
        text = self.ok("KeyframePlan", **args)
        plan_id = int(text.split(":")[0].split()[1])
        self.step(150)  # the preview goes out with the next output tick (10 Hz)
        self.setpoints.clear()
        self.ok("KeyframeAck", Plan=plan_id)  # this tick is t = 0 of the run
        return text


@pytest.fixture
def library(tmp_path: Path) -> Path:
    return tmp_path / "plans.sqlite"


@pytest.fixture
def daemon(library: Path) -> Iterator[Daemon]:
    d = Daemon(library)
    try:
        yield d
    finally:
        d.close()


def at_keyframes(setpoints: list[list[float]], frames: list[tuple[float, list[float]]]) -> Any:
    q = np.array(setpoints)
    return np.array([q[round(t / PERIOD)] for t, _ in frames])


# ============================================================================ simulated time
@pytest.mark.req("SR-LIB-1")
def test_a_saved_plan_survives_a_restart_and_runs_to_the_same_keyframes(library: Path) -> None:
    first = Daemon(library)
    try:
        first.ok("Enable")
        first.ok("Run")
        first.plan_and_ack(Interpolation="spline", Mode="continuous", Steepness=5)
        first.step(round(DEMO_END / PERIOD) + 100)
        ran = at_keyframes(first.setpoints, DEMO)
        assert np.max(np.abs(ran - [p for _, p in DEMO])) <= 1e-6
        reply = first.ok("KeyframeSave", Set="demo-sweep")
        assert reply.startswith("saved 'demo-sweep': 4 keyframes (joint, spline, continuous)")
        assert "robot 'keyframe'" in reply
    finally:
        first.close()
    second = Daemon(library)  # a new daemon on the same file
    try:
        second.ok("KeyframeClear")
        listing = second.ok("KeyframeLibrary")
        assert "1 saved set in" in listing
        assert "demo-sweep: robot 'keyframe', 4 keyframes (joint, spline, continuous), 8.500 s" in (
            listing
        )
        second.ok("Enable")
        second.ok("Run")
        held = list(second.sim.robot.data.commanded())  # where Enable found the arm
        text = second.ok("KeyframeLoad", Set="demo-sweep")
        assert "4 keyframes (joint) from the library: 'demo-sweep'" in text
        assert "does not run by itself" in text
        assert "from library demo-sweep" in second.ok("KeyframeList")
        # RUNNING, loaded, and it holds: a loaded set never runs by itself
        second.setpoints.clear()
        second.step(2000)
        assert all(sp == held for sp in second.setpoints)
        assert "no plan is previewed" in second.refused("KeyframeAck", Plan=1)
        # planned with the settings it was saved with (no arguments given)
        plan = second.plan_and_ack()
        assert "(joint, spline, continuous), 8.500 s" in plan
        second.step(round(DEMO_END / PERIOD) + 100)
        again = at_keyframes(second.setpoints, DEMO)
        # the same keyframes, met on their ticks; the same plan up to where the simulated
        # drive settled at Enable (the start pose, 1e-5 rad from home)
        assert np.max(np.abs(again - [p for _, p in DEMO])) <= 1e-6
        assert np.max(np.abs(again - ran)) <= 1e-6
        n = len(second.setpoints)
        start_gap = np.max(np.abs(np.subtract(held, first.setpoints[0])))
        assert start_gap < 1e-4
        gap = np.max(np.abs(np.array(second.setpoints) - np.array(first.setpoints[:n])))
        assert gap <= start_gap + 1e-12, (gap, start_gap)
        assert second.kf.stats()["library_loaded"] == 1
        assert second.sim.robot.state is RobotState.RUNNING
    finally:
        second.close()


@pytest.mark.req("SR-LIB-1")
def test_a_plan_from_another_robot_or_configuration_never_loads(library: Path) -> None:
    d = Daemon(library)
    try:
        d.ok("Enable")
        d.ok("Run")
        d.plan_and_ack()
        d.ok("KeyframeSave", Set="demo")
    finally:
        d.close()
    other = Daemon(library, name="other-arm")  # same arm, another robot's name
    try:
        before = other.kf.kset
        error = other.refused("KeyframeLoad", Set="demo")
        assert "saved for robot 'keyframe', not for this robot 'other-arm'" in error
        assert other.kf.kset is before  # nothing changed
        assert "[another robot: not loadable here]" in other.ok("KeyframeLibrary")
        assert "no set named 'demo' for robot 'other-arm'" in other.refused(
            "KeyframeDelete", Set="demo"
        )
        assert other.kf.stats()["library_refused"] == 2
    finally:
        other.close()
    # the same name, another kinematic chain: the tool tip moved to another link of the URDF
    frame = {"urdf": str(robots_dir() / "occ_slave.urdf"), "tip_link": "tool_link"}
    moved = Daemon(library, frame=frame)
    try:
        error = moved.refused("KeyframeLoad", Set="demo")
        assert "another kinematic configuration" in error and "it is refused" in error
        assert "[another kinematic configuration: refused]" in moved.ok("KeyframeLibrary")
    finally:
        moved.close()
    # the same robot from the same URDF written out in full loads it
    frame = {"urdf": str(robots_dir() / "occ_slave.urdf"), "tip_link": "tool_tip"}
    same = Daemon(library, frame=frame)
    try:
        assert "from the library: 'demo'" in same.ok("KeyframeLoad", Set="demo")
    finally:
        same.close()


def test_only_a_planned_and_acknowledged_set_is_saved(daemon: Daemon) -> None:
    d = daemon
    assert "only a planned and acknowledged set" in d.refused("KeyframeSave", Set="a")
    d.ok("Enable")
    d.ok("Run")
    d.ok("KeyframePlan")
    assert "only a planned and acknowledged set" in d.refused("KeyframeSave", Set="a")
    d.step(150)
    d.ok("KeyframeAck", Plan=1)
    assert "acknowledged: plan 1" in d.ok("KeyframeList")
    # saved while it runs: the set was acknowledged
    assert d.ok("KeyframeSave", Set="a").startswith("saved 'a'")
    assert "needs Set" in d.refused("KeyframeSave")
    assert "bad name 'a b'" in d.refused("KeyframeSave", Set="a b")
    assert "bad name" in d.refused("KeyframeSave", Set="x'; DROP TABLE keyframes; --")
    assert "Replace must be 1 or 0" in d.refused("KeyframeSave", Set="a", Replace="maybe")
    error = d.refused("KeyframeSave", Set="a")
    assert "'a' exists for robot 'keyframe'" in error and "Replace=1" in error
    assert d.ok("KeyframeSave", Set="a", Replace=1).startswith("replaced 'a'")
    d.step(round(DEMO_END / PERIOD) + 50)
    assert d.ok("KeyframeSave", Set="b").startswith("saved 'b'")  # after the run, too
    # a changed set is not the acknowledged one
    d.ok("KeyframeAdd", T=9.5, Pose="0.1 0.35 0.05")
    assert "changed since plan 1 was acknowledged" in d.refused("KeyframeSave", Set="c")
    assert "acknowledged" not in d.ok("KeyframeList")
    listing = d.ok("KeyframeLibrary")
    assert "2 saved sets" in listing and "  a: " in listing and "  b: " in listing
    assert d.kf.stats()["library_saved"] == 3


def test_delete_list_and_file_loading_beside_the_library(daemon: Daemon) -> None:
    d = daemon
    d.ok("Enable")
    d.ok("Run")
    d.plan_and_ack()
    for name in ("one", "two"):
        d.ok("KeyframeSave", Set=name)
    assert "deleted 'one'" in d.ok("KeyframeDelete", Set="one")
    assert "no set named 'one'" in d.refused("KeyframeDelete", Set="one")
    assert "no set named 'one'" in d.refused("KeyframeLoad", Set="one")
    listing = d.ok("KeyframeLibrary")
    assert "1 saved set in" in listing and "  two: " in listing and "one" not in listing
    # KeyframeLoad File=... works as before
    assert "from entry_target.yaml" in d.ok("KeyframeLoad", File="entry_target.yaml")
    assert "not both" in d.refused("KeyframeLoad", File="entry_target.yaml", Set="two")
    assert "needs File" in d.refused("KeyframeLoad")
    assert "from the library: 'two'" in d.ok("KeyframeLoad", Set="two")
    assert "library: " in d.ok("KeyframeList")


def test_without_a_library_the_commands_say_so() -> None:
    d = Daemon(None)
    try:
        for name, args in (
            ("KeyframeSave", {"Set": "a"}),
            ("KeyframeLibrary", {}),
            ("KeyframeDelete", {"Set": "a"}),
            ("KeyframeLoad", {"Set": "a"}),
        ):
            assert "no trajectory library in the configuration" in d.refused(name, **args)
        assert "from demo.yaml" in d.ok("KeyframeLoad", File="demo.yaml")
    finally:
        d.close()


def test_the_database_work_is_off_the_loop_thread(daemon: Daemon, library: Path) -> None:
    """Another process holds the library's write lock: the save waits on the planner thread
    while the loop ticks on, and is answered when the lock is released."""
    d = daemon
    d.ok("Enable")
    d.ok("Run")
    d.plan_and_ack()
    other = sqlite3.connect(library, isolation_level=None)
    other.execute("BEGIN IMMEDIATE")
    try:
        cid = d.slicer.send_command("KeyframeSave", xml("KeyframeSave", Set="late"))
        d.step(50)  # the loop does not wait for the file (a busy timeout of 2 s)
        assert d.slicer.reply_to(cid) is None
        assert d.kf.wait_idle(0) is False
        busy = d.slicer.send_command("KeyframeLibrary", xml("KeyframeLibrary"))
        d.step(1)
        assert "busy" in d.slicer.reply_to(busy).metadata["Error"]  # type: ignore[union-attr]
    finally:
        other.execute("COMMIT")
        other.close()
    assert d.kf.wait_idle(30.0)
    assert d.slicer.reply_to(cid).metadata["Status"] == "SUCCESS"  # type: ignore[union-attr]


def test_config_errors_name_the_library(tmp_path: Path) -> None:
    data = keyframe_config(tmp_path / "missing" / "plans.sqlite")
    with pytest.raises(ConfigError) as info:
        parse_config(yaml.safe_dump(data), source="kf.yaml", base_dir=CONFIGS)
    (error,) = info.value.errors
    assert "controller.params.library" in error and "does not exist" in error
    junk = tmp_path / "notes.txt"
    junk.write_text("not a database\n" * 100)
    cfg = parse_config(yaml.safe_dump(keyframe_config(junk)), source="kf.yaml", base_dir=CONFIGS)
    with pytest.raises(ConfigError, match="library: .*not a trajectory library"):
        SimRobot(cfg)
    # relative to the config file's folder
    (tmp_path / "kf.yaml").write_text(yaml.safe_dump(keyframe_config(Path("plans.sqlite"))))
    cfg = load_config(tmp_path / "kf.yaml")
    assert cfg.controllers[0].params["library"] == str(tmp_path / "plans.sqlite")


# ============================================================================ real processes
@pytest.mark.realtime
@pytest.mark.req("SR-LIB-1")
def test_occd_saves_is_killed_starts_again_and_runs_the_plan_by_name(tmp_path: Path) -> None:
    """Two ``occd`` processes one after the other on the same library: the first plans,
    runs and saves a set and is killed (SIGKILL, no clean shutdown); the second loads it by
    name, plans, is acknowledged and ends on the same last keyframe, exactly."""
    port = free_port()
    data = keyframe_config(tmp_path / "plans.sqlite")
    data["interfaces"][0]["port"] = port
    data["interfaces"][0]["outputs"].append(
        {"type": "NDARRAY", "device": "Setpoint", "source": "setpoint", "rate_hz": 20}
    )
    cfg = write_yaml(tmp_path / "kf.yaml", data)
    frames = [(1.0, [0.2, 0.4, 0.06]), (2.0, [-0.1, 0.45, 0.07])]

    def start() -> subprocess.Popen[bytes]:
        proc = subprocess.Popen(
            [sys.executable, "-m", "occ.cli", str(cfg), "--log-level", "ERROR"],
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        if not wait_port(port, proc=proc):
            stop_processes([proc])
            err = proc.stderr.read().decode() if proc.stderr else ""
            raise AssertionError(f"occd did not start: {err}")
        return proc

    def command(client: SlicerStandIn, name: str, **args: Any) -> tuple[bool, str]:
        reply = client.wait_reply(client.send_command(name, xml(name, **args)), 20.0)
        assert reply is not None, f"no reply to {name}"
        ok = reply.metadata["Status"] == "SUCCESS"
        return ok, str(reply.metadata["Message"])

    def ok(client: SlicerStandIn, name: str, **args: Any) -> str:
        good, text = command(client, name, **args)
        assert good, f"{name}: {text}"
        return text

    def until(client: SlicerStandIn, name: str, text: str, **args: Any) -> str:
        """Ask again (bounded) until the answer succeeds and says ``text``."""
        for _ in range(300):
            good, reply = command(client, name, **args)
            if good and text in reply:
                return reply
            time.sleep(0.05)
        raise AssertionError(f"{name}: {reply}")

    def run(client: SlicerStandIn) -> None:
        """Plan, wait for the preview, acknowledge, wait for the end (Run again if this
        shared machine's stall stopped the robot; the test is about the library)."""
        plan_id = int(ok(client, "KeyframePlan").split(":")[0].split()[1])
        until(client, "KeyframeAck", "running", Plan=plan_id)  # once previewed
        until(client, "KeyframeList", f"plan {plan_id} completed")

    def setpoint(client: SlicerStandIn) -> np.ndarray:
        client.replies.clear()
        for _ in range(200):
            arrays = [m for m in list(client.replies) if m.device_name == "Setpoint"]
            if arrays:
                return np.asarray(arrays[-1].array, dtype=float).reshape(-1)  # type: ignore[attr-defined]
            time.sleep(0.02)
        raise AssertionError("no Setpoint NDARRAY")

    proc = start()
    try:
        with SlicerStandIn("127.0.0.1", port) as slicer:
            assert slicer.connected.wait(10.0)
            ok(slicer, "Enable")
            ok(slicer, "Run")
            ok(slicer, "KeyframeClear")
            for t, pose in frames:
                ok(slicer, "KeyframeAdd", T=t, Pose=" ".join(map(str, pose)))
            run(slicer)
            assert np.max(np.abs(setpoint(slicer) - frames[-1][1])) <= 1e-9
            assert ok(slicer, "KeyframeSave", Set="entry-1").startswith("saved 'entry-1'")
        proc.kill()  # no clean shutdown
        proc.wait(10.0)
    finally:
        stop_processes([proc])
    proc = start()
    try:
        with SlicerStandIn("127.0.0.1", port) as slicer:
            assert slicer.connected.wait(10.0)
            assert "entry-1: robot 'keyframe', 2 keyframes" in ok(slicer, "KeyframeLibrary")
            ok(slicer, "Enable")
            ok(slicer, "Run")
            held = setpoint(slicer)
            ok(slicer, "KeyframeLoad", Set="entry-1")
            listing = ok(slicer, "KeyframeList")
            assert "2 joint from library entry-1" in listing
            assert "pose=[0.2 0.4 0.06]" in listing and "pose=[-0.1 0.45 0.07]" in listing
            assert np.array_equal(setpoint(slicer), held)  # loaded: it has not moved
            run(slicer)
            assert np.max(np.abs(setpoint(slicer) - frames[-1][1])) <= 1e-9
    finally:
        stop_processes([proc])
    assert proc.returncode == 0, proc.stderr.read().decode() if proc.stderr else ""
