"""The return channel slave -> master (occ/haptics/returnlink.py) in simulated time: what the slave
sends, how the master judges it (late: stale and the force fades; lost or dead: zero at once
and an alert; back: re-armed), and the real pair (configs/slave.yaml + configs/master.yaml on
one SimClock) keeping the tool on the slave's tip through the clutch; the collaborative trio
through a hand-over. Over real sockets: tests/occ/test_fixture_pair_e2e.py."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import igtl
from occ.clock import SimClock
from occ.core.safety import RobotState
from occ_testkit.rigs import SimMaster
from occ_testkit.testing import SimRobot

from ..tools.tooling import load_tool

ROOT = Path(__file__).resolve().parents[2]
standin = load_tool("slicer_standin")


def keepout(master: SimMaster, depth_mm: float = 6.0) -> None:
    """A forbidden sphere (radius 1 mm patient = 10 mm of the handle) with the tool
    ``depth_mm`` (of the handle) deep, on the tool's -x side of the centre."""
    t = master.feed.handle_mm()
    c = master.feed.patient((t[0] + 10.0 - depth_mm, t[1], t[2]))
    master.op.send(
        igtl.VirtualFixtureMessage(
            hardness=0.5,
            spheres=((*c, 1.0),),
            device_name="VF",
            header_version=2,
            metadata={"kind": "forbidden"},
        )
    )
    master.feed.step(1)


def force(master: SimMaster) -> float:
    """The fixtures' force on the handle (N)."""
    return math.hypot(*master.ctl.fixtures.force_n)


@pytest.fixture
def master() -> Any:
    m = SimMaster(feed=True)
    yield m
    m.close()


# ------------------------------------------------------------------ the master's loss rules
@pytest.mark.req("SR-FIX-2")
def test_a_late_tip_is_kept_marked_stale_and_its_force_fades_never_recomputed(master) -> None:
    master.run()
    keepout(master)
    master.feed.step(5)
    f0 = master.ctl.fixtures.force_n
    assert math.hypot(*f0) == pytest.approx(3.0, abs=0.3)
    tip = master.ctl.stats()["tool_mm"]
    master.feed.paused = True  # the slave's samples stop coming (not lost yet)
    forces = []
    for _ in range(40):
        master.feed.step(1)
        forces.append(master.ctl.fixtures.force_n)
    st = master.ctl.stats()
    assert st["slave_tip"]["status"] == "stale" and st["slave_tip"]["late"] == 1
    assert st["tool_mm"] == tip  # the last tip is kept, shown
    # late from 7 ms: from there the force is the last one computed, scaled down (same
    # direction, never a new force from the stale pose), and zero within tip_fade_ms (20 ms)
    late = forces[6:]
    for f in late:
        assert f[1] == pytest.approx(f0[1] * f[0] / f0[0], abs=1e-9)
    mags = [math.hypot(*f) for f in late]
    assert all(b <= a for a, b in zip(mags, mags[1:]))
    assert mags[21] == 0.0 and not master.alerts("ALERT")
    # back in time: fresh again, the force fades back in; no alert (late is not lost)
    master.feed.paused = False
    master.feed.step(25)
    assert master.ctl.stats()["slave_tip"]["status"] == "fresh"
    assert force(master) == pytest.approx(3.0, abs=0.4) and not master.alerts("ALERT")


@pytest.mark.req("SR-FIX-2")
def test_a_lost_tip_zeroes_the_force_at_once_and_alerts_the_operators(master) -> None:
    master.run()
    keepout(master)
    master.feed.step(5)
    assert force(master) > 2.5
    master.feed.skip(3)  # three sequence numbers lost on the way: proven loss
    master.feed.step(1)
    assert force(master) == 0.0
    (alert,) = master.alerts("ALERT")
    assert "slave tip on slave lost" in alert and "3 consecutive packets lost" in alert
    assert master.ctl.stats()["slave_tip"]["losses"] == 1
    # the next good sample re-arms it (a STREAM status says so) and the force fades back in
    master.feed.step(1)
    assert master.ctl.stats()["slave_tip"]["status"] == "fresh"
    assert any("back" in t for t in master.alerts("STREAM"))
    assert {m.code for m in master.op.messages("STATUS") if m.error_name == "STREAM"} == {
        int(igtl.StatusCode.OK)
    }
    master.feed.step(25)
    assert force(master) > 2.5 and master.sim.robot.state is RobotState.RUNNING


