"""Power-up off the loop thread (occ/core/powerup.py, issue 38): the slave on three CiA 402
drives (configs/slave-cia402.yaml on python-can's ``virtual`` bus) against the drive emulator
in this process, in simulated time (:class:`~occ_testkit.testing.SimRobot`).

The emulator's own thread answers the activation's SYNCs; a test holds it
(:meth:`DriveEmulator.held`) to keep the activation waiting while the loop ticks, and waits on
the wall clock for the activation's thread (``StateEffects.await_power_up``) without ticking, so the
ticks the test counts are its own.

The last part takes :class:`~occ.core.transitions.StateEffects` alone, on recording fakes of
its narrow ports and the real state machine: what each transition asks of the drives and the
robot's parts, and with which arguments.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

import igtl
from occ.clock import SimClock
from occ.core.hardware import HardwareFailure
from occ.core.loader import load_config
from occ.core.safety import RobotState
from occ.drivers.base import DriverState
from occ.drivers.cia402_sim import DriveEmulator
from occ.net.commands import Deferred
from occ_testkit import CONFIGS
from occ_testkit.testing import SimPeer, SimRobot, wait_until

_channels = itertools.count(1)
#: where the emulated joints start (counts): yaw 0, pitch 0.1 rad, insertion 50 mm
START = {1: 0.0, 2: 0.1 * 52152.0, 3: 0.05 * 2.0e6}


class PowerUpRig:
    """The CiA 402 slave and its three emulated drives on one simulated clock."""

    def __init__(self, **params: Any) -> None:
        self.channel = f"occ-powerup-{next(_channels)}"
        self.clock = SimClock()
        self.emu = DriveEmulator([1, 2, 3], channel=self.channel, clock=self.clock.now)
        for nid, counts in START.items():
            self.emu.node(nid).position = counts
        self.emu.start()
        cfg = load_config(CONFIGS / "slave-cia402.yaml")
        drv = cfg.robot.drivers[0]
        p = {
            **dict(drv.params),
            "interface": "virtual",
            "channel": self.channel,
            "state_timeout_ms": 2000.0,
            **params,
        }
        robot = cfg.robot.model_copy(update={"drivers": (drv.model_copy(update={"params": p}),)})
        self.sim = SimRobot(cfg.model_copy(update={"robot": robot}), clock=self.clock)
        self.robot = self.sim.robot
        self.op: SimPeer = self.sim.peer("operator")
        self.ticks(3)

    @property
    def arm(self) -> Any:
        return self.robot.hardware.drivers[0]

    def tick(self, settle: bool = True) -> None:
        self.sim.tick()
        if settle:
            self.emu.settle()  # its TPDOs are there for the next tick's read

    def ticks(self, n: int, settle: bool = True) -> None:
        for _ in range(n):
            self.tick(settle)

    def enable_waiting(self, ticks: int) -> int:
        """Inside ``emu.held()``: an operator's Enable, ``ticks`` ticks, and the power-up's
        thread waiting on the drives; the Enable's command id."""
        cid = self.op.send_command("Enable")
        self.ticks(ticks, settle=False)
        assert self.robot.effects.powering_up
        assert wait_until(lambda: self.arm.activating, 5.0, 0.001)  # its thread waits
        return cid

    def landed(self) -> None:
        """The activation's thread has ended (wall clock, no tick), and the tick that
        completes the power-up has run."""
        assert self.robot.effects.await_power_up(10.0)
        self.tick()
        assert not self.robot.effects.powering_up

    def reply(self, cid: int) -> tuple[bool, str] | None:
        msg = self.op.reply_to(cid)
        if msg is None:
            return None
        meta = msg.metadata
        return meta.get("Status") == "SUCCESS", meta.get("Message", "")

    def states(self) -> list[str]:
        return [self.emu.node(n).describe()["state"] for n in (1, 2, 3)]

    def close(self) -> None:
        try:
            self.sim.close()
        finally:
            self.emu.stop()


@pytest.fixture
def rig() -> Iterator[type[PowerUpRig]]:
    made: list[PowerUpRig] = []

    class Made(PowerUpRig):
        def __init__(self, **params: Any) -> None:
            made.append(self)
            super().__init__(**params)

    yield Made
    for r in made:
        r.close()


@pytest.mark.req("SR-HW-39")
def test_enable_powers_the_drives_up_while_the_loop_goes_on_ticking(rig: type[PowerUpRig]) -> None:
    r = rig()
    assert r.arm.activation_waits
    with r.emu.held():  # the drives answer nothing yet: the activation waits
        cid = r.op.send_command("Enable")
        before = r.robot.ticks
        r.ticks(50, settle=False)
        # the loop ticked 50 times while the activation waited on its thread: READY, no
        # reply yet, the drive busy (neither read nor written by the loop)
        assert r.robot.ticks - before == 50
        assert r.robot.state is RobotState.READY and r.robot.effects.powering_up
        assert r.reply(cid) is None
        assert r.robot.hardware.busy == frozenset({r.arm})
        assert r.arm.state is DriverState.INACTIVE
        assert not r.robot.hardware.all_safe()  # a drive coming up is not safe
    r.landed()
    assert r.reply(cid) == (True, "READY -> ENABLED")
    assert r.robot.state is RobotState.ENABLED
    assert r.arm.state is DriverState.ACTIVE and not r.robot.hardware.busy
    r.ticks(100)  # held where it was measured, heartbeats and TPDOs judged as usual
    assert r.robot.state is RobotState.ENABLED, r.robot.last_alert
    assert r.states() == ["OPERATION ENABLED"] * 3
    assert [j.position for j in r.robot.joints] == pytest.approx([0.0, 0.1, 0.05], abs=1e-4)
    stats = r.robot.snapshot()["power_up"]
    assert stats["count"] == 1 and stats["last_ms"] > 0.0 and not stats["under_way"]


