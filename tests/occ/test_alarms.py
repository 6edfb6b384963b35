"""occ/core/alarms.py piece by piece: what each failure does to the robot's state, to its drives
and to what every operator hears, with the words they hear it in.

The alarms are given narrow ports (a state machine, a clock, ``send``, the drives, the streams),
so each is a small fake here that records what was asked of it; the daemon-level tests
(test_robot_sim, test_drive_truth, test_supervisor_thread) show the same paths end to end.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import pytest

import igtl
from occ.core.alarms import Alarms
from occ.core.hardware import HardwareFailure
from occ.core.safety import LossEvent, RobotState
from occ_testkit import CONFIGS
from occ_testkit.testing import SimRobot


@dataclass
class States:
    state: RobotState = RobotState.RUNNING
    asked: list[tuple[str, str]] = field(default_factory=list)

    def try_request(self, event: str, reason: str) -> None:
        self.asked.append((event, reason))
        self.state = {
            "fault": RobotState.FAULT,
            "stop": RobotState.STOPPED,
        }.get(event, self.state)


class Clock:
    def now(self) -> float:
        return 12.5

    def wall_time(self) -> float:
        return 1000.25


@dataclass
class Drives:
    unconfirmed: list[HardwareFailure] = field(default_factory=list)
    powered: bool = False
    stops: list[str] = field(default_factory=list)

    def safe_stop(self, reason: str) -> list[HardwareFailure]:
        self.stops.append(reason)
        return list(self.unconfirmed)

    def unsafe(self) -> bool:
        return self.powered


@dataclass
class Streams:
    input: str = "master"
    policy: str = "hold"


class AlarmsRig:
    def __init__(self, state: RobotState = RobotState.RUNNING) -> None:
        self.states = States(state)
        self.sent: list[igtl.StatusMessage] = []
        self.order: list[str] = []
        self.drives = Drives()
        self.streams = Streams()
        self.alarms = Alarms(
            "slave",
            self.states,  # type: ignore[arg-type]
            Clock(),  # type: ignore[arg-type]
            self._send,
            self.drives,  # type: ignore[arg-type]
            self.streams,  # type: ignore[arg-type]
        )
        self.notes: list[tuple[str, Any]] = []
        self.alarms.note = lambda what, obj: self.notes.append((what, obj))

    def _send(self, msg: Any) -> None:
        self.order.append(f"send {msg.error_name}")
        self.sent.append(msg)

    def heard(self) -> list[tuple[str, str, int]]:
        return [(m.error_name, m.status_message, m.code) for m in self.sent]


def event(kind: str, cause: str = "no packet for 100.00 ms") -> LossEvent:
    return LossEvent(kind=kind, cause=cause, source="grace", run=3, time=2.0, since_last_good_s=0.1)


@pytest.mark.req("SR-LOSS-4")
@pytest.mark.parametrize(
    "state", [RobotState.READY, RobotState.ENABLED, RobotState.STOPPED, RobotState.FAULT]
)
def test_a_loss_is_only_counted_when_the_stream_does_not_move_the_robot(
    state: RobotState,
) -> None:
    rig = AlarmsRig(state)
    for kind in ("latch", "hold", "resume", "refused"):
        rig.alarms.loss_event(event(kind), state)
    assert rig.sent == [] and rig.states.asked == [] and rig.alarms.last_alert == ""
    # the black box still learns each event as judged, with the state it came in
    assert [n[0] for n in rig.notes] == ["loss"] * 4
    assert all(n[1]["stream"] == "master" and n[1]["state"] == state.value for n in rig.notes)


@pytest.mark.req("SR-LOSS-1")
@pytest.mark.parametrize("policy", ["hold", "fault"])
def test_a_latched_loss_while_running_stops_the_robot_naming_the_stream(policy: str) -> None:
    rig = AlarmsRig()
    rig.streams.policy = policy
    ev = event("latch", "3 packets lost (seq 10-12)")
    rig.alarms.loss_event(ev, RobotState.RUNNING)
    reason = "packet loss on master: 3 packets lost (seq 10-12)"
    assert rig.alarms.last_alert == reason
    assert rig.states.asked == [("stop" if policy == "hold" else "fault", reason)]
    assert rig.notes == [("loss", {"stream": "master", "state": "RUNNING", "event": ev})]
    assert not rig.alarms.safety_stopping  # set only while the stop's transition runs


@pytest.mark.req("SR-LOSS-2")
def test_a_hold_is_silent_and_a_resume_or_a_refusal_is_a_stream_warning() -> None:
    rig = AlarmsRig()
    rig.alarms.loss_event(event("hold", "overdue"), RobotState.RUNNING)
    assert rig.sent == [] and rig.states.asked == []
    rig.alarms.loss_event(event("resume", "back after 9 ms"), RobotState.RUNNING)
    rig.alarms.loss_event(event("refused", "a jump of 12 mm"), RobotState.RUNNING)
    assert rig.heard() == [
        ("STREAM", "stream master: back after 9 ms", igtl.StatusCode.OK),
        ("STREAM", "stream master: a jump of 12 mm", igtl.StatusCode.OK),
    ]
    assert rig.states.asked == [] and rig.alarms.last_alert == ""
    m = rig.sent[0]
    assert m.device_name == "slave" and m.timestamp == 1000.25


@pytest.mark.req("SR-HW-18")
def test_a_supervisor_trip_alerts_first_then_stops_every_drive_and_names_the_unproven() -> None:
    rig = AlarmsRig()
    rig.alarms.on_supervisor_trip = lambda text: rig.order.append(f"cell {text}")
    rig.drives.safe_stop = lambda reason: (  # type: ignore[method-assign]
        rig.order.append(f"stop {reason}") or [HardwareFailure("arm", "stop", "no answer in 50 ms")]
    )
    rig.alarms.supervisor_trip("control loop did not tick for 20.2 ms")
    assert rig.order == [
        "cell supervisor: control loop did not tick for 20.2 ms",
        "send SUPERVISOR",
        "stop control loop did not tick for 20.2 ms",
        "send ALERT",
    ]
    assert rig.heard() == [
        (
            "SUPERVISOR",
            "supervisor: control loop did not tick for 20.2 ms",
            igtl.StatusCode.HARDWARE_FAILURE,
        ),
        (
            "ALERT",
            "supervisor: drives not proven stopped: driver arm: stop failed: no answer in 50 ms",
            igtl.StatusCode.HARDWARE_FAILURE,
        ),
    ]
    assert rig.alarms.last_alert == "supervisor: control loop did not tick for 20.2 ms"
    assert rig.states.asked == []  # the state machine is the loop's: it latches on its return


@pytest.mark.req("SR-SUP-1")
def test_a_supervisor_trip_with_every_drive_stopped_is_one_status() -> None:
    rig = AlarmsRig()
    rig.alarms.supervisor_trip("hung")
    assert rig.heard() == [("SUPERVISOR", "supervisor: hung", igtl.StatusCode.HARDWARE_FAILURE)]
    assert rig.drives.stops == ["hung"]


@dataclass
class Sup:
    reason: str = "control loop did not tick for 31.0 ms"
    resets: int = 0

    def reset(self) -> None:
        self.resets += 1


@pytest.mark.req("SR-SUP-1")
@pytest.mark.parametrize(
    ("state", "powered", "latched"),
    [
        (RobotState.INIT, False, False),
        (RobotState.READY, False, False),
        (RobotState.READY, True, True),  # a drive still on: something could have moved
        (RobotState.ENABLED, False, True),
        (RobotState.RUNNING, False, True),
        (RobotState.STOPPED, False, True),
    ],
)
def test_the_loop_back_after_a_trip_faults_unless_nothing_was_powered(
    state: RobotState, powered: bool, latched: bool
) -> None:
    rig = AlarmsRig(state)
    rig.drives.powered = powered
    sup = Sup()
    assert rig.alarms.supervisor_back(sup) is latched  # type: ignore[arg-type]
    reason = "supervisor: control loop did not tick for 31.0 ms"
    if latched:
        assert rig.states.asked == [("fault", reason)] and rig.alarms.last_alert == reason
        assert sup.resets == 0 and rig.sent == []
    else:
        assert rig.states.asked == [] and sup.resets == 1
        assert rig.heard() == [
            ("SUPERVISOR", f"{reason}; no drive powered: not latched", igtl.StatusCode.OK)
        ]


@pytest.mark.req("SR-EXC-1")
def test_a_plugin_error_faults_once_naming_it_and_its_log_is_bounded(
    caplog: pytest.LogCaptureFixture,
) -> None:
    rig = AlarmsRig()
    caplog.set_level(logging.ERROR, logger="occ.core.robot")
    err = ZeroDivisionError("division by zero")
    rig.alarms.plugin_error("controller teleop.update", err)
    reason = "controller teleop.update raised ZeroDivisionError: division by zero"
    assert rig.states.asked == [("fault", reason)] and rig.alarms.last_alert == reason
    first = [r for r in caplog.records if r.getMessage() == reason]
    assert len(first) == 1 and first[0].exc_info is not None and first[0].exc_info[1] is err
    assert f"FAULT: {reason}" in [r.getMessage() for r in caplog.records]
    # in FAULT already: no second transition, and the log stops after 20 lines
    caplog.clear()
    for _ in range(30):
        rig.alarms.plugin_error("controller teleop.update", err)
    assert rig.states.asked == [("fault", reason)]
    assert sum(r.getMessage() == reason for r in caplog.records) == 19
    rig.alarms.cleared()  # a Reset that succeeded: the next errors are logged again, 20
    caplog.clear()
    for _ in range(25):
        rig.alarms.plugin_error("controller teleop.update", err)
    assert sum(r.getMessage() == reason for r in caplog.records) == 20


@pytest.mark.req("SR-HW-17")
def test_drives_that_failed_to_stop_are_an_alert_and_are_not_told_again_while_faulted() -> None:
    rig = AlarmsRig(RobotState.FAULT)
    failed = [HardwareFailure("arm", "stop", "bus off"), HardwareFailure("wrist", "stop", "EMCY")]
    rig.alarms.hardware_alert(failed)
    text = (
        "drives failed to stop: driver arm: stop failed: bus off; driver wrist: stop failed: EMCY"
    )
    assert rig.heard() == [("ALERT", text, igtl.StatusCode.HARDWARE_FAILURE)]
    # the same failures seen again in FAULT are already told
    rig.alarms.hardware_fault(failed)
    assert len(rig.sent) == 1


@pytest.mark.req("SR-HW-19")
@pytest.mark.parametrize("state", [RobotState.RUNNING, RobotState.ENABLED, RobotState.READY])
def test_a_drive_failure_faults_naming_each_drive_and_is_noted_for_the_black_box(
    state: RobotState,
) -> None:
    rig = AlarmsRig(state)
    failed = [HardwareFailure("arm", "read", "timeout"), HardwareFailure("tool", "write", "EMCY")]
    rig.alarms.hardware_fault(failed)
    reason = "driver arm: read failed: timeout; driver tool: write failed: EMCY"
    assert rig.states.asked == [("fault", reason)] and rig.alarms.last_alert == reason
    assert rig.notes == [("drive failure", {"state": state.value, "failures": failed})]
    # the FAULT STATUS is the transition's (the state machine's listener): no ALERT here
    assert rig.sent == []


@pytest.mark.req("SR-HW-19")
@pytest.mark.parametrize("state", [RobotState.FAULT, RobotState.ESTOP])
def test_a_new_failure_while_faulted_is_an_alert_once_and_repeats_are_logged_boundedly(
    state: RobotState, caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 36's "faults nobody hears": a read error during an E-stop, a second drive faulting
    while FAULT, are an ALERT to every operator, once each (drive and operation), never a
    transition; a failure told already is only logged, at most 20 times until a Reset."""
    caplog.set_level(logging.ERROR, logger="occ.core.robot")
    rig = AlarmsRig(state)
    first = HardwareFailure("arm", "read", "timeout")
    rig.alarms.hardware_fault([first])
    w = state.value
    assert rig.heard() == [
        ("ALERT", f"while {w}: driver arm: read failed: timeout", igtl.StatusCode.HARDWARE_FAILURE)
    ]
    assert rig.notes == [("drive failure", {"state": w, "failures": [first]})]
    assert rig.states.asked == []
    # the same drive and operation again, and with a new one: only the new one is told
    second = HardwareFailure("tool", "read", "EMCY 0x2310")
    rig.alarms.hardware_fault([HardwareFailure("arm", "read", "timeout again"), second])
    assert rig.heard()[1:] == [
        (
            "ALERT",
            f"while {w}: driver tool: read failed: EMCY 0x2310",
            igtl.StatusCode.HARDWARE_FAILURE,
        )
    ]
    assert rig.notes[1] == ("drive failure", {"state": w, "failures": [second]})
    # the same drive, another operation: news
    rig.alarms.hardware_fault([HardwareFailure("arm", "write", "bus off")])
    assert rig.heard()[2][1] == f"while {w}: driver arm: write failed: bus off"
    caplog.clear()
    for _ in range(25):
        rig.alarms.hardware_fault([first])
    assert len(rig.sent) == 3 and rig.states.asked == []
    repeated = f"while {w}: driver arm: read failed: timeout"
    assert [r.getMessage() for r in caplog.records] == [repeated] * 20
    rig.alarms.cleared()  # a Reset that worked: the same failure is news again
    rig.alarms.hardware_fault([first])
    assert len(rig.sent) == 4 and rig.heard()[3][1] == repeated