@pytest.mark.req("SR-FIX-2")
def test_a_dead_slave_zeroes_the_force_and_alerts_once(master) -> None:
    master.run()
    keepout(master)
    master.feed.step(5)
    master.feed.paused = True
    master.feed.step(99)
    assert force(master) == 0.0 and not master.alerts("ALERT")  # faded out, late: no alert yet
    master.feed.step(5)  # past the grace (100 ms)
    (alert,) = master.alerts("ALERT")
    assert "no packet for" in alert and "virtual-fixture force off" in alert
    codes = [m.code for m in master.op.messages("STATUS") if m.error_name == "ALERT"]
    assert codes == [int(igtl.StatusCode.TIME_OUT)]  # a lost link, as the slave's own alerts say
    master.feed.step(300)
    assert len(master.alerts("ALERT")) == 1  # latched: said once
    assert master.ctl.stats()["slave_tip"]["status"] == "lost"
    assert master.sim.robot.state is RobotState.RUNNING  # the master itself goes on


def test_a_master_whose_slave_never_answers_is_told(master) -> None:
    master.feed.paused = True
    for c in ("Enable", "Run"):
        master.op.send_command(c)
        master.feed.step(1)
    master.feed.step(120)
    (alert,) = master.alerts("ALERT")
    assert "slave tip on slave lost" in alert
    st = master.ctl.stats()
    assert st["tool_mm"] is None and st["slave_tip"]["status"] == "lost"


def test_the_grace_of_a_slave_silent_since_a_stop_counts_from_run(master) -> None:
    """The slave answered until the master stopped, then fell silent: stopped for 80 ms, the
    master runs again and the alert comes a grace (100 ms) after Run, not after the Stop."""
    master.run()
    assert master.ctl.stats()["slave_tip"]["status"] == "fresh"
    assert master.command("Stop").metadata["Status"] == "SUCCESS"
    master.feed.paused = True
    master.feed.step(80)
    assert master.command("Run").metadata["Status"] == "SUCCESS"
    master.feed.step(90)
    assert master.sim.robot.state is RobotState.RUNNING and not master.alerts("ALERT")
    master.feed.step(30)
    (alert,) = master.alerts("ALERT")
    assert "slave tip on slave lost" in alert


def test_a_slave_that_does_not_follow_this_master_gives_no_force(master) -> None:
    master.run()
    keepout(master)
    master.feed.step(5)
    assert force(master) > 2.5
    master.feed.following = False  # another master has control, or the slave holds
    master.feed.step(20)
    assert force(master) == 0.0 and master.ctl.stats()["slave_tip"]["following"] is False
    master.feed.following = True
    master.feed.step(20)
    assert force(master) > 2.5


def test_a_tip_from_anywhere_but_the_slave_link_is_refused_and_answered(master) -> None:
    n = len(master.op.received)
    master.op.send(
        igtl.TransformMessage.from_position(
            (0.0, 0.0, 0.0), device_name="SlaveTip", header_version=2, message_id=1
        )
    )
    master.feed.step(1)
    (reply,) = [m for m in master.op.received[n:] if m.message_type == "STATUS"]
    assert "is a slave's return stream" in reply.status_message
    assert master.ctl.stats()["slave_tip"]["samples"] == 1  # the feed's, not this one


def test_a_bad_map_is_counted_and_its_sample_not_used(master) -> None:
    master.run()
    master.feed.linear = "1,2,3"
    master.feed.step(1)
    st = master.ctl.stats()["slave_tip"]
    assert st["bad"] == 1 and "expected 9 numbers" in st["last_error"]


# ------------------------------------------------------------------ the slave's side
def test_the_slave_sends_its_tip_back_as_slicer_sees_it() -> None:
    with SimRobot(ROOT / "configs" / "slave.yaml") as sim:
        link = sim.peer("master", address=("127.0.0.1", 40000))
        slicer = sim.peer("slicer")
        op = sim.peer("operator")
        for c in ("Enable", "Run"):
            op.send_command(c)
            sim.step(1)
        for seq in range(1, 301):
            link.send_position((0.0, 50.0, 20.0 + 0.01 * seq), seq=seq)
            sim.step(2)
        tips = link.messages("POSITION", "SlaveTip")
        assert len(tips) == 301  # 500 Hz
        assert [m.message_id for m in tips] == list(range(1, 302))
        assert all(m.header_version == 2 and m.layout == 28 for m in tips)
        last = tips[-1]
        assert last.metadata["following"] == "1" and last.metadata["state"] == "RUNNING"
        assert [float(v) for v in last.metadata["map"].split(",")] == pytest.approx(
            [0.1, 0, 0, 0, 0.1, 0, 0, 0, 0.1]
        )
        # the same pose as the Tip 3D Slicer gets (patient frame), at the same tick
        sim.step(100 - sim.k % 100)  # the next 10 Hz Tip
        sim.step(1)
        tip = slicer.messages("TRANSFORM", "Tip")[-1]
        back = link.messages("POSITION", "SlaveTip")[-1]
        assert back.position == pytest.approx(tip.translation, abs=1e-3)
        # the master stops streaming run=1: following 0
        link.send_position((0.0, 50.0, 23.0), seq=301, run=False)
        sim.step(2)
        assert link.messages("POSITION", "SlaveTip")[-1].metadata["following"] == "0"


