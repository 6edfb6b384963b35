"""The slave robot in simulated time: loss logic exact to the tick, teleop following, commands.

No sockets are opened: messages enter through the interface's routing callback (what the
transport's I/O thread calls), and the loop is stepped tick by tick on a SimClock.
"""

from __future__ import annotations

from pathlib import Path

import pytest

import igtl
from igtl.transport import Peer
from occ.clock import SimClock
from occ.config import load_config
from occ.robot import build_robot
from occ.safety import RobotState

ROOT = Path(__file__).resolve().parents[2]
MASTER_PEER = Peer(1, ("127.0.0.1", 40000))
OPERATOR = Peer(2, ("127.0.0.1", 40001))


class SimSlave:
    """Drives a slave Robot tick by tick; the master sends one POSITION every 2 ms."""

    def __init__(self, **teleop: object) -> None:
        cfg = load_config(ROOT / "configs" / "slave.yaml")
        if teleop:
            cfg = cfg.model_copy(update={"teleop": cfg.teleop.model_copy(update=teleop)})
        self.clock = SimClock()
        self.robot = build_robot(cfg, clock=self.clock)
        self.robot.configure()
        self.k = 0
        self.seq = 0
        self.master_pos = [0.0, 50.0, 270.0]
        self.replies: list[igtl.Message] = []
        # capture what the robot sends to operators instead of real sockets
        self.robot.interfaces["slicer"].send_to_peer = self._capture  # type: ignore[method-assign]
        self.robot.interfaces["slicer"].send = lambda m, peer=None: self._capture(m, None)  # type: ignore[method-assign]

    def _capture(self, msg: igtl.Message, peer: object) -> bool:
        self.replies.append(msg)
        return True

    def packet(self, *, run: bool = True, drop: bool = False) -> None:
        self.seq += 1
        if drop:
            return
        msg = igtl.PositionMessage(
            tuple(self.master_pos), (0.0, 0.0, 0.0, 1.0), 24, device_name="Master",
            header_version=2, message_id=self.seq, metadata={"run": "1" if run else "0", "clutch": "0"},
        )
        self.robot.interfaces["master"]._on_message(MASTER_PEER, igtl.unpack(msg.pack()))

    def tick(self) -> None:
        now = self.k * 0.001
        self.clock.set(now)
        self.robot.tick(now, self.k)
        self.k += 1

    def step_ms(self, ms: int, *, drops: set[int] | None = None, run: bool = True) -> None:
        """Advance ms ticks; a packet is sent on even ticks, dropped if its seq is in drops."""
        for _ in range(ms):
            if self.k % 2 == 0:
                self.packet(run=run, drop=drops is not None and (self.seq + 1) in drops)
            self.tick()

    def command(self, name: str) -> igtl.Message:
        cls = igtl.REGISTRY["COMMAND"]
        msg = cls(command_id=len(self.replies) + 100, command_name=name, command="",
                  device_name="command", header_version=2)
        self.robot.interfaces["slicer"]._on_message(OPERATOR, msg)
        n = len(self.replies)
        self.tick()
        assert len(self.replies) > n, f"no reply to {name}"
        return [r for r in self.replies if r.message_type == "RTS_COMMAND"][-1]


@pytest.fixture
def slave() -> SimSlave:
    s = SimSlave()
    yield s
    s.robot.shutdown()


def run(slave: SimSlave) -> None:
    for name in ("Enable", "Run"):
        r = slave.command(name)
        assert r.metadata["Status"] == "SUCCESS", r
    assert slave.robot.state is RobotState.RUNNING


def test_two_consecutive_losses_never_stop(slave: SimSlave) -> None:
    run(slave)
    slave.step_ms(20)
    drops = {s for base in range(20, 400, 7) for s in (base, base + 1)}  # pairs of losses
    slave.step_ms(800, drops=drops)
    assert slave.robot.state is RobotState.RUNNING
    c = slave.robot.loss_monitor.counters()
    assert c["lost_total"] == sum(1 for d in drops if d <= slave.seq)
    assert c["max_run"] == 2 and c["trips"] == 0


def test_three_consecutive_losses_stop_within_7ms_and_alert(slave: SimSlave) -> None:
    run(slave)
    slave.step_ms(30)
    last_good_tick = slave.k - 2 if slave.k % 2 == 0 else slave.k - 1
    seq0 = slave.seq + 1
    stopped_at = None
    for _ in range(20):
        slave.step_ms(1, drops={seq0, seq0 + 1, seq0 + 2})
        if slave.robot.state is RobotState.STOPPED and stopped_at is None:
            stopped_at = slave.k - 1
    assert stopped_at is not None
    # the last good packet was taken at last_good_tick; three 2 ms periods + one 1 ms tick
    assert stopped_at - last_good_tick == 7
    alerts = [r for r in slave.replies if r.message_type == "STATUS" and r.error_name == "STOPPED"]
    # the deadline notices the silence first: the cause names the loss and the three periods
    assert alerts and "packet loss on master" in alerts[-1].status_message
    assert "3 periods" in alerts[-1].status_message or "3 consecutive" in alerts[-1].status_message
    # stays stopped although packets flow again, until an operator Run
    slave.step_ms(50)
    assert slave.robot.state is RobotState.STOPPED
    assert slave.command("Run").metadata["Status"] == "SUCCESS"
    slave.step_ms(10)
    assert slave.robot.state is RobotState.RUNNING


def test_dead_master_caught_by_deadline(slave: SimSlave) -> None:
    run(slave)
    slave.step_ms(30)
    last_packet_tick = slave.k - 2 if slave.k % 2 == 0 else slave.k - 1
    for _ in range(20):
        slave.tick()  # no packets at all: the master process is gone
        if slave.robot.state is RobotState.STOPPED:
            break
    assert slave.robot.state is RobotState.STOPPED
    assert (slave.k - 1) - last_packet_tick == 7