@pytest.mark.req("SR-HW-19")
def test_a_failure_that_faulted_the_robot_is_not_told_again_as_an_alert() -> None:
    rig = AlarmsRig(RobotState.RUNNING)
    failed = [HardwareFailure("arm", "write", "bus off")]
    rig.alarms.hardware_fault(failed)  # FAULT (the transition's STATUS names it)
    assert rig.states.state is RobotState.FAULT
    rig.alarms.hardware_fault(failed)  # the next tick sees it again
    assert rig.sent == []


@pytest.mark.req("SR-WD-2")
def test_a_safety_stop_holds_a_moving_robot_faults_by_policy_and_tells_a_still_one(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """``policy: hold`` stops a RUNNING or ENABLED robot (the stop's transition runs with
    ``safety_stopping`` set, so its listeners tell it from an operator's Stop); ``fault``
    latches FAULT; a robot not moving is told why, as an ALERT, and nothing changes."""
    caplog.set_level(logging.ERROR, logger="occ.core.robot")
    for state in (RobotState.RUNNING, RobotState.ENABLED):
        rig = AlarmsRig(state)
        seen: list[bool] = []
        ask = rig.states.try_request

        def watching(
            event: str, reason: str, rig: AlarmsRig = rig, ask: Any = ask, seen: list[bool] = seen
        ) -> None:
            seen.append(rig.alarms.safety_stopping)
            ask(event, reason)

        rig.states.try_request = watching  # type: ignore[method-assign]
        rig.alarms.safety_stop("watchdog: 20 consecutive overruns", "hold")
        assert rig.states.asked == [("stop", "watchdog: 20 consecutive overruns")]
        assert seen == [True] and rig.alarms.safety_stopping is False
        assert rig.sent == [] and rig.alarms.last_alert == "watchdog: 20 consecutive overruns"
    rig = AlarmsRig(RobotState.RUNNING)
    rig.alarms.safety_stop("collision: link 3 inside its margin", "fault")
    assert rig.states.asked == [("fault", "collision: link 3 inside its margin")]
    for state in (RobotState.READY, RobotState.STOPPED):
        rig = AlarmsRig(state)
        rig.alarms.safety_stop("gap of 60.000 ms between ticks", "hold")
        assert rig.states.asked == []
        assert rig.heard() == [
            ("ALERT", "gap of 60.000 ms between ticks", igtl.StatusCode.TIME_OUT)
        ]
        assert rig.alarms.last_alert == "gap of 60.000 ms between ticks"
    assert "SAFETY STOP: gap of 60.000 ms between ticks" in [r.getMessage() for r in caplog.records]


@pytest.mark.req("SR-BOX-2")
def test_a_black_box_dump_is_told_ok_or_as_a_resource_error() -> None:
    rig = AlarmsRig()
    rig.alarms.black_box_written("black box of fault written to /tmp/x", True)
    rig.alarms.black_box_written("black box not written: disk full", False)
    assert rig.heard() == [
        ("BLACKBOX", "black box of fault written to /tmp/x", igtl.StatusCode.OK),
        ("BLACKBOX", "black box not written: disk full", igtl.StatusCode.RESOURCE_ERROR),
    ]


@dataclass
class Monitor:
    resets: list[Any] = field(default_factory=list)

    def reset(self, now: Any) -> None:
        self.resets.append(now)


@pytest.mark.parametrize("state", [RobotState.READY, RobotState.STOPPED, RobotState.ENABLED])
def test_a_bystanders_loss_while_not_running_only_rearms_its_monitor(state: RobotState) -> None:
    """A master not in control (collaboration) moves nothing: out of RUNNING its latch only
    re-arms its monitor (it may be handed control later), and nobody is told."""
    rig = AlarmsRig(state)
    rig.streams.input = "mentor"
    mon = Monitor()
    for kind in ("hold", "resume", "latch"):
        rig.alarms.bystander_loss("trainee", mon, event(kind), state)  # type: ignore[arg-type]
    assert mon.resets == [None] and rig.sent == [] and rig.states.asked == []
    assert [n[1]["owner"] for n in rig.notes] == ["mentor"] * 3
    assert all(n[1]["stream"] == "trainee" and n[1]["state"] == state.value for n in rig.notes)


def test_a_bystanders_loss_while_running_alerts_and_never_stops_the_robot() -> None:
    rig = AlarmsRig()
    rig.streams.input = "mentor"
    mon = Monitor()
    rig.alarms.bystander_loss("trainee", mon, event("hold"), RobotState.RUNNING)  # type: ignore[arg-type]
    assert rig.sent == [] and mon.resets == []
    rig.alarms.bystander_loss(
        "trainee",
        mon,  # type: ignore[arg-type]
        event("latch", "3 packets lost (seq 7-9)"),
        RobotState.RUNNING,
    )
    rig.alarms.bystander_loss(
        "trainee",
        mon,  # type: ignore[arg-type]
        event("resume", "back after 9 ms"),
        RobotState.RUNNING,
    )
    assert mon.resets == [None]
    assert rig.heard() == [
        (
            "ALERT",
            "stream trainee (not in control) lost: 3 packets lost (seq 7-9); following mentor",
            igtl.StatusCode.TIME_OUT,
        ),
        ("STREAM", "stream trainee: back after 9 ms", igtl.StatusCode.OK),
    ]
    assert rig.states.asked == [] and rig.alarms.last_alert == ""


@pytest.mark.req("SR-COLL-2")
@pytest.mark.parametrize(("policy", "event_"), [("hold", "stop"), ("fault", "fault")])
def test_a_collision_is_a_collision_alert_then_the_safety_stop(policy: str, event_: str) -> None:
    rig = AlarmsRig()
    why = "link wrist_3 within 4.0 mm of region table (margin 10.0 mm)"
    rig.alarms.collision_stop(why, policy)
    assert rig.heard() == [("COLLISION", why, igtl.StatusCode.ILLEGAL_INSTRUCTION)]
    assert rig.states.asked == [(event_, why)] and rig.alarms.last_alert == why


@pytest.mark.req("SR-REC-1")
def test_a_recording_that_failed_is_a_recording_status_and_moves_nothing() -> None:
    rig = AlarmsRig()
    rig.alarms.recording_failed("recording to /data/x.igtl failed: [Errno 28] No space left")
    assert rig.heard() == [
        (
            "RECORDING",
            "recording to /data/x.igtl failed: [Errno 28] No space left",
            igtl.StatusCode.RESOURCE_ERROR,
        )
    ]
    assert rig.states.asked == [] and rig.alarms.last_alert == ""


@pytest.mark.req("SR-WD-1")
def test_a_watchdog_alert_is_a_watchdog_status_with_its_reason(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, logger="occ.core.robot")
    rig = AlarmsRig()
    rig.alarms.watchdog_alert("overrun: compute 1.200 ms > budget 1.000 ms (3 consecutive)", 7)
    assert rig.heard() == [
        (
            "WATCHDOG",
            "watchdog: overrun: compute 1.200 ms > budget 1.000 ms (3 consecutive)",
            igtl.StatusCode.TIME_OUT,
        )
    ]
    assert rig.states.asked == []
    assert [r.getMessage() for r in caplog.records] == [
        "watchdog: overrun: compute 1.200 ms > budget 1.000 ms (3 consecutive) (7 overruns so far)"
    ]


class Recorder:
    def __init__(self) -> None:
        self.recorded: list[tuple[Any, str, str, float]] = []
        self.failure_hook: Any = None

    def record_message(self, msg: Any, direction: str, iface: str, t: float) -> None:
        self.recorded.append((msg, direction, iface, t))

    def on_failure(self, hook: Any) -> None:
        self.failure_hook = hook


@pytest.mark.req("SR-REC-1")
def test_every_status_sent_is_recorded_and_tapped_as_going_out_to_everyone() -> None:
    """A broadcast goes to every viewer and operator, into the recording (direction ``out``,
    interface ``*``, the loop clock's time) and to the black box's tap; a recorder that fails
    is announced by the alarms that watch it."""
    rig = AlarmsRig()
    rec = Recorder()
    assert rig.alarms.watch_recording(rec) is rec and rig.alarms.recorder is rec
    tapped: list[tuple[Any, str]] = []
    rig.alarms.tap = lambda msg, iface: tapped.append((msg, iface))
    rig.alarms.broadcast("ALERT", "one", igtl.StatusCode.TIME_OUT)
    rig.alarms.broadcast("STOPPED", "two", igtl.StatusCode.OK, timestamp=77.5)
    first, second = rig.sent
    assert (first.timestamp, second.timestamp) == (1000.25, 77.5)
    assert (first.code, first.error_name, first.status_message) == (
        igtl.StatusCode.TIME_OUT,
        "ALERT",
        "one",
    )
    assert rec.recorded == [(first, "out", "*", 12.5), (second, "out", "*", 12.5)]
    assert tapped == [(first, "*"), (second, "*")]
    rec.failure_hook("recording to x failed: disk full")  # the recorder's failure: heard
    assert rig.heard()[-1] == (
        "RECORDING",
        "recording to x failed: disk full",
        igtl.StatusCode.RESOURCE_ERROR,
    )
    assert rig.alarms.watch_recording(None) is None and rig.alarms.recorder is None
    rig.alarms.broadcast("ALERT", "three", igtl.StatusCode.OK)
    assert len(rec.recorded) == 3  # the failure's own STATUS; none after it was unwatched


def test_a_robot_name_longer_than_a_device_name_is_cut_to_its_20_bytes() -> None:
    """OpenIGTLink's device name holds 20 bytes: every STATUS of a robot named longer carries
    the name's first 20 characters, and packs (one character more would not)."""
    rig = AlarmsRig()
    name = "slave-left-arm-of-cell-3"  # 24 characters
    alarms = Alarms(name, rig.states, Clock(), rig._send, rig.drives, rig.streams)  # type: ignore[arg-type]
    alarms.broadcast("ALERT", "one", igtl.StatusCode.OK)
    (m,) = rig.sent
    assert m.device_name == name[:20] == "slave-left-arm-of-ce"
    assert igtl.unpack(m.pack()).device_name == name[:20]


def test_a_new_alarms_is_not_stopping_and_notes_a_bystanders_loss_as_a_loss() -> None:
    rig = AlarmsRig()
    assert rig.alarms.safety_stopping is False and rig.alarms.recorder is None
    rec = Recorder()
    given = Alarms("x", rig.states, Clock(), rig._send, rig.drives, rig.streams, recorder=rec)  # type: ignore[arg-type]
    assert given.recorder is rec
    rig.alarms.bystander_loss("trainee", Monitor(), event("hold"), RobotState.RUNNING)  # type: ignore[arg-type]
    ((what, obj),) = rig.notes
    assert what == "loss" and obj["event"].kind == "hold" and obj["owner"] == "master"


@pytest.mark.req("SR-HW-19")
def test_a_failure_told_before_a_reset_is_news_again_after_it() -> None:
    """On the simulated slave: a drive's read failure faults the robot; Reset brings it back to
    READY, and with it every failure becomes news again: the same drive failing the same way in
    a later FAULT is an ALERT to every operator, not something told already."""
    sim = SimRobot(CONFIGS / "slave.yaml")
    try:
        robot = sim.robot
        op, viewer = sim.peer("operator"), sim.peer("slicer")
        sim.tick()
        drive = robot.hardware.pairs[0][0].name
        failure = HardwareFailure(drive, "read", "encoder lost")
        robot.alarms.hardware_fault([failure])
        assert robot.state is RobotState.FAULT
        robot.alarms.hardware_fault([failure])  # told already in this FAULT: no ALERT
        cid = op.send_command("Reset")
        sim.tick()
        sim.tick()
        assert robot.state is RobotState.READY, (op.reply_to(cid), robot.last_alert)
        robot.alarms.fault("an operator's test fault")
        assert robot.state is RobotState.FAULT
        robot.alarms.hardware_fault([failure])
        alerts = [m.status_message for m in viewer.messages("STATUS") if m.error_name == "ALERT"]
        assert alerts == [f"while FAULT: driver {drive}: read failed: encoder lost"], alerts
    finally:
        sim.close()