# ------------------------------------------------------------------ the real pair
class Pair:
    """configs/master.yaml + configs/slave.yaml on one SimClock, the stream and the return
    channel wired both ways (what tools/fixture_motion.py runs)."""

    def __init__(self) -> None:
        clock = SimClock()
        self.master = SimRobot(ROOT / "configs" / "master.yaml", clock=clock)
        self.slave = SimRobot(ROOT / "configs" / "slave.yaml", clock=clock)
        box: dict[str, Any] = {}
        m_link = self.master.peer("slave", on_message=lambda m: box["s"].send(m))
        box["s"] = self.slave.peer("master", address=("127.0.0.1", 40000), on_message=m_link.send)
        self.m_op = self.master.peer("operator", address=("127.0.0.1", 41000))
        self.s_op = self.slave.peer("operator", address=("127.0.0.1", 41001))
        self.slicer = self.slave.peer("slicer")
        self.ctrl: Any = self.master.robot.controller.controllers[0]

    def step(self, n: int = 1) -> None:
        for _ in range(n):
            self.master.tick()
            self.slave.tick()

    def start(self) -> None:
        for op in (self.s_op, self.m_op):
            for name in ("Enable", "Run"):
                op.send_command(name)
                self.step(1)

    def slicer_tip(self) -> tuple[float, float, float]:
        return tuple(self.slicer.messages("TRANSFORM", "Tip")[-1].translation)

    def close(self) -> None:
        self.master.close()
        self.slave.close()


def test_the_pair_keeps_the_tool_on_the_slaves_tip_through_the_clutch() -> None:
    pair = Pair()
    try:
        pair.start()
        pair.step(1000)
        tip = pair.slicer_tip()
        pair.m_op.send(standin.markups_points([tip], "Target", radius=20.0))
        worst, peak = 0.0, 0.0
        for k in range(6000):
            pair.step(1)
            if k == 1500:
                pair.m_op.send_command("Clutch", '<Command Name="Clutch" Value="1"/>')
            if k == 3000:
                pair.m_op.send_command("Clutch", '<Command Name="Clutch" Value="0"/>')
            if k % 100 == 99:  # every Tip 3D Slicer gets: the master's tool is there
                worst = max(worst, math.dist(pair.ctrl.stats()["tool_mm"], pair.slicer_tip()))
            peak = max(peak, math.hypot(*pair.ctrl.fixtures.force_n))
        assert pair.ctrl.stats()["slave_tip"]["status"] == "fresh"
        # the Tip and the tool are the same sample at most 2 ms apart (500 Hz)
        assert worst < 0.2
        assert peak == 0.0  # the tool never left the sphere around it: no force, ever
        assert pair.master.robot.state is pair.slave.robot.state is RobotState.RUNNING
    finally:
        pair.close()


def test_the_pair_pulls_the_hand_toward_a_sphere_20_mm_away() -> None:
    pair = Pair()
    try:
        pair.start()
        pair.step(1000)
        t = pair.ctrl.stats()["tool_mm"]
        centre = (t[0] + 40.0, t[1], t[2])  # surface 20 mm from the tool
        k = 0.02  # N per mm of master motion: 20 mm deep in the patient = 200 mm = 4 N
        pair.m_op.send(standin.markups_points([centre], "Target", radius=20.0, stiffness=k))
        for _ in range(10):
            pair.step(200)
            st = pair.ctrl.stats()
            tool, f = st["tool_mm"], st["force_n"]
            depth = math.dist(tool, centre) - 20.0
            toward = [(c - x) / (depth + 20.0) for c, x in zip(centre, tool)]
            mag = math.hypot(*f)
            assert 0.0 < mag <= 10.0
            assert mag == pytest.approx(k * depth / 0.1, rel=0.05)
            assert sum(a * b for a, b in zip(f, toward)) / mag > 0.99
    finally:
        pair.close()


