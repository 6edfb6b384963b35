"""CANDriver against SimulatedDriveNode on python-can's in-process ``virtual`` bus."""

from __future__ import annotations

import contextlib
import itertools
import math
import sys
from collections.abc import Iterator

import can
import pytest
from can.interfaces.virtual import VirtualBus

from occ.drivers import DriverState, create_driver
from occ.drivers.can import (
    COMMAND_FRAME,
    FEEDBACK_FRAME,
    HEARTBEAT_LOST,
    MAX_FRAMES_PER_JOINT,
    MODE_DISABLED,
    CANDriver,
    round_saturated,
)
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


def settle(node: SimulatedDriveNode, drv: CANDriver) -> None:
    """Every frame the driver sent so far received and answered by ``node`` (answers only,
    none muted): its answers are then in the driver's receive queue (the virtual bus delivers
    before ``send`` returns)."""
    sent = drv.stats()["command_frames"]
    assert node.wait_commands(sent, timeout=2.0) and node.wait_feedback(sent, timeout=2.0)


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
        drv.read(0.0)  # reads the answers, polls again (mode 0: not ACTIVE)
        drv.activate()
        drv.write([0.0012345, 0.0001], 0.001)
        settle(node, drv)
        # The drive saw counts = round(value * counts_per_unit).
        assert node.axes[0].target == 12.0 and node.axes[1].target == 20.0
        assert node.axes[0].mode == 1
        drv.read(0.002)
        assert js[0].position == pytest.approx(12 / CPU[0])
        assert js[1].position == pytest.approx(20 / CPU[1])
        assert js[0].measured and js[1].stamp == 0.002
        stats = drv.stats()
        # configure's query, the poll of the first read, the command: each answered once
        assert stats["feedback_frames"] == 6 and stats["writes"] == 1
        assert stats["command_frames"] == 6 and stats["polls"] == 2
    assert drv.state is DriverState.SHUTDOWN
    # deactivate (from the context manager's shutdown) sent mode-0 frames.
    assert node.wait_commands(8, timeout=2.0)
    assert node.axes[0].mode == 0


def test_sequence_numbers_reach_the_drive(channel: str, node: SimulatedDriveNode) -> None:
    drv = CANDriver("arm", make_joints(), params(channel))
    drv.configure()
    assert node.wait_feedback(2, timeout=2.0)
    drv.read(0.0)
    drv.activate()
    for k in range(1, 6):
        drv.write([0.0, 0.0], k * 0.001)
    assert node.wait_commands(14, timeout=2.0)
    # the query at configure, the poll of the read and five commands, numbered without a gap
    assert node.axes[0].commands == 7 and node.axes[0].lost_commands == 0
    drv.shutdown()


def test_feedback_timeout_faults(channel: str, node: SimulatedDriveNode) -> None:
    drv = CANDriver("arm", make_joints(), params(channel, feedback_timeout=0.01))
    drv.configure()
    assert node.wait_feedback(2, timeout=2.0)
    drv.read(0.0)
    drv.activate()
    drv.write([0.0, 0.0], 0.001)
    settle(node, drv)
    drv.read(0.002)  # answers the command sent at 0.001
    node.mute()
    drv.write([0.0, 0.0], 0.003)
    assert node.wait_commands(drv.stats()["command_frames"], timeout=2.0)
    drv.read(0.010)  # the command of 3 ms unanswered for 7 ms: still fine
    with pytest.raises(
        DriverError,
        match=r"joint yaw: no feedback on id 0x181 for 12\.0 ms: "
        r"feedback age 12\.0 ms > feedback_timeout 10\.0 ms "
        r"\(1 command unanswered\)",
    ):
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
        peer.send(
            can.Message(
                arbitration_id=0x181,
                is_extended_id=False,
                data=FEEDBACK_FRAME.pack(-5000, -10, 1234),
            )
        )
        peer.send(can.Message(arbitration_id=0x181, is_extended_id=False, data=b"\x00"))
        peer.send(
            can.Message(
                arbitration_id=0x182, is_extended_id=False, data=FEEDBACK_FRAME.pack(2000, 1, -1)
            )
        )
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
    drv.reset()  # nothing was opened, nothing to tell: ready to try again
    assert drv.state is DriverState.UNCONFIGURED
    with pytest.raises(DriverError, match="cannot open bus"):
        drv.configure()
    drv.shutdown()
    with pytest.raises(ValueError, match=r"^can driver: params\['joints'\] is required"):
        CANDriver("arm", make_joints(), {"interface": "virtual"})
    bad = params("x")
    bad["joints"]["yaw"]["can_id"] = 0x800
    with pytest.raises(ValueError, match="11-bit"):
        CANDriver("arm", make_joints(), bad)


def test_command_saturates_instead_of_wrapping(channel: str, node: SimulatedDriveNode) -> None:
    js = [Joint("big", "prismatic", JointLimits(-1e9, 1e9, math.inf, math.inf))]
    p = {
        "interface": "virtual",
        "channel": channel,
        "joints": [{"can_id": 0x101, "feedback_id": 0x181, "counts_per_unit": 1e6}],
    }
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
    with pytest.raises(
        DriverError,
        match=r"joint yaw: heartbeat lost: the drive stopped itself "
        r"\(no command for 20 ms\)",
    ):
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
            peer.send(
                can.Message(
                    arbitration_id=0x181, is_extended_id=False, data=FEEDBACK_FRAME.pack(3000, 0, 0)
                )
            )
            drv.read(0.001)
        finally:
            peer.shutdown()
        assert js[0].measured and js[0].position == pytest.approx(0.3)
        assert not js[1].measured
    finally:
        drv.shutdown()


# ---------------------------------------------------------------- bus errors (SR-HW-12, -13)
def error_frame(error_class: int) -> can.Message:
    return can.Message(arbitration_id=error_class, is_error_frame=True, dlc=8)


def active_driver(channel: str, node: SimulatedDriveNode, **extra: object) -> CANDriver:
    """Configured, measured and ACTIVE, with one command answered."""
    # the scripted drive answers at a position of its own, not the one commanded: this is
    # about the age of its answers, not about following (the base's following error)
    extra.setdefault("following_error", None)
    drv = CANDriver("arm", make_joints(), params(channel, **extra))
    drv.configure()
    assert node.wait_feedback(2, timeout=2.0)
    drv.read(0.0)
    drv.activate()
    drv.write([0.0, 0.0], 0.001)
    settle(node, drv)
    return drv


def test_error_frames_up_to_the_limit_are_counted_one_more_faults(
    channel: str, node: SimulatedDriveNode
) -> None:
    drv = active_driver(channel, node, error_frames=3, feedback_timeout=10.0)
    peer = can.Bus(interface="virtual", channel=channel)
    try:
        for k in range(3):
            peer.send(error_frame(0x04))  # controller problem: noise, not bus-off
            drv.read(0.010 + k * 0.010)
        assert drv.state is DriverState.ACTIVE and drv.stats()["error_frames"] == 3
        peer.send(error_frame(0x04))
        with pytest.raises(
            DriverError,
            match=r"4 error frames in 100 ms on occ-test-\d+ "
            r"\(limit 3; last 0x4\)",
        ):
            drv.read(0.040)
        assert drv.state is DriverState.FAULT and drv.stats()["error_frames"] == 4
        # entering FAULT from ACTIVE told every drive to brake
        settle(node, drv)
        assert [a.mode for a in node.axes] == [MODE_DISABLED, MODE_DISABLED]
    finally:
        peer.shutdown()
        drv.shutdown()


