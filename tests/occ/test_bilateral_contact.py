"""Stiff contact, delay and loss, a stop in contact, a hard hit (issue 37), in simulated time.

The shipped master (the simulated hand on a haptic device) and the wall slave with a stiffer
wall, as the sweep of tools/bilateral_sweep.py runs them (:class:`occ_testkit.testing.SimPair`): the
hardest conditions of the sweep hold its bars (the hand's energy, measured independently of
the controllers, never below -1 % of its peak; no buzz; no growth; the hand under 10 N), a hit
at 95 mm/s with 50 ms each way keeps the instrument under ``max_tissue_force_n``, and a stop
latched in contact lets go of the tissue within 200 ms and tells the hand."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import pytest

from occ.core.safety import RobotState
from occ_testkit.testing import CONFIGS, SimPair

from ..tools.tooling import load_tool

sweep = load_tool("bilateral_sweep")


# ------------------------------------------------------------------ the sweep's hardest corners
@pytest.mark.req("SR-FORCE-4")
@pytest.mark.parametrize(
    ("stiffness", "delay_ms", "loss"),
    [
        (10.0, 50.0, "none"),  # -8.7 mJ and the damper at its cap before
        (10.0, 10.0, "none"),  # the handle buzzed at 6-7 Hz before
        (10.0, 50.0, "bursts-return"),  # the force dropped and snapped back before
        (5.0, 25.0, "bursts"),  # stops latched in contact, released, run again
    ],
)
def test_the_hardest_conditions_of_the_sweep_hold(
    stiffness: float, delay_ms: float, loss: str
) -> None:
    r = sweep.run_condition(stiffness, delay_ms, loss, seconds=20.0)
    assert r["holds"], r
    assert r["energy_min_mj"] >= -0.01 * r["energy_peak_mj"]
    assert r["hf_velocity_mm_s"] <= 10.0 and r["hand_peak_n"] <= 10.0
    assert r["instrument_peak_n"] > 2.0  # the hand really pressed on the wall
    if loss == "bursts":
        assert r["stops"] > 0 and r["reruns"] > 0
    if loss == "bursts-return":
        assert r["counts"]["return_lost"] > 100


@pytest.mark.req("SR-FORCE-4")
def test_the_slaves_port_runs_on_the_energy_the_masters_stream_carries() -> None:
    """The shipped master (passivity on) streaming to a slave on the wall: the slave's port
    takes the hand's energy from the stream's ``energy_j`` and is active from the first
    samples (GetStats' ``instrument.passivity``), none of them refused."""
    pair = _pair(10.0, 0.0)
    try:
        ctl = _slave_ctl(pair)
        pair.start()
        pair.step(100)
        port = ctl.stats()["instrument"]["passivity"]
        assert port["on"] is True and port["active"] is True and port["bad_energy"] == 0
    finally:
        pair.close()


@pytest.mark.req("SR-FORCE-4")
def test_the_sweeps_bars_catch_the_one_port_controller_of_before() -> None:
    """The bars can fail: with the master's controller off (observed only, no energy sent)
    the stiffest, longest condition gives the hand energy and the handle oscillates."""
    r = sweep.run_condition(10.0, 50.0, "none", seconds=10.0, master_params={"passivity": False})
    assert not r["checks"]["energy"] and not r["checks"]["buzz"], r


def test_the_loss_patterns_are_what_they_say() -> None:
    n = 20000
    for name, runs in (("single5", {1}), ("double5", {2}), ("bursts", set(range(3, 21)))):
        rule = sweep.loss_rule(name, 37)
        lost = [rule("return", None, i) for i in range(n)]
        found: list[int] = []
        run = 0
        for x in [*lost, False]:
            if x:
                run += 1
            elif run:
                found.append(run)
                run = 0
        assert set(found) <= runs, (name, sorted(set(found)))
        share = sum(lost) / n
        if name != "bursts":
            assert share == pytest.approx(0.05, abs=0.01), (name, share)
        else:
            assert len(found) == pytest.approx(n / 500, rel=0.3)
    rule = sweep.loss_rule("bursts-return", 37)
    assert not any(rule("forward", None, i) for i in range(n))
    assert sweep.loss_rule("none") is None
    with pytest.raises(ValueError, match="unknown loss pattern"):
        sweep.loss_rule("most")


# ------------------------------------------------------------------ the force limit
@pytest.mark.req("SR-FORCE-7")
def test_a_hit_at_95_mm_s_with_50_ms_each_way_stays_under_the_limit_with_no_energy_given() -> None:
    """The hand drives the handle into a 10 N/mm wall at 95 mm/s (the tool at 9.5 mm/s) with
    50 ms each way and keeps pushing: the instrument stays under ``max_tissue_force_n`` (10 N,
    the default), the hand's energy never below zero (to a microjoule: the one-tick
    prediction), and the operators are told when the limit is reached."""
    r = sweep.run_impact(delay_ms=50.0)
    assert r["instrument_truth_peak_n"] < 10.0 and r["over_10n_ms"] == 0.0, r
    assert r["energy_min_mj"] >= -1e-3, r
    assert r["states"] == ["RUNNING", "RUNNING"]
    # without the limit the same hit presses past it (the hand's clamp is the hand's only)
    free = sweep.run_impact(delay_ms=50.0, slave_params={"max_tissue_force_n": None})
    assert free["instrument_truth_peak_n"] > 12.0, free


@pytest.mark.req("SR-FORCE-7")
@pytest.mark.parametrize(("limit", "below"), [(10.0, True), (None, False)])
def test_the_limit_holds_alone_when_the_loop_shakes_and_alerts_once_per_episode(
    limit: float | None, below: bool
) -> None:
    """With the master's passivity off, 50 ms each way and a 5 N/mm wall, the delayed loop
    shakes the tool against the wall (12.5 N without the limit): the slave's limit alone keeps
    the instrument under it (its approach rate: 5 mm/s per N short of 90 %)."""
    pair = _pair(5.0, 50.0, master_params={"passivity": False},
                 slave_params={"max_tissue_force_n": limit})  # fmt: skip
    try:
        ctl = _slave_ctl(pair)
        env = pair.slave.robot.hardware.environment
        peak = 0.0
        pair.start()
        for _ in range(10000):
            pair.step(1)
            peak = max(peak, math.hypot(*env.force_n))
        alerts = _statuses(pair.s_op, "ForceLimit")
        st = ctl.stats()["instrument"]
    finally:
        pair.close()
    if not below:
        assert peak > 12.0 and not alerts and st["limit_ticks"] == 0
        return
    assert peak < 10.0 and len(alerts) == st["limit_hits"]


@pytest.mark.req("SR-FORCE-7")
def test_the_tool_is_shaped_between_samples_too() -> None:
    """The delayed loop of the test above shaking the tool against the wall, the 500 Hz stream
    on the 1 kHz loop: the contact's shaping moves the setpoint on ticks without a new sample
    too (418 of the 2000 such ticks here), not only when a sample comes."""
    pair = _pair(5.0, 50.0, master_params={"passivity": False},
                 slave_params={"max_tissue_force_n": 10.0})  # fmt: skip
    try:
        ctl = _slave_ctl(pair)
        data = pair.slave.robot.data
        pair.start()
        samples, setpoint, between = ctl.samples, list(data.setpoint), 0
        for _ in range(4000):
            pair.step(1)
            if ctl.samples == samples and list(data.setpoint) != setpoint:
                between += 1
            samples, setpoint = ctl.samples, list(data.setpoint)
        assert between > 100, between
        assert pair.slave.robot.state is RobotState.RUNNING
    finally:
        pair.close()


@pytest.mark.req("SR-FORCE-7")
def test_reaching_the_limit_alerts_once_per_episode() -> None:
    """The paper's motion on a 10 N/mm wall presses ~7 N; with a 5 N limit the slave stops at
    it (the hand's force follows the instrument's), one ForceLimit alert a turn, re-armed only
    after the force fell under 80 %."""
    pair = _pair(10.0, 0.0, slave_params={"max_tissue_force_n": 5.0})
    try:
        ctl = _slave_ctl(pair)
        env = pair.slave.robot.hardware.environment
        pair.start()
        peak = 0.0
        for _ in range(20000):  # two turns
            pair.step(1)
            peak = max(peak, math.hypot(*env.force_n))
        alerts = _statuses(pair.s_op, "ForceLimit")
        st = ctl.stats()["instrument"]
    finally:
        pair.close()
    assert 4.5 <= peak < 5.0
    assert len(alerts) == st["limit_hits"] == 2 and st["limit_ticks"] > 100
    assert "at the limit (max_tissue_force_n 5)" in alerts[0]


def test_a_limit_without_a_measured_force_is_a_config_error() -> None:
    from occ.config import DaemonConfig
    from occ.controllers.teleop import SlaveController

    cfg = DaemonConfig.model_validate(_yaml(CONFIGS / "slave.yaml"))
    params = SlaveController.Params.model_validate({"max_tissue_force_n": 5.0})
    problems = SlaveController.check(params, cfg)
    assert (
        ("max_tissue_force_n",),
        "needs `force` (a measured contact force to limit)",
    ) in problems
    # the default is not applied without a force: no problem, no limit
    params = SlaveController.Params.model_validate({})
    assert not [p for p in SlaveController.check(params, cfg) if p[0] == ("max_tissue_force_n",)]
    assert SlaveController(params).shaper.max_tissue_force is None


# ------------------------------------------------------------------ a stop in contact
def _yaml(path: Any) -> dict[str, Any]:
    import yaml

    return dict(yaml.safe_load(path.read_text()))


def _pair(stiffness: float, delay_ms: float, **kw: Any) -> SimPair:
    cut = {"on": False}

    def drop(direction: str, msg: Any, index: int) -> bool:
        return direction == "forward" and cut["on"]

    slave_params = kw.pop("slave_params", None)
    pair = SimPair(
        CONFIGS / "master.yaml",
        sweep.wall_config(stiffness, slave_params),
        delay_ms=delay_ms,
        drop=drop,
        **kw,
    )
    pair.cut = cut  # type: ignore[attr-defined]
    return pair


def _slave_ctl(pair: SimPair) -> Any:
    return pair.slave.robot.controller.controllers[0]


def _statuses(peer: Any, name: str) -> list[str]:
    return [m.status_message for m in peer.messages("STATUS") if m.error_name == name]


def _press(pair: SimPair, force_n: float) -> None:
    env = pair.slave.robot.hardware.environment
    for _ in range(5000):
        if math.hypot(*env.force_n) >= force_n:
            return
        pair.step(1)
    raise AssertionError(f"never pressed {force_n} N")


@pytest.mark.req("SR-FORCE-6")
@pytest.mark.parametrize(("stiffness", "delay_ms"), [(2.0, 0.0), (10.0, 50.0), (5.0, 25.0)])
def test_a_stop_latched_in_contact_lets_go_within_200_ms_and_the_hand_is_told(
    stiffness: float, delay_ms: float
) -> None:
    """The master's stream lost while the tool presses 3 N on the tissue: the slave holds
    (late), latches a stop at the grace, and from the stop the tissue force is under 0.5 N
    within 200 ms, and stays there; the slave's operators get a Release alert when it starts
    and when it is done, the master's (the hand's) an ALERT that it lets go; Run again
    re-indexes from where it let go, no jump."""
    pair = _pair(stiffness, delay_ms)
    try:
        env = pair.slave.robot.hardware.environment
        ctl = _slave_ctl(pair)
        pair.start()
        _press(pair, 3.0)
        pair.cut["on"] = True  # type: ignore[attr-defined]
        t_stop = None
        forces = []
        for i in range(1000):
            pair.step(1)
            if t_stop is None and pair.slave.robot.state is RobotState.STOPPED:
                t_stop = i
            if t_stop is not None:
                forces.append(math.hypot(*env.force_n))
        assert t_stop is not None and forces[0] > 2.0
        under = next(i for i, f in enumerate(forces) if f < 0.5)
        assert under <= 200, under
        assert max(forces[under:]) < 0.5
        st = ctl.stats()["instrument"]
        assert st["releases"] == 1 and not st["releasing"] and 0.0 < st["released_mm"] < 10.0
        release = _statuses(pair.s_op, "Release")
        assert len(release) == 2
        assert "backing out along the force" in release[0] and "let go" in release[1]
        told = [a for a in _statuses(pair.m_op, "ALERT") if "lets go of the tissue" in a]
        assert len(told) == 1 and "STOPPED while pressing" in told[0]
        # Run again: from where it let go, no jump
        pair.cut["on"] = False  # type: ignore[attr-defined]
        held = list(pair.slave.robot.data.hold_setpoint)  # what the drives are told
        q = list(pair.slave.robot.data.q)
        pair.s_op.send_command("Run")
        pair.step(2)
        assert pair.slave.robot.state is RobotState.RUNNING
        # (joint units: rad and m; 1e-4 is 0.1 mm of insertion, 1-2 um at the tip for yaw)
        data = pair.slave.robot.data
        assert max(abs(a - b) for a, b in zip(data.setpoint, held, strict=True)) < 1e-4
        assert max(abs(a - b) for a, b in zip(data.q, q, strict=True)) < 1e-4
    finally:
        pair.close()


@pytest.mark.req("SR-FORCE-6")
def test_a_stop_in_free_space_holds_where_it_is() -> None:
    pair = _pair(5.0, 0.0)
    try:
        pair.start()
        pair.run_for(0.3)  # the tool not yet at the wall (it reaches it at 0.65 s)
        assert math.hypot(*pair.slave.robot.hardware.environment.force_n) == 0.0
        pair.s_op.send_command("Stop")
        pair.step(1)
        held = list(pair.slave.robot.data.hold_setpoint)
        pair.run_for(0.5)
        assert pair.slave.robot.state is RobotState.STOPPED
        assert list(pair.slave.robot.data.hold_setpoint) == held
        assert not _statuses(pair.s_op, "Release")
        assert _slave_ctl(pair).stats()["instrument"]["releases"] == 0
    finally:
        pair.close()


@pytest.mark.req("SR-FORCE-6")
def test_the_release_never_backs_out_farther_than_release_max_mm() -> None:
    pair = _pair(2.0, 0.0, slave_params={"release_max_mm": 0.2})
    try:
        env = pair.slave.robot.hardware.environment
        pair.start()
        _press(pair, 3.0)
        pair.s_op.send_command("Stop")
        pair.run_for(0.5)
        st = _slave_ctl(pair).stats()["instrument"]
        assert st["released_mm"] == pytest.approx(0.2)
        assert math.hypot(*env.force_n) > 2.0  # 1.5 mm deep at 2 N/mm: still pressing
        (still,) = [a for a in _statuses(pair.s_op, "Release") if "still pressing" in a]
        assert "release_max_mm" in still
    finally:
        pair.close()


@pytest.mark.req("SR-FORCE-6")
def test_each_stop_in_contact_lets_go_with_its_own_release_max_mm() -> None:
    """Two stops in contact, Run between them, on a 10 N/mm wall: the second backs the tool
    out again from its own ``release_max_mm`` (1.2 mm here; the first release takes 0.84 mm
    from 3 N, the second 0.60 mm from 1.3 N), not from what the first one left (0.36 mm: the
    tool would stop short, still pressing about 0.9 N, and alert)."""
    pair = _pair(10.0, 0.0, slave_params={"release_max_mm": 1.2})
    try:
        env = pair.slave.robot.hardware.environment
        ctl = _slave_ctl(pair)
        pair.start()
        # after the first Run the re-index keeps the tool where it let go: the hand's circle
        # then presses only about 1.4 N
        for turn, force_n in ((1, 3.0), (2, 1.3)):
            _press(pair, force_n)
            pair.s_op.send_command("Stop")
            pair.run_for(0.3)
            assert pair.slave.robot.state is RobotState.STOPPED
            st = ctl.stats()["instrument"]
            assert math.hypot(*env.force_n) < 0.5, turn
            assert st["releases"] == turn and 0.3 < st["released_mm"] < 1.1, (turn, st)
            pair.s_op.send_command("Run")
            pair.step(2)
            assert pair.slave.robot.state is RobotState.RUNNING
        release = _statuses(pair.s_op, "Release")
        assert sum("let go" in a for a in release) == 2, release
        assert not [a for a in release if "still pressing" in a], release
    finally:
        pair.close()


@pytest.mark.req("SR-FORCE-6")
def test_run_during_a_release_ends_it_in_the_stats() -> None:
    """Run while the tool is still backing out: GetStats' ``instrument`` no longer says it
    releases, and counts no travel for a stop that is over."""
    pair = _pair(2.0, 0.0)
    try:
        ctl = _slave_ctl(pair)
        pair.start()
        _press(pair, 3.0)
        pair.s_op.send_command("Stop")
        pair.step(10)  # 10 ms at 40 mm/s: 0.4 mm of the 1.4 mm
        st = ctl.stats()["instrument"]
        assert st["releasing"] and st["released_mm"] > 0.1, st
        pair.s_op.send_command("Run")
        pair.step(2)
        assert pair.slave.robot.state is RobotState.RUNNING
        st = ctl.stats()["instrument"]
        assert st["releasing"] is False and st["released_mm"] == 0.0, st
        assert st["releases"] == 1
    finally:
        pair.close()


@pytest.mark.req("SR-FORCE-4")
def test_a_new_master_is_not_the_ports_until_its_energy_comes() -> None:
    """A hand-over: the first sample of another master clears the port's activity, which is
    false (not unknown) in GetStats until that master's ``energy_j`` comes."""
    from occ.controllers.teleop import SlaveController
    from occ.samples import PoseSample

    # no phase lock: it reads the loop's clock, which a controller alone has not
    ctl = SlaveController(SlaveController.Params.model_validate({"phase_lock_us": None}))

    def port() -> Any:
        return ctl.shaper.stats()["passivity"]["active"]

    ctl.on_sample(PoseSample("m1", None, "Tool", (0.0, 0.0, 0.0), meta={"energy_j": "0.001"}), 0.0)
    assert port() is True
    ctl.on_sample(PoseSample("m2", None, "Tool", (1.0, 0.0, 0.0)), 0.001)
    assert port() is False and ctl.source == "m2"
    ctl.on_sample(PoseSample("m2", None, "Tool", (1.0, 0.0, 0.0), meta={"energy_j": "0.0"}), 0.002)
    assert port() is True


@pytest.mark.req("SR-FORCE-7")
def test_tissue_pressing_onto_the_tool_is_backed_out_of_on_every_tick() -> None:
    """The tool rests in contact under the limit (2 N, no gap: the master's passivity off)
    and the tissue moves 0.4 mm onto it (6 N, over 90 % of the 5 N limit): from the first tick
    that reads the force, the commanded tip moves out along it every tick, a new master
    sample or not, until the force is under 90 % of the limit."""
    pair = _pair(10.0, 0.0, master_params={"passivity": False},
                 slave_params={"max_tissue_force_n": 5.0})  # fmt: skip
    try:
        env = pair.slave.robot.hardware.environment
        ctl = _slave_ctl(pair)
        robot = pair.slave.robot
        pair.start()
        _press(pair, 2.0)
        (wall,) = [c for c in env.contacts if c.name == "wall"]
        assert ctl.shaper.cmd == ctl.shaper.raw  # nothing to give back: no reason to shape
        moved = dataclasses.replace(wall, point=(wall.point[0] - 0.4, *wall.point[1:]))
        env.define("wall", [moved])
        over = idle = 0
        for _ in range(40):
            f = ctl.shaper.force_base()  # what the next tick reads
            before = robot.frame.tip_position(list(robot.data.setpoint))
            samples = ctl.samples
            pair.step(1)
            if f is None or math.hypot(*f) < 4.5:
                continue
            over += 1
            idle += ctl.samples == samples
            after = robot.frame.tip_position(list(robot.data.setpoint))
            out = sum((a - b) * c for a, b, c in zip(after, before, f, strict=True))
            assert out > 0.0, (over, ctl.samples == samples)
        assert over >= 20 and idle >= 10, (over, idle)
    finally:
        pair.close()


def test_a_clamped_target_in_contact_is_counted_once_a_sample() -> None:
    """The pitch joint's limit raised to 0.30 rad clamps the tool's target while it presses
    on the wall (the paper's motion takes pitch from 0.35 to 0.24 rad): GetStats'
    ``ik_clamped`` counts each sample whose target was clamped once; a tick between samples,
    its target left as it was, is not a new target and is neither solved nor counted."""
    cfg = sweep.wall_config(10.0)
    cfg["robot"]["joints"][1]["limits"]["min"] = 0.30
    pair = SimPair(CONFIGS / "master.yaml", cfg, master_params={"passivity": False})
    try:
        ctl = _slave_ctl(pair)
        env = pair.slave.robot.hardware.environment
        pair.start()
        in_contact = between = 0
        for _ in range(4000):
            samples, clamped = ctl.samples, ctl.clamped
            pair.step(1)
            if ctl.clamped > clamped:
                in_contact += env.in_contact
                between += ctl.samples == samples
        assert ctl.stats()["ik_clamped"] == ctl.clamped
        assert in_contact > 500 and between == 0, (in_contact, between)
    finally:
        pair.close()