def test_a_hand_over_moves_the_force_to_the_master_in_control() -> None:
    clock = SimClock()
    slave = SimRobot(ROOT / "configs" / "collab" / "slave.yaml", clock=clock)
    mentor = SimRobot(ROOT / "configs" / "collab" / "mentor.yaml", clock=clock)
    trainee = SimRobot(ROOT / "configs" / "collab" / "trainee.yaml", clock=clock)
    robots = (mentor, trainee, slave)
    try:
        for name, m, port in (("mentor", mentor, 40000), ("trainee", trainee, 40001)):
            box: dict[str, Any] = {}
            link = m.peer("slave", on_message=lambda msg, box=box: box["s"].send(msg))
            box["s"] = slave.peer(name, address=("127.0.0.1", port), on_message=link.send)
        ops = [r.peer("operator") for r in robots]
        bedside = ops[2]

        def step(n: int) -> None:
            for _ in range(n):
                for r in robots:
                    r.tick()

        for op in (ops[2], ops[0], ops[1]):
            for c in ("Enable", "Run"):
                op.send_command(c)
                step(1)
        step(500)
        cm, ct = (r.robot.controller.controllers[0] for r in (mentor, trainee))
        # both know where the tool is (the same tip); only the owner's is followed
        assert cm.stats()["tool_mm"] == pytest.approx(ct.stats()["tool_mm"], abs=1e-6)
        assert cm.stats()["slave_tip"]["following"] and not ct.stats()["slave_tip"]["following"]
        t = cm.stats()["tool_mm"]
        # an accessible sphere whose surface is 20 mm from the tool: a pull toward it
        target = standin.markups_points(
            [(t[0] + 40.0, t[1], t[2])], "Target", radius=20.0, stiffness=0.02
        )
        for op in ops[:2]:
            op.send(target)
        step(50)
        assert math.hypot(*cm.fixtures.force_n) > 1.0 and ct.fixtures.force_n == (0.0, 0.0, 0.0)
        bedside.send_command("Handover", '<Command Name="Handover" To="trainee"/>')
        step(50)
        assert ct.stats()["slave_tip"]["following"] and not cm.stats()["slave_tip"]["following"]
        assert math.hypot(*ct.fixtures.force_n) > 1.0 and cm.fixtures.force_n == (0.0, 0.0, 0.0)
        assert ct.stats()["tool_mm"] == pytest.approx(cm.stats()["tool_mm"], abs=1e-6)
    finally:
        for r in robots:
            r.close()


# ------------------------------------------------------------------ the slave's force (issue 27)
def feedback(master: SimMaster) -> tuple[float, float, float]:
    return tuple(master.ctl.display.feedback_n)


@pytest.fixture
def unpassivated() -> Any:
    """The master with the passivity controller off: a constant force on the moving hand is
    work the network never received, which the controller would damp (its own test below)."""
    m = SimMaster(params=dict(passivity=False), feed=True)
    yield m
    m.close()


@pytest.mark.req("SR-FORCE-2")
def test_the_slaves_force_is_displayed_scaled_and_summed_with_the_fixtures(unpassivated) -> None:
    master = unpassivated
    master.run()
    master.feed.force = (-2.0, 0.5, 1.0)  # N, patient frame; the map is 0.1 I: same axes
    master.feed.step(30)
    assert feedback(master) == pytest.approx((-2.0, 0.5, 1.0), abs=1e-9)
    st = master.ctl.stats()
    assert st["slave_tip"]["force_n"] == [-2.0, 0.5, 1.0]
    assert st["force_n"] == pytest.approx([-2.0, 0.5, 1.0], abs=1e-3)  # the hand feels it
    # a fixture pushing too: the hand feels the sum
    keepout(master)
    master.feed.step(10)
    fix = master.ctl.fixtures.force_n
    shown = master.ctl.display.displayed_n
    for i in range(3):
        assert shown[i] == pytest.approx(fix[i] + feedback(master)[i], abs=0.05)


