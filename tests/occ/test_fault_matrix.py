"""The hardware fault matrix (occ_testkit/faultmatrix.py; docs/SAFETY.md SR-HW-1..22 and
SR-HW-30..39), one test a row.

Each fault is injected into the drive ``tool`` of the shipped slave, whose other drive
``arm`` stays healthy. Every row must end with: every drive safe in the tick the robot
noticed, the robot FAULT (or the transition refused, its state unchanged), a STATUS naming
the drive and the cause to the operator and to the viewer, Enable refused until Reset, never
a tick RUNNING on part of the hardware, and the robot working again once the drive is repaired
and reset. The time from detection to the last drive safe is measured (``tools/fault_matrix.py``
prints it); here it is only required to exist, since it is a wall-clock figure.
"""

from __future__ import annotations

import pytest

from occ_testkit.faultmatrix import ROWS, Outcome, run_row

BY_NAME = {row.name: row for row in ROWS}


def check(name: str, cause: str, state: str = "FAULT", when_ms: float = 1.0) -> Outcome:
    out = run_row(BY_NAME[name])
    assert not out.notes, out.notes
    assert out.partial_ticks == 0  # never RUNNING with a drive that is not ACTIVE
    assert out.ticks_to_safe == 0  # every drive safe in the tick the fault was noticed
    assert out.state == state
    for alert in (out.alert_operator, out.alert_viewer):
        assert "tool" in alert and cause in alert, alert
    assert out.detected_ms is not None and out.detected_ms <= when_ms
    assert out.enable_refused, out.enable_reply
    assert out.recovered
    assert out.ok
    return out


def check_running(name: str, cause: str, when_ms: float = 1.0) -> None:
    out = check(name, cause, when_ms=when_ms)
    assert out.fault_to_safe_us is not None and out.fault_to_safe_us > 0.0
    assert out.enable_reply.startswith("'enable' refused in state FAULT")


@pytest.mark.req("SR-HW-1")
def test_configure_fails_the_robot_starts_in_fault_naming_the_drive() -> None:
    out = check("configure", "configure failed: driver tool: configure failed", when_ms=0.0)
    assert out.alert_operator.startswith("slave is FAULT: ")  # the greeting says why


@pytest.mark.req("SR-HW-2")
def test_power_on_fails_enable_is_vetoed_and_the_robot_faults() -> None:
    out = check("activate", "enable failed: driver tool: activate failed")
    assert out.enable_reply.startswith("'enable' failed in state READY: driver tool: activate ")
    assert out.alert_operator.startswith("READY -> FAULT: ")  # never ENABLED, never RUNNING


@pytest.mark.req("SR-HW-3")
def test_a_joint_never_measured_refuses_enable_and_keeps_the_state() -> None:
    out = check(
        "unmeasured", "no measurement yet from driver tool joints ['insertion']", state="READY"
    )
    assert out.enable_reply.startswith("'enable' refused in state READY: no measurement")


@pytest.mark.req("SR-HW-4")
def test_a_hook_exception_mid_run_stops_every_drive_in_the_tick() -> None:
    check_running("hook", "exception in the drive's read hook")


@pytest.mark.req("SR-HW-5")
def test_a_write_that_raises_stops_every_drive_in_the_tick() -> None:
    check_running("write", "driver tool: write failed")


@pytest.mark.req("SR-HW-6")
def test_heartbeat_lost_stops_every_drive_when_the_drive_reports_it() -> None:
    # commands stop reaching the drive, so it holds while its command moves on: the
    # following error says so (at 46 ms) before the drive's own heartbeat report (50 ms)
    out = check("heartbeat", "joint insertion: following error", when_ms=50.0)
    assert out.fault_to_safe_us is not None


@pytest.mark.req("SR-HW-7")
def test_feedback_nan_after_measured_is_feedback_lost() -> None:
    check_running("nan", "joint insertion: feedback lost (position nan)")


@pytest.mark.req("SR-HW-8", "SR-HW-14")
def test_feedback_frozen_while_the_heartbeat_lives_is_caught() -> None:
    # the tool moves on while its encoder stays: the following error sees it first (35 ms:
    # the window crossed, then 3 ms), before the frozen rule's 50 ms
    check_running("frozen", "joint insertion: following error", when_ms=40.0)


@pytest.mark.req("SR-HW-9")
def test_a_position_jump_beyond_the_velocity_limit_is_caught() -> None:
    check_running("jump", "joint insertion: feedback jump of")