@pytest.mark.req("SR-HW-39")
def test_a_node_that_never_enables_vetoes_enable_and_every_node_goes_off(
    rig: type[PowerUpRig],
) -> None:
    r = rig(state_timeout_ms=100.0)
    r.emu.refuse_enable(2)
    cid = r.op.send_command("Enable")
    r.tick()
    assert r.robot.effects.powering_up and r.reply(cid) is None
    r.landed()
    answer = r.reply(cid)
    assert answer is not None
    ok, text = answer
    assert not ok
    assert "node 2 (joint pitch) in SWITCHED ON" in text, text
    assert "every node switched off again" in text
    assert r.robot.state is RobotState.FAULT  # never ENABLED
    assert r.arm.state is DriverState.FAULT and r.robot.hardware.all_safe()
    r.ticks(3)
    assert r.states() == ["SWITCH ON DISABLED"] * 3
    assert all(r.emu.node(n).controlwords[-1] == 0x00 for n in (1, 2, 3))


@pytest.mark.req("SR-HW-39")
def test_an_estop_while_powering_up_wins_every_node_off_and_estop(rig: type[PowerUpRig]) -> None:
    r = rig()
    with r.emu.held():
        enable = r.enable_waiting(5)
        estop = r.op.send_command("EStop")
        r.tick(settle=False)
        assert r.robot.state is RobotState.ESTOP
        assert r.reply(estop) == (True, "READY -> ESTOP")
        answer = r.reply(enable)  # refused at once: the power-up's result is discarded
        assert answer is not None and not answer[0] and "cancelled" in answer[1], answer
        assert r.robot.effects.await_power_up(10.0)  # it gave up without waiting for the drives
    r.landed()
    assert r.robot.state is RobotState.ESTOP
    assert r.arm.state is DriverState.FAULT  # latched: safe stop while powering up
    assert "safe stop while powering up" in (r.arm.fault_reason or "")
    assert r.robot.hardware.all_safe()
    r.ticks(3)
    for nid in (1, 2, 3):
        node = r.emu.node(nid)
        assert 0x02 in node.controlwords, (nid, node.controlwords)  # quick stop
        assert node.describe()["state"] != "OPERATION ENABLED"
    # after a Reset the drives come up again
    assert r.sim.command(r.op, "Reset").metadata["Status"] == "SUCCESS"
    r.ticks(3)
    reply = r.sim.command(r.op, "Enable")
    assert reply.metadata["Status"] == "SUCCESS", reply.metadata
    assert r.robot.state is RobotState.ENABLED


@pytest.mark.req("SR-HW-39")
def test_a_disable_while_powering_up_cancels_it_and_the_drives_stay_usable(
    rig: type[PowerUpRig],
) -> None:
    r = rig()
    with r.emu.held():
        enable = r.enable_waiting(3)
        disable = r.op.send_command("Disable")
        again = r.op.send_command("Enable")  # same tick: refused, the power-up has not ended
        r.tick(settle=False)
        ok, text = r.reply(disable) or (False, "no reply")
        assert ok and "power-up is cancelled" in text
        answer = r.reply(enable)
        assert answer is not None and not answer[0] and "operator Disable" in answer[1]
        answer = r.reply(again)
        assert answer is not None and not answer[0] and "powering up" in answer[1]
    r.landed()
    assert r.robot.state is RobotState.READY
    assert r.arm.state is DriverState.INACTIVE  # switched off, not faulted
    r.ticks(3)
    assert r.states() == ["SWITCH ON DISABLED"] * 3
    reply = r.sim.command(r.op, "Enable")
    assert reply.metadata["Status"] == "SUCCESS", reply.metadata
    r.ticks(20)
    assert r.robot.state is RobotState.ENABLED
    assert r.states() == ["OPERATION ENABLED"] * 3


@pytest.mark.req("SR-HW-39")
def test_the_supervisors_safe_stop_while_powering_up_switches_every_node_off(
    rig: type[PowerUpRig],
) -> None:
    r = rig()
    with r.emu.held():
        r.enable_waiting(1)
        # the supervisor's thread (as Alarms.supervisor_trip does): every drive's safe stop
        assert r.robot.hardware.safe_stop("loop hung") == []
        assert r.robot.effects.await_power_up(10.0)
    r.landed()
    assert r.arm.state is DriverState.FAULT
    assert r.robot.state is not RobotState.ENABLED
    r.ticks(3)
    assert all(0x02 in r.emu.node(n).controlwords for n in (1, 2, 3))
    assert all(s != "OPERATION ENABLED" for s in r.states())


@pytest.mark.req("SR-HW-39")
def test_start_enabled_powers_up_then_runs(rig: type[PowerUpRig]) -> None:
    """``occd --start running``: Enable powers up off the loop thread, Run follows it."""
    r = rig()
    r.robot.start_in("enable", "run")
    r.tick()
    assert r.robot.effects.powering_up and r.robot.state is RobotState.READY
    r.landed()
    r.tick()
    assert r.robot.state is RobotState.RUNNING, r.robot.last_alert