@pytest.mark.req("SR-FORCE-2")
def test_force_scale_and_the_10_n_clamp() -> None:
    m = SimMaster(params=dict(force_scale=2.5, passivity=False), feed=True)
    try:
        m.run()
        m.feed.force = (0.0, 2.0, 0.0)
        m.feed.step(30)
        assert feedback(m) == pytest.approx((0.0, 5.0, 0.0), abs=1e-9)
        m.feed.force = (3.0, 0.0, -4.0)  # 5 N x 2.5 = 12.5 N: clamped to 10 N, same direction
        m.feed.step(30)
        shown = m.ctl.display.displayed_n
        assert math.hypot(*shown) == pytest.approx(10.0, abs=1e-9)
        assert shown[0] / shown[2] == pytest.approx(-0.75)
        assert m.ctl.stats()["force_clamped_ticks"] > 0
    finally:
        m.close()


@pytest.mark.req("SR-FORCE-2", "SR-FORCE-5")
def test_a_late_or_lost_force_is_held_and_faded_never_dropped_and_snapped_back(master) -> None:
    """Late or lost, the slave's force is held and fades out linearly within
    ``feedback_fade_ms`` (300 ms), the same direction, never dropped to zero at once; a lost
    link alerts once; back, the force returns within ``tip_fade_ms`` (20 ms) from where the
    fade had brought it, not from zero (issue 37: a force dropped and snapped back gave the
    hand energy it never put in)."""
    # the fade itself, not what the controller makes of it
    master = SimMaster(params=dict(passivity=False), feed=True)
    master.run()
    master.feed.force = (0.0, 0.0, 3.0)
    master.feed.step(30)
    assert feedback(master)[2] == pytest.approx(3.0)
    master.feed.paused = True  # late (from 7 ms): held, fading
    shown = []
    for _ in range(40):
        master.feed.step(1)
        shown.append(feedback(master)[2])
    assert all(b <= a for a, b in zip(shown, shown[1:], strict=False))
    assert shown[39] == pytest.approx(3.0 * (1.0 - 33e-3 / 0.3), abs=0.02)  # 1/300 per ms
    assert not master.alerts("ALERT")
    master.feed.paused = False
    master.feed.step(30)
    assert feedback(master)[2] == pytest.approx(3.0)
    master.feed.skip(3)  # proven loss: an alert, the force held and fading, not zero
    master.feed.step(1)
    master.feed.paused = True
    assert feedback(master)[2] == pytest.approx(3.0, abs=0.02)
    assert any("lost" in a and "held and fading" in a for a in master.alerts("ALERT"))
    master.feed.step(99)  # 100 ms lost: a third gone
    assert feedback(master)[2] == pytest.approx(2.0, abs=0.02)
    master.feed.paused = False  # back: from 2 N up to 3 N within 20 ms, never through zero
    back = []
    for _ in range(25):
        master.feed.step(1)
        back.append(feedback(master)[2])
    assert min(back) >= 1.95 and back[-1] == pytest.approx(3.0)
    assert all(b >= a for a, b in zip(back, back[1:], strict=False))
    master.close()


@pytest.mark.req("SR-FORCE-2")
def test_a_dead_slave_leaves_no_force_on_the_hand(master) -> None:
    master.run()
    master.feed.force = (1.0, 1.0, 1.0)
    master.feed.step(30)
    master.feed.paused = True
    master.feed.step(150)  # past the 100 ms grace: lost, one alert, the force fading
    assert len([a for a in master.alerts("ALERT") if "lost" in a]) == 1
    assert 0.0 < feedback(master)[0] < 1.0
    master.feed.step(160)  # feedback_fade_ms (300 ms) from late: gone
    assert master.ctl.display.displayed_n == (0.0, 0.0, 0.0)
    assert len([a for a in master.alerts("ALERT") if "lost" in a]) == 1


@pytest.mark.req("SR-FORCE-2")
@pytest.mark.parametrize("bad", ["1,2", "1,2,x", "nan,0,0", "1,2,3,4", ""])
def test_a_malformed_force_is_refused_and_counted_not_displayed(master, bad: str) -> None:
    master.run()
    master.feed.force = (0.0, 2.0, 0.0)
    master.feed.step(30)
    before = master.ctl.stats()["slave_tip"]
    master.feed.force = bad
    master.feed.step(1)
    st = master.ctl.stats()["slave_tip"]
    assert st["bad"] == before["bad"] + 1 and "force_n" in st["last_error"]
    assert st["samples"] == before["samples"]  # the whole sample refused: its tip too
    assert st["force_n"] == [0.0, 2.0, 0.0]  # the last good force, fading as any late one


