"""CANDriver against SimulatedDriveNode on python-can's in-process ``virtual`` bus."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator

import can
import pytest

from occ.drivers import DriverState, create_driver
from occ.drivers.can import MODE_DISABLED, COMMAND_FRAME, FEEDBACK_FRAME, CANDriver
from occ.drivers.can_sim import DriveAxis, SimulatedDriveNode
from occ.errors import DriverError
from occ.joint import Joint, JointLimits, PIDGains

_channels = itertools.count()
CPU = [10000.0, 200000.0]  # counts per rad, counts per metre


def make_joints(gains: PIDGains | None = None) -> list[Joint]:
    return [
        Joint("yaw", "revolute", JointLimits(-1.0, 1.0, 10.0, 20.0), gains=gains),
        Joint("insertion", "prismatic", JointLimits(0.0, 0.15, 1.0, 50.0), home=0.0, gains=gains),
    ]


def params(channel: str, **extra: object) -> dict:
    return {
        "interface": "virtual",
        "channel": channel,
        "joints": {
            "yaw": {"can_id": 0x101, "feedback_id": 0x181, "counts_per_unit": CPU[0]},
            "insertion": {"can_id": 0x102, "feedback_id": 0x182, "counts_per_unit": CPU[1]},
        },
        **extra,
    }


@pytest.fixture
def channel() -> str:
    return f"occ-test-{next(_channels)}"


@pytest.fixture
def node(channel: str) -> Iterator[SimulatedDriveNode]:
    axes = [DriveAxis(0x101, 0x181), DriveAxis(0x102, 0x182)]
    with SimulatedDriveNode(axes, channel=channel, tau=0.0) as n:
        yield n
    assert n.error is None


def test_round_trip_position_and_scaling(channel: str, node: SimulatedDriveNode) -> None:
    js = make_joints()
    drv = create_driver("can", "arm", js, params(channel))
    assert isinstance(drv, CANDriver)
    with drv:
        drv.configure()  # asks each drive where it is (a mode-0 command each)
        assert node.wait_feedback(2, timeout=2.0)
        drv.read(0.0)
        drv.activate()
        drv.write([0.0012345, 0.0001], 0.001)
        assert node.wait_feedback(4, timeout=2.0)
        # The drive saw counts = round(value * counts_per_unit).
        assert node.axes[0].target == 12.0 and node.axes[1].target == 20.0
        assert node.axes[0].mode == 1
        drv.read(0.002)
        assert js[0].position == pytest.approx(12 / CPU[0])
        assert js[1].position == pytest.approx(20 / CPU[1])
        assert js[0].measured and js[1].stamp == 0.002
        stats = drv.stats()
        assert stats["feedback_frames"] == 4 and stats["writes"] == 1
    assert drv.state is DriverState.SHUTDOWN
    # deactivate (from the context manager's shutdown) sent mode-0 frames.
    assert node.wait_commands(6, timeout=2.0)
    assert node.axes[0].mode == 0


def test_sequence_numbers_reach_the_drive(channel: str, node: SimulatedDriveNode) -> None:
    drv = CANDriver("arm", make_joints(), params(channel))
    drv.configure()
    assert node.wait_feedback(2, timeout=2.0)
    drv.read(0.0)
    drv.activate()
    for k in range(1, 6):
        drv.write([0.0, 0.0], k * 0.001)
    assert node.wait_commands(12, timeout=2.0)
    # the query at configure and five commands, numbered without a gap
    assert node.axes[0].commands == 6 and node.axes[0].lost_commands == 0
    drv.shutdown()


def test_feedback_timeout_faults(channel: str, node: SimulatedDriveNode) -> None:
    drv = CANDriver("arm", make_joints(), params(channel, feedback_timeout=0.01))
    drv.configure()
    assert node.wait_feedback(2, timeout=2.0)
    drv.read(0.0)
    drv.activate()
    drv.write([0.0, 0.0], 0.001)
    assert node.wait_feedback(4, timeout=2.0)
    drv.read(0.002)
    node.mute()
    drv.write([0.0, 0.0], 0.003)
    assert node.wait_commands(6, timeout=2.0)
    drv.read(0.010)  # 8 ms since last feedback: still fine
    with pytest.raises(DriverError, match=r"joint yaw: no feedback on id 0x181 for 13\.0 ms"):
        drv.read(0.015)
    assert drv.state is DriverState.FAULT
    drv.shutdown()


def test_effort_interface_sends_milli_units(channel: str, node: SimulatedDriveNode) -> None:
    js = make_joints(gains=PIDGains(kp=100.0))
    drv = CANDriver("arm", js, params(channel), command_interface="effort")
    drv.configure()
    assert node.wait_feedback(2, timeout=2.0)
    drv.read(0.0)
    drv.activate()
    drv.write([0.005, 0.0002], 0.001)  # kp * error = 0.5 N*m and 0.02 N
    assert node.wait_feedback(4, timeout=2.0)
    assert node.axes[0].mode == 2
    assert node.axes[0].effort == 500 and node.axes[1].effort == 20
    drv.read(0.002)
    assert js[0].effort == pytest.approx(0.5) and js[1].effort == pytest.approx(0.02)
    drv.shutdown()


def test_frame_layout_is_big_endian_and_foreign_frames_are_ignored(channel: str) -> None:
    assert COMMAND_FRAME.size == 8 and FEEDBACK_FRAME.size == 8
    assert COMMAND_FRAME.pack(-2, 1, 7, 50) == bytes([0xFF, 0xFF, 0xFF, 0xFE, 1, 7, 50, 0])
    peer = can.Bus(interface="virtual", channel=channel)
    js = make_joints()
    drv = CANDriver("arm", js, params(channel))
    try:
        drv.configure()
        peer.send(can.Message(arbitration_id=0x181, is_extended_id=False,
                              data=FEEDBACK_FRAME.pack(-5000, -10, 1234)))
        peer.send(can.Message(arbitration_id=0x181, is_extended_id=False, data=b"\x00"))
        peer.send(can.Message(arbitration_id=0x182, is_extended_id=False,
                              data=FEEDBACK_FRAME.pack(2000, 1, -1)))
        drv.read(0.0)
        assert js[0].position == pytest.approx(-0.5)
        assert js[0].velocity == pytest.approx(-10 * 1000 / CPU[0])
        assert js[0].effort == pytest.approx(1.234)
        assert js[1].position == pytest.approx(0.01)
        assert drv.stats()["ignored_frames"] == 1
    finally:
        drv.shutdown()
        peer.shutdown()


def test_bad_bus_and_params() -> None:
    drv = CANDriver("arm", make_joints(), params("x", interface="no_such_interface"))
    with pytest.raises(DriverError, match="cannot open bus"):
        drv.configure()
    assert drv.state is DriverState.FAULT
    drv.shutdown()
    with pytest.raises(ValueError, match="required"):
        CANDriver("arm", make_joints(), {"interface": "virtual"})
    bad = params("x")
    bad["joints"]["yaw"]["can_id"] = 0x800
    with pytest.raises(ValueError, match="11-bit"):
        CANDriver("arm", make_joints(), bad)


def test_command_saturates_instead_of_wrapping(channel: str, node: SimulatedDriveNode) -> None:
    js = [Joint("big", "prismatic", JointLimits(-1e9, 1e9, math.inf, math.inf))]
    p = {"interface": "virtual", "channel": channel,
         "joints": [{"can_id": 0x101, "feedback_id": 0x181, "counts_per_unit": 1e6}]}
    drv = CANDriver("big", js, p)
    drv.configure()
    drv.activate()
    drv.write([1e6], 0.001)
    assert node.wait_commands(2, timeout=2.0)
    assert node.axes[0].target == 2**31 - 1
    drv.shutdown()


def test_the_drive_stops_itself_without_heartbeat(channel: str, node: SimulatedDriveNode) -> None:
    js = make_joints()
    drv = CANDriver("arm", js, params(channel, heartbeat_ms=20, feedback_timeout=10.0))
    drv.configure()
    assert node.wait_feedback(2, timeout=2.0)
    drv.read(0.0)
    drv.activate()
    drv.write([0.1, 0.05], 0.001)
    assert node.wait_commands(4, timeout=2.0)
    assert node.axes[0].heartbeat_s == pytest.approx(0.020)  # told in every command frame
    sent = node.feedback_sent
    # the host goes silent: each axis stops itself and says so in a feedback frame
    assert node.wait_feedback(sent + 2, timeout=5.0)
    assert [a.heartbeat_trips for a in node.axes] == [1, 1]
    assert all(a.mode == MODE_DISABLED and a.heartbeat_lost for a in node.axes)
    with pytest.raises(DriverError, match="joint yaw: heartbeat lost: the drive stopped itself"):
        drv.read(0.5)
    assert drv.state is DriverState.FAULT
    # entering FAULT sent mode 0 (the acknowledgement): after a reset the drive obeys again
    drv.reset()
    drv.activate()
    n = node.commands_received
    drv.write([0.2, 0.05], 0.6)
    assert node.wait_commands(n + 2, timeout=2.0)
    assert not node.axes[0].heartbeat_lost and node.axes[0].mode == 1
    drv.shutdown()


def test_safe_stop_sends_mode_0_from_another_thread(channel: str, node: SimulatedDriveNode) -> None:
    import threading

    js = make_joints()
    drv = CANDriver("arm", js, params(channel, heartbeat_ms=0))
    drv.configure()
    assert node.wait_feedback(2, timeout=2.0)
    drv.read(0.0)
    drv.activate()
    drv.write([0.1, 0.05], 0.001)
    assert node.wait_commands(4, timeout=2.0)
    n = node.commands_received
    t = threading.Thread(target=drv.safe_stop, args=("supervisor",))
    t.start()
    t.join(5.0)
    assert node.wait_commands(n + 2, timeout=2.0)
    assert all(a.mode == MODE_DISABLED for a in node.axes)
    assert drv.state is DriverState.FAULT and drv.fault_reason == "safe stop: supervisor"
    drv.shutdown()


def test_a_joint_is_unmeasured_until_its_drive_answers(channel: str) -> None:
    """No feedback yet: the joint is not measured (not a made-up 0), so a robot cannot hold
    it at a position the drive never reported."""
    js = make_joints()
    drv = CANDriver("arm", js, params(channel))
    try:
        drv.configure()  # nobody on the bus answers the query
        drv.read(0.0)
        assert not js[0].measured and not js[1].measured
        peer = can.Bus(interface="virtual", channel=channel)
        try:
            peer.send(can.Message(arbitration_id=0x181, is_extended_id=False,
                                  data=FEEDBACK_FRAME.pack(3000, 0, 0)))
            drv.read(0.001)
        finally:
            peer.shutdown()
        assert js[0].measured and js[0].position == pytest.approx(0.3)
        assert not js[1].measured
    finally:
        drv.shutdown()