@pytest.mark.req("SR-HW-39")
def test_a_reset_of_cia402_drives_runs_off_the_loop_thread_and_is_refused_while_the_cause_persists(
    rig: type[PowerUpRig],
) -> None:
    r = rig(state_timeout_ms=200.0)
    assert r.sim.command(r.op, "Enable").metadata["Status"] == "SUCCESS"
    r.ticks(10)
    r.emu.inject_emcy(2, 0x2310, persist=True)
    for _ in range(20):
        r.tick()
        if r.robot.state is RobotState.FAULT:
            break
    assert r.robot.state is RobotState.FAULT and r.arm.state is DriverState.FAULT
    r.ticks(3)
    with r.emu.held():  # the fault reset waits for the drives: the loop goes on ticking
        cid = r.op.send_command("Reset")
        before = r.robot.ticks
        r.ticks(20, settle=False)
        assert r.robot.ticks - before == 20 and r.robot.effects.powering_up
        assert r.robot.state is RobotState.FAULT and r.reply(cid) is None
    r.landed()
    answer = r.reply(cid)
    assert answer is not None and not answer[0], answer
    assert "fault reset refused" in answer[1] and "node 2 (joint pitch): still FAULT" in answer[1]
    assert r.robot.state is RobotState.FAULT
    r.emu.clear(2)
    reply = r.sim.command(r.op, "Reset")
    assert reply.metadata["Status"] == "SUCCESS", reply.metadata
    assert reply.metadata["Message"] == "FAULT -> READY"
    r.ticks(3)
    assert r.sim.command(r.op, "Enable").metadata["Status"] == "SUCCESS"
    r.ticks(20)
    assert r.robot.state is RobotState.ENABLED, r.robot.last_alert


@pytest.mark.req("SR-HW-39")
def test_start_whose_enable_fails_never_asks_run_and_says_why(
    rig: type[PowerUpRig], caplog: pytest.LogCaptureFixture
) -> None:
    """``occd --start running`` with a node that never enables: the Enable's failure ends the
    start (its words in the log); Run is never asked, so no second refusal follows it."""
    r = rig(state_timeout_ms=100.0)
    r.emu.refuse_enable(2)
    with r.emu.held():
        r.robot.start_in("enable", "run")
        r.tick()
        assert r.robot.effects.powering_up
        # an operator's Enable meanwhile is refused, naming who is powering up: --start
        cid = r.op.send_command("Enable")
        r.ticks(2, settle=False)
        answer = r.reply(cid)
        assert answer is not None and not answer[0]
        assert "the drives are powering up (--start)" in answer[1], answer
    r.landed()
    r.ticks(3)
    assert r.robot.state is RobotState.FAULT and r.robot.effects.pending_start == []
    lines = [m for rec in caplog.records if (m := rec.getMessage()).startswith("--start")]
    assert len(lines) == 1 and lines[0].startswith("--start: enable refused or failed ("), lines
    assert "node 2 (joint pitch) in SWITCHED ON" in lines[0]


class _Drive:
    """A driver's face as a PowerUp sees it: what it was asked, in order."""

    def __init__(self, name: str, state: DriverState = DriverState.INACTIVE) -> None:
        self.name = name
        self.state = state
        self.asked: list[tuple[str, str]] = []

    def cancel_activation(self, why: str) -> None:
        self.asked.append(("cancel", why))

    def safe_stop(self, why: str) -> None:
        self.asked.append(("safe_stop", why))


@pytest.mark.req("SR-HW-39")
def test_a_power_up_cancelled_then_stopped_answers_once_and_stops_each_drive_once() -> None:
    """A Disable (cancel) then an EStop (stop) while the drives come up: each activation is
    cancelled with the Disable's words, then each drive safe-stopped once with the EStop's;
    the operator's Enable is refused once, naming the first; the drives that came up all the
    same (ACTIVE) are the leftovers the loop switches off."""
    from occ.core.powerup import PowerUp
    from occ.net.commands import Deferred

    a, b = _Drive("arm"), _Drive("tool", DriverState.ACTIVE)
    answer = Deferred()
    pu = PowerUp([a, b], "operator Enable", answer)  # type: ignore[list-item]
    pu.cancel("operator Disable", stop=False)
    assert a.asked == b.asked == [("cancel", "operator Disable")]
    assert answer.result == (
        False,
        "Enable cancelled while the drives worked: operator Disable",
    )
    pu.cancel("EStop", stop=True)
    pu.cancel("shutdown", stop=True)  # idempotent: stopped once
    assert a.asked == b.asked == [("cancel", "operator Disable"), ("safe_stop", "EStop")]
    assert pu.cancelled == "operator Disable" and pu.stopped is True
    assert answer.result[1].endswith("operator Disable")  # type: ignore[index]
    assert pu.leftovers() == [b]


@pytest.mark.req("SR-HW-39")
def test_a_reset_cancelled_leaves_its_drives_alone_and_says_reset() -> None:
    from occ.core.powerup import PowerUp
    from occ.net.commands import Deferred

    a = _Drive("arm", DriverState.FAULT)
    answer = Deferred()
    pu = PowerUp([a], "operator Reset", answer, action="reset")  # type: ignore[list-item]
    pu.cancel("EStop", stop=True)
    assert a.asked == [] and pu.stopped is False
    assert answer.result == (False, "Reset cancelled while the drives worked: EStop")
    assert pu.leftovers() == []