@pytest.mark.req("SR-FORCE-2")
def test_a_slave_whose_samples_all_come_refused_is_late_then_lost_never_a_held_force(
    master,
) -> None:
    """Samples keep coming, none usable (a malformed force in each): not a fresh link holding
    the last good force on the hand, but a late one (the force fades within feedback_fade_ms),
    then a lost one past the grace (one ALERT naming the cause; the force gone by the end of
    the fade); good samples re-arm it."""
    master.run()
    master.feed.force = (0.0, 0.0, 3.0)
    master.feed.step(30)
    assert feedback(master)[2] == pytest.approx(3.0)
    master.feed.force = "nan,0,0"
    shown = []
    for _ in range(40):
        master.feed.step(1)
        shown.append(feedback(master)[2])
    assert all(b <= a for a, b in zip(shown, shown[1:], strict=False))
    assert 0.0 < shown[30] < shown[8] < 3.0 and not master.alerts("ALERT")
    st = master.ctl.stats()["slave_tip"]
    assert st["status"] == "stale" and st["bad"] == 40 and st["lost_total"] == 0
    master.feed.step(62)  # 101 ms without a usable tip: past the grace
    (alert,) = master.alerts("ALERT")
    assert "slave tip on slave lost: no usable tip for 101.00 ms (limit 100.0 ms)" in alert
    assert "101 samples refused" in alert and "force_n 'nan,0,0'" in alert
    assert master.ctl.stats()["slave_tip"]["status"] == "lost"
    master.feed.step(210)  # 300 ms of fade since it went late: gone
    assert len(master.alerts("ALERT")) == 1 and feedback(master) == (0.0, 0.0, 0.0)
    assert master.ctl.stats()["slave_tip"]["losses"] == 1
    master.feed.force = (0.0, 0.0, 3.0)
    master.feed.step(30)
    st = master.ctl.stats()["slave_tip"]
    assert st["status"] == "fresh" and st["recoveries"] == 1
    assert any("back" in t for t in master.alerts("STREAM"))
    assert feedback(master)[2] == pytest.approx(3.0) and len(master.alerts("ALERT")) == 1


@pytest.mark.req("SR-FORCE-2")
def test_force_feedback_off_displays_only_the_fixtures() -> None:
    m = SimMaster(params=dict(force_feedback=False), feed=True)
    try:
        m.run()
        m.feed.force = (0.0, 2.0, 0.0)
        m.feed.step(30)
        shown = m.ctl.display
        assert shown.feedback_n == (0.0, 0.0, 0.0) and shown.displayed_n == (0.0, 0.0, 0.0)
        assert m.ctl.stats()["slave_tip"]["force_n"] == [0.0, 2.0, 0.0]  # received, not shown
    finally:
        m.close()


@pytest.mark.req("SR-FORCE-1")
def test_the_passivity_controller_damps_a_force_the_network_gave_no_energy_for(master) -> None:
    """A constant 3 N on the moving hand from nothing the hand pushed (no spring, no wall, no
    energy from the slave): the observer sees the network giving energy and the controller cuts
    it; the hand's balance (what the port observed over the handle's real displacement) stays
    within 30 uJ of zero (the one-tick prediction: the force shown accelerates the handle within
    the tick, 3 N on 0.5 kg), where uncut it would give the hand tens of millijoules."""
    master.run()
    master.feed.force = (3.0, 3.0, 0.0)
    energies = []
    for _ in range(2000):
        master.feed.step(1)
        energies.append(master.ctl.display.passivity.account.net)
    st = master.ctl.stats()["passivity"]
    assert st["on"] and st["active_ticks"] > 0 and st["dissipated_mj"] > 10.0
    assert min(energies) >= -3e-5


