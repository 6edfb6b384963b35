"""The supervisor thread in real time: a tick that hangs is caught from outside the loop.

No timing is asserted: the test waits (bounded) for the trip, then checks what it did.
"""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from occ.clock import RealClock
from occ.core.loader import load_config
from occ.core.robot import Robot, build_robot
from occ.core.safety import RobotState
from occ_testkit.testing import wait_until as wait_for

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.realtime


def _slave() -> Robot:
    """The shipped slave on the real clock, on free ports, without SCHED_FIFO."""
    cfg = load_config(ROOT / "configs" / "slave.yaml")
    ifaces = tuple(i.model_copy(update={"port": 0}) for i in cfg.interfaces)
    rt = cfg.robot.realtime.model_copy(update={"fifo_priority": None})
    cfg = cfg.model_copy(
        update={"interfaces": ifaces, "robot": cfg.robot.model_copy(update={"realtime": rt})}
    )
    return build_robot(cfg, clock=RealClock(spin_us=0))


@pytest.mark.req("SR-SUP-1")
def test_a_hung_tick_is_caught_by_the_supervisor_thread() -> None:
    robot = _slave()
    release = threading.Event()
    hung = threading.Event()
    update = robot.controller.update  # the set of the one controller (a plain Python class)
    ticks = 0

    def hanging_update(now: float, current):
        nonlocal ticks
        ticks += 1
        if ticks == 50:
            hung.set()
            release.wait(10.0)  # a blocked call inside the tick
        return update(now, current)

    robot.controller.update = hanging_update  # type: ignore[method-assign]
    robot.configure()
    robot.activate()
    loop = threading.Thread(target=robot.run, kwargs={"duration": 30.0})
    try:
        robot.start_in("enable", "run")  # in the first tick, as occd --start does
        loop.start()
        assert hung.wait(10.0)
        drv = robot.hardware.drivers[0]
        # while the loop is still stuck: the drives go to their safe state (the trip flag is
        # set just before the supervisor thread acts, so wait for the act itself)
        assert wait_for(lambda: drv.state.value == "fault")
        assert robot.supervisor.tripped and not release.is_set()
        assert "did not tick" in (drv.fault_reason or "")
        assert robot.state is RobotState.RUNNING  # the state machine belongs to the loop
        release.set()
        assert wait_for(lambda: robot.state is RobotState.FAULT)
        assert "supervisor" in robot.last_alert
    finally:
        release.set()
        robot.stop_loop()
        loop.join(10.0)
        robot.shutdown()


@pytest.mark.req("SR-SUP-1")
def test_a_loop_that_ends_on_purpose_is_not_taken_for_a_hung_one(monkeypatch) -> None:
    """The end of a run (the loop leaves SCHED_FIFO, unfreezes the collector, logs) can be
    slow on a loaded machine: once the loop has lost its priority, other processes may keep
    it off the CPU for longer than the supervisor's timeout. The supervisor (SCHED_FIFO, one
    above the loop) must not read that as a hung loop and fault a daemon that is shutting
    down (a CI run: the master beside two CPU hogs exited FAULT at the end of its soak)."""
    import occ.core.loop as loop_mod

    slow_end = threading.Event()
    real = loop_mod.apply_realtime

    def apply_realtime(priority, cpu):
        parts, restore = real(priority, cpu)

        def slow_restore() -> None:
            restore()
            slow_end.set()
            threading.Event().wait(0.15)  # kept off the CPU: many supervisor timeouts

        return parts, slow_restore

    monkeypatch.setattr(loop_mod, "apply_realtime", apply_realtime)
    robot = _slave()
    robot.configure()
    robot.activate()
    try:
        robot.start_in("enable", "run")
        robot.run(ticks=200)
        assert slow_end.is_set()
        assert not robot.supervisor.tripped, robot.supervisor.reason
        assert robot.state is RobotState.RUNNING, robot.last_alert
        assert all(d.state.value != "fault" for d in robot.hardware.drivers)
    finally:
        robot.shutdown()
