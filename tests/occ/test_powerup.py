"""Power-up off the loop thread (occ/core/powerup.py, issue 38): the slave on three CiA 402
drives (configs/slave-cia402.yaml on python-can's ``virtual`` bus) against the drive emulator
in this process, in simulated time (:class:`~occ_testkit.testing.SimRobot`).

The emulator's own thread answers the activation's SYNCs; a test holds it
(:meth:`DriveEmulator.held`) to keep the activation waiting while the loop ticks, and waits on
the wall clock for the activation's thread (``StateEffects.await_power_up``) without ticking, so the
ticks the test counts are its own.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

import igtl
from occ.clock import SimClock
from occ.core.loader import load_config
from occ.core.safety import RobotState
from occ.drivers.base import DriverState
from occ.drivers.cia402_sim import DriveEmulator
from occ_testkit import CONFIGS
from occ_testkit.testing import SimPeer, SimRobot, wait_until

_channels = itertools.count(1)
#: where the emulated joints start (counts): yaw 0, pitch 0.1 rad, insertion 50 mm
START = {1: 0.0, 2: 0.1 * 52152.0, 3: 0.05 * 2.0e6}


class Rig:
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
def rig() -> Iterator[type[Rig]]:
    made: list[Rig] = []

    class Made(Rig):
        def __init__(self, **params: Any) -> None:
            made.append(self)
            super().__init__(**params)

    yield Made
    for r in made:
        r.close()


@pytest.mark.req("SR-HW-39")
def test_enable_powers_the_drives_up_while_the_loop_goes_on_ticking(rig: type[Rig]) -> None:
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
    rig: type[Rig],
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
def test_an_estop_while_powering_up_wins_every_node_off_and_estop(rig: type[Rig]) -> None:
    r = rig()
    with r.emu.held():
        enable = r.op.send_command("Enable")
        r.ticks(5, settle=False)
        assert r.robot.effects.powering_up
        assert wait_until(
            lambda: r.arm.activating, 5.0, 0.001
        )  # its thread is waiting for the drives
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
    rig: type[Rig],
) -> None:
    r = rig()
    with r.emu.held():
        enable = r.op.send_command("Enable")
        r.ticks(3, settle=False)
        assert wait_until(lambda: r.arm.activating, 5.0, 0.001)
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
    rig: type[Rig],
) -> None:
    r = rig()
    with r.emu.held():
        r.op.send_command("Enable")
        r.tick(settle=False)
        assert r.robot.effects.powering_up
        assert wait_until(lambda: r.arm.activating, 5.0, 0.001)
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
def test_start_enabled_powers_up_then_runs(rig: type[Rig]) -> None:
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
    rig: type[Rig],
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
    rig: type[Rig], caplog: pytest.LogCaptureFixture
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
    rig: type[Rig], monkeypatch: pytest.MonkeyPatch, stop: str
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
    rig: type[Rig],
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