# ------------------------------------------------------------------ an external force (servo_cf)
@pytest.mark.req("SR-FORCE-2")
def test_an_external_force_is_displayed_while_it_keeps_coming(unpassivated) -> None:
    """SENSOR ``ServoCF`` from an operator (CRTK servo_cf through occ-ros2): N in the master's
    axes, displayed with the slave's force while it is fresh (100 ms), then no more; a reading
    that is no force is refused with an error reply to its sender, nothing displayed. (With
    passivity on, the hand yielding to it would be work the network never received: damped.)"""
    from igtl.messages.sensor import Unit

    master = unpassivated
    master.run()

    def servo_cf(values: tuple[float, ...], unit: Unit = Unit(0, ((11, 1),))) -> None:
        master.op.send(igtl.SensorMessage(values, unit, device_name="ServoCF", header_version=2))

    servo_cf((0.0, 0.0, 1.5))
    master.feed.step(2)
    assert master.ctl.display.displayed_n[2] == pytest.approx(1.5, abs=0.05)
    st = master.ctl.stats()
    assert st["external_n"] == [0.0, 0.0, 1.5] and st["external_fresh"]
    master.feed.step(99)  # 100 ms after it came: still shown
    assert master.ctl.display.displayed_n[2] == pytest.approx(1.5, abs=0.05)
    master.feed.step(2)  # past the timeout: gone
    assert master.ctl.display.displayed_n == (0.0, 0.0, 0.0)
    assert not master.ctl.stats()["external_fresh"]
    before = len(master.op.messages())
    servo_cf((0.0, 0.0, 1.5), Unit(0, ((1, 1),)))  # metres: no force
    master.feed.step(2)
    assert master.ctl.display.displayed_n == (0.0, 0.0, 0.0)
    replies = master.op.messages()[before:]
    assert any(
        "is not a force" in str(getattr(m, "status_message", "")) + str(getattr(m, "command", ""))
        for m in replies
    ), replies


def _servo_cf(master: SimMaster, values: tuple[float, float, float]) -> None:
    """An operator's SENSOR ``ServoCF`` in newtons (occ-ros2's servo_cf)."""
    from igtl.messages.sensor import Unit

    unit = Unit(0, ((11, 1),))
    master.op.send(igtl.SensorMessage(values, unit, device_name="ServoCF", header_version=2))


@pytest.mark.req("SR-FORCE-2")
def test_a_stop_shows_no_force_and_reports_none_from_that_tick(unpassivated) -> None:
    """While the robot is not RUNNING the hand is given no force: what the master reports
    as displayed (GetStats ``force_n``, ``feedback_n``) and what its Force output sends (ROS
    2's measured_cf) is zero from the Stop on, not the last force shown, until RUNNING shows
    the slave's force again."""
    master = unpassivated
    master.run()
    master.feed.force = (0.0, 0.0, 3.0)
    master.feed.step(30)
    st = master.ctl.stats()
    assert st["feedback_n"][2] == pytest.approx(3.0) and st["force_n"][2] == pytest.approx(3.0)
    master.op.send_command("Stop")
    master.feed.step(1)
    assert master.sim.robot.state is RobotState.STOPPED
    st = master.ctl.stats()
    assert st["force_n"] == [0.0, 0.0, 0.0] and st["feedback_n"] == [0.0, 0.0, 0.0]
    n = len(master.op.messages("SENSOR", "Force"))
    master.feed.step(100)  # Force goes at 50 Hz: five of them while stopped
    sent = master.op.messages("SENSOR", "Force")[n:]
    assert len(sent) == 5 and all(tuple(m.data) == (0.0, 0.0, 0.0) for m in sent)
    assert master.ctl.stats()["force_n"] == [0.0, 0.0, 0.0]


@pytest.mark.req("SR-FORCE-2")
def test_an_external_force_across_stop_and_run_is_shown_from_the_first_tick_after_run(
    unpassivated,
) -> None:
    """An external force (servo_cf) that keeps coming while the robot is stopped and run
    again: none while stopped, shown whole on the first tick after Run (the handle's
    velocity has no previous tick yet: nothing to passivate), the loop unharmed."""
    master = unpassivated
    master.run()
    _servo_cf(master, (0.0, 0.0, 1.5))
    master.feed.step(2)
    assert master.ctl.display.displayed_n[2] == pytest.approx(1.5, abs=0.05)
    master.op.send_command("Stop")
    master.feed.step(1)
    assert master.sim.robot.state is RobotState.STOPPED
    assert master.ctl.display.displayed_n == (0.0, 0.0, 0.0)
    _servo_cf(master, (0.0, 0.0, 1.5))
    master.feed.step(1)
    master.op.send_command("Run")
    master.feed.step(1)
    assert master.sim.robot.state is RobotState.RUNNING
    assert master.ctl.display.displayed_n == pytest.approx((0.0, 0.0, 1.5), abs=1e-9)
    master.feed.step(5)
    assert master.sim.robot.state is RobotState.RUNNING
    assert master.ctl.display.displayed_n[2] == pytest.approx(1.5, abs=0.05)