def test_error_frames_older_than_100_ms_leave_the_window(
    channel: str, node: SimulatedDriveNode
) -> None:
    """A slow trickle of error frames (one every 110 ms) never faults a limit of 1; two
    within 100 ms do."""
    drv = active_driver(channel, node, error_frames=1, feedback_timeout=10.0)
    peer = can.Bus(interface="virtual", channel=channel)
    try:
        for k in range(1, 8):
            peer.send(error_frame(0x04))
            drv.read(k * 0.110)
        assert drv.state is DriverState.ACTIVE and drv.stats()["error_frames"] == 7
        peer.send(error_frame(0x04))
        with pytest.raises(DriverError, match=r"2 error frames in 100 ms"):
            drv.read(7 * 0.110 + 0.090)
    finally:
        peer.shutdown()
        drv.shutdown()


def test_zero_error_frames_tolerated_faults_on_the_first(
    channel: str, node: SimulatedDriveNode
) -> None:
    drv = active_driver(channel, node, error_frames=0, feedback_timeout=10.0)
    node.send_error_frame(0x04)
    with pytest.raises(DriverError, match=r"1 error frames in 100 ms .*limit 0"):
        drv.read(0.002)
    assert drv.state is DriverState.FAULT
    drv.shutdown()


def test_bus_off_faults_on_the_first_frame_whatever_the_limit(
    channel: str, node: SimulatedDriveNode
) -> None:
    drv = active_driver(channel, node, error_frames=1000, feedback_timeout=10.0)
    node.send_error_frame(0x40 | 0x04)  # bus-off among other classes
    with pytest.raises(
        DriverError,
        match=r"bus-off on occ-test-\d+: the controller left the "
        r"bus \(error frame 0x44\)",
    ):
        drv.read(0.002)
    assert drv.state is DriverState.FAULT and drv.stats()["error_frames"] == 1
    settle(node, drv)
    assert [a.mode for a in node.axes] == [MODE_DISABLED, MODE_DISABLED]
    drv.shutdown()


def test_reset_forgets_the_error_frames_before_the_fault(
    channel: str, node: SimulatedDriveNode
) -> None:
    drv = active_driver(channel, node, error_frames=1, feedback_timeout=10.0)
    node.send_error_frame(0x04)
    node.send_error_frame(0x04)
    with pytest.raises(DriverError, match="2 error frames"):
        drv.read(0.002)
    drv.reset()
    drv.read(0.003)
    drv.activate()
    node.send_error_frame(0x04)  # one, within 100 ms of the two before the reset
    drv.read(0.004)
    assert drv.state is DriverState.ACTIVE and drv.stats()["error_frames"] == 3
    drv.shutdown()


# ---------------------------------------------------------------- configuration refused
@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda p: p["joints"]["yaw"].update(feedback_id=0x182), "feedback_id values must be"),
        (lambda p: p["joints"]["yaw"].update(can_id=0x102), "can_id values must be distinct"),
        (lambda p: p["joints"]["yaw"].update(feedback_id=-1), r"joint 'yaw': id -0x1 not 11-bit"),
        (lambda p: p["joints"]["insertion"].update(can_id=0x800), r"'insertion': id 0x800 not 11"),
        (lambda p: p["joints"]["yaw"].pop("can_id"), r"joint 'yaw': bad entry"),
        (lambda p: p["joints"]["yaw"].update(feedback_id="x"), r"joint 'yaw': bad entry"),
        (lambda p: p["joints"]["yaw"].update(counts_per_unit=None), r"joint 'yaw': bad entry"),
        (lambda p: p["joints"]["yaw"].update(counts_per_unit=0.0), "counts_per_unit must be != 0"),
        (lambda p: p["joints"]["yaw"].update(counts_per_unit=math.inf), "counts_per_unit must"),
        (lambda p: p["joints"]["yaw"].update(counts_per_unit=math.nan), "counts_per_unit must"),
        (lambda p: p["joints"].pop("yaw"), r"joints params missing \['yaw'\], unknown set\(\)"),
        (lambda p: p["joints"].update(roll={}), r"missing \[\], unknown \{'roll'\}"),
        (lambda p: p.update(joints=[p["joints"]["yaw"]]), "one joints entry per joint"),
        (lambda p: p.update(feedback_timeout=0.0), "feedback_timeout must be > 0"),
        (lambda p: p.update(feedback_timeout=math.nan), "feedback_timeout must be > 0"),
        (lambda p: p.update(error_frames=-1), "error_frames must be >= 0"),
        (lambda p: p.update(lost_after=0.005), "lost_after must be >= feedback_timeout"),
        (lambda p: p.update(poll_period=0.01), "poll_period must be >= 0 and < feedback_timeout"),
        (lambda p: p.update(poll_period=-0.001), "poll_period must be >= 0"),
        (lambda p: p.update(heartbeat_ms=256), "heartbeat_ms must be <= 255, got 256"),
    ],
)
def test_a_bad_joint_table_is_refused_with_the_reason(change, message: str) -> None:
    p = params("unused")
    change(p)
    with pytest.raises(ValueError, match=message) as refused:
        CANDriver("arm", make_joints(), p)
    assert str(refused.value).startswith("can driver")  # whose configuration it is


def test_the_joint_table_as_a_list_in_joint_order(channel: str) -> None:
    """The list form: entry k is joint k; ids 0 and 0x7FF are 11-bit; counts_per_unit
    defaults to 1 (one count per radian or metre); heartbeat 255 ms fits in its byte."""
    p = params(channel, heartbeat_ms=255)
    p["joints"] = [{"can_id": 0x7FF, "feedback_id": 0x000}, {"can_id": 0x000, "feedback_id": 0x7FF}]
    js = make_joints()
    peer = can.Bus(interface="virtual", channel=channel)
    drv = CANDriver("arm", js, p)
    try:
        drv.configure()
        sent = [peer.recv(timeout=1.0) for _ in range(2)]
        assert [m.arbitration_id for m in sent] == [0x7FF, 0x000]
        assert [m.is_extended_id for m in sent] == [False, False]
        assert [COMMAND_FRAME.unpack(m.data) for m in sent] == [(0, MODE_DISABLED, 0, 255)] * 2
        peer.send(
            can.Message(
                arbitration_id=0x7FF, is_extended_id=False, data=FEEDBACK_FRAME.pack(0, 0, 0)
            )
        )
        peer.send(
            can.Message(
                arbitration_id=0x000, is_extended_id=False, data=FEEDBACK_FRAME.pack(-1, 0, 0)
            )
        )
        drv.read(0.0)  # (one count is a metre here: the insertion's range holds only 0)
        assert js[0].position == -1.0 and js[1].position == 0.0
    finally:
        drv.shutdown()
        peer.shutdown()


# ---------------------------------------------------------------- what the drives are told
def drain(bus: can.BusABC) -> list[can.Message]:
    out = []
    while (msg := bus.recv(timeout=0.0)) is not None:
        out.append(msg)
    return out