@pytest.mark.req("SR-HW-39")
@pytest.mark.parametrize("stop", ["Disable", "Stop", "EStop"])
def test_a_drive_that_came_up_after_the_power_up_was_called_off_is_switched_off(
    rig: type[PowerUpRig], monkeypatch: pytest.MonkeyPatch, stop: str
) -> None:
    """A drive whose activation cannot be called back (its driver ignores the cancel) comes
    up all the same after a Disable or an EStop: the loop, collecting the power-up, switches
    it off (Disable: INACTIVE, READY) or latches it FAULT (EStop: ESTOP); the Enable is
    refused, and no node is left OPERATION ENABLED."""
    r = rig()
    monkeypatch.setattr(r.arm, "cancel_activation", lambda why: None)
    with r.emu.held():
        cid = r.op.send_command("Enable")
        r.ticks(2, settle=False)
        sid = r.op.send_command(stop)
        r.ticks(2, settle=False)
        if stop == "Disable":  # called off, still under way: another Enable, a Reset wait
            again, reset = r.op.send_command("Enable"), r.op.send_command("Reset")
            r.ticks(2, settle=False)
            refused = r.reply(again)
            assert refused is not None and not refused[0]
            assert "the drives are powering up (" in refused[1], refused
            assert "; cancelled: " in refused[1] and refused[1].endswith("(disable))"), refused
            no = r.reply(reset)
            assert no is not None and not no[0]
            assert (
                "'reset' refused in state READY: the drives are still working (activate, "
                in (no[1])
            ), no
    r.landed()
    answer = r.reply(cid)
    assert answer is not None and not answer[0]
    assert answer[1].startswith("Enable cancelled while the drives worked: "), answer
    assert r.reply(sid) is not None and r.reply(sid)[0]  # type: ignore[index]
    r.ticks(3)
    assert all(s != "OPERATION ENABLED" for s in r.states()), r.states()
    if stop != "EStop":  # a Stop in READY is no transition: it cancels the power-up
        assert r.robot.state is RobotState.READY and r.arm.state is DriverState.INACTIVE
    else:
        assert r.robot.state is RobotState.ESTOP and r.arm.state is DriverState.FAULT
    assert r.robot.hardware.all_safe()


class _Activating(_Drive):
    """A drive whose activation runs on the PowerUp's thread: it fails (``err``), waits for
    ``release`` or comes up; it notes the thread it ran on."""

    def __init__(self, name: str, err: Exception | None = None, release: Any = None) -> None:
        super().__init__(name)
        self.err = err
        self.release = release
        self.thread: Any = None

    def activate(self) -> None:
        self.thread = threading.current_thread()
        if self.release is not None:
            self.release.wait(10.0)
        if self.err is not None:
            raise self.err
        self.state = DriverState.ACTIVE


@pytest.mark.req("SR-HW-39")
def test_each_activation_runs_on_a_daemon_thread_of_its_own_and_its_failure_is_named() -> None:
    """Each drive on a thread named for it, a daemon (a hung activation never keeps the
    daemon's process alive at exit); failures in the drives' order, an error without words
    named by its type; the time taken measured from the start to the last one's end."""
    from occ.core.powerup import PowerUp

    gate = threading.Event()
    a = _Activating("arm", RuntimeError("node 2: no answer"))
    b = _Activating("tool", ValueError(), release=gate)
    c = _Activating("wrist")
    t0 = time.perf_counter()
    pu = PowerUp([a, b, c], "operator Enable").start()  # type: ignore[list-item]
    assert pu.action == "activate" and pu.reason == "operator Enable"
    assert not pu.wait(0.05) and not pu.done and pu.took_s is None  # tool still waits
    gate.set()
    assert pu.wait(10.0) and pu.done
    elapsed = time.perf_counter() - t0
    assert [str(f) for f in pu.failures()] == [
        "driver arm: activate failed: node 2: no answer",
        "driver tool: activate failed: ValueError",
    ]
    assert [(d.thread.name, d.thread.daemon) for d in (a, b, c)] == [
        ("occ-power-up-arm", True),
        ("occ-power-up-tool", True),
        ("occ-power-up-wrist", True),
    ]
    assert pu.took_s is not None and 0.0 < pu.took_s <= elapsed
    assert pu.leftovers() == [c]


def test_waiting_for_no_power_up_is_at_once_true() -> None:
    sim = SimRobot(CONFIGS / "slave.yaml")
    try:
        assert sim.robot.effects.powerup is None and sim.robot.effects.await_power_up(0.0)
        # GetStats before any power-up: none under way, none counted, no time taken (null)
        assert sim.robot.snapshot()["power_up"] == {
            "under_way": False,
            "count": 0,
            "last_ms": None,
        }
    finally:
        sim.close()


