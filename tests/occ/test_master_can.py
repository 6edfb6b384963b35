"""A CAN haptic master: the master's joints come from CAN drives (python-can `virtual` bus with a
simulated drive node), and the hand-moved handle position streams to the slave as POSITION."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest

import igtl
from occ.drivers.can_sim import DriveAxis, SimulatedDriveNode
from occ.core.loader import load_config
from occ.core.robot import build_robot
from occ.core.safety import RobotState
from occ_testkit.testing import SimPeer, inproc_config
from occ_testkit.testing import wait_until as _wait

ROOT = Path(__file__).resolve().parents[2]
COUNTS_PER_M = 1_000_000  # 1 count = 1 um


def _can_driver(cfg: Any, channel: str, feedback_timeout: float) -> Any:
    """The master's driver made the CAN one, in effort mode, on ``channel`` of python-can's
    virtual bus: joints x, y, z on command ids 0x100-0x102, feedback 0x180-0x182."""
    joints = {
        name: {"can_id": 0x100 + i, "feedback_id": 0x180 + i, "counts_per_unit": COUNTS_PER_M}
        for i, name in enumerate(("x", "y", "z"))
    }
    return cfg.robot.drivers[0].model_copy(
        update={
            "plugin": "can",
            "params": {
                "interface": "virtual",
                "channel": channel,
                "joints": joints,
                "feedback_timeout": feedback_timeout,
                "command_interface": "effort",
            },
        }
    )


@pytest.mark.realtime
def test_can_master_streams_hand_motion() -> None:
    channel = f"occ-test-{time.monotonic_ns()}"
    cfg = load_config(ROOT / "configs" / "master.yaml")
    driver = _can_driver(cfg, channel, feedback_timeout=0.05)
    robot_cfg = cfg.robot.model_copy(
        update={
            "drivers": (driver,),
            "realtime": cfg.robot.realtime.model_copy(update={"fifo_priority": None}),
        }
    )
    cfg = cfg.model_copy(update={"robot": robot_cfg}).with_params(input="driver")
    axes = [
        DriveAxis(0x100, 0x180, position=0.0),
        DriveAxis(0x101, 0x181, position=50_000.0),
        DriveAxis(0x102, 0x182, position=20_000.0),
    ]
    # the stream goes to an in-process slave: what it receives is what the wire would carry
    cfg = inproc_config(cfg)
    with SimulatedDriveNode(axes, channel=channel, tau=0.0, feedback_period=0.001):
        robot = build_robot(cfg)
        slave = SimPeer(cfg.interface("slave").channel or "")
        sent: list[igtl.Message] = slave.received
        try:
            robot.configure()
            # the interfaces only: this test is about the CAN input, and a supervisor thread
            # could trip on a loaded machine
            robot.interfaces.start()
            robot.start_in("enable", "run")  # in the first tick, as occd --start does
            robot.loop.run_in_thread(duration=3.0)
            assert _wait(lambda: len(sent) > 20, 2.0)
            # the operator pushes the handle 12 mm along x (the drive reports it), at a hand's
            # speed: a 12 mm teleport in one period is a feedback jump (the driver faults)
            for step in range(1, 61):
                axes[0].position = axes[0].target = 200.0 * step
                time.sleep(0.001)
            assert _wait(
                lambda: (
                    abs(
                        sent[-1].position[0]
                        - robot.controller.controllers[0].origin[0] * 1e3
                        - 12.0
                    )
                    < 0.05
                ),
                2.0,
            ), sent[-1]
            assert robot.state is RobotState.RUNNING
        finally:
            robot.loop.stop()
            robot.loop.join(5.0)
            robot.shutdown()
            slave.close()
    assert robot.hardware.drivers[0].stats()["errors"] == 0


def test_no_enable_before_every_joint_is_measured() -> None:
    """Drives that never answered leave their joints unmeasured: Enable is refused with the
    joints named (the robot would otherwise hold them at a position nobody reported), and
    allowed once they have answered."""
    from occ.clock import SimClock
    from occ.errors import StateError

    channel = f"occ-test-{time.monotonic_ns()}"
    cfg = load_config(ROOT / "configs" / "master.yaml")
    driver = _can_driver(cfg, channel, feedback_timeout=10.0)
    cfg = inproc_config(
        cfg.model_copy(update={"robot": cfg.robot.model_copy(update={"drivers": (driver,)})})
    )
    robot = build_robot(cfg, clock=SimClock())
    try:
        robot.configure()  # nothing on the bus answers
        with pytest.raises(
            StateError, match=r"no measurement yet from driver hand joints \['x', 'y', 'z'\]"
        ):
            robot.state_machine.request("enable", "test")
        assert robot.state is RobotState.READY
        axes = [
            DriveAxis(0x100 + i, 0x180 + i, position=p)
            for i, p in enumerate((0.0, 50_000.0, 20_000.0))
        ]
        with SimulatedDriveNode(axes, channel=channel, tau=0.0, feedback_period=0.001) as node:
            assert node.wait_feedback(3, timeout=2.0)
            robot.tick(robot.clock.now(), 0)
            robot.state_machine.request("enable", "test")
            assert robot.state is RobotState.ENABLED
            # held where the drives are, not at a default
            assert robot.data.hold_setpoint == pytest.approx([0.0, 0.05, 0.02])
            robot.state_machine.request("disable", "test")
    finally:
        robot.shutdown()


def test_can_haptic_master_gets_the_fixture_force_on_its_effort_interface() -> None:
    """The CAN haptic master (drives in effort mode on python-can's virtual bus, a simulated
    drive node): the fixture force computed each tick goes out as effort frames (mode 2,
    mN), zero while only ENABLED."""
    from occ.drivers.can import MODE_EFFORT
    from occ_testkit.testing import SimRobot, SlaveTipFeed

    channel = f"occ-test-{time.monotonic_ns()}"
    cfg = load_config(ROOT / "configs" / "master.yaml")
    driver = _can_driver(cfg, channel, feedback_timeout=10.0)
    cfg = cfg.model_copy(update={"robot": cfg.robot.model_copy(update={"drivers": (driver,)})})
    axes = [
        DriveAxis(0x100 + i, 0x180 + i, position=p) for i, p in enumerate((0.0, 50_000.0, 20_000.0))
    ]
    box: dict[str, SimRobot] = {}
    # the node on the simulated clock: its heartbeat is judged in the test's time
    node = SimulatedDriveNode(
        axes,
        channel=channel,
        tau=0.0,
        effort_gain=0.0,
        clock=lambda: box["sim"].clock.now() if "sim" in box else 0.0,
    )
    with node:
        sim = SimRobot(cfg)
        box["sim"] = sim
        try:
            drv = sim.robot.hardware.drivers[0]
            op = sim.peer("operator", address=("127.0.0.1", 41000))

            def settle() -> None:  # every frame the driver sent so far handled by the node
                assert node.wait_commands(3 + 3 * drv.stats()["writes"], timeout=5.0)

            assert node.wait_feedback(3, timeout=5.0)
            sim.step(1)
            feed = SlaveTipFeed(sim)  # the slave's tip: 0.1 x the handle (patient frame)
            op.send_command("Enable")
            feed.step(1)
            assert sim.robot.state is RobotState.ENABLED
            handle = [v * 1e3 for v in sim.robot.frame.tip_position(sim.robot.data.q)]
            # 4 mm of the handle to the tool's +x, 10 mm of the handle in radius
            centre = feed.patient((handle[0] + 4.0, handle[1], handle[2]))
            op.send(
                igtl.VirtualFixtureMessage(
                    hardness=0.5,
                    spheres=((*centre, 1.0),),
                    device_name="VF",
                    header_version=2,
                    metadata={"kind": "forbidden"},
                )
            )
            feed.step(5)
            settle()
            assert [a.mode for a in axes] == [MODE_EFFORT] * 3 and [a.effort for a in axes] == [
                0,
                0,
                0,
            ]
            op.send_command("Run")
            feed.step(21)  # the force fades in within tip_fade_ms (20 ms)
            settle()
            assert sim.robot.state is RobotState.RUNNING
            # 6 mm deep at 0.5 N/mm: -3 N along x, as -3000 mN
            assert axes[0].effort == -3000 and axes[1].effort == 0 and axes[2].effort == 0
            assert drv.stats()["errors"] == 0
        finally:
            sim.close()
