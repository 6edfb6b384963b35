"""The teleoperation mapping of the slave, exact to float precision (occ/controllers/teleop/).

``target = slave_ref + scale * R * (master - master_ref)``: the slave robot (configs/slave.yaml)
on in-process channels, stepped tick by tick; the master's stream comes from a peer. The
slave's inverse kinematics is analytic, so the tip of the setpoint it writes is the mapped
target to ~1e-9 mm, and every entry of ``scale * R`` can be read back from it. Each of these
tests was written against a mutant that the older, coarser tests let live
(docs/VERIFICATION.md, "teleop").
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

import igtl
from occ.kinematics.frame import Frame
from occ.core.safety import RobotState
from occ_testkit.rigs import SimMaster, SlaveRig
from occ_testkit.testing import SlaveTipFeed

ROOT = Path(__file__).resolve().parents[2]
#: where the master's handle is when the tests start (mm)
HANDLE = (0.0, 50.0, 270.0)

# controllers that never use their frame still get a real one (a compiled ControllerContext checks
# the type of each field)
SLAVE_FRAME = Frame.builtin("occ_slave")


def rotation(yaw: float, pitch: float, roll: float) -> list[list[float]]:
    """A rotation whose nine entries all differ (a swapped index changes the mapping)."""
    cz, sz = math.cos(yaw), math.sin(yaw)
    cy, sy = math.cos(pitch), math.sin(pitch)
    cx, sx = math.cos(roll), math.sin(roll)
    rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    return (rz @ ry @ rx).tolist()


R = rotation(0.3, -0.5, 0.7)


@pytest.fixture
def rig() -> Any:
    r = SlaveRig(target=HANDLE)
    yield r
    r.close()


@pytest.mark.req("SR-TELE-1")
def test_every_entry_of_scale_times_rotation_is_applied() -> None:
    rig = SlaveRig(params={"scale": 0.2, "rotation": R}, target=HANDLE)
    try:
        rig.running()
        start = rig.tip_mm()
        stats = rig.ctl.stats()
        assert stats["slave_ref_mm"] == pytest.approx(start.tolist(), abs=1e-6)
        assert stats["master_ref_mm"] == pytest.approx(rig.target)
        m0 = list(rig.target)
        for axis in range(3):  # 3 mm along each master axis in turn: one column of 0.2 R each
            rig.target = list(m0)
            rig.target[axis] += 3.0
            rig.step(2)
            moved = rig.tip_mm() - start
            expect = [0.2 * 3.0 * R[row][axis] for row in range(3)]
            assert moved.tolist() == pytest.approx(expect, abs=1e-6), axis
        rig.target = [m0[0] + 1.0, m0[1] - 2.0, m0[2] + 4.0]  # a general displacement
        rig.step(2)
        d = np.array([1.0, -2.0, 4.0])
        expect = (0.2 * np.array(R) @ d).tolist()
        assert (rig.tip_mm() - start).tolist() == pytest.approx(expect, abs=1e-6)
        assert rig.ctl.stats()["reindexes"] == 1
    finally:
        rig.close()


@pytest.mark.req("SR-CLUTCH-1")
def test_clutch_holds_exactly_and_release_reindexes_where_the_master_is(rig: SlaveRig) -> None:
    rig.running()
    rig.target[0] += 5.0
    rig.step(2)
    before = rig.tip_mm()
    setpoint = list(rig.robot.data.setpoint)
    assert rig.ctl.stats()["reindexes"] == 1
    rig.clutch = True
    for _ in range(10):
        rig.target[1] += 2.0
        rig.step(2)
        assert list(rig.robot.data.setpoint) == setpoint  # not one bit of motion
    stats = rig.ctl.stats()
    assert stats["master_clutch"] is True and stats["master_ref_mm"] is None
    rig.clutch = False
    rig.step(2)  # released 20 mm away: the new references are here, no jump
    stats = rig.ctl.stats()
    assert stats["master_clutch"] is False and stats["reindexes"] == 2
    assert stats["master_ref_mm"] == pytest.approx(rig.target)
    assert rig.tip_mm().tolist() == pytest.approx(before.tolist(), abs=1e-6)
    rig.target[2] -= 10.0
    rig.step(2)
    assert (rig.tip_mm() - before).tolist() == pytest.approx([0.0, 0.0, -1.0], abs=1e-6)
    assert rig.ctl.stats()["reindexes"] == 2  # pressing and holding does not re-index again


@pytest.mark.req("SR-CLUTCH-1")
def test_run_flag_zero_holds_and_its_rising_edge_reindexes(rig: SlaveRig) -> None:
    rig.running()
    setpoint = list(rig.robot.data.setpoint)
    before = rig.tip_mm()
    rig.run = False
    rig.target[0] += 30.0
    rig.step(10)
    assert list(rig.robot.data.setpoint) == setpoint
    assert rig.ctl.stats()["master_run"] is False
    rig.run = True
    rig.step(2)
    stats = rig.ctl.stats()
    assert stats["master_run"] is True and stats["reindexes"] == 2
    assert rig.tip_mm().tolist() == pytest.approx(before.tolist(), abs=1e-6)
    rig.target[0] += 1.0
    rig.step(2)
    assert (rig.tip_mm() - before).tolist() == pytest.approx([0.1, 0.0, 0.0], abs=1e-6)


@pytest.mark.req("SR-TELE-1")
def test_entering_running_reindexes_from_the_held_pose(rig: SlaveRig) -> None:
    rig.running()
    rig.target[0] += 10.0
    rig.step(4)
    rig.command("Stop")
    held = rig.tip_mm()
    rig.target[0] += 40.0  # the master moves on while the slave is stopped
    rig.step(10)
    rig.command("Run")
    rig.step(2)
    assert rig.robot.state is RobotState.RUNNING
    assert rig.ctl.stats()["reindexes"] == 2
    assert rig.tip_mm().tolist() == pytest.approx(held.tolist(), abs=1e-6)


def test_samples_are_counted_and_filtered_by_interface_device_and_type() -> None:
    rig = SlaveRig(params={"input_device": "Master"}, target=HANDLE)
    try:
        rig.running()
        stats = rig.ctl.stats()
        n = stats["samples"]
        assert stats["last_seq"] == rig.seq and stats["source"] == "master"
        assert stats["source_changes"] == 0
        before = rig.tip_mm()
        # another device on the same interface: ignored
        rig.seq += 1
        rig.source.send_position(
            (rig.target[0] + 50.0, rig.target[1], rig.target[2]), seq=rig.seq, device="Other"
        )
        rig.sim.tick()
        rig.sim.tick()
        assert rig.ctl.stats()["samples"] == n
        assert rig.tip_mm().tolist() == pytest.approx(before.tolist(), abs=1e-9)
    finally:
        rig.close()


def test_a_sample_on_another_interface_is_not_followed() -> None:
    rig = SlaveRig(target=HANDLE)
    try:
        rig.running()
        n = rig.ctl.stats()["samples"]
        before = rig.tip_mm()
        other = rig.sim.peer("operator", address=("127.0.0.1", 40009))
        other.send_position((rig.target[0] + 50.0, rig.target[1], rig.target[2]), seq=1)
        rig.sim.tick()
        rig.sim.tick()
        assert rig.ctl.stats()["samples"] == n and rig.ctl.stats()["source"] == "master"
        assert rig.tip_mm().tolist() == pytest.approx(before.tolist(), abs=1e-9)
    finally:
        rig.close()


# -- the master's side: its stream, the clutch command, the fixture commands ---------------
@pytest.fixture
def master() -> Any:
    m = SimMaster()
    yield m
    m.close()


def _status(reply: igtl.Message) -> tuple[str, str]:
    md = reply.metadata
    return md["Status"], md.get("Message", "") + md.get("Error", "")


@pytest.mark.req("SR-CLUTCH-1")
def test_clutch_command_values(master: SimMaster) -> None:
    cases = [
        ('<Command Name="Clutch" Value="1"/>', True),
        ('<Command Name="Clutch" Value="0"/>', False),
        ('<Command Name="Clutch" Value=" TRUE "/>', True),
        ('<Command Name="Clutch" Value="off"/>', False),
        ('<Command Name="Clutch" value="On"/>', True),  # the attribute in lower case too
        ('<Command Name="Clutch" value="no"/>', False),
        ('<Command Name="Clutch" Value="Yes"/>', True),
        ('<Command Name="Clutch" Value="false"/>', False),
        ('<Command Name="Clutch"/>', True),  # no value: pressed
    ]
    for text, pressed in cases:
        status, message = _status(master.command("Clutch", text))
        assert status == "SUCCESS", text
        assert message == ("clutch pressed" if pressed else "clutch released"), text
        assert master.ctl.clutch is pressed, text
        master.sim.step(2)
        assert master.sent[-1].metadata["clutch"] == ("1" if pressed else "0"), text


def test_the_stream_carries_the_handle_the_time_and_the_run_flag(master: SimMaster) -> None:
    master.sim.step(4)
    m = master.sent[-1]
    assert m.metadata["run"] == "0" and m.device_name == "Master"
    for name in ("Enable", "Run"):
        assert _status(master.command(name))[0] == "SUCCESS"
    n = len(master.sent)
    while len(master.sent) == n:  # the next tick that sends (500 Hz: every other tick)
        master.sim.tick()
    m = master.sent[-1]
    assert m.timestamp == pytest.approx(master.sim.clock.wall_time(), abs=1e-6)
    assert m.metadata["run"] == "1" and m.device_name == "Master" and m.layout == 24
    # with the hand's energy into the channel (passivity on, the slave's force displayed): the
    # slave's port keeps what it puts into the tissue below it
    assert dict(m.metadata) == {"run": "1", "clutch": "0", "energy_j": "0"}
    assert tuple(m.quaternion[:3]) == (0.0, 0.0, 0.0)
    tip = master.robot.frame.tip_position(master.robot.data.q)
    assert m.position == pytest.approx([v * 1e3 for v in tip], abs=1e-3)


def test_fixture_commands_and_unknown_ones(master: SimMaster) -> None:
    status, message = _status(master.command("GetFixtures"))
    assert (status, message) == ("SUCCESS", "0 fixtures; models follow")
    status, message = _status(master.command("ClearFixtures"))
    assert (status, message) == ("SUCCESS", "fixtures cleared")
    status, message = _status(master.command("Fly"))
    assert status == "FAIL" and "unknown command 'Fly'" in message
    # a master without a gripper has no Grip: refused as any unknown command
    status, message = _status(master.command("Grip", '<Command Name="Grip" Value="close"/>'))
    assert status == "FAIL" and "unknown command 'Grip'" in message
    status, message = _status(master.command("Select", '<Command Name="Select" to="left"/>'))
    assert status == "FAIL" and "nothing to select" in message


def test_select_names_the_slave_in_either_case() -> None:
    from occ.core.loader import load_config

    cfg = load_config(ROOT / "configs" / "master.yaml")
    link = cfg.interface("slave")
    links = [link.model_copy(update={"name": side}) for side in ("left", "right")]
    cfg = cfg.model_copy(
        update={"interfaces": (*[i for i in cfg.interfaces if i.name != "slave"], *links)}
    ).with_params(slaves=["left", "right"])
    m = SimMaster(cfg, link="left")
    try:
        assert _status(m.command("Select", '<Command Name="Select" to="right"/>')) == (
            "SUCCESS",
            "slave left -> right",
        )
        assert _status(m.command("Select", '<Command Name="Select" To="left"/>')) == (
            "SUCCESS",
            "slave right -> left",
        )
        status, message = _status(m.command("Select"))
        assert status == "FAIL" and "slave interface '' is not one of ['left', 'right']" in message
    finally:
        m.close()


def test_a_target_outside_the_workspace_is_clamped_once_per_sample(rig: SlaveRig) -> None:
    rig.running()
    rig.target[2] += 5000.0  # 500 mm deeper at the slave: past the insertion limit
    rig.step(10)  # five samples, ten ticks: each sample solved once
    assert rig.ctl.stats()["ik_clamped"] == 5
    setpoint = list(rig.robot.data.setpoint)
    rig.sim.tick()  # no new sample: the same target, not solved again
    assert rig.ctl.stats()["ik_clamped"] == 5 and list(rig.robot.data.setpoint) == setpoint


def test_a_sample_that_cannot_be_solved_is_counted_and_the_slave_holds(rig: SlaveRig) -> None:
    rig.running()
    setpoint = list(rig.robot.data.setpoint)
    good = list(rig.target)
    rig.target = [math.nan, good[1], good[2]]
    rig.step(4)  # two samples the inverse kinematics refuses
    assert rig.ctl.stats()["ik_failures"] == 2
    assert list(rig.robot.data.setpoint) == setpoint
    rig.target = [good[0] + 1.0, good[1], good[2]]
    rig.step(2)  # and a good one is followed again, from the same references
    assert rig.ctl.stats()["ik_failures"] == 2 and rig.ctl.stats()["reindexes"] == 1
    assert rig.robot.data.setpoint != setpoint


def test_sample_latency_is_measured_from_the_masters_timestamp(rig: SlaveRig) -> None:
    rig.running()
    for _ in range(10):
        # sampled 0.5 ms before it is sent, sent one tick (1 ms) before the tick that uses it
        rig.seq += 1
        stamp = rig.sim.clock.wall_time() - 0.0005
        rig.source.send_position(rig.target, seq=rig.seq, timestamp=stamp)
        rig.sim.tick()
        rig.sim.tick()
    stats = rig.ctl.stats()
    lat = stats["sample_to_write_us"]
    assert lat["n"] == 10 and lat["p50"] == pytest.approx(1500.0, abs=1.0)
    assert lat["max"] == pytest.approx(1500.0, abs=1.0)
    # received by the interface as it was sent: 0.5 ms from the sample to the reception
    assert stats["sample_to_rx_us"]["p50"] == pytest.approx(500.0, abs=1.0)
    assert stats["sample_to_rx_us"]["p99"] == pytest.approx(500.0, abs=1.0)


def test_stop_and_run_between_two_stamped_samples_keeps_following(rig: SlaveRig) -> None:
    rig.running()
    rig.seq += 1
    rig.source.send_position(rig.target, seq=rig.seq, timestamp=rig.sim.clock.wall_time())
    rig.sim.tick()  # the stamped sample is followed (its latency measured)
    rig.command("Stop")
    rig.command("Run")
    assert rig.robot.state is RobotState.RUNNING
    # no new sample yet: no reference from the one before the stop (issue 37: after a latched
    # loss the master has moved on, and its next sample would jump the tool); the next one
    # re-indexes, and the slave follows from there
    assert rig.ctl.stats()["reindexes"] == 1
    rig.step(2)
    assert rig.ctl.stats()["reindexes"] == 2
    before = rig.tip_mm()
    rig.target[1] += 10.0
    rig.step(2)
    assert rig.robot.state is RobotState.RUNNING
    assert (rig.tip_mm() - before)[1] != 0.0 and rig.ctl.stats()["reindexes"] == 2


def test_the_base_pose_from_a_tracker_does_not_stop_the_following() -> None:
    from occ.config import InputConfig
    from occ.core.loader import load_config

    cfg = load_config(ROOT / "configs" / "slave.yaml")
    slicer = cfg.interface("slicer").model_copy(
        update={
            "inputs": (
                InputConfig(type="TRANSFORM", queue="stream", depth=10),
                InputConfig(type="POSITION", queue="stream", depth=10),
            )
        }
    )
    cfg = cfg.model_copy(
        update={
            "interfaces": tuple(slicer if i.name == "slicer" else i for i in cfg.interfaces),
        }
    ).with_params(base_interface="slicer", base_mm=None)
    rig = SlaveRig(cfg, target=HANDLE)
    try:
        tracker = rig.sim.peer("slicer")
        tracker.send(igtl.TransformMessage.from_position((10.0, 20.0, 30.0), device_name="Base"))
        rig.sim.tick()
        expect = np.eye(4)
        expect[:3, 3] = [0.010, 0.020, 0.030]
        assert rig.robot.data.base.ravel().tolist() == pytest.approx(
            expect.ravel().tolist(), abs=1e-12
        )
        # other devices and types on the tracker's interface leave the base alone
        tracker.send(igtl.TransformMessage.from_position((1.0, 2.0, 3.0), device_name="Probe"))
        tracker.send(
            igtl.PositionMessage((4.0, 5.0, 6.0), (0.0, 0.0, 0.0, 1.0), 24, device_name="Base")
        )
        rig.sim.tick()
        assert rig.robot.data.base.ravel().tolist() == pytest.approx(
            expect.ravel().tolist(), abs=1e-12
        )
        rig.running()  # and the master's stream is still followed
        before = rig.tip_mm()
        rig.target[0] += 10.0
        rig.step(2)
        assert (rig.tip_mm() - before).tolist() == pytest.approx([1.0, 0.0, 0.0], abs=1e-6)
    finally:
        rig.close()


def test_the_simulated_hand_resumes_where_it_was_held() -> None:
    from tests.occ.test_master_sim import position_master

    m = SimMaster(position_master())
    try:
        ctl = m.ctl
        assert _status(m.command("Enable"))[0] == "SUCCESS"
        assert _status(m.command("Run"))[0] == "SUCCESS"
        t_run1 = m.sim.now - m.sim.period  # the tick that entered RUNNING
        m.sim.step(700)
        assert _status(m.command("Stop"))[0] == "SUCCESS"
        t_stop = m.sim.now - m.sim.period  # the tick that left RUNNING
        held = ctl.operator_target(t_stop)
        m.sim.step(500)  # time passes while stopped: the hand's trajectory does not
        assert _status(m.command("Run"))[0] == "SUCCESS"
        t_run2 = m.sim.now - m.sim.period
        assert ctl.operator_target(t_run2) == pytest.approx(held, abs=1e-12)
        m.sim.step(300)
        t = m.sim.now
        run_time = (t_stop - t_run1) + (t - t_run2)  # the time spent RUNNING, only
        w = 2 * math.pi * 0.1
        ox, oy, oz = (ctl.origin + np.array([0.0, 0.0, 0.020])).tolist()
        x, y, z = ctl.operator_target(t)
        assert (x - ox, y - oy, z - oz) == pytest.approx(
            (0.050 * math.sin(w * run_time), 0.050 * math.cos(w * run_time), 0.0), abs=1e-12
        )
    finally:
        m.close()


def test_on_sample_takes_position_and_transform_and_counts_source_changes() -> None:
    """The controller alone (no robot): which samples it takes and from whom."""
    from occ.clock import SimClock
    from occ.controllers import ControllerContext
    from occ.controllers.teleop import SlaveController
    from occ.net.decoders import pose_sample

    ctrl = SlaveController({"phase_lock_us": None})
    ctrl.ctx = ControllerContext(
        clock=SimClock(),
        frame=SLAVE_FRAME,
        rate_hz=1000.0,
        interfaces=(),  # type: ignore[arg-type]
        loop_t0=lambda: math.nan,
        period_s=0.001,
        shift=lambda s: None,
    )

    def take(itf: str, msg: igtl.Message, t: float) -> None:
        sample = pose_sample(itf, None, msg, t)  # what the interface makes of it
        if sample is not None:  # not a pose: no sample (the interface passes it on as an input)
            ctrl.on_sample(sample, t)

    assert ctrl.stats() == {  # before any sample
        "mapping": "relative",
        "samples": 0,
        "last_seq": None,
        "master_run": False,
        "master_clutch": False,
        "reindexes": 0,
        "source": None,
        "source_changes": 0,
        "ik_clamped": 0,
        "ik_failures": 0,
        "phase_shifts": 0,
        "phase_error_us": None,
        "phase_history_us": [],
        "master_ref_mm": None,
        "slave_ref_mm": None,
    }

    take(
        "a",
        igtl.PositionMessage((1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), 24, device_name="Master"),
        0.001,
    )
    assert ctrl.master_pos == pytest.approx((0.001, 0.002, 0.003))
    take("a", igtl.StringMessage("hello", device_name="Master"), 0.002)  # not a pose: ignored
    assert ctrl.samples == 1 and ctrl.master_pos == pytest.approx((0.001, 0.002, 0.003))
    take("b", igtl.TransformMessage.from_position((4.0, 5.0, 6.0), device_name="Master"), 0.003)
    assert ctrl.master_pos == pytest.approx((0.004, 0.005, 0.006))
    take("a", igtl.TransformMessage.from_position((7.0, 8.0, 9.0), device_name="Master"), 0.004)
    stats = ctrl.stats()
    assert stats["samples"] == 3 and stats["source"] == "a" and stats["source_changes"] == 2
    # no run/clutch metadata (a plain tracker, a v1 peer): following, not clutched
    assert ctrl.last_sample_t == 0.004 and ctrl.master_run is True
    assert ctrl.master_clutch is False


def test_only_the_configured_interface_and_device_are_followed() -> None:
    from occ.clock import SimClock
    from occ.controllers import ControllerContext
    from occ.controllers.teleop import SlaveController
    from occ.net.decoders import pose_sample

    ctrl = SlaveController(
        {"input_interface": "master", "input_device": "Master", "phase_lock_us": None}
    )
    ctrl.ctx = ControllerContext(
        clock=SimClock(),
        frame=SLAVE_FRAME,
        rate_hz=1000.0,
        interfaces=(),  # type: ignore[arg-type]
        loop_t0=lambda: math.nan,
        period_s=0.001,
        shift=lambda s: None,
    )
    for itf, dev in (("other", "Master"), ("master", "Other")):
        msg = igtl.PositionMessage((1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), 24, device_name=dev)
        ctrl.on_sample(pose_sample(itf, None, msg, 0.0), 0.0)  # type: ignore[arg-type]
    assert ctrl.samples == 0 and ctrl.master_pos is None
    msg = igtl.PositionMessage((1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), 24, device_name="Master")
    ctrl.on_sample(pose_sample("master", None, msg, 0.0), 0.0)  # type: ignore[arg-type]
    assert ctrl.samples == 1


@pytest.mark.req("SR-CLUTCH-1")
@pytest.mark.parametrize("held", [2, 1], ids=["held-2-samples", "held-1-sample"])
@pytest.mark.parametrize("flag", ["clutch", "run"])
def test_a_clutch_or_run_cycle_inside_one_tick_still_reindexes(
    rig: SlaveRig, flag: str, held: int
) -> None:
    """Samples queued between two ticks are all seen by on_sample, the mapping only once:
    a press and release (or run 0 then 1) among them must still re-index, or the slave
    would jump by the master's motion while it was not followed. Also when the press is a
    single sample (the shortest the stream carries: the release is the very next one)."""
    rig.running()
    before = rig.tip_mm()
    n = rig.ctl.stats()["reindexes"]
    cycle = [(10.0, False)] + [(20.0, False)] * (held - 1) + [(20.0, True)]
    for moved, following in cycle:
        rig.seq += 1
        rig.source.send_position(
            (moved, 50.0, 270.0),
            seq=rig.seq,
            clutch=(flag == "clutch" and not following),
            run=(flag != "run" or following),
        )
    rig.target = [20.0, 50.0, 270.0]
    rig.sim.tick()
    assert rig.ctl.stats()["reindexes"] == n + 1
    assert rig.tip_mm().tolist() == pytest.approx(before.tolist(), abs=1e-6)


def test_the_masters_fixture_force_is_off_while_the_robot_is_not_running(
    master: SimMaster,
) -> None:
    """Fixtures do not follow the master's handle any more (the tool is the slave's tip): what
    leaving and re-entering RUNNING does is zero the displayed force and fade it back in."""
    feed = SlaveTipFeed(master.sim)
    for name in ("Enable", "Run"):
        assert _status(master.command(name))[0] == "SUCCESS"
    feed.step(50)
    t = feed.handle_mm()
    master.op.send(
        igtl.VirtualFixtureMessage(
            hardness=1.0,
            spheres=((*feed.patient((t[0] + 4.0, t[1], t[2])), 1.0),),
            device_name="VF",
            header_version=2,
            metadata={"kind": "forbidden"},
        )
    )
    feed.step(30)
    assert master.ctl.display.gain == 1.0 and math.hypot(*master.ctl.fixtures.force_n) > 2.0
    assert _status(master.command("Stop"))[0] == "SUCCESS"
    assert master.robot.state is RobotState.STOPPED and master.ctl.display.gain == 0.0
    assert master.ctl.fixtures.force_n == (0.0, 0.0, 0.0)
    feed.step(300)
    assert _status(master.command("Run"))[0] == "SUCCESS"
    feed.step(10)
    assert 0.3 < master.ctl.display.gain < 0.7  # half way through tip_fade_ms
    feed.step(20)
    assert master.ctl.display.gain == 1.0


def test_a_teleop_output_that_is_not_position_faults_and_says_so() -> None:
    import yaml

    raw = yaml.safe_load((ROOT / "configs" / "master.yaml").read_text())
    for itf in raw["interfaces"]:
        if itf["name"] == "slave":
            itf["outputs"][0]["type"] = "TRANSFORM"
    m = SimMaster(raw)
    try:
        m.sim.step(3)
        assert m.robot.state is RobotState.FAULT
        texts = [getattr(s, "status_message", "") for s in m.op.messages("STATUS")]
        assert any("teleop output must be of type POSITION" in t for t in texts), texts
    finally:
        m.close()


@pytest.mark.req("SR-LOSS-2")
@pytest.mark.parametrize("flag", ["run", "clutch", None])
def test_a_re_entry_ramp_after_a_late_stream_finishes_when_the_master_lets_go(
    rig: SlaveRig, flag: str | None
) -> None:
    """The stream goes silent (the slave holds), the master moves 20 mm meanwhile, and the
    slave re-joins the mapped target at half the velocity limits. If the operator then lets go
    (run flag 0 or clutch) in the middle of that ramp, the ramp still ends on the last target
    the slave was given, not where it happened to be."""
    rig.running()
    before = rig.tip_mm()
    reentries = rig.robot.motion.reentries
    for _ in range(12):  # 12 ms without a sample: the loss monitor holds
        rig.sim.tick()
    assert rig.robot.streams.monitor.holding and rig.robot.state is RobotState.RUNNING
    rig.target[0] += 20.0  # 2 mm of the slave's tip at the configured scale
    rig.step(4)
    mid = rig.tip_mm() - before
    assert 0.01 < mid[0] < 1.0  # on the way, far from the target
    if flag is not None:
        setattr(rig, flag, True if flag == "clutch" else False)
    rig.step(300)
    assert (rig.tip_mm() - before).tolist() == pytest.approx([2.0, 0.0, 0.0], abs=1e-6)
    assert rig.robot.motion.reentries == reentries + 1


def test_the_tick_that_stops_the_master_keeps_its_fixture_work_budget(master: SimMaster) -> None:
    """Leaving RUNNING in the middle of a tick: the tick's budget
    of compiled definitions (max_fixtures, 64) goes on counting, so 40 definitions before
    the Stop and 40 after it in the same tick are not 80 compiled in one tick."""
    for name in ("Enable", "Run"):
        assert _status(master.command(name))[0] == "SUCCESS"
    master.sim.step(50)
    spheres = tuple((float(i), 0.0, 0.0, 5.0) for i in range(40))
    burst = igtl.VirtualFixtureMessage(
        hardness=1.0, spheres=spheres, device_name="Burst", header_version=2
    )
    master.op.send(burst)
    cid = master.op.send_command("Stop")
    master.op.send(burst)
    master.sim.tick()  # all three in one tick, in that order
    assert master.robot.state is RobotState.STOPPED
    assert _status(master.op.reply_to(cid))[0] == "SUCCESS"
    refused = [
        m.status_message
        for m in master.op.received
        if m.message_type == "STATUS" and "busy" in m.status_message
    ]
    assert refused == [
        "fixture refused (VFIXTURE 'Burst': busy: 40 fixtures compiled this tick "
        "already; send it again); the previous set stays"
    ]
    stats = master.ctl.stats()
    assert (stats["fixtures"], stats["fixtures_applied"], stats["fixtures_refused"]) == (40, 1, 1)
    master.op.send(burst)
    master.sim.tick()  # the next tick has a budget of its own
    assert master.ctl.stats()["fixtures_applied"] == 2


@pytest.mark.req("SR-EXC-1")
def test_a_refused_fixture_on_a_stream_queue_is_answered_and_faults_nothing() -> None:
    """A VFIXTURE routed to a *stream* queue (a config that treats fixtures as a stream) and
    refused by the fixtures is answered to its sender and counted, as on the command queue,
    and the robot keeps RUNNING (before, the refusal escaped the tick and latched FAULT)."""
    cfg = yaml.safe_load((ROOT / "configs" / "master.yaml").read_text())
    routed = 0
    for itf in cfg["interfaces"]:
        for inp in itf.get("inputs", []):
            if inp["type"] == "VFIXTURE":
                inp["queue"] = "stream"
                routed += 1
    assert routed == 1
    m = SimMaster(cfg)
    try:
        for name in ("Enable", "Run"):
            assert _status(m.command(name))[0] == "SUCCESS"
        m.sim.step(50)
        spheres = tuple((float(i), 0.0, 0.0, 5.0) for i in range(40))
        burst = igtl.VirtualFixtureMessage(
            hardness=1.0, spheres=spheres, device_name="Burst", header_version=2
        )
        m.op.send(burst)
        m.op.send(burst)
        m.sim.tick()  # both in one tick: the second is over the tick's budget of 64
        assert m.robot.state is RobotState.RUNNING
        refused = [
            x.status_message
            for x in m.op.received
            if x.message_type == "STATUS" and "busy" in x.status_message
        ]
        assert refused == [
            "fixture refused (VFIXTURE 'Burst': busy: 40 fixtures compiled this tick "
            "already; send it again); the previous set stays"
        ]
        assert m.robot.operators.refused == 1
        stats = m.ctl.stats()
        assert (stats["fixtures_applied"], stats["fixtures_refused"]) == (1, 1)
    finally:
        m.close()


def test_a_sample_that_is_no_point_is_never_taken_as_the_reference(rig: SlaveRig) -> None:
    """The first samples after Run (the re-index) carry NaN: they are counted as failures and
    the slave holds; the first good sample becomes the reference and the slave follows from
    there (before the fix, the NaN reference made every later target NaN until a clutch)."""
    rig.command("Enable")
    rig.command("Run")
    held = list(rig.robot.data.setpoint)
    good = list(rig.target)
    rig.target = [math.nan, good[1], good[2]]
    rig.step(4)  # two samples, four ticks
    stats = rig.ctl.stats()
    assert stats["ik_failures"] == 2 and stats["master_ref_mm"] is None
    assert list(rig.robot.data.setpoint) == held
    rig.target = [good[0] + 10.0, good[1], good[2]]
    rig.step(2)
    before = rig.tip_mm()
    assert rig.ctl.stats()["master_ref_mm"] == pytest.approx(rig.target)
    rig.target[0] += 5.0
    rig.step(2)
    assert (rig.tip_mm() - before).tolist() == pytest.approx([0.5, 0.0, 0.0], abs=1e-6)
    assert rig.ctl.stats()["ik_failures"] == 2 and rig.ctl.stats()["reindexes"] == 1