def test_stop_frames_are_mode_0_with_value_0_to_each_drive(channel: str) -> None:
    """Deactivate, a fault and the supervisor's safe stop all send each drive one classic
    8-byte frame on its own command id: value 0, mode 0, its next sequence number, the
    heartbeat byte."""
    spy = can.Bus(interface="virtual", channel=channel)
    drv = CANDriver("arm", make_joints(), params(channel, heartbeat_ms=40, feedback_timeout=10.0))
    try:
        drv.configure()
        spy.send(
            can.Message(
                arbitration_id=0x181, is_extended_id=False, data=FEEDBACK_FRAME.pack(0, 0, 0)
            )
        )
        spy.send(
            can.Message(
                arbitration_id=0x182, is_extended_id=False, data=FEEDBACK_FRAME.pack(0, 0, 0)
            )
        )
        drv.read(0.0)
        drv.activate()
        drv.write([0.001, 0.001], 0.001)
        drv.deactivate()
        frames = drain(spy)
        assert [(m.arbitration_id, m.dlc, m.is_extended_id) for m in frames] == [
            (0x101, 8, False),
            (0x102, 8, False),
        ] * 4
        told = [COMMAND_FRAME.unpack(m.data) for m in frames]
        # configure's query, the read's poll, the command, the stop
        assert told == [
            (0, MODE_DISABLED, 0, 40),
            (0, MODE_DISABLED, 0, 40),
            (0, MODE_DISABLED, 1, 40),
            (0, MODE_DISABLED, 1, 40),
            (10, 1, 2, 40),
            (200, 1, 2, 40),
            (0, MODE_DISABLED, 3, 40),
            (0, MODE_DISABLED, 3, 40),
        ]
        drv.activate()
        drv.write([0.001, 0.002], 0.002)
        drain(spy)
        drv.safe_stop("test")
        frames = drain(spy)
        assert [(m.arbitration_id, m.dlc) for m in frames] == [(0x101, 8), (0x102, 8)]
        assert [COMMAND_FRAME.unpack(m.data)[:2] for m in frames] == [(0, MODE_DISABLED)] * 2
        assert [COMMAND_FRAME.unpack(m.data)[3] for m in frames] == [40, 40]
    finally:
        drv.shutdown()
        spy.shutdown()


def test_a_jammed_bus_faults_the_write_instead_of_blocking_the_loop(
    channel: str, caplog: pytest.LogCaptureFixture
) -> None:
    """A receiver whose queue is full (a bus on which nothing gets through): a command send
    gives up after send_timeout and the driver faults; the supervisor's safe stop gives up
    too and still latches FAULT. Neither blocks its thread."""
    import threading

    feeder = can.Bus(interface="virtual", channel=channel)
    drv = CANDriver(
        "arm", make_joints(), params(channel, send_timeout=0.001, feedback_timeout=10.0)
    )

    def ready(now: float) -> None:
        for fid in (0x181, 0x182):
            feeder.send(
                can.Message(
                    arbitration_id=fid, is_extended_id=False, data=FEEDBACK_FRAME.pack(0, 0, 0)
                )
            )
        drv.read(now)
        drv.activate()

    def in_thread(call) -> bool:  # True when the call returned within 5 s
        t = threading.Thread(target=call, daemon=True)
        t.start()
        t.join(5.0)
        return not t.is_alive()

    failures: list[str] = []

    def write() -> None:
        try:
            drv.write([0.0, 0.0], 0.001)  # the first frame fits the jammed queue, not the second
        except DriverError as err:
            failures.append(str(err))

    try:
        drv.configure()
        ready(0.0)
        jam = can.Bus(interface="virtual", channel=channel, rx_queue_size=1)
        before = drv.stats()["command_frames"]
        returned = in_thread(write)
        drain(jam)  # unblocks a send that would wait for ever
        assert returned
        assert failures and "send to id 0x102 failed" in failures[0]
        assert drv.stats()["command_frames"] == before + 1  # the frame not sent is not counted
        assert drv.state is DriverState.FAULT
        jam.shutdown()
        drv.reset()
        ready(0.002)
        jam = can.Bus(interface="virtual", channel=channel, rx_queue_size=1)
        with caplog.at_level("ERROR", logger="occ.drivers.can"):
            returned = in_thread(lambda: drv.safe_stop("supervisor"))
        drain(jam)
        assert returned
        # the frame that could not go out is in the log, with the reason
        lost = [r for r in caplog.records if r.name == "occ.drivers.can"]
        assert [r.getMessage() for r in lost] == ["can driver arm: safe stop frame not sent"]
        assert lost[0].exc_info is not None
        assert drv.state is DriverState.FAULT and drv.fault_reason == "safe stop: supervisor"
        jam.shutdown()
    finally:
        drv.shutdown()
        feeder.shutdown()


# ---------------------------------------------------------------- frames that are not feedback
def test_foreign_remote_and_short_frames_are_counted_and_change_nothing(channel: str) -> None:
    js = make_joints()
    drv = CANDriver("arm", js, params(channel, feedback_timeout=10.0))
    peer = can.Bus(interface="virtual", channel=channel)
    try:
        drv.configure()
        for fid, pos in ((0x181, 100), (0x182, 200)):
            peer.send(
                can.Message(
                    arbitration_id=fid, is_extended_id=False, data=FEEDBACK_FRAME.pack(pos, 0, 0)
                )
            )
        drv.read(0.0)
        # another node's full 8-byte frame, a remote request on a feedback id, a short frame
        peer.send(
            can.Message(
                arbitration_id=0x183, is_extended_id=False, data=FEEDBACK_FRAME.pack(999, 9, 9)
            )
        )
        peer.send(
            can.Message(arbitration_id=0x181, is_extended_id=False, is_remote_frame=True, dlc=8)
        )
        peer.send(can.Message(arbitration_id=0x182, is_extended_id=False, data=b"\x00" * 7))
        drv.read(0.001)
        assert drv.state is DriverState.INACTIVE
        assert drv.stats()["ignored_frames"] == 3 and drv.stats()["feedback_frames"] == 2
        assert [j.position for j in js] == [100 / CPU[0], 200 / CPU[1]]
    finally:
        drv.shutdown()
        peer.shutdown()


def test_feedback_exactly_feedback_timeout_old_is_still_on_time(channel: str) -> None:
    """The deadline is 'older than feedback_timeout' (times exact in binary)."""
    peer = can.Bus(interface="virtual", channel=channel)
    drv = CANDriver("arm", make_joints(), params(channel, feedback_timeout=0.25))
    try:
        drv.configure()
        for fid in (0x181, 0x182):
            peer.send(
                can.Message(
                    arbitration_id=fid, is_extended_id=False, data=FEEDBACK_FRAME.pack(0, 0, 0)
                )
            )
        drv.read(0.5)
        drv.read(0.75)
        assert drv.state is DriverState.INACTIVE
        with pytest.raises(
            DriverError,
            match=r"joint yaw: no feedback on id 0x181 for 250\.1 ms: "
            r"feedback age 250\.1 ms > feedback_timeout "
            r"250\.0 ms \(1 command unanswered\)",
        ):
            drv.read(0.7501)
    finally:
        drv.shutdown()
        peer.shutdown()


