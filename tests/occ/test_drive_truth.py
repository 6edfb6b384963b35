"""A drive that lies, or stays broken, never moves the robot (issue 36), on the shipped slave
with its joints split over two drives, ``arm`` (yaw, pitch) and ``tool`` (insertion), as in the
fault matrix (occ_testkit/faultmatrix.py), in simulated time with an operator and a viewer.

- Reset proves the repair: refused, the state unchanged, while a drive is still broken.
- Enable is proven by a checked read and a write before ENABLED is said; never SUCCESS with a
  broken drive, whatever the order or timing of the commands.
- A switch-off that fails is never forgotten: named, unsafe in GetStats, the robot FAULT.
- The supervisor alerts first and stops drives in parallel: one whose stop hangs on the lock
  its hung read holds delays neither the others nor the alert.
- Every fault in every state reaches every connected operator, once.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Sequence
from typing import Any

import pytest

import igtl
from occ.clock import SimClock
from occ.core.hardware import HardwareSet
from occ.core.safety import RobotState
from occ.drivers import register_driver
from occ.drivers.base import DriverState
from occ.drivers.sim import SimDriver
from occ.joint import Joint, JointLimits
from occ_testkit.faultmatrix import slave_config
from occ_testkit.testing import SimPeer, SimRobot


class PluginDrive(SimDriver):
    """A plugin drive (a sim underneath) whose hooks a test breaks by name: ``breaks`` holds
    the hooks that raise (``deactivate``, ``write``, ``read``), ``on_activate`` runs inside the
    power-up (a slow power stage), and its reset always succeeds: a plugin that does not check
    its own hardware, so only the robot's own checks stand between it and motion."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.breaks: set[str] = set()
        self.on_activate: Callable[[], None] | None = None
        self.powered = False

    def _activate(self) -> None:
        if self.on_activate is not None:
            self.on_activate()
        super()._activate()
        self.powered = True

    def _deactivate(self) -> None:
        if "deactivate" in self.breaks:
            raise RuntimeError("the power stage does not answer the switch-off")
        super()._deactivate()
        self.powered = False

    def _reset(self) -> None:
        self._faults.clear()  # "reset OK", whatever is still wrong
        super()._reset()

    def _write(self, values: Sequence[float], now: float) -> None:
        if "write" in self.breaks:
            raise RuntimeError("the command does not reach the drive")
        super()._write(values, now)

    def _read(self, now: float) -> tuple[Sequence[float], Sequence[float], Sequence[float]]:
        pos, vel, eff = super()._read(now)
        if "read" in self.breaks:
            pos = list(pos)
            pos[-1] = 5.0  # far outside every joint's range
        return pos, vel, eff


register_driver("test-plugin-drive", PluginDrive)


class Bench:
    """The split slave (``arm`` and ``tool``), an operator and a viewer, in simulated time."""

    def __init__(self, tool_faults: tuple[str, ...] = (), plugin: tuple[str, ...] = ()) -> None:
        cfg = slave_config("sim", tool_faults)
        drivers = tuple(
            d.model_copy(update={"plugin": "test-plugin-drive"}) if d.name in plugin else d
            for d in cfg.robot.drivers
        )
        cfg = cfg.model_copy(update={"robot": cfg.robot.model_copy(update={"drivers": drivers})})
        self.sim = SimRobot(cfg, clock=SimClock())
        self.robot = self.sim.robot
        self.op: SimPeer = self.sim.peer("operator")
        self.viewer: SimPeer = self.sim.peer("slicer")
        self.sim.step(3)

    def drive(self, name: str) -> Any:
        return next(d for d in self.robot.hardware.drivers if d.name == name)

    def send(self, *names: str) -> list[int]:
        """Commands sent together: the next tick handles them all."""
        return [self.op.send_command(n) for n in names]

    def replies(self, ids: list[int]) -> list[tuple[str, str]]:
        out = []
        for cid in ids:
            reply = self.op.reply_to(cid)
            assert reply is not None
            out.append((reply.metadata.get("Status", ""), reply.metadata.get("Message", "")))
        return out

    def together(self, *names: str) -> list[tuple[str, str]]:
        """Commands in one write, handled in the same tick; their replies."""
        ids = self.send(*names)
        self.sim.step(2)
        return self.replies(ids)

    def command(self, name: str) -> tuple[str, str]:
        ids = self.send(name)
        self.sim.step(1)
        return self.replies(ids)[0]

    def statuses(self, peer: SimPeer | None = None) -> list[tuple[str, str]]:
        peer = peer or self.op
        return [
            (m.error_name, m.status_message)
            for m in peer.messages("STATUS")
            if isinstance(m, igtl.StatusMessage)
        ]

    def announced(self, state: str) -> bool:
        return any(name == state for name, _ in self.statuses())

    def stats(self) -> dict[str, Any]:
        return dict(self.robot.snapshot())

    def close(self) -> None:
        self.sim.close()


