"""The slave robot in simulated time: loss logic exact to the tick, teleop following, commands.

No sockets are opened: the robot's interfaces are in-process channels
(occ_testkit.testing.SimRobot); the master's stream and the operator's requests come from peers on
those channels, through the real codec and the interfaces' routing, and each peer reads only what
the robot sent to it. The loop is stepped tick by tick on a SimClock.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

import igtl
from occ.clock import SimClock
from occ.core.loader import load_config
from occ.core.robot import build_robot
from occ.core.safety import RobotState
from occ_testkit.testing import SimRobot

ROOT = Path(__file__).resolve().parents[2]
MASTER_ADDRESS = ("127.0.0.1", 40000)
OPERATOR_ADDRESS = ("127.0.0.1", 40001)


class SimSlave:
    """Drives a slave Robot tick by tick; the master sends one POSITION every 2 ms."""

    def __init__(self, config: object = None, **teleop: object) -> None:
        config = ROOT / "configs" / "slave.yaml" if config is None else config
        self.sim = SimRobot(config, params=teleop or None)  # type: ignore[arg-type]
        self.robot = self.sim.robot
        self.clock = self.sim.clock
        self.master = self.sim.peer("master", address=MASTER_ADDRESS)
        self.operator = self.sim.peer("operator", address=OPERATOR_ADDRESS)
        self.seq = 0
        self.master_pos = [0.0, 50.0, 270.0]
        #: everything the robot sent to the operator (replies, alerts, Tip/Base)
        self.replies = self.operator.received

    @property
    def k(self) -> int:
        return self.sim.k

    stamp = False  # put the sim clock's wall time in the header, as the master does
    clutch = False  # the master's clutch flag in the samples sent

    def position(self, *, run: bool = True, skew: float = 0.0) -> igtl.Message:
        ts = self.clock.wall_time() + skew if self.stamp else 0.0
        return igtl.PositionMessage(
            tuple(self.master_pos),
            (0.0, 0.0, 0.0, 1.0),
            24,
            device_name="Master",
            header_version=2,
            message_id=self.seq,
            timestamp=ts,
            metadata={"run": "1" if run else "0", "clutch": "1" if self.clutch else "0"},
        )

    def packet(self, *, run: bool = True, drop: bool = False) -> None:
        self.seq += 1
        if drop:
            return
        assert self.master.send(self.position(run=run)) == 1

    def tick(self) -> None:
        self.sim.tick()

    def step_ms(self, ms: int, *, drops: set[int] | None = None, run: bool = True) -> None:
        """Advance ms ticks; a packet is sent on even ticks, dropped if its seq is in drops."""
        for _ in range(ms):
            if self.k % 2 == 0:
                self.packet(run=run, drop=drops is not None and (self.seq + 1) in drops)
            self.tick()

    def command(self, name: str) -> igtl.Message:
        cid = self.operator.send_command(name)
        n = len(self.replies)
        self.tick()
        assert len(self.replies) > n, f"no reply to {name}"
        reply = self.operator.reply_to(cid)
        assert reply is not None, f"no RTS_COMMAND for {name} (command ID {cid})"
        return reply

    def close(self) -> None:
        self.sim.close()


@pytest.fixture
def slave() -> SimSlave:
    s = SimSlave()
    yield s
    s.close()


def run(slave: SimSlave) -> None:
    for name in ("Enable", "Run"):
        r = slave.command(name)
        assert r.metadata["Status"] == "SUCCESS", r
    assert slave.robot.state is RobotState.RUNNING


@pytest.mark.req("SR-LOSS-1")
def test_two_consecutive_losses_never_stop(slave: SimSlave) -> None:
    run(slave)
    slave.step_ms(20)
    drops = {s for base in range(20, 400, 7) for s in (base, base + 1)}  # pairs of losses
    slave.step_ms(800, drops=drops)
    assert slave.robot.state is RobotState.RUNNING
    c = slave.robot.streams.monitor.counters()
    assert c["lost_total"] == sum(1 for d in drops if d <= slave.seq)
    assert c["max_run"] == 2 and c["trips"] == 0


def driver_setpoint(slave: SimSlave) -> list[float]:
    return list(slave.robot.data.setpoint)


@pytest.mark.req("SR-LOSS-1")
def test_three_missing_numbers_hold_at_7ms_then_latch_with_an_alert(slave: SimSlave) -> None:
    run(slave)
    slave.step_ms(30)
    last_good_tick = slave.k - 2 if slave.k % 2 == 0 else slave.k - 1
    seq0 = slave.seq + 1
    held_at = stopped_at = None
    for _ in range(20):
        before = driver_setpoint(slave)
        slave.master_pos[0] += 1.0  # the master keeps moving: a held slave must not follow
        slave.step_ms(1, drops={seq0, seq0 + 1, seq0 + 2})
        if held_at is None and slave.robot.streams.monitor.holding:
            held_at = slave.k - 1
        if held_at is not None and stopped_at is None:
            assert driver_setpoint(slave) == before  # motion stopped: the last safe setpoint
        if slave.robot.state is RobotState.STOPPED and stopped_at is None:
            stopped_at = slave.k - 1
    # the 3rd missing packet is due at +6 ms: motion holds at the +7 ms tick, exactly
    assert held_at is not None and held_at - last_good_tick == 7
    # the next packet (+8 ms) proves three numbers missing: latched STOP with an alert
    assert stopped_at is not None and stopped_at - last_good_tick == 8
    alerts = [r for r in slave.replies if r.message_type == "STATUS" and r.error_name == "STOPPED"]
    assert alerts and "packet loss on master" in alerts[-1].status_message
    assert f"seq {seq0}-{seq0 + 2} missing" in alerts[-1].status_message
    # stays stopped although packets flow again, until an operator Run
    slave.step_ms(50)
    assert slave.robot.state is RobotState.STOPPED
    assert slave.command("Run").metadata["Status"] == "SUCCESS"
    slave.step_ms(10)
    assert slave.robot.state is RobotState.RUNNING


@pytest.mark.req("SR-LOSS-2")
def test_a_30ms_late_burst_holds_and_resumes_without_latch_or_jump(slave: SimSlave) -> None:
    run(slave)
    slave.step_ms(40)
    held: list[igtl.Message] = []
    # 30 ms in which the master's packets are delayed (a frozen master, a VM hiccup)...
    late: list[igtl.Message] = []
    for _ in range(30):
        if slave.k % 2 == 0:
            slave.seq += 1
            slave.master_pos[0] += 1.0
            late.append(slave.position())
        slave.tick()
        held.append(slave.robot.streams.monitor.holding)
    assert any(held) and slave.robot.state is RobotState.RUNNING
    # ... then arrive together, numbers contiguous: late, not lost
    for msg in late:
        assert slave.master.send(msg) == 1
    steps = []
    for _ in range(40):
        before = driver_setpoint(slave)
        slave.step_ms(1)
        steps.append(max(abs(a - b) for a, b in zip(driver_setpoint(slave), before)))
    assert slave.robot.state is RobotState.RUNNING
    c = slave.robot.streams.monitor.counters()
    assert c["holds"] == 1 and c["resumes"] == 1 and c["trips"] == 0 and c["lost_total"] == 0
    # re-entry rate-limited to half the joint velocity limits: no jump
    limit = max(0.5 * j.limits.velocity * 0.001 for j in slave.robot.joints)
    assert max(steps) <= limit + 1e-12
    warnings = [r for r in slave.replies if r.message_type == "STATUS" and r.error_name == "STREAM"]
    assert warnings and "following again" in warnings[-1].status_message


@pytest.mark.req("SR-LOSS-3")
def test_a_dead_master_holds_at_7ms_and_latches_after_the_grace(slave: SimSlave) -> None:
    run(slave)
    slave.step_ms(30)
    last_packet_tick = slave.k - 2 if slave.k % 2 == 0 else slave.k - 1
    held_at = None
    for _ in range(200):
        slave.tick()  # no packets at all: the master process is gone
        if held_at is None and slave.robot.streams.monitor.holding:
            held_at = slave.k - 1
        if slave.robot.state is RobotState.STOPPED:
            break
    assert held_at is not None and held_at - last_packet_tick == 7
    assert slave.robot.state is RobotState.STOPPED
    assert (slave.k - 1) - last_packet_tick == 101  # silent for more than the 100 ms grace
    alerts = [r for r in slave.replies if r.message_type == "STATUS" and r.error_name == "STOPPED"]
    assert "no packet for 101.00 ms" in alerts[-1].status_message


@pytest.mark.req("SR-LOSS-4")
def test_a_30ms_stall_of_the_slaves_own_loop_is_not_network_loss(slave: SimSlave) -> None:
    run(slave)
    slave.step_ms(20)
    # the loop stalls for 30 ms while the master's 15 packets arrive (queue depth 10)
    for _ in range(15):
        slave.packet()
    slave.sim.stall(30)
    slave.tick()
    q = slave.robot.interfaces["master"].streams["POSITION"]
    assert q.dropped == 5  # a local overflow, counted as such
    slave.step_ms(20)
    c = slave.robot.streams.monitor.counters()
    assert c["lost_total"] == 0 and c["trips"] == 0 and c["accepted"] == c["received"]
    assert slave.robot.state is RobotState.RUNNING
    assert slave.robot.interfaces.stats()["master"]["streams"]["POSITION"]["dropped"] == 5


@pytest.mark.req("SR-LOSS-4")
def test_no_loss_alert_while_not_running(slave: SimSlave) -> None:
    slave.step_ms(10)  # READY: packets, then the master dies
    for _ in range(200):
        slave.tick()
    assert slave.robot.state is RobotState.READY
    # the only STATUS is the greeting the operator got on connecting
    assert [r.error_name for r in slave.replies if r.message_type == "STATUS"] == ["READY"]
    assert slave.robot.last_alert == ""


@pytest.mark.req("SR-TIME-1")
def test_stale_and_future_samples_are_refused_and_not_followed(slave: SimSlave) -> None:
    run(slave)
    slave.stamp = True
    slave.step_ms(40)
    setpoint = driver_setpoint(slave)
    mon = slave.robot.streams.monitor
    # one sample an hour old and one a day ahead, with plausible numbers and a far target
    slave.master_pos[0] += 500.0
    for skew in (-3600.0, 86400.0):
        slave.seq += 1
        assert slave.master.send(slave.position(skew=skew)) == 1
        slave.tick()
    assert mon.stale == 1 and mon.future == 1
    assert driver_setpoint(slave) == pytest.approx(setpoint, abs=1e-9)
    assert slave.robot.state is RobotState.RUNNING


@pytest.mark.req("SR-EXC-1")
def test_a_controller_exception_faults_and_the_daemon_keeps_serving(slave: SimSlave) -> None:
    run(slave)
    slave.step_ms(10)

    def broken(now: float, current: object) -> None:
        raise ZeroDivisionError("bad maths")

    # the set of one controller, named after it (a compiled controller's own methods cannot be
    # replaced on the instance)
    assert slave.robot.controller.name == "teleop-slave"
    slave.robot.controller.update = broken  # type: ignore[method-assign]
    slave.step_ms(2)
    assert slave.robot.state is RobotState.FAULT
    alerts = [r for r in slave.replies if r.message_type == "STATUS" and r.error_name == "FAULT"]
    assert "teleop-slave: update raised ZeroDivisionError: bad maths" in alerts[-1].status_message
    slave.step_ms(5)  # the loop goes on
    assert slave.command("GetState").metadata["Status"] == "SUCCESS"
    assert slave.command("Reset").metadata["Status"] == "SUCCESS"
    assert slave.robot.state is RobotState.READY


@pytest.mark.req("SR-EXC-1")
def test_a_failing_command_handler_faults_and_answers(slave: SimSlave) -> None:
    def broken(request: object, now: float) -> str:
        raise KeyError("oops")

    slave.robot.controller.on_command = broken  # type: ignore[method-assign]
    reply = slave.command("Clutch")
    assert reply.metadata["Status"] == "FAIL"
    assert slave.robot.state is RobotState.FAULT


def _tip_mm(slave: SimSlave) -> list[float]:
    return [float(v) * 1000.0 for v in slave.robot.data.tip[:3, 3]]


@pytest.mark.req("SR-CLUTCH-1")
def test_the_slave_stands_still_while_clutched_and_reindexes_on_release(slave: SimSlave) -> None:
    run(slave)
    slave.step_ms(50)
    reindexes = slave.robot.controller.stats()["reindexes"]
    tip0 = _tip_mm(slave)
    slave.clutch = True  # the operator presses the clutch and moves the master 20 mm
    for i in range(100):
        slave.master_pos[0] = 20.0 * (i + 1) / 100
        slave.step_ms(2)
    slave.step_ms(100)
    assert _tip_mm(slave) == pytest.approx(tip0, abs=1e-3)  # the slave did not follow
    slave.clutch = False  # released where it is: re-index, no jump of 2 mm
    slave.step_ms(100)
    assert _tip_mm(slave) == pytest.approx(tip0, abs=1e-3)
    assert slave.robot.controller.stats()["reindexes"] == reindexes + 1
    for i in range(100):  # and from there it follows again, scaled 10:1
        slave.master_pos[0] = 20.0 + 10.0 * (i + 1) / 100
        slave.step_ms(2)
    slave.step_ms(300)
    moved = [a - b for a, b in zip(_tip_mm(slave), tip0, strict=True)]
    assert moved[0] == pytest.approx(1.0, abs=0.05)
    assert abs(moved[1]) < 0.05 and abs(moved[2]) < 0.05


@pytest.mark.req("SR-TELE-1")
def test_the_rotation_is_applied_as_given_not_transposed() -> None:
    # rows are slave axes: slave y = master x, slave x = -master y (90 degrees about z)
    slave = SimSlave(rotation=[[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    try:
        run(slave)
        slave.step_ms(50)
        tip0 = _tip_mm(slave)
        for i in range(200):
            slave.master_pos[0] = 20.0 * (i + 1) / 200  # master +20 mm in x
            slave.step_ms(2)
        slave.step_ms(300)
        moved = [a - b for a, b in zip(_tip_mm(slave), tip0, strict=True)]
        assert moved[1] == pytest.approx(2.0, abs=0.05)  # transposed, it would be -2
        assert abs(moved[0]) < 0.05 and abs(moved[2]) < 0.05
    finally:
        slave.close()


def _slave_config(policy: str) -> dict:
    data = yaml.safe_load((ROOT / "configs" / "slave.yaml").read_text())
    data["safety"]["watchdog"]["policy"] = policy
    return data


@pytest.mark.req("SR-WD-2")
@pytest.mark.parametrize(
    ("policy", "state"), [("hold", RobotState.STOPPED), ("fault", RobotState.FAULT)]
)
def test_a_watchdog_stop_stops_the_robot(policy: str, state: RobotState) -> None:
    slave = SimSlave(_slave_config(policy))
    try:
        run(slave)
        slave.step_ms(20)
        n = len(slave.replies)
        slave.robot.watchdog.feed(0.060, 0.0)  # a 60 ms gap between ticks (hard limit 50 ms)
        assert slave.robot.state is state
        alerts = [m for m in slave.replies[n:] if m.message_type == "STATUS"]
        assert any("watchdog: gap of 60.000 ms" in m.status_message for m in alerts), alerts
        q = list(slave.robot.data.q)
        slave.master_pos[0] = 20.0  # the master moves on: the robot does not
        slave.step_ms(100)
        assert list(slave.robot.data.q) == pytest.approx(q, abs=1e-6)
        assert slave.robot.state is state  # latched
    finally:
        slave.close()


@pytest.mark.req("SR-ROUTE-1")
def test_errors_and_refusals_go_only_to_the_asker(slave: SimSlave) -> None:
    bob = slave.sim.peer("operator")
    viewer = slave.sim.peer("slicer")
    for name in ("Fly", "Run"):  # unknown; not allowed in READY
        cid = slave.operator.send_command(name)
        slave.tick()
        assert slave.operator.reply_to(cid).metadata["Status"] == "FAIL"
    cid = viewer.send_command("Enable")  # a viewer may not command: refused, to it alone
    slave.tick()
    assert viewer.reply_to(cid).metadata["Status"] == "FAIL"
    assert slave.robot.state is RobotState.READY
    slave.operator.send(igtl.StringMessage("GetState", device_name="CMD_7", header_version=2))
    slave.tick()
    assert any(m.device_name == "ACK_7" for m in slave.operator.messages("STRING"))
    for other in (bob, viewer):
        assert [m for m in other.messages("STRING") if m.device_name.startswith("ACK_")] == []
    assert bob.messages("RTS_COMMAND") == []
    assert [m.metadata.get("Status") for m in viewer.messages("RTS_COMMAND")] == ["FAIL"]


@pytest.mark.req("SR-TELE-1")
def test_slave_follows_scaled_master_motion_without_jump(slave: SimSlave) -> None:
    run(slave)
    slave.step_ms(50)
    tip0 = slave.robot.data.tip[:3, 3].copy()
    # master moves 20 mm in x (scaled 10:1 -> 2 mm at the slave), in small steps
    for i in range(200):
        slave.master_pos[0] = 20.0 * (i + 1) / 200
        slave.step_ms(2)
    slave.step_ms(300)
    moved = (slave.robot.data.tip[:3, 3] - tip0) * 1000.0
    assert moved[0] == pytest.approx(2.0, abs=0.05)
    assert abs(moved[1]) < 0.05 and abs(moved[2]) < 0.05


@pytest.mark.req("SR-CLUTCH-1")
def test_clutch_reindexes(slave: SimSlave) -> None:
    run(slave)
    slave.step_ms(50)
    tip0 = slave.robot.data.tip[:3, 3].copy()
    slave.master_pos[0] = 100.0  # a big master jump while not running (run=0)
    slave.step_ms(100, run=False)
    slave.step_ms(300)  # run again: the slave re-indexes, it must not jump 10 mm
    assert abs((slave.robot.data.tip[:3, 3] - tip0)[0] * 1000.0) < 0.05
    assert slave.robot.controller.stats()["reindexes"] >= 2


@pytest.mark.req("SR-HOLD-1")
def test_unknown_and_refused_commands_change_nothing(slave: SimSlave) -> None:
    r = slave.command("Fly")
    assert r.metadata["Status"] == "FAIL" and "Fly" in r.metadata["Error"]
    r = slave.command("Run")  # READY -> Run is not allowed
    assert r.metadata["Status"] == "FAIL"
    assert slave.robot.state is RobotState.READY
    r = slave.command("GetState")
    assert r.metadata["Status"] == "SUCCESS" and "READY" in r.metadata["Message"]


@pytest.mark.req("SR-STATE-1")
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
    slave.operator.send(igtl.StringMessage('<Command Name="Enable"/>', device_name="CMD_7"))
    slave.tick()
    ack = [r for r in slave.replies if r.message_type == "STRING" and r.device_name == "ACK_7"]
    assert ack and 'Status="SUCCESS"' in ack[-1].string
    assert slave.robot.state is RobotState.ENABLED
    get = igtl.REGISTRY["GET_STATUS"]
    slave.operator.send(get(type_name="GET_STATUS"))
    slave.tick()
    st = [r for r in slave.replies if r.message_type == "STATUS"][-1]
    assert st.error_name == "ENABLED"


def test_tip_is_sent_in_world_coordinates_with_the_base_offset() -> None:
    s = SimSlave(base_mm=(100.0, -20.0, 5.0))
    try:
        s.operator.send(igtl.REGISTRY["GET_TRANS"](type_name="GET_TRANS", device_name="Tip"))
        s.tick()
        tip = [r for r in s.replies if r.message_type == "TRANSFORM" and r.device_name == "Tip"][-1]
        fk = s.robot.data.tip[:3, 3] * 1000.0
        assert tip.translation == pytest.approx(
            (fk[0] + 100.0, fk[1] - 20.0, fk[2] + 5.0), abs=1e-3
        )
    finally:
        s.close()


def test_base_pose_from_a_tracker_transform() -> None:
    from occ.config import InputConfig

    cfg = load_config(ROOT / "configs" / "slave.yaml")
    slicer = cfg.interface("slicer").model_copy(
        update={"inputs": (InputConfig(type="TRANSFORM", device="Base", queue="stream", depth=10),)}
    )
    cfg = cfg.model_copy(
        update={
            "interfaces": tuple(slicer if i.name == "slicer" else i for i in cfg.interfaces),
        }
    ).with_params(base_interface="slicer", base_mm=None)
    with SimRobot(cfg) as sim:
        robot = sim.robot
        tracker = sim.peer("slicer")
        m = igtl.TransformMessage.from_position((10.0, 20.0, 30.0), device_name="Base")
        assert tracker.send(m) == 1
        sim.tick()
        assert robot.data.base[:3, 3] * 1000.0 == pytest.approx([10.0, 20.0, 30.0])
        assert robot.data.world_tip()[:3, 3] * 1000.0 == pytest.approx(
            robot.data.tip[:3, 3] * 1000.0 + [10, 20, 30]
        )


def test_joints_must_match_the_kinematic_model() -> None:
    from occ.errors import OCCError

    cfg = load_config(ROOT / "configs" / "slave.yaml")
    joints = (cfg.robot.joints[1], cfg.robot.joints[0], cfg.robot.joints[2])  # order swapped
    bad = cfg.model_copy(update={"robot": cfg.robot.model_copy(update={"joints": joints})})
    with pytest.raises(OCCError, match="do not match the joints of the kinematic model"):
        build_robot(bad, clock=SimClock())


@pytest.mark.req("SR-OWN-1")
def test_the_stream_belongs_to_its_first_sender_until_reset(slave: SimSlave) -> None:
    run(slave)
    slave.step_ms(20)
    setpoint = driver_setpoint(slave)
    intruder = slave.sim.peer("master", address=("127.0.0.1", 40999))
    iface = slave.robot.interfaces["master"]
    # a second local sender with plausible numbers and a far target: refused, robot unmoved
    for _ in range(20):
        slave.master_pos[0] += 300.0
        slave.seq += 1  # the next number the owner will send
        assert intruder.send(slave.position()) == 1
        slave.seq -= 1
        slave.master_pos[0] -= 300.0
        slave.step_ms(1)  # the owner's stream goes on (one packet every 2 ms)
    assert iface.counters.foreign == 20
    assert driver_setpoint(slave) == pytest.approx(setpoint, abs=1e-9)
    assert iface.stats()["stream_owner"] == ["127.0.0.1", 40000]
    # after a Reset a restarted master (a new port) may own the stream
    assert slave.robot.state is RobotState.RUNNING
    assert slave.command("Stop").metadata["Status"] == "SUCCESS"
    assert slave.command("Reset").metadata["Status"] == "SUCCESS"
    assert iface.stream_owner is None
    slave.seq += 1
    intruder.send(slave.position())
    assert iface.stream_owner == ("127.0.0.1", 40999)


@pytest.mark.req("SR-SUP-1")
def test_a_hung_tick_trips_the_supervisor_drivers_stop_then_fault(slave: SimSlave) -> None:
    run(slave)
    sup = slave.robot.supervisor
    for _ in range(4):  # the supervisor thread checks every 5 ms
        slave.step_ms(5)
        assert sup.check((slave.k - 1) * 0.001) is None
    last = slave.k - 1
    # the loop hangs inside a tick; the supervisor goes on checking every 5 ms
    for dt in (0.005, 0.010, 0.015, 0.020):
        assert sup.check(last * 0.001 + dt) is None
    reason = sup.check(last * 0.001 + 0.025)
    assert reason is not None and "did not tick for 25.0 ms" in reason
    drv = slave.robot.hardware.drivers[0]
    assert drv.state.value == "fault" and drv.fault_reason.startswith("safe stop: ")
    alerts = [
        r for r in slave.replies if r.message_type == "STATUS" and r.error_name == "SUPERVISOR"
    ]
    assert alerts and reason in alerts[-1].status_message
    # the loop comes back: latched FAULT, and it stays there until Reset
    slave.step_ms(5)
    assert slave.robot.state is RobotState.FAULT
    assert "supervisor" in slave.robot.describe_state()
    assert slave.command("Reset").metadata["Status"] == "SUCCESS"
    assert slave.robot.state is RobotState.READY and not sup.tripped
    assert slave.command("Enable").metadata["Status"] == "SUCCESS"
    assert drv.state.value == "active"


@pytest.mark.req("SR-SUP-1")
def test_a_hung_tick_of_an_unpowered_robot_is_an_alert_and_is_watched_again(
    slave: SimSlave,
) -> None:
    """READY, every drive off: nothing moved or could; a loaded machine's stall is told, not
    latched, and the supervisor watches again (a later trip while powered still faults)."""
    slave.step_ms(5)
    assert slave.robot.state is RobotState.READY
    sup = slave.robot.supervisor
    last = slave.k - 1
    assert sup.check(last * 0.001 + 0.010) is None
    assert sup.check(last * 0.001 + 0.025) is not None
    slave.step_ms(2)
    assert slave.robot.state is RobotState.READY and not sup.tripped
    alerts = [
        r for r in slave.replies if r.message_type == "STATUS" and r.error_name == "SUPERVISOR"
    ]
    assert alerts and "no drive powered: not latched" in alerts[-1].status_message
    run(slave)
    last = slave.k - 1
    assert sup.check(last * 0.001 + 0.010) is None
    assert sup.check(last * 0.001 + 0.025) is not None
    slave.step_ms(2)
    assert slave.robot.state is RobotState.FAULT


@pytest.mark.req("SR-HB-1")
def test_sim_drives_stop_themselves_when_the_loop_stops_refreshing(slave: SimSlave) -> None:
    run(slave)
    slave.step_ms(20)
    slave.sim.stall(200)  # the whole process froze for 200 ms (supervisor frozen too)
    slave.step_ms(2)
    assert slave.robot.state is RobotState.FAULT
    assert "heartbeat lost" in slave.robot.last_alert


def _with_raw_name(msg: igtl.Message, name: bytes) -> bytes:
    """``msg`` as a peer might send it: a device name that is not valid UTF-8."""
    data = bytearray(msg.pack())
    data[14:34] = name.ljust(20, b"\0")
    return bytes(data)


def _packs(m: igtl.Message) -> bool:
    return len(m.pack()) >= 58


def test_names_that_cannot_be_re_encoded_are_answered_safely(slave: SimSlave) -> None:
    cmd = _with_raw_name(
        igtl.StringMessage('<Command Name="GetState"/>', device_name="CMD_x", header_version=2),
        b"CMD_" + b"\xff" * 16,
    )
    get = _with_raw_name(
        igtl.REGISTRY["GET_STATUS"](type_name="GET_STATUS", device_name="x"), b"\xff" * 20
    )
    answers = []
    for data in (cmd, get):
        slave.replies.clear()
        assert slave.operator.send(data) == 1
        slave.tick()
        mine = [r for r in slave.replies if r.message_type in ("STRING", "STATUS")]
        assert len(mine) == 1, f"no answer to {igtl.unpack(data).message_type}"
        assert _packs(mine[0])
        answers.append(mine[0])
    ack, status = answers
    assert ack.device_name.startswith("ACK_") and 'Status="SUCCESS"' in ack.string
    assert status.message_type == "STATUS" and status.error_name == "READY"
    assert slave.robot.operators.reply_errors == 0 and slave.robot.state is RobotState.READY


def test_xml_with_a_dtd_is_refused_before_parsing(slave: SimSlave) -> None:
    laughs = (
        '<?xml version="1.0"?><!DOCTYPE l [<!ENTITY a "aaaaaaaaaa">'
        + "".join(
            f'<!ENTITY {c} "&{p};&{p};&{p};&{p};&{p};&{p};&{p};&{p};&{p};&{p};">'
            for p, c in zip("abcdefg", "bcdefgh")
        )
        + ']><Command Name="&h;"/>'
    )
    slave.operator.send(igtl.StringMessage(laughs, device_name="CMD_9"))
    # answered at once by the interface thread, never queued for the loop
    assert len(slave.robot.interfaces.commands) == 0
    ack = slave.replies[-1]
    assert ack.device_name == "ACK_9" and 'Status="FAIL"' in ack.string and "DOCTYPE" in ack.string
    big = '<Command Name="Run" X="' + "y" * 9000 + '"/>'
    slave.operator.send(igtl.StringMessage(big, device_name="CMD_10"))
    assert "too long" in slave.replies[-1].string


@pytest.mark.req("SR-ROUTE-1")
def test_command_replies_echo_the_request_message_id(slave: SimSlave) -> None:
    cls = igtl.REGISTRY["COMMAND"]
    msg = cls(
        command_id=5,
        command_name="GetState",
        command="",
        device_name="command",
        header_version=2,
        message_id=4242,
    )
    slave.operator.send(msg)
    slave.tick()
    rts = [r for r in slave.replies if r.message_type == "RTS_COMMAND"][-1]
    assert rts.message_id == 4242 and rts.command_id == 5


@pytest.mark.req("SR-ROUTE-1")
def test_query_replies_echo_the_request_message_id(slave: SimSlave) -> None:
    """GET_TRANS, GET_STATUS, GET_CAPABIL and an STT_ query nobody streams: each answer
    carries the asker's v2 message ID (SR-ROUTE-1)."""
    asks = [
        igtl.REGISTRY[t](type_name=t, device_name=d, header_version=2, message_id=i)
        for t, d, i in [
            ("GET_TRANS", "Tip", 71),
            ("GET_STATUS", "slave", 72),
            ("GET_CAPABIL", "slave", 73),
            ("STT_TDATA", "Tip", 74),
        ]
    ]
    for ask in asks:
        slave.operator.send(ask)
    slave.tick()
    got = {r.message_type: r.message_id for r in slave.replies}
    assert got["TRANSFORM"] == 71 and got["STATUS"] == 72 and got["CAPABILITY"] == 73
    assert got["RTS_TDATA"] == 74


def test_a_command_whose_bytes_do_not_fit_its_declared_charset_is_answered(slave: SimSlave) -> None:
    text = '<Command Name="GetState" Note="é"/>'.encode().decode("ascii", "surrogateescape")
    msg = igtl.StringMessage(text, 3, True, device_name="CMD_5")  # US-ASCII declared
    slave.operator.send(msg)
    slave.tick()
    ack = [r for r in slave.replies if r.message_type == "STRING" and r.device_name == "ACK_5"]
    assert ack and _packs(ack[-1])