def test_error_frames_exactly_100_ms_apart_share_the_window(
    channel: str, node: SimulatedDriveNode
) -> None:
    drv = active_driver(channel, node, error_frames=1, feedback_timeout=10.0)
    node.send_error_frame(0x04)
    drv.read(0.1)
    node.send_error_frame(0x04)
    with pytest.raises(DriverError, match="2 error frames in 100 ms"):
        drv.read(0.2)  # 0.2 - 0.1 == 0.1 exactly
    drv.shutdown()


def test_a_heartbeat_flag_while_not_active_reads_as_no_effort(channel: str) -> None:
    """A drive still flagging its heartbeat stop answers the mode-0 frames of a driver that is
    not ACTIVE (it was just told to brake): no fault, its position read, its effort 0."""
    js = make_joints()
    peer = can.Bus(interface="virtual", channel=channel)
    drv = CANDriver("arm", js, params(channel, feedback_timeout=10.0))
    try:
        drv.configure()
        peer.send(
            can.Message(
                arbitration_id=0x181,
                is_extended_id=False,
                data=FEEDBACK_FRAME.pack(500, 0, HEARTBEAT_LOST),
            )
        )
        peer.send(
            can.Message(
                arbitration_id=0x182, is_extended_id=False, data=FEEDBACK_FRAME.pack(0, 0, 0)
            )
        )
        drv.read(0.0)
        assert drv.state is DriverState.INACTIVE
        assert js[0].position == 500 / CPU[0] and js[0].effort == 0.0
    finally:
        drv.shutdown()
        peer.shutdown()


def test_shutdown_closes_the_bus(channel: str) -> None:
    drv = CANDriver("arm", make_joints(), params(channel))
    drv.configure()
    bus = drv._bus
    assert bus is not None
    drv.shutdown()
    with pytest.raises(can.CanOperationError):  # a closed python-can bus refuses to send
        bus.send(can.Message(arbitration_id=0x101, is_extended_id=False, data=bytes(8)))


# ---------------------------------------------------------------- SocketCAN's kernel settings
class KernelSocket:
    """Records the options set on a SocketCAN raw socket (the machines that run the tests
    have no AF_CAN: python-can's socketcan bus cannot be opened there)."""

    def __init__(self, refuse: bool = False) -> None:
        self.options: list[tuple[int, int, bytes]] = []
        self.refuse = refuse

    def setsockopt(self, level: int, optname: int, value: bytes, /) -> None:
        if self.refuse:
            raise OSError(92, "Protocol not available")
        self.options.append((level, optname, bytes(value)))


class SocketBus(VirtualBus):
    """A virtual bus with a raw socket beside it, standing in for python-can's socketcan bus;
    set_filters records what the kernel would be told instead of filtering in software."""

    def __init__(self, sock: KernelSocket, channel: str) -> None:
        super().__init__(channel=channel)
        self.socket = sock
        self.kernel_filters: list | None = None

    def set_filters(self, filters=None) -> None:  # noqa: ANN001 - python-can's signature
        self.kernel_filters = filters
        super().set_filters(None)  # the kernel filters, python-can passes everything on


@pytest.mark.parametrize("refuse", [False, True])
def test_socketcan_gets_the_feedback_ids_and_every_error_class(
    channel: str,
    node: SimulatedDriveNode,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
    refuse: bool,
) -> None:
    """On SocketCAN the kernel filters the feedback identifiers (11-bit, exact) and lets
    error frames of every class through (CAN_RAW_ERR_FILTER): without it no bus-off ever
    reaches the driver. A kernel that refuses the option leaves a warning, not a failure."""
    sock = KernelSocket(refuse)
    opened: list[SocketBus] = []

    def bus(**args: object) -> SocketBus:
        assert args["interface"] == "socketcan" and args["bitrate"] == 1_000_000
        opened.append(SocketBus(sock, channel=channel))
        return opened[0]

    monkeypatch.setattr(can, "Bus", bus)
    drv = CANDriver("arm", make_joints(), params(channel, interface="socketcan"))
    with caplog.at_level("WARNING", logger="occ.drivers.can"):
        drv.configure()
    try:
        assert opened[0].kernel_filters == [
            {"can_id": 0x181, "can_mask": 0x7FF, "extended": False},
            {"can_id": 0x182, "can_mask": 0x7FF, "extended": False},
        ]
        if refuse:
            assert sock.options == []
            assert [r.getMessage() for r in caplog.records] == [
                "can driver arm: error frames not enabled: [Errno 92] Protocol not available"
            ]
        else:
            assert sock.options == [(101, 2, (0x1FFFFFFF).to_bytes(4, sys.byteorder))]
            assert caplog.text == ""
        assert node.wait_feedback(2, timeout=2.0)
        drv.read(0.0)
        assert drv.stats()["feedback_frames"] == 2
    finally:
        drv.shutdown()


def test_other_interfaces_keep_their_error_frames(
    channel: str, node: SimulatedDriveNode, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Only SocketCAN filters in the kernel: on any other interface (even one whose bus has
    a socket) the driver sets no python-can filters, which would drop error frames."""
    opened: list[SocketBus] = []

    def bus(**args: object) -> SocketBus:
        opened.append(SocketBus(KernelSocket(), channel=channel))
        return opened[0]

    monkeypatch.setattr(can, "Bus", bus)
    drv = active_driver(channel, node, feedback_timeout=10.0)
    assert opened[0].kernel_filters is None and opened[0].socket.options == []
    node.send_error_frame(0x40)
    with pytest.raises(DriverError, match="bus-off"):
        drv.read(0.002)
    drv.shutdown()


# ---------------------------------------------------------------- a drive mounted reversed
def test_a_reversed_drive_is_pushed_toward_the_setpoint_in_effort_mode(channel: str) -> None:
    """A negative counts_per_unit (accepted: only 0 is refused) is a drive whose counts run
    against the joint. Its position and velocity are read reversed; so must its effort be,
    both ways: else the joint's PID pushes the joint away from its setpoint (positive
    feedback, a runaway)."""
    js = make_joints(gains=PIDGains(kp=100.0))
    p = params(channel, feedback_timeout=10.0)
    p["joints"]["yaw"]["counts_per_unit"] = -CPU[0]
    del p["joints"]["insertion"]["counts_per_unit"]  # 1 count per metre, the default
    axes = [DriveAxis(0x101, 0x181), DriveAxis(0x102, 0x182)]
    # effort_gain 0: the drives hold still, the efforts alone are compared
    with SimulatedDriveNode(axes, channel=channel, tau=0.0, effort_gain=0.0) as node:
        drv = CANDriver("arm", js, p, command_interface="effort")
        try:
            drv.configure()
            assert node.wait_feedback(2, timeout=2.0)
            drv.read(0.0)
            drv.activate()
            drv.write([0.005, 0.0002], 0.001)  # +0.5 N*m toward +0.005 rad, +0.02 N
            assert node.wait_feedback(4, timeout=2.0)
            # the reversed drive pushes its counts down, which is the joint up
            assert node.axes[0].mode == 2 and node.axes[0].effort == -500
            assert node.axes[1].mode == 2 and node.axes[1].effort == 20  # not reversed
            drv.read(0.002)
            # what they report, in the joints' sense
            assert js[0].effort == pytest.approx(0.5) and js[1].effort == pytest.approx(0.02)
        finally:
            drv.shutdown()
    assert node.error is None


def test_a_29_bit_frame_with_a_feedback_number_is_not_feedback(channel: str) -> None:
    """The feedback identifiers are 11-bit. A 29-bit frame whose identifier has the same
    number (another device, e.g. J1939, on a bus python-can filters in software) is a
    different frame: it must not become the joint's position."""
    with fed_driver(channel) as (js, peer, drv):
        peer.send(
            can.Message(
                arbitration_id=0x181, is_extended_id=True, data=FEEDBACK_FRAME.pack(-90000, 0, 0)
            )
        )
        drv.read(0.001)
        assert js[0].position == 100 / CPU[0]
        assert drv.stats()["ignored_frames"] == 1 and drv.stats()["feedback_frames"] == 2