@pytest.fixture
def bench_factory() -> Any:
    benches: list[Bench] = []

    def make(*args: Any, **kwargs: Any) -> Bench:
        b = Bench(*args, **kwargs)
        benches.append(b)
        return b

    yield make
    for b in benches:
        b.close()


# ------------------------------------------------------------ Reset proves the repair
@pytest.mark.req("SR-HW-15")
def test_reset_is_refused_while_the_drive_is_still_broken(bench_factory: Any) -> None:
    # the documented `faults: [write]`: on today's main Reset and Enable answered SUCCESS again
    # and again, the broken drive powered each time
    b = bench_factory(("write",))
    announced = len(b.statuses())  # INIT -> READY
    status, text = b.command("Enable")
    assert status == "FAIL" and "driver tool: write failed" in text
    assert b.robot.state is RobotState.FAULT and not b.announced("ENABLED")
    for _ in range(5):
        status, text = b.command("Reset")
        assert status == "FAIL", text
        assert "driver tool: reset failed" in text and "fault persists (write)" in text
        assert b.robot.state is RobotState.FAULT  # unchanged
        status, _ = b.command("Enable")
        assert status == "FAIL"
    # never READY or ENABLED (a black box's dump of the FAULT is told after it, when on)
    assert [n for n, _ in b.statuses()[announced:] if n != "BLACKBOX"] == ["FAULT"]
    assert all(d.state is not DriverState.ACTIVE for d in b.robot.hardware.drivers)
    # repaired, the same Reset is accepted and the robot works on all of its hardware
    b.drive("tool").clear_faults()
    assert [s for s, _ in b.together("Reset", "Enable", "Run")] == ["SUCCESS"] * 3


@pytest.mark.req("SR-HW-15", "SR-HW-16")
def test_reset_enable_run_in_one_write_never_announces_running(bench_factory: Any) -> None:
    b = bench_factory(plugin=("tool",))
    tool = b.drive("tool")
    tool.breaks.add("write")  # its reset says OK: only the robot's checks can tell
    for _ in range(4):
        ids = b.send("Reset", "Enable", "Run")
        b.sim.step(2)
        enable, run = b.replies(ids)[1:]
        assert enable[0] == "FAIL" and "driver tool: write failed" in enable[1]
        assert run[0] == "FAIL"
        assert b.robot.state is RobotState.FAULT
    assert not b.announced("ENABLED") and not b.announced("RUNNING")
    assert not tool.powered and all(d.state is not DriverState.ACTIVE for d in (tool,))


@pytest.mark.req("SR-HW-15")
def test_a_reset_whose_fresh_read_fails_is_refused_naming_the_drive(bench_factory: Any) -> None:
    b = bench_factory(plugin=("tool",))
    tool = b.drive("tool")
    tool.breaks.add("read")  # the insertion reads 5 m: outside its range
    b.sim.step(2)
    assert b.robot.state is RobotState.FAULT
    status, text = b.command("Reset")
    assert status == "FAIL"
    assert "driver tool: reset failed: a fresh read failed" in text
    assert "joint insertion: measured position 5 outside its limits" in text
    assert b.robot.state is RobotState.FAULT
    tool.breaks.clear()
    assert b.command("Reset")[0] == "SUCCESS" and b.robot.state is RobotState.READY