def test_slave_follows_scaled_master_motion_without_jump(slave: SimSlave) -> None:
    run(slave)
    slave.step_ms(50)
    tip0 = slave.robot.tip[:3, 3].copy()
    # master moves 20 mm in x (scaled 10:1 -> 2 mm at the slave), in small steps
    for i in range(200):
        slave.master_pos[0] = 20.0 * (i + 1) / 200
        slave.step_ms(2)
    slave.step_ms(300)
    moved = (slave.robot.tip[:3, 3] - tip0) * 1000.0
    assert moved[0] == pytest.approx(2.0, abs=0.05)
    assert abs(moved[1]) < 0.05 and abs(moved[2]) < 0.05


def test_clutch_reindexes(slave: SimSlave) -> None:
    run(slave)
    slave.step_ms(50)
    tip0 = slave.robot.tip[:3, 3].copy()
    slave.master_pos[0] = 100.0  # a big master jump while not running (run=0)
    slave.step_ms(100, run=False)
    slave.step_ms(300)  # run again: the slave re-indexes, it must not jump 10 mm
    assert abs((slave.robot.tip[:3, 3] - tip0)[0] * 1000.0) < 0.05
    assert slave.robot.controller.stats()["reindexes"] >= 2


def test_unknown_and_refused_commands_change_nothing(slave: SimSlave) -> None:
    r = slave.command("Fly")
    assert r.metadata["Status"] == "FAIL" and "Fly" in r.metadata["Error"]
    r = slave.command("Run")  # READY -> Run is not allowed
    assert r.metadata["Status"] == "FAIL"
    assert slave.robot.state is RobotState.READY
    r = slave.command("GetState")
    assert r.metadata["Status"] == "SUCCESS" and "READY" in r.metadata["Message"]


def test_estop_latches_until_reset(slave: SimSlave) -> None:
    run(slave)
    slave.step_ms(10)
    assert slave.command("EStop").metadata["Status"] == "SUCCESS"
    assert slave.robot.state is RobotState.ESTOP
    assert slave.command("Run").metadata["Status"] == "FAIL"
    assert slave.command("Enable").metadata["Status"] == "FAIL"
    assert slave.command("Reset").metadata["Status"] == "SUCCESS"
    assert slave.robot.state is RobotState.READY


def test_plus_style_string_command_and_queries(slave: SimSlave) -> None:
    iface = slave.robot.interfaces["slicer"]
    iface._on_message(OPERATOR, igtl.StringMessage('<Command Name="Enable"/>', device_name="CMD_7"))
    slave.tick()
    ack = [r for r in slave.replies if r.message_type == "STRING" and r.device_name == "ACK_7"]
    assert ack and 'Status="SUCCESS"' in ack[-1].string
    assert slave.robot.state is RobotState.ENABLED
    get = igtl.REGISTRY["GET_STATUS"]
    iface._on_message(OPERATOR, igtl.unpack(get(type_name="GET_STATUS").pack()))
    slave.tick()
    st = [r for r in slave.replies if r.message_type == "STATUS"][-1]
    assert st.error_name == "ENABLED"


def test_tip_is_sent_in_world_coordinates_with_the_base_offset() -> None:
    s = SimSlave(base_mm=(100.0, -20.0, 5.0))
    try:
        s.robot.interfaces["slicer"]._on_message(
            OPERATOR, igtl.unpack(igtl.REGISTRY["GET_TRANS"](type_name="GET_TRANS", device_name="Tip").pack()))
        s.tick()
        tip = [r for r in s.replies if r.message_type == "TRANSFORM" and r.device_name == "Tip"][-1]
        fk = s.robot.tip[:3, 3] * 1000.0
        assert tip.translation == pytest.approx((fk[0] + 100.0, fk[1] - 20.0, fk[2] + 5.0), abs=1e-3)
    finally:
        s.robot.shutdown()


def test_base_pose_from_a_tracker_transform() -> None:
    from occ.config import InputConfig

    cfg = load_config(ROOT / "configs" / "slave.yaml")
    slicer = cfg.interface("slicer").model_copy(
        update={"inputs": (InputConfig(type="TRANSFORM", device="Base", queue="stream", depth=10),)}
    )
    cfg = cfg.model_copy(update={
        "interfaces": tuple(slicer if i.name == "slicer" else i for i in cfg.interfaces),
        "teleop": cfg.teleop.model_copy(update={"base_interface": "slicer", "base_mm": None}),
    })
    clock = SimClock()
    robot = build_robot(cfg, clock=clock)
    robot.configure()
    try:
        m = igtl.TransformMessage.from_position((10.0, 20.0, 30.0), device_name="Base")
        robot.interfaces["slicer"]._on_message(OPERATOR, m)
        robot.tick(0.0, 0)
        assert robot.base[:3, 3] * 1000.0 == pytest.approx([10.0, 20.0, 30.0])
        assert robot.world_tip()[:3, 3] * 1000.0 == pytest.approx(robot.tip[:3, 3] * 1000.0 + [10, 20, 30])
    finally:
        robot.shutdown()


def test_joints_must_match_the_kinematic_model() -> None:
    from occ.errors import OCCError

    cfg = load_config(ROOT / "configs" / "slave.yaml")
    joints = (cfg.robot.joints[1], cfg.robot.joints[0], cfg.robot.joints[2])  # order swapped
    bad = cfg.model_copy(update={"robot": cfg.robot.model_copy(update={"joints": joints})})
    with pytest.raises(OCCError, match="do not match the joints of the kinematic model"):
        build_robot(bad, clock=SimClock())