@contextlib.contextmanager
def fed_driver(channel: str) -> Iterator[tuple[list[Joint], can.Bus, CANDriver]]:
    """A CAN driver configured on ``channel`` (feedback timeout 10 s) that has read one
    feedback frame of 100 counts per joint, sent by a raw peer on the bus; both shut down
    after."""
    js = make_joints()
    peer = can.Bus(interface="virtual", channel=channel)
    drv = CANDriver("arm", js, params(channel, feedback_timeout=10.0))
    try:
        drv.configure()
        for fid in (0x181, 0x182):
            peer.send(
                can.Message(
                    arbitration_id=fid, is_extended_id=False, data=FEEDBACK_FRAME.pack(100, 0, 0)
                )
            )
        drv.read(0.0)
        yield js, peer, drv
    finally:
        drv.shutdown()
        peer.shutdown()


@pytest.mark.parametrize(("heartbeat_ms", "told"), [(0, 0), (1, 1), (254.4, 254), (255.4, 255)])
def test_the_heartbeat_byte_is_the_nearest_whole_ms(
    channel: str, heartbeat_ms: float, told: int
) -> None:
    spy = can.Bus(interface="virtual", channel=channel)
    drv = CANDriver("arm", make_joints(), params(channel, heartbeat_ms=heartbeat_ms))
    try:
        drv.configure()
        assert [COMMAND_FRAME.unpack(m.data)[3] for m in drain(spy)] == [told, told]
    finally:
        drv.shutdown()
        spy.shutdown()


def test_a_bus_that_fails_to_receive_faults_with_the_reason(channel: str) -> None:
    """The interface goes away under the driver (its python-can bus closed): the next read
    faults and says so, it does not report the last positions as current."""
    drv = CANDriver("arm", make_joints(), params(channel))
    drv.configure()
    bus = drv._bus
    assert bus is not None
    bus.shutdown()
    with pytest.raises(DriverError, match=r"^can driver 'arm': receive failed: "):
        drv.read(0.0)
    assert drv.state is DriverState.FAULT
    drv.shutdown()


def test_a_babbling_bus_costs_a_read_a_bounded_number_of_frames(channel: str) -> None:
    """A read takes at most MAX_FRAMES_PER_JOINT frames per joint off the bus (the bound the
    driver declares); the rest wait for the next read: a node that floods the bus costs each tick a
    bounded amount of work and never holds the loop in the driver."""
    with fed_driver(channel) as (js, peer, drv):
        bound = MAX_FRAMES_PER_JOINT * len(js)
        for _ in range(bound + 5):  # frames for nobody here (29-bit): each one read, ignored
            peer.send(can.Message(arbitration_id=0x181, is_extended_id=True, data=bytes(8)))
        drv.read(0.001)
        assert drv.stats()["ignored_frames"] == bound
        drv.read(0.002)
        assert drv.stats()["ignored_frames"] == bound + 5


# ---------------------------------------------------------------- polling (SR-HW-20)
COMMAND_IDS = {0x101: 0x181, 0x102: 0x182}  # command id -> feedback id, as in params()


def commands_sent(spy: can.BusABC) -> int:
    """How many command frames went out since the last call (the spy sees the node's
    feedback frames too: those are not counted)."""
    return sum(1 for m in drain(spy) if m.arbitration_id in COMMAND_IDS)


@pytest.mark.req("SR-HW-20")
def test_a_node_that_only_answers_keeps_an_inactive_driver_healthy(
    channel: str, node: SimulatedDriveNode
) -> None:
    """The project's own node answers commands only. While INACTIVE the driver polls it (a
    mode-0 frame a read, once the last one is answered), so READY lasts: 300 reads, 30 times
    the feedback timeout, without a fault. While ACTIVE nothing but the commands goes out;
    after deactivate the polls resume."""
    spy = can.Bus(interface="virtual", channel=channel)
    drv = CANDriver("arm", make_joints(), params(channel))  # feedback_timeout 10 ms
    try:
        drv.configure()
        sent = commands_sent(spy)
        for k in range(300):
            assert node.wait_commands(sent, timeout=2.0) and node.wait_feedback(sent, timeout=2.0)
            drv.read(k * 0.001)
            sent += commands_sent(spy)
        assert drv.state is DriverState.INACTIVE
        settle(node, drv)
        assert [a.commands for a in node.axes] == [301, 301]  # configure's query + 300 polls
        assert [a.mode for a in node.axes] == [MODE_DISABLED] * 2
        assert max(drv.feedback_age(0.299)) <= 0.001 + 1e-12  # the poll of the read before
        drv.activate()
        for k in range(300, 320):
            drv.write([0.001, 0.001], k * 0.001)
            assert commands_sent(spy) == 2  # the commands, no poll
            settle(node, drv)
            drv.read((k + 1) * 0.001)
            assert commands_sent(spy) == 0
        assert drv.state is DriverState.ACTIVE and [a.mode for a in node.axes] == [1, 1]
        drv.deactivate()
        settle(node, drv)
        drv.read(0.321)
        assert commands_sent(spy) == 4  # the stop frames, then a poll each
        assert drv.state is DriverState.INACTIVE and drv.stats()["polls"] == 2 * 301
    finally:
        drv.shutdown()
        spy.shutdown()