# -------------------------------------------------------------- Enable is verified
@pytest.mark.req("SR-HW-16")
def test_a_slow_power_up_cut_by_the_supervisor_never_answers_success(bench_factory: Any) -> None:
    # the tool's power stage takes long; the supervisor, finding the loop stuck inside it,
    # safe-stops every drive from its thread. The arm (already up) latches FAULT; the tool
    # comes up after the stop. On today's main the robot announced ENABLED and answered
    # SUCCESS with the arm in FAULT.
    b = bench_factory(plugin=("tool",))
    tool = b.drive("tool")

    def supervisor_trips_meanwhile() -> None:
        t = threading.Thread(target=b.robot.alarms.supervisor_trip, args=("loop hung 21 ms",))
        t.start()
        t.join()

    tool.on_activate = supervisor_trips_meanwhile
    status, text = b.command("Enable")
    assert status == "FAIL", text
    assert "safe stop while powering up" in text or "left ACTIVE" in text
    assert b.robot.state is RobotState.FAULT and not b.announced("ENABLED")
    assert not tool.powered
    assert all(d.state is not DriverState.ACTIVE for d in b.robot.hardware.drivers)


@pytest.mark.req("SR-HW-16")
def test_a_drive_that_stops_itself_during_power_up_vetoes_enable(bench_factory: Any) -> None:
    b = bench_factory(plugin=("tool",))
    arm = b.drive("arm")
    tool = b.drive("tool")
    # the arm's power stage drops out while the tool comes up: up, then not ACTIVE
    tool.on_activate = lambda: arm.safe_stop("overcurrent")
    status, text = b.command("Enable")
    assert status == "FAIL" and "driver arm" in text
    assert b.robot.state is RobotState.FAULT and not tool.powered


# ---------------------------------------------------------- switch-offs never forgotten
@pytest.mark.req("SR-HW-17")
def test_a_failed_switch_off_in_the_roll_back_is_named_unsafe_and_fault(
    bench_factory: Any,
) -> None:
    b = bench_factory(plugin=("arm", "tool"))
    arm, tool = b.drive("arm"), b.drive("tool")
    tool.inject("activate")  # the tool does not come up ...
    arm.breaks.add("deactivate")  # ... and the arm does not go off again in the roll-back
    status, text = b.command("Enable")
    assert status == "FAIL"
    assert "driver tool: activate failed" in text and "driver arm: deactivate failed" in text
    assert b.robot.state is RobotState.FAULT
    assert arm.powered and arm.stop_failed  # still on: never counted safe
    hw = b.stats()["hardware"]
    assert hw["unsafe"] == {"arm": arm.stop_failed} and hw["all_safe"] is False
    alerts = [t for n, t in b.statuses() if n in ("FAULT", "ALERT")]
    assert any("driver arm" in t for t in alerts) and any("driver tool" in t for t in alerts)
    # Reset switches it off first; while it cannot, Reset is refused
    tool.clear_faults()
    status, text = b.command("Reset")
    assert status == "FAIL" and "driver arm" in text and arm.powered
    arm.breaks.clear()
    assert b.command("Reset")[0] == "SUCCESS"
    assert not arm.powered and b.stats()["hardware"]["unsafe"] == {}


@pytest.mark.req("SR-HW-17")
def test_a_disable_whose_switch_off_fails_leaves_the_robot_fault(bench_factory: Any) -> None:
    b = bench_factory(plugin=("arm",))
    arm = b.drive("arm")
    assert b.command("Enable")[0] == "SUCCESS"
    arm.breaks.add("deactivate")
    b.command("Disable")
    assert b.robot.state is RobotState.FAULT
    assert "switch-off failed" in b.robot.last_alert and "driver arm" in b.robot.last_alert
    assert b.stats()["hardware"]["unsafe"].keys() == {"arm"}
    assert arm.powered