@pytest.mark.req("SR-HW-10")
def test_a_can_node_that_stops_answering_is_caught_by_the_feedback_deadline() -> None:
    check_running("can-silent", "no feedback on id 0x181", when_ms=12.0)


@pytest.mark.req("SR-HW-11")
def test_a_can_node_that_answers_late_is_caught_by_the_feedback_deadline() -> None:
    check_running("can-late", "no feedback on id 0x181", when_ms=12.0)


@pytest.mark.req("SR-HW-12")
def test_can_bus_off_stops_every_drive_in_the_tick() -> None:
    check_running("can-busoff", "bus-off on")


@pytest.mark.req("SR-HW-13")
def test_can_error_frames_past_the_limit_stop_every_drive() -> None:
    check_running("can-errors", "11 error frames in 100 ms")


# ------------------------------------------------------------ issue 36: feedback that lies
def check_lie(name: str, rule: str, when_ms: float) -> Outcome:
    """A drive whose encoder lies while it answers and its heartbeat lives: FAULT within
    ``when_ms`` of the fault itself (not of its detection), the alert naming the drive, the
    joint and the rule, before the measured position ever leaves the joint's limits."""
    out = check(name, f"joint insertion: {rule}", when_ms=when_ms)
    assert out.inject_to_safe_ms is not None and out.inject_to_safe_ms <= 20.0
    assert out.outside_limits_mm == 0.0
    return out


@pytest.mark.req("SR-HW-14")
def test_a_runaway_encoder_at_a_tick_s_velocity_limit_is_caught_by_the_following_error() -> None:
    # 0.1 mm a tick, the insertion's velocity limit exactly: no jump, no limit crossed for
    # a second; on today's main the robot stayed RUNNING to 0.258 m (issue 36)
    out = check_lie("drift", "following error", when_ms=20.0)
    assert "commanded" in out.alert_operator and "time_ms 3" in out.alert_operator


@pytest.mark.req("SR-HW-9")
def test_a_runaway_encoder_at_five_times_the_limit_is_a_jump_in_its_first_tick() -> None:
    check_lie("drift-fast", "feedback jump of 0.000521 in 1 ms", when_ms=1.0)


@pytest.mark.req("SR-HW-9")
def test_a_single_slip_of_five_ticks_worth_is_caught() -> None:
    # 10 x the velocity limit let it through; 2 x plus the encoder's quantum does not
    check_lie("slip", "feedback jump of", when_ms=1.0)


@pytest.mark.req("SR-HW-14")
def test_a_can_node_whose_stale_position_dithers_by_a_count_is_caught() -> None:
    # frames keep coming, the heartbeat lives, the position toggles by one count while the
    # tool moves on: on today's main never judged frozen (issue 36). Caught by the following
    # error with the drive's own figures (window 0.2 mm, lag 5 ms; the node's servo trails by
    # 2 ms): 19 ms after the fault; with the generic defaults (0.5 mm, 20 ms) it is 47 ms.
    check_lie("can-dither", "following error", when_ms=20.0)


# issue 38: a CiA 402 drive (the cia402 driver and its emulator)
@pytest.mark.req("SR-HW-33")
def test_a_cia402_emcy_stops_every_drive_in_the_tick() -> None:
    check_running("cia402-emcy", "node 3 (joint insertion): EMCY 0x2310 (continuous overcurrent")


@pytest.mark.req("SR-HW-33")
def test_a_cia402_statusword_fault_bit_without_emcy_stops_every_drive() -> None:
    check_running("cia402-fault-bit", "node 3 (joint insertion): statusword", when_ms=3.0)


@pytest.mark.req("SR-HW-33")
def test_a_cia402_node_whose_heartbeat_stops_is_caught_by_its_consumer() -> None:
    check_running("cia402-heartbeat", "heartbeat consumer timeout", when_ms=32.0)


@pytest.mark.req("SR-HW-33")
def test_cia402_tpdos_later_than_the_feedback_timeout_are_caught() -> None:
    check_running("cia402-tpdo-late", "no TPDO for", when_ms=12.0)


@pytest.mark.req("SR-HW-32")
def test_a_cia402_node_that_will_not_enable_vetoes_enable_and_the_robot_faults() -> None:
    out = check("cia402-refuse", "enable failed: driver tool: ", when_ms=2.0)
    assert "node 3 (joint insertion) in SWITCHED ON" in out.enable_reply
    assert "every node switched off again" in out.enable_reply
    assert out.alert_operator.startswith("READY -> FAULT: ")  # never ENABLED, never RUNNING