class ScriptedDrive:
    """A drive played by the test on a raw bus of its own, all in the test's thread: at each
    :meth:`step` it takes the command frames sent since, and answers each one with one
    feedback frame (100 counts) ``lag`` steps later (0: at once). ``answer = False`` drops
    the commands (a drive that lost power: what it was asked it never answers)."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.lag = 0
        self.answer = True
        self.k = 0
        self.queue: list[tuple[int, int]] = []  # (due step, feedback id)
        self.counts = 100  # the position every answer reports

    def step(self) -> None:
        for msg in drain(self.bus):
            fid = COMMAND_IDS.get(msg.arbitration_id)
            if fid is not None and self.answer:
                self.queue.append((self.k + self.lag, fid))
        due = [q for q in self.queue if q[0] <= self.k]
        self.queue = [q for q in self.queue if q[0] > self.k]
        for _, fid in due:
            self.bus.send(
                can.Message(
                    arbitration_id=fid,
                    is_extended_id=False,
                    data=FEEDBACK_FRAME.pack(self.counts, 0, 0),
                )
            )
        self.k += 1


@contextlib.contextmanager
def scripted(channel: str, **extra: object) -> Iterator[tuple[ScriptedDrive, CANDriver]]:
    drive = ScriptedDrive(channel)
    # the scripted drive answers at a position of its own, not the one commanded: this is
    # about the age of its answers, not about following (the base's following error)
    extra.setdefault("following_error", None)
    drv = CANDriver("arm", make_joints(), params(channel, **extra))
    try:
        drv.configure()
        yield drive, drv
    finally:
        drv.shutdown()
        drive.bus.shutdown()


def tick(drive: ScriptedDrive, drv: CANDriver, k: int) -> None:
    """Tick k (k ms on the loop clock): the drive answers what is due, the driver reads (and
    polls), and if ACTIVE commands. A read that fails while FAULT is swallowed (the robot
    reads a faulted drive on)."""
    drive.step()
    now = k * 0.001
    try:
        drv.read(now)
    except DriverError:
        if drv.state is not DriverState.FAULT:
            raise
        return
    if drv.state is DriverState.ACTIVE:
        drv.write([0.0, 0.0], now)


@pytest.mark.req("SR-HW-20")
def test_poll_period_spaces_the_polls(channel: str) -> None:
    with scripted(channel, poll_period=0.004) as (drive, drv):
        ages = []
        for k in range(20):
            tick(drive, drv, k)
            ages.append(max(drv.feedback_age(k * 0.001)))
        # at 0, 4, 8, 12 and 16 ms, to each joint
        assert drv.stats()["polls"] == 10 and drv.state is DriverState.INACTIVE
        assert max(ages) == pytest.approx(0.004)  # a poll answered at the next read


# ---------------------------------------------------------------- feedback age (SR-HW-21)
@pytest.mark.req("SR-HW-21")
def test_a_late_drive_faults_on_its_age_and_fails_the_first_read_after_reset(
    channel: str,
) -> None:
    """A drive whose every answer comes 50 ms late still delivers a frame every tick once its
    backlog flows. Judged by arrival it looked healthy after a reset (the deadline restarted
    there); judged by age (the send time of the command each frame answers) it faults while
    running, and the first read after the reset fails with the age and the limit. Once it
    answers on time again (its backlog drained, nothing lost) it is healthy again."""
    with scripted(channel) as (drive, drv):
        for k in range(10):
            tick(drive, drv, k)
        drv.activate()
        for k in range(10, 30):
            tick(drive, drv, k)
        assert drv.state is DriverState.ACTIVE
        drive.lag = 50
        k = 30
        with pytest.raises(
            DriverError,
            match=r"^can driver 'arm': joint yaw: no feedback on id "
            r"0x181 for 11\.0 ms: feedback age 11\.0 ms > "
            r"feedback_timeout 10\.0 ms \(11 commands "
            r"unanswered\)$",
        ):
            while True:
                drive.step()
                drv.read(k * 0.001)
                drv.write([0.0, 0.0], k * 0.001)
                k += 1
        # the read at 40 ms: the command of 29 ms (the first one the drive holds back) owed for
        # 11 ms, and the ten after it
        assert k == 40 and drv.state is DriverState.FAULT
        for k in range(41, 200):  # read on while FAULT: the backlog arrives, 50 ms late
            tick(drive, drv, k)
        assert drv.stats()["feedback_frames"] > 60  # frames kept coming, every one stale
        drv.reset()
        drive.step()
        # the newest answer came at least 50 ms after its poll (it was not in the queue at
        # the read before): late until a newer one comes on time, whatever the reset
        with pytest.raises(
            DriverError,
            match=r"joint yaw: feedback on id 0x181 answers a command "
            r"sent at least 50\.0 ms before it arrived: feedback "
            r"age 50\.0 ms > feedback_timeout 10\.0 ms \(answer "
            r"late; 2 commands unanswered\)$",
        ):
            drv.read(0.200)
        assert drv.state is DriverState.FAULT
        drive.lag = 0  # on time again
        for k in range(201, 300):
            tick(drive, drv, k)
        drv.reset()
        tick(drive, drv, 300)
        drv.activate()
        for k in range(301, 320):
            tick(drive, drv, k)
        assert drv.state is DriverState.ACTIVE and max(drv.feedback_age(0.319)) <= 0.001 + 1e-12
        assert drv.stats()["lost_answers"] == 0  # a late drive's answers all came


@pytest.mark.req("SR-HW-21")
def test_lost_answers_are_given_up_only_after_lost_after_of_quiet(channel: str) -> None:
    """A drive that lost power answers nothing of what it was asked, then comes back. Until
    nothing has been heard from the joint for lost_after, the commands it owes could still
    be coming (a late drive), so the first read after a reset fails; then the commands older
    than that are given up, the joint is polled afresh, and a reset passes."""
    with scripted(channel, lost_after=0.05) as (drive, drv):
        for k in range(5):
            tick(drive, drv, k)
        drv.activate()
        for k in range(5, 10):
            tick(drive, drv, k)
        drive.answer = False  # from the command of 9 ms on (the drive steps before the read)
        for k in range(10, 25):
            tick(drive, drv, k)
        assert drv.state is DriverState.FAULT
        assert drv.fault_reason is not None and "feedback age 11.0 ms" in drv.fault_reason
        drive.answer = True  # repaired
        drv.reset()
        # it answers the reset's stop frames: taken for the oldest command owed (of 9 ms), which
        # judges it older, never younger, than it is; the next owed (10 ms) is 15 ms old
        drive.step()
        with pytest.raises(
            DriverError,
            match=r"joint yaw: no feedback on id 0x181 for 15\.0 ms: "
            r"feedback age 15\.0 ms > feedback_timeout "
            r"10\.0 ms \(12 commands unanswered\)$",
        ):
            drv.read(0.025)
        for k in range(26, 76):  # last heard at 25 ms (read at 26)
            tick(drive, drv, k)
        assert drv.stats()["lost_answers"] == 0
        # 50 ms without a frame: the 12 owed per joint given up (the commands of 10 to 19 ms,
        # the stop frames of the fault and of the reset), a poll
        tick(drive, drv, 76)
        assert drv.stats()["lost_answers"] == 24
        tick(drive, drv, 77)  # the poll answered: fresh
        assert max(drv.feedback_age(0.077)) == pytest.approx(0.001)
        drv.reset()
        drive.step()
        drv.read(0.078)
        assert drv.state is DriverState.INACTIVE


@pytest.mark.req("SR-HW-21")
def test_frames_with_no_command_outstanding_are_counted_and_do_not_refresh(
    channel: str, caplog: pytest.LogCaptureFixture
) -> None:
    """A frame the driver did not ask for (a drive that also sends cyclically) has no known
    age: its values are read but it does not count as fresh data (feedback_age); it is
    counted, and the first one logged."""
    peer = can.Bus(interface="virtual", channel=channel)
    drv = CANDriver("arm", make_joints(), params(channel, feedback_timeout=0.004))
    try:
        drv.configure()
        drv.read(0.0)  # configure's query unanswered: polls wait for it
        for fid in (0x181, 0x182):  # one answer each, and a frame nobody asked for
            for pos in (100, 200):
                peer.send(
                    can.Message(
                        arbitration_id=fid,
                        is_extended_id=False,
                        data=FEEDBACK_FRAME.pack(pos, 0, 0),
                    )
                )
        with caplog.at_level("WARNING", logger="occ.drivers.can"):
            drv.read(0.003)
        assert drv.stats()["unsolicited_frames"] == 2
        assert [r.getMessage() for r in caplog.records] == [
            "can driver arm: joint yaw sends feedback on its own: cyclic frames cannot be told "
            "from answers, its feedback age is judged too young if they are late"
        ]
        assert drv.joints[0].position == 200 / CPU[0]  # the newest values are read
        for fid in (0x181, 0x182):  # frames again, but the polls of 3 ms are owed: answers
            peer.send(
                can.Message(
                    arbitration_id=fid, is_extended_id=False, data=FEEDBACK_FRAME.pack(300, 0, 0)
                )
            )
        drv.read(0.006)
        assert max(drv.feedback_age(0.006)) == pytest.approx(0.003)
        for fid in (0x181, 0x182):  # nothing owed now (polls of 6 ms answered below first)
            peer.send(
                can.Message(
                    arbitration_id=fid, is_extended_id=False, data=FEEDBACK_FRAME.pack(400, 0, 0)
                )
            )
            peer.send(
                can.Message(
                    arbitration_id=fid, is_extended_id=False, data=FEEDBACK_FRAME.pack(500, 0, 0)
                )
            )
        drv.read(0.009)
        assert drv.stats()["unsolicited_frames"] == 4
        # the data: from the answer to the poll of 6 ms, not from the frames nobody asked for
        assert max(drv.feedback_age(0.009)) == pytest.approx(0.003)
        assert drv.joints[0].position == 500 / CPU[0] and drv.state is DriverState.INACTIVE
    finally:
        drv.shutdown()
        peer.shutdown()


# ---------------------------------------------------------------- a bus still flooding
@pytest.mark.req("SR-HW-13")
def test_a_reset_with_the_bus_still_flooding_fails_its_first_read(
    channel: str, node: SimulatedDriveNode
) -> None:
    """The error frames that faulted the driver are forgotten by a reset; those heard since
    are not: a bus that still floods (3 error frames with every command, the polls of the
    faulted driver included) fails the first read after the reset. Once it has been clean
    for 100 ms, a reset passes."""
    drv = active_driver(channel, node, feedback_timeout=10.0)  # error_frames 10 (default)
    node.error_flood(3)
    k = 2
    with pytest.raises(DriverError, match=r"11 error frames in 100 ms"):
        while True:
            drv.write([0.0, 0.0], k * 0.001)
            settle(node, drv)
            drv.read(k * 0.001 + 0.0005)
            k += 1
    assert k == 3  # 6 with the first command, 6 more with the second
    for k in range(4, 10):  # while FAULT the driver polls: the flood goes on
        settle(node, drv)
        with pytest.raises(DriverError, match=r"error frames in 100 ms"):
            drv.read(k * 0.001)
    drv.reset()
    settle(node, drv)
    with pytest.raises(DriverError, match=r"\d+ error frames in 100 ms"):
        drv.read(0.010)
    node.error_flood(0)
    for k in range(11, 120):  # clean for more than 100 ms
        settle(node, drv)
        try:
            drv.read(k * 0.001)
        except DriverError:
            assert drv.state is DriverState.FAULT
    drv.reset()
    settle(node, drv)
    drv.read(0.120)
    assert drv.state is DriverState.INACTIVE
    drv.shutdown()


# ---------------------------------------------------------------- the node's fault modes
def test_the_nodes_error_flood_puts_error_frames_before_each_answer(channel: str) -> None:
    axes = [DriveAxis(0x101, 0x181)]
    with SimulatedDriveNode(axes, channel=channel, tau=0.0) as node:
        host = can.Bus(interface="virtual", channel=channel)
        try:
            node.error_flood(2, error_class=0x10)
            for seq in range(3):
                host.send(
                    can.Message(
                        arbitration_id=0x101,
                        is_extended_id=False,
                        data=COMMAND_FRAME.pack(0, MODE_DISABLED, seq, 0),
                    )
                )
                assert node.wait_feedback(seq + 1, timeout=2.0)
            node.error_flood(0)
            host.send(
                can.Message(
                    arbitration_id=0x101,
                    is_extended_id=False,
                    data=COMMAND_FRAME.pack(0, MODE_DISABLED, 3, 0),
                )
            )
            assert node.wait_feedback(4, timeout=2.0)
            got = [(m.is_error_frame, m.arbitration_id) for m in drain(host)]
            assert got == [(True, 0x10), (True, 0x10), (False, 0x181)] * 3 + [(False, 0x181)]
            assert node.error_frames_sent == 6
        finally:
            host.shutdown()
    assert node.error is None


def test_the_nodes_stale_dither_freezes_the_position_toggling_one_count(
    channel: str, node: SimulatedDriveNode
) -> None:
    """Under stale_dither the node reports the position it had when frozen (at its next
    frame: the answer to the first command, 1 mm), one count more every other frame, while
    its axes follow the commands: the tool moves, the feedback does not (but never stays
    exactly the same)."""
    # the node's own behaviour, with the base's feedback checks (which catch it) off
    drv = active_driver(
        channel,
        node,
        feedback_timeout=10.0,
        feedback_jump=0,
        following_error=None,
        frozen_feedback_ms=0,
    )  # at 0 counts
    node.stale_dither(1)
    seen = []
    for k in range(2, 12):
        drv.write([0.0, 0.001 * (k - 1)], k * 0.001)  # insertion +1 mm a tick
        settle(node, drv)
        drv.read(k * 0.001)
        seen.append(round(drv.joints[1].position * CPU[1]))
    assert seen == [200, 201] * 5
    assert node.axes[1].position == 10 * 200  # the axis went 10 mm
    assert node.axes[1].stale is not None and node.axes[1].stale[0] == 200
    node.stale_dither(0)
    drv.write([0.0, 0.011], 0.012)
    settle(node, drv)
    drv.read(0.012)
    assert round(drv.joints[1].position * CPU[1]) == 11 * 200 and node.axes[1].stale is None
    drv.shutdown()


# ----------------------------------- what the fresh mutation run of 2026-11-29 found unchecked
U = 2.0**-7  # a tick of 7.8125 ms: every time below is exact in binary


def test_round_saturated_refuses_nan_and_keeps_the_bounds() -> None:
    with pytest.raises(ValueError, match="^NaN cannot be sent$"):
        round_saturated(math.nan, -10, 10)
    assert round_saturated(10.0, -10, 10) == 10 and round_saturated(-10.0, -10, 10) == -10
    assert round_saturated(9.5, -10, 10) == 10 and round_saturated(1e30, -10, 10) == 10


@pytest.mark.req("SR-HW-21")
def test_a_drive_silent_from_the_start_is_aged_from_the_first_read(channel: str) -> None:
    """Never heard from: the age of its joints runs from the first read (the queries of
    configure were sent before any time was known), it faults past feedback_timeout saying
    none was ever answered, and the query is given up lost_after (by default ten times
    feedback_timeout) after the first read."""
    drv = CANDriver("arm", make_joints(), params(channel, feedback_timeout=2 * U))
    try:
        drv.configure()
        drv.read(0.0)
        assert drv.feedback_age(3 * U) == [3 * U, 3 * U]
        drv.read(2 * U)
        assert drv.state is DriverState.INACTIVE
        with pytest.raises(DriverError) as info:
            drv.read(3 * U)
        assert str(info.value) == (
            "can driver 'arm': joint yaw: no feedback on id 0x181 for 23.4 ms: feedback age "
            "23.4 ms > feedback_timeout 15.6 ms (1 command unanswered, none ever answered)"
        )
        for k in range(4, 21):
            with contextlib.suppress(DriverError):
                drv.read(k * U)
            assert drv.stats()["lost_answers"] == (2 if k == 20 else 0), k
    finally:
        drv.shutdown()
    # lost_after may equal feedback_timeout
    CANDriver("arm", make_joints(), params(channel, feedback_timeout=0.01, lost_after=0.01))


@pytest.mark.req("SR-HW-21")
def test_only_the_commands_older_than_lost_after_are_given_up_exactly_then(channel: str) -> None:
    peer = can.Bus(interface="virtual", channel=channel)
    drv = CANDriver(
        "arm",
        make_joints(),
        params(channel, feedback_timeout=2 * U, lost_after=8 * U, following_error=None),
    )
    try:
        drv.configure()
        for fid in (0x181, 0x182):  # the queries answered, then never again
            peer.send(
                can.Message(
                    arbitration_id=fid, is_extended_id=False, data=FEEDBACK_FRAME.pack(0, 0, 0)
                )
            )
        drv.read(0.0)  # heard at 0; a poll each, owed from 0
        drv.activate()
        for k in (1, 2):
            drv.read(k * U)
            drv.write([0.0, 0.0], k * U)
        with pytest.raises(DriverError, match="no feedback on id 0x181 for 23.4 ms"):
            drv.read(3 * U)  # its switch-off frames owed from 3 U too
        for k in range(4, 8):
            with contextlib.suppress(DriverError):
                drv.read(k * U)
        assert drv.stats()["lost_answers"] == 0
        with contextlib.suppress(DriverError):
            drv.read(8 * U)  # 8 U of quiet: the poll of 0 given up, the commands of 1-3 U not
        assert drv.stats()["lost_answers"] == 2
    finally:
        drv.shutdown()
        peer.shutdown()


@pytest.mark.req("SR-HW-21")
def test_an_age_or_a_round_trip_of_exactly_the_limit_is_on_time(channel: str) -> None:
    peer = can.Bus(interface="virtual", channel=channel)
    drv = CANDriver("arm", make_joints(), params(channel, feedback_timeout=0.25))
    limit = 0.25 * (1.0 + 1e-9)  # the driver's own slack for float rounding

    def answer() -> None:
        for fid in (0x181, 0x182):
            peer.send(
                can.Message(
                    arbitration_id=fid, is_extended_id=False, data=FEEDBACK_FRAME.pack(0, 0, 0)
                )
            )

    try:
        drv.configure()
        drv.read(0.0)
        drv.read(limit)  # the queries owed for exactly the limit
        answer()
        drv.read(limit + 0.001)  # answered after a round trip of exactly the limit
        assert drv.state is DriverState.INACTIVE
        # the poll of limit + 1 ms unanswered: a fault, then its answer's round trip named
        with pytest.raises(DriverError, match=r"for 624\.0 ms"):
            drv.read(0.875)
        answer()
        with pytest.raises(DriverError) as info:
            drv.read(1.0)
        assert str(info.value) == (
            "can driver 'arm': joint yaw: feedback on id 0x181 answers a command sent at least "
            "624.0 ms before it arrived: feedback age 624.0 ms > feedback_timeout 250.0 ms "
            "(answer late; 1 command unanswered)"
        )
    finally:
        drv.shutdown()
        peer.shutdown()


@pytest.mark.req("SR-HW-21")
def test_an_effort_command_is_owed_from_the_time_it_was_written(channel: str) -> None:
    with scripted(channel, command_interface="effort") as (drive, drv):
        for k in range(5):
            tick(drive, drv, k)
        drive.step()
        drv.read(0.005)  # a poll each, owed from 5 ms
        drv.activate()
        drive.step()  # the polls answered
        drive.answer = False
        drv.write_effort([0.0, 0.0], 0.009)
        drive.step()
        drv.read(0.0185)  # owed 9.5 ms: on time
        assert drv.state is DriverState.ACTIVE


@pytest.mark.req("SR-HW-21")
def test_the_stop_frames_of_a_safe_stop_are_counted_and_owed_an_answer(channel: str) -> None:
    with scripted(channel) as (drive, drv):
        for k in range(5):
            tick(drive, drv, k)
        drv.activate()
        for k in range(5, 10):
            tick(drive, drv, k)
        before = drv.stats()
        drv.safe_stop("supervisor")
        assert drv.stats()["command_frames"] == before["command_frames"] + 2
        drive.step()
        drv.read(0.010)  # their answers, taken as theirs
        after = drv.stats()
        # the commands written at 9 ms and the stop frames (sent at the last read's now)
        assert after["feedback_frames"] == before["feedback_frames"] + 4
        assert after["unsolicited_frames"] == 0
        assert drv.feedback_age(0.010) == pytest.approx([0.001, 0.001])


@pytest.mark.req("SR-HW-8")
def test_a_position_dithering_by_two_counts_is_moving_by_one_is_still(channel: str) -> None:
    """A CAN drive's encoder noise is one count: a reading that toggles by two is a joint
    that moves (never frozen however long), one that toggles by one is frozen."""
    for step, frozen in ((2, False), (1, True)):
        with scripted(channel + f"-{step}") as (drive, drv):
            for k in range(5):
                tick(drive, drv, k)
            drv.activate()
            for k in range(5, 120):
                # 102 and 104 counts: 0.0104 - 0.0102 rad is a hair under 2e-4 in floats, so a
                # noise of two counts would call it still
                drive.counts = 102 + step * (k % 2)
                tick(drive, drv, k)
            assert (drv.state is DriverState.FAULT) is frozen
            if frozen:
                assert "feedback frozen" in (drv.fault_reason or "")


def test_a_reset_keeps_the_error_frames_heard_while_faulted_by_something_else(
    channel: str, node: SimulatedDriveNode
) -> None:
    drv = active_driver(channel, node, error_frames=1, feedback_timeout=10.0)
    drv.safe_stop("supervisor")  # a fault that is not the error frames'
    node.send_error_frame(0x04)
    drv.read(0.002)  # heard while FAULT: not what faulted it
    drv.reset()
    drv.read(0.003)
    drv.activate()
    node.send_error_frame(0x04)  # with the one kept: two in 100 ms, one over the limit
    with pytest.raises(DriverError, match="2 error frames"):
        drv.read(0.004)
    drv.reset()  # forgets both
    drv.read(0.005)
    drv.activate()
    drv.safe_stop("supervisor")
    node.send_error_frame(0x04)
    drv.read(0.006)
    drv.reset()  # keeps the one heard while stopped
    drv.read(0.007)
    assert drv.state is DriverState.INACTIVE and drv.stats()["error_frames"] == 3
    drv.activate()
    node.send_error_frame(0x04)
    with pytest.raises(DriverError, match="2 error frames"):
        drv.read(0.008)
    drv.shutdown()