# ------------------------------------------------------ the supervisor alerts first
class HangingDrive(SimDriver):
    """A plugin whose stop waits on the lock its (hung) read holds."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.lock = threading.Lock()

    def _safe_stop(self) -> None:
        with self.lock:
            super()._safe_stop()


@pytest.mark.req("SR-HW-18")
def test_a_stop_that_hangs_delays_neither_the_other_drives_nor_the_alert() -> None:
    def joints(names: str) -> list[Joint]:
        return [Joint(n, "revolute", JointLimits(-1.0, 1.0, 1.0, 50.0)) for n in names]

    hung = HangingDrive("hung", joints("a"), {"heartbeat_ms": 0})
    ok = SimDriver("ok", joints("b"), {"heartbeat_ms": 0})
    hw = HardwareSet([(hung, [0]), (ok, [1])])
    hw.configure()
    hw.read(0.0)
    assert hw.activate() == []
    order: list[str] = []

    class Sender:
        def __call__(self, msg: igtl.StatusMessage) -> None:
            order.append(f"{msg.error_name}: ok={ok.state.value} hung={hung.state.value}")

    from occ.core.alarms import Alarms
    from occ.core.safety import StateMachine

    alarms = Alarms("slave", StateMachine(), SimClock(), Sender(), hw, None)  # type: ignore[arg-type]
    hung.lock.acquire()  # the loop thread is stuck in hung's read, holding its lock
    try:
        alarms.supervisor_trip("loop hung")
        # the alert went out first, before any drive was touched; the healthy drive stopped
        # without waiting for the hung one, which is named as not proven stopped
        assert order[0] == "SUPERVISOR: ok=active hung=active"
        assert ok.state is DriverState.FAULT and hung.state is DriverState.ACTIVE
        assert order[1].startswith("ALERT") and len(order) == 2
        assert not hw.all_safe()
    finally:
        hung.lock.release()
    for _ in range(200):  # the hung stop goes through once the read lets go of the lock
        if hung.state is DriverState.FAULT:
            break
        threading.Event().wait(0.005)
    assert hung.state is DriverState.FAULT and hw.all_safe()
    hw.shutdown()


# --------------------------------------------------- every fault reaches every operator
@pytest.mark.req("SR-HW-19")
def test_a_read_error_during_an_estop_is_told_to_every_operator_once(bench_factory: Any) -> None:
    b = bench_factory()
    assert b.command("EStop")[0] == "SUCCESS"
    before = len(b.statuses())
    before_viewer = len(b.statuses(b.viewer))
    b.drive("tool").inject("hook")
    b.sim.step(10)
    assert b.robot.state is RobotState.ESTOP  # E-stop outranks a fault
    new = b.statuses()[before:]
    assert [n for n, _ in new] == ["ALERT"]  # once, not every tick
    assert new[0][1].startswith("while ESTOP: driver tool: read failed")
    assert [n for n, _ in b.statuses(b.viewer)[before_viewer:]] == ["ALERT"]


@pytest.mark.req("SR-HW-19")
def test_a_second_drive_faulting_while_fault_is_told(bench_factory: Any) -> None:
    b = bench_factory()
    assert [s for s, _ in b.together("Enable", "Run")] == ["SUCCESS", "SUCCESS"]
    b.sim.step(1)
    b.drive("tool").inject("hook")
    b.sim.step(3)
    assert b.robot.state is RobotState.FAULT
    before = len(b.statuses())
    b.drive("arm").inject("nan", 1)
    b.sim.step(10)
    new = b.statuses()[before:]
    assert [n for n, _ in new] == ["ALERT"]
    assert "while FAULT: driver arm: read failed" in new[0][1] and "joint pitch" in new[0][1]
    # a Reset that clears it makes failures news again (the tool's is told once more)
    for d in ("arm", "tool"):
        b.drive(d).clear_faults()
    assert b.command("Reset")[0] == "SUCCESS"


def test_getstats_reports_safety_of_every_drive(bench_factory: Any) -> None:
    b = bench_factory()
    hw = b.stats()["hardware"]
    assert hw["unsafe"] == {} and hw["all_safe"] is True
    json.dumps(hw)  # GetStats is JSON


@pytest.mark.req("SR-HW-16")
def test_a_power_up_that_raises_after_its_drives_came_up_leaves_none_of_them_on() -> None:
    """Enable's check after the drives came up raises instead of naming a failure (a plugin's
    bug): the robot is FAULT with the exception's words, and no drive is left ACTIVE, though
    the robot never became ENABLED."""
    sim = SimRobot(slave_config("sim"))
    try:
        op = sim.peer("operator")
        sim.tick()

        def broken(*args: Any, **kwargs: Any) -> list[Any]:
            raise RuntimeError("verify broke")

        sim.robot.hardware.verify = broken  # type: ignore[method-assign]
        reply = sim.command(op, "Enable")
        assert reply.metadata["Status"] == "FAIL" and "verify broke" in reply.metadata["Error"]
        assert sim.robot.state_machine.state is RobotState.FAULT
        drives = sim.robot.hardware.drivers
        assert drives and all(d.state is not DriverState.ACTIVE for d in drives), [
            (d.name, d.state) for d in drives
        ]
        assert sim.robot.hardware.all_safe()
    finally:
        sim.close()