@pytest.mark.req("SR-HW-39")
def test_a_start_event_refused_ends_the_start_with_its_words(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """``--start`` asking Run of a READY robot: refused by the state machine, logged with
    the event and the refusal, and nothing of the start is left."""
    sim = SimRobot(CONFIGS / "slave.yaml")
    try:
        sim.robot.start_in("run", "enable")
        sim.tick()
        assert sim.robot.state is RobotState.READY and sim.robot.effects.pending_start == []
        (line,) = [m for r in caplog.records if (m := r.getMessage()).startswith("--start")]
        assert line.startswith("--start: run refused or failed ('run' "), line
        assert "READY" in line
    finally:
        sim.close()


@pytest.mark.req("SR-HW-3")
def test_enable_with_a_joint_never_measured_is_refused_and_told_to_every_operator() -> None:
    """The guard, on the slave in simulated time: a joint whose drive never reported a
    position refuses Enable (servos would hold a position nobody measured), the requester
    gets the refusal, every operator an ALERT naming the drive and its joints; READY stays.
    Run, Stop and the other events are not guarded by it."""
    sim = SimRobot(CONFIGS / "slave.yaml")
    try:
        robot = sim.robot
        op, viewer = sim.peer("operator"), sim.peer("slicer")
        sim.tick()
        joint = robot.joints[2]
        drive = robot.hardware.pairs[0][0].name
        missing = f"driver {drive} joints ['{joint.name}']"  # as HardwareSet.unmeasured says
        asked: list[list[str]] = []

        def unmeasured(joints: Any) -> str:
            asked.append([j.name for j in joints])
            return missing

        robot.hardware.unmeasured = unmeasured  # type: ignore[method-assign]
        cid = op.send_command("Enable")
        sim.tick()
        reply = op.reply_to(cid)
        assert reply is not None and reply.metadata.get("Status") != "SUCCESS"
        assert robot.state is RobotState.READY
        alerts = [
            (m.error_name, m.status_message, m.code)
            for m in viewer.messages("STATUS")
            if m.error_name == "ALERT"
        ]
        assert asked == [[j.name for j in robot.joints]]
        assert alerts == [
            (
                "ALERT",
                f"enable refused: no measurement yet from driver {drive} joints "
                f"['{joint.name}'] (are the drives on and answering?)",
                igtl.StatusCode.NOT_READY,
            )
        ]
        assert robot.effects.may_power(RobotState.READY, "run") == "" and len(asked) == 1
        missing = ""
        assert robot.effects.may_power(RobotState.READY, "enable") == ""
    finally:
        sim.close()


@pytest.mark.req("SR-HW-39")
def test_a_shutdown_while_powering_up_stops_every_drive_and_refuses_the_enable(
    rig: type[PowerUpRig],
) -> None:
    r = rig()
    with r.emu.held():
        r.op.send_command("Enable")
        r.ticks(2, settle=False)
        assert r.robot.effects.powering_up
        pu = r.robot.effects.powerup
        assert pu is not None and pu.answer is not None
        # the shutdown stops the power-up (the drives' safe stop) and waits for it
        done = threading.Event()
        threading.Thread(
            target=lambda: (r.robot.effects.finish(timeout=10.0), done.set()), daemon=True
        ).start()
        assert wait_until(lambda: pu.cancelled is not None, 5.0, 0.001)
    assert done.wait(10.0)
    assert pu.cancelled == "shutdown" and pu.stopped is True
    assert pu.answer.result == (False, "Enable cancelled while the drives worked: shutdown")
    assert r.robot.effects.powerup is None
    assert r.arm.state is DriverState.FAULT and r.robot.hardware.all_safe()


# ------------------------------------------------ StateEffects alone, with recording fakes
# What each state change asks of the drives and of the robot's parts, and with which
# arguments: the HardwareSet, the data, the controllers, the setpoints, the streams and the
# alarms are small fakes recording each call; the state machine is the real one, wired to the
# effects as occ/core/wiring.py ``build_effects`` does. The slow drives are _Activating ones,
# on the PowerUp's real threads (waited for on the wall clock, no tick).

#: the tick under way (``tick_now``), the clock's own time and its wall time: three values, so
#: each use says which one it took
TICK, CLOCK_NOW, WALL = 3.25, 7.0, 1000.5


class _Resetting(_Activating):
    """A drive latched FAULT whose fault reset runs on the PowerUp's thread: it fails with
    ``reset_err`` or clears the fault; then it powers up as an _Activating one."""

    def __init__(self, name: str, reset_err: Exception | None = None, release: Any = None) -> None:
        super().__init__(name, release=release)
        self.state = DriverState.FAULT
        self.reset_err = reset_err

    def reset(self) -> None:
        if self.reset_err is not None:
            raise self.reset_err
        self.state = DriverState.INACTIVE


class _Hardware:
    """The HardwareSet as StateEffects uses it: ``slow`` are the drives whose activation
    waits; each call is recorded with its arguments; activate and reset fail with what they
    were given (the power-up's failures), deactivate with ``stop_failures``."""

    def __init__(self, slow: list[Any]) -> None:
        self.slow = slow
        self.busy: frozenset[Any] = frozenset()
        self.calls: list[tuple[Any, ...]] = []
        self.stop_failures: list[Any] = []
        self.verify_error: Exception | None = None
        self.reset_error: Exception | None = None

    def waiting(self, state: DriverState = DriverState.INACTIVE) -> list[Any]:
        return [d for d in self.slow if d.state is state and d not in self.busy]

    def hold(self, drivers: Any) -> None:
        self.busy = self.busy | frozenset(drivers)

    def release(self, drivers: Any) -> None:
        self.busy = self.busy - frozenset(drivers)

    def activate(self, prior: Any = ()) -> list[Any]:
        self.calls.append(("activate", list(prior)))
        return list(prior)

    def verify(self, joints: Any, now: float, effort: bool = False) -> list[Any]:
        self.calls.append(("verify", now, effort))
        if self.verify_error is not None:
            raise self.verify_error
        return []

    def deactivate(self) -> list[Any]:
        self.calls.append(("deactivate",))
        for d in self.slow:
            if d.state is DriverState.ACTIVE:
                d.state = DriverState.INACTIVE
        return list(self.stop_failures)

    def reset(self, now: float | None = None, prior: Any = ()) -> list[Any]:
        self.calls.append(("reset", now, list(prior)))
        if self.reset_error is not None:
            raise self.reset_error
        return list(prior)

    def unsafe(self) -> list[Any]:
        return []

    def unmeasured(self, joints: Any) -> str:
        return ""


class _Parts:
    """The data, controllers, setpoints (motion), streams and alarms: one recorder of every
    call made to any of them, in order."""

    def __init__(self) -> None:
        self.calls: list[tuple[Any, ...]] = []
        self.state: RobotState | None = None  # the data's
        self.commands_effort = False  # the controllers'

    # data
    def measured_from(self, joints: Any) -> None:
        self.calls.append(("measured_from",))

    # controllers, motion
    def on_state(self, *args: Any) -> None:
        self.calls.append(("controller" if len(args) == 3 else "motion", *args))

    # streams
    def reset(self) -> None:
        self.calls.append(("streams.reset",))

    # alarms
    def broadcast(self, name: str, text: str, code: int, timestamp: float | None = None) -> None:
        self.calls.append(("broadcast", name, text, code, timestamp))

    def cleared(self) -> None:
        self.calls.append(("cleared",))

    def fault(self, reason: str) -> None:
        self.calls.append(("fault", reason))

    def hardware_alert(self, failures: Any) -> None:
        self.calls.append(("hardware_alert", list(failures)))

    def plugin_error(self, where: str, err: BaseException) -> None:
        self.calls.append(("plugin_error", where, err))

    def of(self, kind: str) -> list[tuple[Any, ...]]:
        return [c[1:] for c in self.calls if c[0] == kind]


class _Clock:
    def now(self) -> float:
        return CLOCK_NOW

    def wall_time(self) -> float:
        return WALL


class _Effects:
    """StateEffects on the fakes, in ``state``, in the middle of a tick at TICK."""

    def __init__(self, state: RobotState, slow: list[Any] | None = None) -> None:
        from occ.core.safety import StateMachine
        from occ.core.transitions import StateEffects

        self.hw = _Hardware(slow or [])
        self.parts = p = _Parts()
        self.states = StateMachine(state, clock=_Clock())
        fx = StateEffects(self.hw, [], _Clock(), p, p, p, p, p)  # type: ignore[arg-type]
        fx.states = self.states
        self.states.add_listener(fx.on_transition)
        self.states.add_guard(fx.may_power)
        self.states.set_effector(fx.effect)
        fx.tick_now = TICK
        self.fx = fx

    def landed(self) -> None:
        """The power-up's threads have ended (wall clock); the loop's tick collects it."""
        assert self.fx.await_power_up(10.0)
        self.fx.land()
        assert self.fx.powerup is None


@pytest.mark.req("SR-HOLD-1")
def test_each_state_change_tells_each_part_its_old_and_new_state_at_the_ticks_time(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The setpoints (Motion.on_state decides the held setpoint from both states: the
    measured position on power-up, what the drives were last told on a stop from RUNNING),
    the controllers (both states and the tick's time, as a replay sees it), the streams
    (re-armed on entering RUNNING only: the first packet after Run arms the loss monitor) and
    every operator (a STATUS named for the new state, ``old -> new`` and the reason if one
    was given, stamped with the transition's time). The log says each one, a warning when
    the robot stops."""
    from occ.net.outputs import STATE_STATUS_CODE

    caplog.set_level(logging.INFO, logger="occ.core.robot")
    e = _Effects(RobotState.READY)
    assert e.fx.request("enable", "") == "READY -> ENABLED"
    assert e.fx.request("run", "operator Run") == "ENABLED -> RUNNING"
    assert e.fx.request("stop", "operator Stop") == "RUNNING -> STOPPED"
    seen = [c for c in e.parts.calls if c[0] != "measured_from"]
    R, E, RUN, S = RobotState.READY, RobotState.ENABLED, RobotState.RUNNING, RobotState.STOPPED
    code = STATE_STATUS_CODE
    assert seen == [
        ("motion", R, E),
        ("controller", R, E, TICK),
        ("broadcast", "ENABLED", "READY -> ENABLED", code[E], WALL),
        ("motion", E, RUN),
        ("streams.reset",),
        ("controller", E, RUN, TICK),
        ("broadcast", "RUNNING", "ENABLED -> RUNNING: operator Run", code[RUN], WALL),
        ("motion", RUN, S),
        ("controller", RUN, S, TICK),
        ("broadcast", "STOPPED", "RUNNING -> STOPPED: operator Stop", code[S], WALL),
    ]
    assert e.parts.state is S  # the data's state: what the tick reads
    assert [(r.levelno, r.getMessage()) for r in caplog.records] == [
        (logging.INFO, "state READY -> ENABLED (enable)"),
        (logging.INFO, "state ENABLED -> RUNNING (run): operator Run"),
        (logging.WARNING, "state RUNNING -> STOPPED (stop): operator Stop"),
    ]


@pytest.mark.req("SR-HW-19")
def test_failures_are_news_again_only_after_fault_or_estop_is_left_not_after_a_disable() -> None:
    """``Alarms.cleared`` (failures told become news again) follows a Reset out of FAULT or
    ESTOP, never a Disable out of ENABLED: a drive that failed to stop in that Disable has
    been told once, and stays told in the FAULT that follows."""
    e = _Effects(RobotState.ENABLED)
    e.fx.request("disable", "operator Disable")
    assert e.parts.of("cleared") == []
    for latched in ("fault", "estop"):
        e.fx.request(latched, "test")
        e.fx.request("reset", "operator Reset")
        assert e.states.state is RobotState.READY
        assert e.parts.of("cleared") == [()] * (1 if latched == "fault" else 2)


@pytest.mark.req("SR-HW-16")
@pytest.mark.parametrize("effort", [False, True])
def test_enable_is_verified_as_the_controllers_command_position_or_effort(effort: bool) -> None:
    """An Enable powered in the tick is proven by a checked read and a write of what the
    controllers command: the held position, or zero effort on an effort drive (verify's
    ``effort``); the reading it used is already the loop's, not taken again."""
    e = _Effects(RobotState.READY)
    e.parts.commands_effort = effort
    assert e.fx.request("enable", "operator Enable") == "READY -> ENABLED"
    assert e.hw.calls == [("activate", []), ("verify", TICK, effort)]
    assert e.parts.of("measured_from") == []


@pytest.mark.req("SR-HW-39")
def test_a_power_up_off_the_loop_lands_with_its_reason_its_time_and_a_fresh_reading() -> None:
    """Enable with a drive whose activation waits: a Deferred, counted; landed, the Enable
    completes with the operator's reason (the ENABLED STATUS says it), the held setpoint
    starts from verify's fresh reading, and GetStats's ``last_ms`` is the time it took in
    milliseconds to the microsecond. A second power-up is counted too."""

    arm = _Activating("arm")
    e = _Effects(RobotState.READY, [arm])
    assert e.fx.last_powerup_ms is None and e.fx.powerups == 0
    answer = e.fx.request("enable", "operator Enable")
    assert isinstance(answer, Deferred) and e.fx.powerups == 1
    assert e.hw.busy == {arm} and e.hw.calls == []
    assert e.fx.await_power_up(10.0)
    assert e.fx.powerup is not None
    e.fx.powerup.took_s = 0.0123456  # measured on the wall clock: fixed here
    e.landed()
    assert answer.result == (True, "READY -> ENABLED")
    assert e.fx.last_powerup_ms == 12.346
    assert e.hw.busy == frozenset()
    assert e.hw.calls == [("activate", []), ("verify", TICK, False)]
    assert e.parts.of("measured_from") == [()]
    (status,) = e.parts.of("broadcast")
    assert status[:2] == ("ENABLED", "READY -> ENABLED: operator Enable")
    e.fx.request("disable", "operator Disable")
    again = e.fx.request("enable", "--start")
    assert isinstance(again, Deferred) and e.fx.powerups == 2
    e.landed()
    assert again.result == (True, "READY -> ENABLED")
    assert e.parts.of("broadcast")[-1][:2] == ("ENABLED", "READY -> ENABLED: --start")


@pytest.mark.req("SR-HW-39")
def test_a_power_up_that_failed_off_the_loop_vetoes_enable_with_its_failure() -> None:
    """A drive whose activation failed on its thread: the loop's Enable is given that failure
    (the HardwareSet powers nothing else and switches off what came up), vetoed, FAULT, and the
    operator's reply names the drive and its cause."""
    arm = _Activating("arm", RuntimeError("node 2 in SWITCHED ON"))
    e = _Effects(RobotState.READY, [arm])
    answer = e.fx.request("enable", "operator Enable")
    e.landed()
    failure = HardwareFailure("arm", "activate", "node 2 in SWITCHED ON")
    assert e.hw.calls[0] == ("activate", [failure])
    assert e.states.state is RobotState.FAULT
    assert answer.result is not None and not answer.result[0]  # type: ignore[union-attr]
    assert "driver arm: activate failed: node 2 in SWITCHED ON" in answer.result[1]  # type: ignore[union-attr]


@pytest.mark.req("SR-HW-39", "SR-HW-17")
def test_a_drive_up_after_an_estop_stopped_its_power_up_is_stopped_again_in_those_words() -> None:
    """An EStop while a drive powers up: its safe stop, in the EStop's words; the drive comes
    up all the same (its activation had got past the stop), so the loop, collecting the
    power-up, safe-stops it again in the same words and switches every drive off; a drive
    whose switch-off fails there is an alert naming it."""
    gate = threading.Event()
    arm = _Activating("arm", release=gate)
    e = _Effects(RobotState.READY, [arm])
    answer = e.fx.request("enable", "operator Enable")
    # its activation has begun: the stop is too late
    assert wait_until(lambda: arm.thread is not None, 5.0, 0.001)
    assert e.fx.request("estop", "operator EStop") == "READY -> ESTOP"
    why = "estop: READY -> ESTOP"
    assert arm.asked == [("safe_stop", why)]
    assert answer.result == (False, f"Enable cancelled while the drives worked: {why}")  # type: ignore[union-attr]
    failed = [HardwareFailure("tool", "deactivate", "bus off")]
    e.hw.stop_failures = failed
    gate.set()
    e.landed()
    assert arm.asked == [("safe_stop", why), ("safe_stop", why)]
    # entering ESTOP switched off what was ACTIVE (the arm, busy, is the power-up's); then
    # the landing switched everything off again
    assert e.hw.calls == [("deactivate",), ("deactivate",)]
    assert e.parts.of("hardware_alert") == [(failed,)]
    assert e.states.state is RobotState.ESTOP


@pytest.mark.req("SR-EXC-1")
@pytest.mark.parametrize("event", ["enable", "reset"])
def test_a_part_that_raises_as_a_power_up_lands_answers_it_and_is_a_plugin_error(
    event: str,
) -> None:
    """An exception (not a refusal) from the transition that completes a power-up or a
    reset off the loop thread: the operator's Enable or Reset is answered with it, and it is a
    plugin error (FAULT naming it) saying where it came from."""
    enable = event == "enable"
    arm = _Activating("arm") if enable else _Resetting("arm")
    e = _Effects(RobotState.READY if enable else RobotState.FAULT, [arm])
    err = RuntimeError("the bus is gone")
    if enable:
        e.hw.verify_error = err
    else:
        e.hw.reset_error = err
    answer = e.fx.request(event, f"operator {event}")
    e.landed()
    assert answer.result == (False, f"{event} failed: the bus is gone")  # type: ignore[union-attr]
    ((where, raised),) = e.parts.of("plugin_error")
    assert where == f"{event} (off the loop thread)" and raised is err


@pytest.mark.req("SR-HW-39")
def test_a_reset_off_the_loop_is_completed_with_its_failures_and_its_reason() -> None:
    """Reset of a drive latched FAULT whose fault reset waits: a Deferred; landed, the loop's
    reset is given what failed on the thread (that drive is not reset twice), vetoed while
    it failed; a Reset that worked says its reason in the READY STATUS."""

    arm = _Resetting("arm", RuntimeError("node 2: still FAULT"))
    e = _Effects(RobotState.FAULT, [arm])
    first = e.fx.request("reset", "operator Reset")
    assert isinstance(first, Deferred)
    e.landed()
    failure = HardwareFailure("arm", "reset", "node 2: still FAULT")
    assert e.hw.calls == [("reset", TICK, [failure])]
    assert e.states.state is RobotState.FAULT
    assert first.result is not None and not first.result[0]
    arm.reset_err = None
    second = e.fx.request("reset", "operator Reset")
    e.landed()
    assert second.result == (True, "FAULT -> READY")  # type: ignore[union-attr]
    assert e.hw.calls[-1] == ("reset", TICK, [])
    assert e.parts.of("broadcast")[-1][:2] == ("READY", "FAULT -> READY: operator Reset")
    assert e.fx.powerups == 0  # a reset is no power-up


@pytest.mark.req("SR-STATE-1")
@pytest.mark.parametrize("event", ["estop", "shutdown", "fault"])
def test_other_events_in_fault_go_through_at_once_whatever_drives_wait(event: str) -> None:
    """Only a Reset of FAULT or ESTOP waits for drives whose fault reset waits: an EStop, a
    shutdown or a Fault in FAULT is the state machine's at once, no power-up started."""
    arm = _Resetting("arm")
    e = _Effects(RobotState.FAULT, [arm])
    new = {"estop": "ESTOP", "shutdown": "SHUTDOWN", "fault": "FAULT"}[event]
    assert e.fx.request(event, "test") == f"FAULT -> {new}"
    assert e.fx.powerup is None and arm.state is DriverState.FAULT


@pytest.mark.req("SR-HW-39")
def test_a_disable_or_a_stop_during_a_power_up_cancels_it_and_is_answered_at_once() -> None:
    """A Disable (or a Stop) while a drive powers up: no transition (READY stays), each
    activation cancelled in the operator's words, the reply at once; a second one changes
    nothing. The drive that came up all the same is switched off (not safe-stopped: nothing
    latches) when the loop collects it."""
    gate = threading.Event()
    arm = _Activating("arm", release=gate)
    e = _Effects(RobotState.READY, [arm])
    answer = e.fx.request("enable", "operator Enable")
    assert wait_until(lambda: arm.thread is not None, 5.0, 0.001)
    said = "READY: the power-up is cancelled; its drives go off as it ends"
    assert e.fx.request("disable", "operator Disable") == said
    assert e.fx.request("Stop", "operator Stop") == said
    assert arm.asked == [("cancel", "operator Disable (disable)")]
    assert answer.result == (  # type: ignore[union-attr]
        False,
        "Enable cancelled while the drives worked: operator Disable (disable)",
    )
    gate.set()
    e.landed()
    assert e.states.state is RobotState.READY and arm.state is DriverState.INACTIVE
    assert e.hw.calls == [("deactivate",)] and arm.asked == [
        ("cancel", "operator Disable (disable)")
    ]
    assert e.parts.of("broadcast") == []


@pytest.mark.req("SR-HW-39")
def test_an_estop_after_a_reset_landed_still_stops_the_next_power_up() -> None:
    """A Reset completed off the loop, then an Enable whose drive powers up, then an EStop:
    the EStop stops that power-up at once (the drive's safe stop, the Enable refused), as it
    would had no Reset come before; what the landed Reset left behind decides nothing."""
    gate = threading.Event()
    arm = _Resetting("arm", release=gate)
    e = _Effects(RobotState.FAULT, [arm])
    assert isinstance(e.fx.request("reset", "operator Reset"), Deferred)
    e.landed()
    assert e.states.state is RobotState.READY
    answer = e.fx.request("enable", "operator Enable")
    assert wait_until(lambda: arm.thread is not None, 5.0, 0.001)
    assert e.fx.request("estop", "operator EStop") == "READY -> ESTOP"
    why = "estop: READY -> ESTOP"
    assert arm.asked == [("safe_stop", why)]
    assert answer.result == (False, f"Enable cancelled while the drives worked: {why}")  # type: ignore[union-attr]
    gate.set()
    e.landed()
    assert e.states.state is RobotState.ESTOP
    assert arm.asked == [("safe_stop", why), ("safe_stop", why)]


@pytest.mark.req("SR-HW-39")
def test_a_power_up_without_an_answer_can_be_stopped() -> None:
    """A PowerUp asked by no operator (no answer to give) is stopped like any other: each
    drive safe-stopped, nothing to refuse."""
    from occ.core.powerup import PowerUp

    a = _Drive("arm")
    pu = PowerUp([a], "--start")  # type: ignore[list-item]
    pu.cancel("EStop", stop=True)
    assert a.asked == [("safe_stop", "EStop")] and pu.cancelled == "EStop" and pu.answer is None