# ------------------------------------------------------------------ the slave's return source
def _return_source(force: Any = None) -> Any:
    """occ/controllers/teleop/returnsrc.py's ReturnSource on stand-ins for the robot: a tip at
    (1, -2, 3) m turned 90 degrees about z, a base moved by the test, a clock at 1234.5 s."""
    from types import SimpleNamespace

    from occ.controllers.teleop.returnsrc import ReturnSource

    rows = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    data = SimpleNamespace(
        base=np.eye(4), state=RobotState.RUNNING, q=[0.1], qdot=[0.2], effort=[0.3],
        tip=np.eye(4), world_tip_pose=lambda: (rows, (1.0, -2.0, 3.0)),
    )  # fmt: skip
    ctx = SimpleNamespace(frame="frame", clock=SimpleNamespace(wall_time=lambda: 1234.5))
    port = SimpleNamespace(account=SimpleNamespace(e_in=0.0123456789012))
    src = ReturnSource(0.5, np.eye(3), port)
    src.bind(force, data, ctx)
    return src, data


def test_the_return_source_numbers_each_output_and_builds_each_metadata_once() -> None:
    from types import SimpleNamespace

    from occ.errors import OCCError

    src, data = _return_source()
    iface = SimpleNamespace(name="slave", stream_owner=None, sends_to_owner=True)
    out_a = SimpleNamespace(type="POSITION", interface=iface, device="Tip")
    out_b = SimpleNamespace(type="POSITION", interface=iface, device="Tip2")
    # a link back to its stream's owner: nobody to send to until a master streams to it
    assert src.check(out_a) is False
    iface.stream_owner = ("127.0.0.1", 5)
    assert src.check(out_a) is True
    iface.sends_to_owner = False  # a fixed remote: always someone
    assert src.check(out_a) is True
    iface.stream_owner = None
    assert src.check(out_a) is True
    with pytest.raises(OCCError) as err:
        src.check(SimpleNamespace(type="TRANSFORM", interface=iface))
    assert str(err.value) == "teleop-return output must be of type POSITION"
    a1, a2, b1 = (
        src.sample(out_a, 0.0, True),
        src.sample(out_a, 0.0, True),
        src.sample(out_b, 0.0, False),
    )
    assert (a1.seq, a2.seq, b1.seq) == (1, 2, 1) and src.returned == 3
    assert (a1.interface, a1.device, b1.device) == ("slave", "Tip", "Tip2")
    assert a1.position_mm == pytest.approx((1000.0, -2000.0, 3000.0))
    assert a1.quaternion == pytest.approx((0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)))
    assert a1.t_sample == 1234.5
    assert dict(a1.meta) == {"following": "1", "state": "RUNNING", "map": "0.5,0,0,0,0.5,0,0,0,0.5"}
    assert dict(b1.meta)["following"] == "0"
    assert a1.meta is a2.meta  # built once per (following, state, map), not per sample
    src._return_seqs[id(out_a)] = 0xFFFFFFFF
    assert src.sample(out_a, 0.0, True).seq == 0  # 32 bits, as on the wire
    # a tracker moving the base: a new map each time, the metadata kept to 65 kinds at most
    for i in range(63):  # two kinds so far (following and not), 65 after these
        data.base = np.eye(4) * (2.0 + i)
        src.meta(True, 0.0)
    assert len(src._return_meta) == 65
    data.base = np.eye(4) * 100.0
    src.meta(True, 0.0)
    assert len(src._return_meta) == 1  # cleared, then this one


@pytest.mark.req("SR-FORCE-1")
def test_the_return_source_sends_the_force_the_energy_and_a_torque_when_there_is_one() -> None:
    from types import SimpleNamespace

    calls: list[Any] = []

    def estimate(now: float, frame: Any, q: Any, qdot: Any, effort: Any, base: Any, rot: Any):
        calls.append((now, frame, q, qdot, effort, base is data.base, rot().shape))
        return (1.234567, -0.5, 2.0)

    force = SimpleNamespace(estimate=estimate, torque_nm=None)
    src, data = _return_source(force)
    meta = src.meta(False, 7.0)
    assert dict(meta) == {
        "following": "0", "state": "RUNNING", "map": "0.5,0,0,0,0.5,0,0,0,0.5",
        "force_n": "1.2346,-0.5000,2.0000", "energy_j": "0.0123456789",
    }  # fmt: skip
    assert calls == [(7.0, "frame", [0.1], [0.2], [0.3], True, (3, 3))]
    force.torque_nm = (0.001, -0.0025, 0.1)
    assert src.meta(False, 8.0)["torque_nm"] == "0.00100,-0.00250,0.10000"
