"""The operator desk (occ/net/operators.py) over in-process interfaces in simulated time: what each
query and command is answered with, to whom, and what the statistics say.

Written to catch faults the robot-level tests let through (mutation testing,
docs/VERIFICATION.md): replies carry the asker's message ID, version and a timestamp; the state
description names the alert and the reason; the statistics hold what they claim.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import igtl
from occ.net.operators import VIEWER_HIDDEN, redact_for_viewer
from occ.core.safety import RobotState
from occ_testkit.testing import SimPeer, SimRobot, wait_until

ROOT = Path(__file__).resolve().parents[2]
SLAVE = ROOT / "configs" / "slave.yaml"


@pytest.fixture
def sim():
    with SimRobot(SLAVE) as s:
        yield s


def query(peer: SimPeer, mtype: str, device: str = "", version: int = 2, mid: int = 31) -> None:
    peer.send(
        igtl.REGISTRY[mtype](
            type_name=mtype,
            device_name=device,
            header_version=version,
            message_id=mid if version == 2 else 0,
        )
    )


def answers(sim: SimRobot, msg: igtl.Message, role: str = "operator") -> list[igtl.Message]:
    """What the desk sends back for ``msg`` (its version, ID and timestamp as built: the
    in-process transport re-packs replies in the version its peer speaks)."""
    from igtl.transport.common import Peer
    from occ.net.interfaces import Inbound

    out: list[igtl.Message] = []
    real = sim.robot.interfaces.reply
    sim.robot.interfaces.reply = lambda item, reply: out.append(reply) or True  # type: ignore
    try:
        item = Inbound("operator", Peer(1, ("127.0.0.1", 5)), msg, sim.now, role=role)
        sim.robot.operators.handle(item, sim.now)
    finally:
        sim.robot.interfaces.reply = real  # type: ignore[method-assign]
    return out


#: how long a test waits for the worker thread that answers GetStats (s)
WORKER_S = 5.0


@pytest.mark.req("SR-ROUTE-1")
def test_get_status_describes_the_state_to_the_asker_only(sim):
    op, other = sim.peer("operator"), sim.peer("operator")
    sim.step()
    query(op, "GET_STATUS", "Probe")
    sim.step()
    (reply,) = [m for m in op.messages("STATUS") if m.device_name == "Probe"]
    assert (reply.code, reply.error_name) == (int(igtl.StatusCode.OK), "READY")
    assert reply.status_message.startswith("state=READY")
    assert (reply.header_version, reply.message_id) == (2, 31)
    assert reply.timestamp == pytest.approx(sim.clock.wall_time(), abs=0.01)
    assert reply.timestamp > 1e9  # a wall-clock time, not 0
    assert [m.device_name for m in other.messages("STATUS")] == ["slave"]  # its greeting only
    get = igtl.REGISTRY["GET_STATUS"]
    (unnamed,) = answers(sim, get(type_name="GET_STATUS", device_name="", header_version=1))
    assert unnamed.device_name == "slave" and unnamed.header_version == 1
    (named,) = answers(
        sim, get(type_name="GET_STATUS", device_name="P", header_version=2, message_id=3)
    )
    assert (named.device_name, named.header_version, named.message_id) == ("P", 2, 3)


def test_the_state_description_names_the_alert_and_the_reason(sim):
    op = sim.peer("operator")
    cid = op.send_command("EStop")
    sim.step()
    assert op.reply_to(cid).metadata["Message"] == "READY -> ESTOP"
    assert sim.robot.state_machine.last_reason == "operator EStop"
    desc = sim.robot.operators.describe_state()
    assert desc == "state=ESTOP; reason=operator EStop"
    cid = op.send_command("GetState")
    sim.step()
    assert op.reply_to(cid).metadata["Message"] == desc
    sim.robot.alarms.last_alert = "master lost"
    assert sim.robot.operators.describe_state() == (
        "state=ESTOP; alert=master lost; reason=operator EStop"
    )


def test_reset_in_stopped_clears_the_alert_and_says_how_to_resume(sim):
    op = sim.peer("operator")
    for name in ("Enable", "Run", "Stop"):
        op.send_command(name)
        sim.step()
    assert sim.robot.state is RobotState.STOPPED
    sim.robot.alarms.last_alert = "something happened"
    cid = op.send_command("Reset")
    sim.step()
    assert op.reply_to(cid).metadata["Message"] == "STOPPED: alerts cleared; send Run to resume"
    assert sim.robot.last_alert == "" and sim.robot.state is RobotState.STOPPED
    cid = op.send_command("Run")
    sim.step()
    assert op.reply_to(cid).metadata["Message"] == "STOPPED -> RUNNING"


def test_cell_commands_on_a_daemon_in_no_cell_are_refused_saying_so(sim):
    op = sim.peer("operator")
    for name in ("CellLeave", "CellJoin", "CellForget"):
        reply = sim.command(op, name)
        assert reply.metadata["Status"] == "FAIL", name
        assert reply.metadata["Error"] == "this daemon is in no cell (no `cell:` section)", name
    assert sim.robot.state is RobotState.READY


def test_get_capabil_lists_what_the_robot_answers(sim):
    viewer = sim.peer("slicer", header_version=1)
    query(viewer, "GET_CAPABIL", "Cap", version=1)
    sim.step()
    (cap,) = viewer.messages("CAPABILITY")
    assert cap.types == (
        "TRANSFORM",
        "POSITION",
        "STATUS",
        "STRING",
        "COMMAND",
        "CAPABILITY",
        "GET_STATUS",
        "GET_CAPABIL",
        "GET_TRANS",
    )
    assert cap.device_name == "Cap"
    assert cap.timestamp == pytest.approx(sim.clock.wall_time(), abs=0.01) and cap.timestamp > 0
    op = sim.peer("operator")
    query(op, "GET_CAPABIL", "Cap", mid=8)
    sim.step()
    (cap,) = op.messages("CAPABILITY")
    assert cap.message_id == 8
    get = igtl.REGISTRY["GET_CAPABIL"]
    for version in (1, 2):
        (cap,) = answers(sim, get(type_name="GET_CAPABIL", device_name="C", header_version=version))
        assert cap.header_version == version


@pytest.mark.parametrize("mtype", ["GET_TRANS", "GET_TRANSFOR"])
def test_get_trans_answers_the_tip_or_the_base(sim, mtype):
    viewer = sim.peer("slicer", header_version=1)
    sim.step()
    base = sim.robot.data.base
    tip = sim.robot.data.world_tip()
    assert not np.allclose(np.asarray(base), np.asarray(tip))
    for device, want, pose in (
        ("", "Tip", tip),
        ("Base", "Base", base),
        ("base", "base", base),
        ("Tip", "Tip", tip),
    ):
        viewer.received.clear()
        query(viewer, mtype, device, version=1)
        sim.step()
        (reply,) = viewer.messages("TRANSFORM", want)
        pose = np.asarray(pose)
        assert np.allclose(reply.matrix[:3, :3], pose[:3, :3]), device
        assert np.allclose(reply.matrix[:3, 3], 1000.0 * pose[:3, 3], atol=1e-3), device
    get = igtl.REGISTRY[mtype]
    for version in (1, 2):
        (reply,) = answers(sim, get(type_name=mtype, device_name="Base", header_version=version))
        assert reply.header_version == version


def test_an_unsupported_query_is_refused_by_name(sim):
    op = sim.peer("operator")
    query(op, "GET_IMAGE", "Vol", mid=4)
    sim.step()
    (reply,) = [m for m in op.messages("STATUS") if m.device_name == "Vol"]
    assert reply.code == int(igtl.StatusCode.ILLEGAL_INSTRUCTION)
    assert reply.status_message == "GET_IMAGE is not supported by slave"
    assert reply.message_id == 4
    assert sim.robot.operators.counters()["refused"] == 1


def test_counters_count_each_request_once(sim):
    op = sim.peer("operator")
    desk = sim.robot.operators
    op.send_command("Enable")
    op.send_command("GetState")
    op.send_command("Run")
    op.send_command("Enable")  # RUNNING -> Enable: refused by the state machine
    op.send_command("NoSuchThing")
    sim.step()
    c = desk.counters()
    assert c["handled"] == 3 and c["refused"] == 2 and c["reply_errors"] == 0
    assert c["worker_refused"] == sim.robot.worker.refused == 0
    assert sim.robot.snapshot()["commands"] == desk.counters()


def test_a_reply_that_cannot_be_sent_is_counted(sim, monkeypatch):
    op = sim.peer("operator")

    def broken(item, msg):
        raise OSError("gone")

    monkeypatch.setattr(sim.robot.interfaces, "reply", broken)
    op.send_command("GetState")
    op.send_command("GetState")
    sim.step()
    assert sim.robot.operators.counters()["reply_errors"] == 2
    assert sim.robot.operators.counters()["handled"] == 2


def test_the_statistics_hold_what_they_name(sim):
    op = sim.peer("operator")
    op.send_command("Enable")
    sim.step(3)
    r = sim.robot
    snap = r.snapshot()
    assert snap["robot"] == "slave" and snap["state"] == "ENABLED"
    assert snap["commands"] == r.operators.counters()
    assert snap["watchdog"] == r.watchdog.counters()
    assert snap["supervisor"] == {
        "timeout_ms": r.supervisor.timeout_s * 1e3,
        "trips": r.supervisor.trips,
        "tripped": r.supervisor.tripped,
        "thread": r.supervisor_thread.report if r.supervisor_thread else None,
    }
    assert snap["supervisor"]["timeout_ms"] > 1.0  # milliseconds, not seconds
    assert snap["reentries"] == r.motion.reentries and snap["last_alert"] == r.last_alert
    assert r.streams.monitor is not None and snap["loss"] == r.streams.monitor.counters()
    assert "owner" not in snap and "collaboration" not in snap  # not a collaboration robot
    assert snap["controller"] == r.controller.stats()
    assert (
        snap["drivers"] == {drv.name: drv.stats() for drv in r.hardware.drivers} and snap["drivers"]
    )
    assert snap["realtime"] == r.loop.realtime_report
    if r.state_table is not None:
        assert snap["state_table"] == r.state_table.stats()
    r.alarms.last_alert = "x"
    assert r.snapshot()["last_alert"] == "x"


def test_viewers_see_statistics_without_what_would_forge_the_stream():
    snap = {"seq": 1, "a": [{"last_seq": 2, "b": 3}, 4], "c": {"stream_owner": "x", "d": [5]}}
    assert redact_for_viewer(snap) == {"a": [{"b": 3}, 4], "c": {"d": [5]}}
    assert VIEWER_HIDDEN == {"seq", "last_seq", "stream_owner"}


def test_getstats_is_compact_json_with_the_lateness_buckets_on_request(sim):
    op = sim.peer("operator")
    sim.step(2)
    plain = op.send_command("GetStats")
    hist = op.send_command("GetStats", '<Command Name="GetStats" Histogram="Lateness"/>')
    sim.step()
    assert wait_until(lambda: op.reply_to(plain) and op.reply_to(hist), WORKER_S)
    text = op.reply_to(plain).metadata["Message"]
    assert ", " not in text and '": ' not in text  # compact separators
    snap = json.loads(text)
    assert "lateness_buckets" not in snap and snap["robot"] == "slave"
    reply = op.reply_to(hist)
    assert reply.timestamp > 1e9 and reply.metadata["Status"] == "SUCCESS"
    buckets = json.loads(reply.metadata["Message"])["lateness_buckets"]
    assert buckets == json.loads(json.dumps(sim.robot.stats.lateness.buckets()))


def test_getstats_as_json_names_the_request_it_answers(sim):
    op = sim.peer("operator", header_version=2)
    op.send(
        igtl.StringMessage(
            '<Command Name="GetStats" Format="JSON"/>',
            device_name="CMD_9",
            header_version=2,
            message_id=66,
        )
    )
    sim.step()
    assert wait_until(lambda: op.messages("STRING", "ACK_9"), WORKER_S)
    (ack,) = op.messages("STRING", "ACK_9")
    assert (ack.header_version, ack.message_id) == (2, 66) and ack.timestamp > 1e9
    assert json.loads(ack.string)["robot"] == "slave"
    viewer = sim.peer("slicer")
    viewer.send(
        igtl.StringMessage(
            '<Command Name="GetStats" Format="json"/>', device_name="CMD_1", header_version=1
        )
    )
    sim.step()
    assert wait_until(lambda: viewer.messages("STRING", "ACK_1"), WORKER_S)
    (ack,) = viewer.messages("STRING", "ACK_1")
    text = ack.string
    assert '"seq"' not in text and '"stream_owner"' not in text


def test_a_statistic_json_cannot_encode_is_given_as_text(sim, monkeypatch):
    op = sim.peer("operator")
    report = sim.robot.operators.report

    monkeypatch.setattr(
        sim.robot.operators, "report", lambda *a, **k: {**report(*a, **k), "odd": {1, 2}.__class__}
    )
    cid = op.send_command("GetStats")
    sim.step()
    assert wait_until(lambda: op.reply_to(cid), WORKER_S)
    assert json.loads(op.reply_to(cid).metadata["Message"])["odd"] == "<class 'set'>"


def test_getstats_as_json_keeps_the_requests_form(sim, monkeypatch):
    from igtl.transport.common import Peer
    from occ.net.interfaces import Inbound

    out: list[igtl.Message] = []
    monkeypatch.setattr(sim.robot.interfaces, "reply", lambda item, reply: out.append(reply))
    xml = '<Command Name="GetStats" Format="json"/>'
    for msg in (
        igtl.StringMessage(xml, device_name="CMD_5", header_version=1),
        igtl.CommandMessage(
            command_id=3,
            command_name="GetStats",
            command=xml,
            device_name="x",
            header_version=2,
            message_id=12,
        ),
    ):
        out.clear()
        item = Inbound("operator", Peer(1, ("127.0.0.1", 5)), msg, sim.now)
        sim.robot.operators.handle(item, sim.now)
        assert wait_until(lambda: out, WORKER_S)
        (reply,) = out
        assert reply.message_type == "STRING"
        assert reply.device_name == ("ACK_5" if msg.message_type == "STRING" else "STATS")
        assert (reply.header_version, reply.message_id) == (msg.header_version, msg.message_id)
        assert reply.timestamp == pytest.approx(sim.clock.wall_time(), abs=0.01)
        assert json.loads(reply.string)["robot"] == "slave"


def desk_replies(sim: SimRobot, monkeypatch, msg: igtl.Message, n: int) -> list[igtl.Message]:
    """The first ``n`` replies the desk sends for ``msg`` (some come from the worker thread)."""
    from igtl.transport.common import Peer
    from occ.net.interfaces import Inbound

    out: list[igtl.Message] = []
    monkeypatch.setattr(sim.robot.interfaces, "reply", lambda item, reply: out.append(reply))
    item = Inbound("operator", Peer(1, ("127.0.0.1", 5)), msg, sim.now)
    sim.robot.operators.handle(item, sim.now)
    assert wait_until(lambda: len(out) >= n, WORKER_S), out
    return out


def table_request(text: str, mid: int = 44) -> igtl.Message:
    return igtl.CommandMessage(
        command_id=2,
        command_name="GetStateTable",
        command=f'<Command Name="GetStateTable" {text}/>',
        device_name="x",
        header_version=2,
        message_id=mid,
    )


@pytest.mark.parametrize(
    ("args", "error"),
    [
        ('Seconds="-1"', "GetStateTable: Seconds must be > 0, got -1.0"),
        ('Seconds="0"', "GetStateTable: Seconds must be > 0, got 0.0"),
        ('seconds="nan"', "GetStateTable: Seconds must be > 0, got nan"),
        ('Every="0"', "GetStateTable: Every must be >= 1, got 0"),
        ('Since="nan"', "GetStateTable: Since must be a number"),
        (
            'Seconds="soon"',
            "GetStateTable: bad argument: could not convert string to float: 'soon'",
        ),
        (
            'Since="later"',
            "GetStateTable: bad argument: could not convert string to float: 'later'",
        ),
        (
            'Every="2.5"',
            "GetStateTable: bad argument: invalid literal for int() with base 10: '2.5'",
        ),
    ],
)
def test_getstatetable_arguments_are_checked_at_once(monkeypatch, args, error):
    with SimRobot(ROOT / "configs" / "collab" / "slave.yaml") as sim:
        sim.step(5)
        (reply,) = desk_replies(sim, monkeypatch, table_request(args), 1)
        assert reply.metadata["Status"] == "FAIL" and reply.metadata["Error"] == error
        assert sim.robot.operators.counters()["refused"] == 1


def test_getstatetable_sends_the_rows_then_the_reply(monkeypatch):
    with SimRobot(ROOT / "configs" / "collab" / "slave.yaml") as sim:
        sim.step(50)
        table = sim.robot.state_table
        assert table is not None
        columns = ",".join(table.columns)
        array, reply = desk_replies(sim, monkeypatch, table_request('seconds="0.01" Every="1"'), 2)
        assert array.message_type == "NDARRAY" and array.device_name == "StateTable"
        assert (array.header_version, array.message_id) == (2, 44)
        assert array.timestamp == pytest.approx(sim.clock.wall_time(), abs=0.01)
        assert array.metadata == {
            "columns": columns,
            "robot": "slave",
            "owners": ",".join(sim.robot.collab.masters),
        }
        rows = array.array
        assert rows.shape[1] == len(table.columns) and 1 <= len(rows) <= 11
        assert np.array_equal(rows, table.window(0.01, since=None, every=1))
        assert reply.metadata["Status"] == "SUCCESS"
        assert reply.metadata["Message"] == (
            f"StateTable: {len(rows)} rows from t={rows[0, 0]:.6f} to t={rows[-1, 0]:.6f}; "
            f"columns {columns}"
        )
        assert sim.robot.operators.counters()["handled"] == 1
        # every 2nd row since a time; none after the last one
        _, reply = desk_replies(sim, monkeypatch, table_request('Since="0.02" Every="2"'), 2)
        every = table.window(None, since=0.02, every=2)
        assert reply.metadata["Message"].startswith(f"StateTable: {len(every)} rows from ")
        empty, reply = desk_replies(sim, monkeypatch, table_request('Since="1000"'), 2)
        assert len(empty.array) == 0
        assert reply.metadata["Message"] == f"StateTable: 0 rows; columns {columns}"


def test_a_deferred_command_is_answered_when_its_work_is_done(sim, monkeypatch):
    from occ.net.commands import Deferred

    pending: list[Deferred] = []

    def on_command(req, now):
        d = Deferred()
        pending.append(d)
        return d

    monkeypatch.setattr(sim.robot.controller, "on_command", on_command)
    out: list[igtl.Message] = []
    monkeypatch.setattr(sim.robot.interfaces, "reply", lambda item, reply: out.append(reply))
    op = sim.peer("operator")
    desk = sim.robot.operators
    for mid, name in ((70, "Plan"), (71, "Plan2")):
        from igtl.transport.common import Peer
        from occ.net.interfaces import Inbound

        msg = igtl.CommandMessage(
            command_id=mid, command_name=name, device_name="x", header_version=2, message_id=mid
        )
        desk.handle(Inbound("operator", Peer(1, ("127.0.0.1", 5)), msg, sim.now), sim.now)
    assert out == [] and desk.counters()["handled"] == 2
    sim.step(10)
    # the flight recorder keeps a late answer as it keeps any reply: the message, its interface
    box = sim.robot.black_box
    assert box is not None
    kept: list[tuple[igtl.Message, str]] = []
    monkeypatch.setattr(box, "sent", lambda msg, interface, now=0.0: kept.append((msg, interface)))
    pending[0].resolve("planned 3 segments")
    pending[1].fail("unreachable pose")
    ok_reply, bad_reply = out
    assert kept == [(ok_reply, "operator"), (bad_reply, "operator")]
    assert (ok_reply.command_id, ok_reply.message_id) == (70, 70)
    assert ok_reply.metadata == {"Status": "SUCCESS", "Message": "planned 3 segments"}
    assert ok_reply.timestamp == pytest.approx(sim.clock.wall_time(), abs=0.01)
    assert (bad_reply.command_id, bad_reply.message_id) == (71, 71)
    assert bad_reply.metadata["Status"] == "FAIL"
    assert bad_reply.metadata["Error"] == "unreachable pose"
    assert bad_reply.timestamp == pytest.approx(sim.clock.wall_time(), abs=0.01)
    assert desk.counters()["refused"] == 1 and desk.counters()["reply_errors"] == 0
    # a reply that cannot be sent is counted, not raised on the finishing thread
    monkeypatch.setattr(
        sim.robot.interfaces, "reply", lambda item, reply: (_ for _ in ()).throw(OSError("gone"))
    )
    msg = igtl.CommandMessage(command_id=72, command_name="Plan", device_name="x")
    desk.handle(Inbound("operator", Peer(1, ("127.0.0.1", 5)), msg, sim.now), sim.now)
    pending[2].resolve("done")
    assert desk.counters()["reply_errors"] == 1
    del op


def handle(sim: SimRobot, msg: igtl.Message, request=None) -> None:
    from igtl.transport.common import Peer
    from occ.net.interfaces import Inbound

    item = Inbound("operator", Peer(1, ("127.0.0.1", 5)), msg, sim.now, request=request)
    sim.robot.operators.handle(item, sim.now)


class Recorder:
    def __init__(self) -> None:
        self.seen: list[tuple] = []

    def record_message(self, msg, direction, interface, t) -> None:
        self.seen.append((msg.message_type, direction, interface, t))

    def __getattr__(self, name):  # every other recorder hook: accepted, ignored
        return lambda *a, **k: None


def test_requests_and_replies_are_recorded_with_interface_and_time():
    rec = Recorder()
    with SimRobot(SLAVE, recorder=rec) as sim:
        sim.step(7)
        rec.seen.clear()
        now = sim.now
        handle(sim, igtl.CommandMessage(command_id=1, command_name="GetState", device_name="x"))
        assert rec.seen == [
            ("COMMAND", "in", "operator", now),
            ("RTS_COMMAND", "out", "operator", now),
        ]


def test_a_discrete_input_refused_by_the_controller_is_answered_and_counted(sim, monkeypatch):
    from occ.errors import CommandError

    seen: list = []

    def refuse(event, now):
        seen.append((event.kind, now))  # a typed event (here UnknownInput), no message
        raise CommandError("fixture 'wall' has no normal")

    monkeypatch.setattr(sim.robot.controller, "on_input", refuse)
    out: list[igtl.Message] = []
    monkeypatch.setattr(sim.robot.interfaces, "reply", lambda item, reply: out.append(reply))
    sim.step(3)
    msg = igtl.StringMessage("wall", device_name="VF", header_version=2, message_id=6)
    handle(sim, msg)
    assert seen == [("STRING", sim.now)]
    (reply,) = out
    assert reply.message_type == "STATUS"
    assert reply.code == int(igtl.StatusCode.ILLEGAL_INSTRUCTION)
    assert reply.status_message == "fixture 'wall' has no normal"
    assert reply.message_id == 6 and reply.timestamp == pytest.approx(sim.clock.wall_time())
    handle(sim, msg)
    assert sim.robot.operators.counters()["refused"] == 2
    assert sim.robot.state is RobotState.READY  # a refusal changes nothing


def test_a_discrete_input_that_breaks_the_controller_faults_naming_it(sim, monkeypatch):
    def broken(item, now):
        raise RuntimeError("division by zero in the fixture")

    monkeypatch.setattr(sim.robot.controller, "on_input", broken)
    handle(sim, igtl.StringMessage("wall", device_name="VF"))
    assert sim.robot.state is RobotState.FAULT
    name = sim.robot.controller.name
    assert sim.robot.state_machine.last_reason == (
        f"controller {name}: on_input raised RuntimeError: division by zero in the fixture"
    )


def test_a_failing_command_handler_faults_and_the_asker_is_told(sim, monkeypatch):
    def broken(req, now):
        raise KeyError("gain")

    monkeypatch.setattr(sim.robot.controller, "on_command", broken)
    out: list[igtl.Message] = []
    monkeypatch.setattr(sim.robot.interfaces, "reply", lambda item, reply: out.append(reply))
    handle(sim, igtl.CommandMessage(command_id=1, command_name="Tune", device_name="x"))
    (reply,) = out
    assert reply.metadata["Error"] == "Tune failed: 'gain'"
    assert reply.timestamp == pytest.approx(sim.clock.wall_time())
    assert sim.robot.state is RobotState.FAULT
    assert sim.robot.state_machine.last_reason == "command 'Tune' raised KeyError: 'gain'"
    assert sim.robot.operators.counters()["refused"] == 1
    # a query that fails: named by its type; its STATUS carries UNKNOWN_ERROR
    monkeypatch.setattr(
        sim.robot.operators, "describe_state", lambda: (_ for _ in ()).throw(ValueError("bad"))
    )
    get = igtl.REGISTRY["GET_STATUS"](type_name="GET_STATUS", device_name="Q")
    handle(sim, get)
    assert out[-1].code == int(igtl.StatusCode.UNKNOWN_ERROR)
    assert out[-1].status_message == "GET_STATUS failed: bad"


def test_an_array_answer_is_sent_by_the_worker_the_ndarray_first_then_the_reply(sim, monkeypatch):
    import threading

    from occ.net.commands import ArrayReply

    path = np.arange(12.0).reshape(4, 3)
    answer = ArrayReply("path of 4 samples", path, "CellPath", {"member": "arm0", "set": "ab"})
    monkeypatch.setattr(sim.robot.controller, "on_command", lambda req, now: answer)
    out: list[tuple[str, igtl.Message]] = []
    to: list[object] = []

    def reply(item, msg):
        to.append(item)
        out.append((threading.current_thread().name, msg))

    monkeypatch.setattr(sim.robot.interfaces, "reply", reply)
    msg = igtl.CommandMessage(
        command_id=81, command_name="CellPath", device_name="x", header_version=2, message_id=81
    )
    handle(sim, msg)
    assert wait_until(lambda: len(out) == 2, 10.0, 0.001)
    (t_array, array), (t_reply, text) = out
    loop = threading.current_thread().name
    assert t_array != loop and t_reply != loop  # packed and sent by the worker
    assert array.message_type == "NDARRAY" and array.device_name == "CellPath"
    assert np.array_equal(array.array, path)
    assert dict(array.metadata) == {"member": "arm0", "set": "ab"}
    assert (array.header_version, array.message_id) == (2, 81)
    assert array.timestamp == pytest.approx(sim.clock.wall_time(), abs=0.01)
    assert (text.message_type, text.command_id, text.message_id) == ("RTS_COMMAND", 81, 81)
    assert text.metadata == {"Status": "SUCCESS", "Message": "path of 4 samples"}
    assert text.timestamp == pytest.approx(sim.clock.wall_time(), abs=0.01)
    assert sim.robot.operators.counters()["handled"] == 1  # counted once, when handed over
    assert [(i.interface, i.msg) for i in to] == [("operator", msg)] * 2  # to the asker
    # a worker still busy with an earlier one: refused at once, nothing sent
    out.clear()
    monkeypatch.setattr(sim.robot.worker.start(), "submit", lambda job: False)
    handle(sim, igtl.CommandMessage(command_id=82, command_name="CellPath", device_name="x"))
    ((_, busy),) = out
    assert busy.metadata["Status"] == "FAIL"
    assert busy.metadata["Error"] == "busy: the worker is still sending an earlier reply; try again"


def test_the_black_box_notes_who_asked_a_command_and_keeps_each_reply(sim, monkeypatch):
    from igtl.auth import HMAC_KEY
    from igtl.transport.common import Peer
    from occ.net.interfaces import Inbound

    box = sim.robot.black_box
    assert box is not None
    notes: list[tuple[str, object]] = []
    kept: list[tuple[igtl.Message, str]] = []
    monkeypatch.setattr(box, "note", lambda what, obj: notes.append((what, obj)))
    monkeypatch.setattr(box, "sent", lambda msg, interface, now=0.0: kept.append((msg, interface)))
    took: list[tuple[object, str]] = []
    monkeypatch.setattr(box, "took_request", lambda item, interface: took.append((item, interface)))
    out: list[igtl.Message] = []
    monkeypatch.setattr(sim.robot.interfaces, "reply", lambda item, reply: out.append(reply))
    desk = sim.robot.operators
    plain = igtl.CommandMessage(command_id=5, command_name="Enable", device_name="x")
    desk.handle(Inbound("operator", Peer(1, ("127.0.0.9", 4000)), plain, sim.now), sim.now)
    signed = igtl.CommandMessage(
        command_id=6, command_name="Disable", device_name="x", header_version=2,
        metadata={HMAC_KEY: "0" * 64},
    )  # fmt: skip
    viewer = Inbound("slicer", Peer(2, ("127.0.0.8", 4001)), signed, sim.now, role="viewer")
    desk.handle(viewer, sim.now)
    query = igtl.REGISTRY["GET_STATUS"](type_name="GET_STATUS", device_name="x")
    desk.handle(Inbound("operator", Peer(1, ("127.0.0.9", 4000)), query, sim.now), sim.now)
    requests = [obj for what, obj in notes if what == "request"]
    assert requests == [  # commands only: a query asks for nothing to be done
        {"interface": "operator", "name": "Enable", "peer": "127.0.0.9:4000",
         "role": "operator", "signed": "no"},
        {"interface": "slicer", "name": "Disable", "peer": "127.0.0.8:4001",
         "role": "viewer", "signed": "yes"},
    ]  # fmt: skip
    assert len(out) == 3 and kept == [
        (out[0], "operator"),
        (out[1], "slicer"),
        (out[2], "operator"),
    ]
    # every item the desk took, as it came (a replay puts them back on the command queue)
    assert [(i.msg, where) for i, where in took] == [
        (plain, "operator"), (signed, "slicer"), (query, "operator")
    ]  # fmt: skip


def test_a_busy_worker_refuses_at_once(sim, monkeypatch):
    out: list[igtl.Message] = []
    monkeypatch.setattr(sim.robot.interfaces, "reply", lambda item, reply: out.append(reply))
    worker = sim.robot.worker.start()
    monkeypatch.setattr(worker, "submit", lambda job: False)
    handle(sim, igtl.CommandMessage(command_id=1, command_name="GetStats", device_name="x"))
    handle(sim, igtl.CommandMessage(command_id=2, command_name="GetStateTable", device_name="x"))
    with SimRobot(ROOT / "configs" / "collab" / "slave.yaml") as table_sim:
        t_out: list[igtl.Message] = []
        monkeypatch.setattr(
            table_sim.robot.interfaces, "reply", lambda item, reply: t_out.append(reply)
        )
        monkeypatch.setattr(table_sim.robot.worker.start(), "submit", lambda job: False)
        handle(
            table_sim,
            igtl.CommandMessage(command_id=3, command_name="GetStateTable", device_name="x"),
        )
        assert t_out[0].metadata["Error"] == "busy: too many requests for the worker; try again"
        assert table_sim.robot.operators.counters() == {
            "handled": 0,
            "refused": 1,
            "reply_errors": 0,
            "worker_refused": 0,
        }
    assert out[0].metadata["Error"] == "busy: too many statistics requests; try again"
    assert out[0].metadata["Status"] == "FAIL"
    assert sim.robot.operators.counters()["handled"] == 0
    assert sim.robot.operators.counters()["refused"] == 2


def test_success_replies_carry_the_wall_time(sim, monkeypatch):
    out: list[igtl.Message] = []
    monkeypatch.setattr(sim.robot.interfaces, "reply", lambda item, reply: out.append(reply))
    sim.step(3)
    handle(sim, igtl.CommandMessage(command_id=1, command_name="Enable", device_name="x"))
    handle(sim, igtl.StringMessage("GetState", device_name="CMD_3"))
    assert [m.timestamp for m in out] == [pytest.approx(sim.clock.wall_time())] * 2
    assert sim.robot.state_machine.last_reason == "operator Enable"


@pytest.mark.req("SR-ROUTE-1")
def test_a_deferred_answer_goes_to_the_asker_only_with_its_code(sim, monkeypatch):
    """Through the real interface: two operators, one asks; the answer that comes later (a
    planner thread's) reaches the asker and not the other, a refusal with its status code,
    each counted once."""
    from occ.net.commands import Deferred

    pending: list[Deferred] = []

    def on_command(req, now):
        pending.append(Deferred())
        return pending[-1]

    monkeypatch.setattr(sim.robot.controller, "on_command", on_command)
    asker, other = sim.peer("operator"), sim.peer("operator")
    sim.step()
    first = asker.send_command("Plan")
    second = asker.send_command("Plan")
    sim.step()
    assert asker.reply_to(first) is None and len(pending) == 2
    pending[0].resolve("planned")
    pending[1].fail("unreachable pose")
    ok, bad = asker.reply_to(first), asker.reply_to(second)
    assert ok is not None and ok.metadata["Status"] == "SUCCESS"
    assert bad is not None and bad.metadata["Status"] == "FAIL"
    assert bad.metadata["Error"] == "unreachable pose"
    assert other.messages("RTS_COMMAND") == []
    desk = sim.robot.operators.counters()
    assert (desk["handled"], desk["refused"]) == (2, 1)


def test_a_new_client_is_greeted_with_the_state_its_code_and_the_time(sim):
    op = sim.peer("operator")
    sim.step()
    (hello,) = op.messages("STATUS")
    assert hello.code == int(igtl.StatusCode.OK) and hello.error_name == "READY"
    assert hello.status_message == f"{sim.robot.name} is READY"
    assert hello.device_name == sim.robot.name[:20]
    assert hello.timestamp == pytest.approx(sim.clock.wall_time(), abs=0.01)


def test_a_long_robot_name_is_cut_to_20_characters_in_the_greeting():
    from occ.core.loader import parse_config

    text = SLAVE.read_text().replace("name: slave", "name: a-slave-with-a-very-long-name", 1)
    cfg = parse_config(text, base_dir=ROOT / "configs")
    assert cfg.robot.name == "a-slave-with-a-very-long-name"
    with SimRobot(cfg) as s:
        op = s.peer("operator")
        s.step()
        (hello,) = op.messages("STATUS")
        assert hello.device_name == "a-slave-with-a-very-"
        assert hello.status_message == "a-slave-with-a-very-long-name is READY"


def test_a_client_joining_a_stopped_robot_is_greeted_with_the_stop_code(sim):
    sim.robot.state_machine.request("enable", "test")
    sim.robot.state_machine.request("stop", "test")
    op = sim.peer("operator")
    sim.step()
    (hello,) = op.messages("STATUS")
    assert (hello.code, hello.error_name) == (int(igtl.StatusCode.DISABLED), "STOPPED")


def test_late_answers_are_counted_each_and_recorded_as_sent(monkeypatch):
    """Every refusal and every reply that could not be sent is counted (not just the first),
    and the recording gets each late answer as sent, on its interface, at the daemon's time."""
    from occ.net.commands import Deferred

    late: list[tuple] = []

    class LateRecorder(Recorder):
        def record_message_late(self, msg, direction, interface, t) -> None:
            late.append((msg, direction, interface, t))

    with SimRobot(SLAVE, recorder=LateRecorder()) as sim:
        pending: list[Deferred] = []

        def on_command(req, now):
            pending.append(Deferred())
            return pending[-1]

        monkeypatch.setattr(sim.robot.controller, "on_command", on_command)
        asker = sim.peer("operator")
        sim.step()
        ids = [asker.send_command("Plan") for _ in range(4)]
        sim.step(5)
        pending[0].fail("no")
        pending[1].fail("still no")
        desk = sim.robot.operators
        assert desk.counters()["refused"] == 2
        assert [m.command_id for m, *_ in late] == ids[:2]
        assert all(d == "out" and i == "operator" for _, d, i, _t in late)
        assert late[0][3] == pytest.approx(sim.clock.now())
        monkeypatch.setattr(
            sim.robot.interfaces, "reply", lambda item, reply: (_ for _ in ()).throw(OSError("x"))
        )
        pending[2].resolve("done")
        pending[3].resolve("done")
        assert desk.counters()["reply_errors"] == 2
        assert len(late) == 2  # what was not sent is not recorded as sent


@pytest.mark.req("SR-ROUTE-1")
def test_refusals_and_handled_requests_are_counted_each_and_answered_to_the_asker():
    """Counted per request, not just the first: two statistics requests handled, two refused
    commands; a refused discrete input (a fixture the controller rejects) is answered to the
    operator who sent it, not to the other one."""
    with SimRobot(ROOT / "configs" / "master.yaml") as sim:
        asker, other = sim.peer("operator"), sim.peer("operator")
        sim.step()
        desk = sim.robot.operators
        asker.send_command("GetStats")
        asker.send_command("GetStats")
        sim.step()
        assert desk.counters()["handled"] == 2
        asker.send_command("NoSuchCommand")
        asker.send_command("NoSuchCommand")
        sim.step()
        assert desk.counters()["refused"] == 2
        bad = igtl.VirtualFixtureMessage(
            hardness=-1.0, spheres=((0.0, 0.0, 0.0, 10.0),), device_name="VF", header_version=2
        )
        asker.send(bad)
        sim.step()
        assert desk.counters()["refused"] == 3
        mine = [m for m in asker.received if m.device_name == "VF"]
        assert mine and all(m.message_type in ("RTS_VFIXTURE", "STATUS") for m in mine)
        assert [m for m in other.received if m.device_name == "VF"] == []


def test_refusals_carry_the_wall_time_and_each_is_counted(sim, monkeypatch):
    """A refused request's reply is stamped with the wall time like any other; two failing
    handlers are two refusals; a request whose parsing fails in an unexpected way is a FAULT
    named by its message type, and the asker is told."""
    out: list[igtl.Message] = []
    monkeypatch.setattr(sim.robot.interfaces, "reply", lambda item, reply: out.append(reply))
    sim.step(3)
    handle(sim, igtl.CommandMessage(command_id=1, command_name="NoSuchThing", device_name="x"))
    (refused,) = out
    assert refused.metadata["Status"] == "FAIL"
    assert refused.timestamp == pytest.approx(sim.clock.wall_time()) and refused.timestamp > 1e9

    def broken(req, now):
        raise KeyError("gain")

    monkeypatch.setattr(sim.robot.controller, "on_command", broken)
    handle(sim, igtl.CommandMessage(command_id=2, command_name="Tune", device_name="x"))
    handle(sim, igtl.CommandMessage(command_id=3, command_name="Tune", device_name="x"))
    assert sim.robot.operators.counters()["refused"] == 3

    def parse_fails(msg):
        raise RuntimeError("parser broke")

    monkeypatch.setattr("occ.net.operators.parse_request", parse_fails)
    out.clear()
    handle(sim, igtl.CommandMessage(command_id=4, command_name="Run", device_name="x"))
    (reply,) = out
    assert reply.metadata["Error"] == "COMMAND failed: parser broke"
    assert sim.robot.operators.counters()["refused"] == 4


def test_getstatetable_without_a_state_table_says_how_to_configure_one(sim, monkeypatch):
    assert sim.robot.state_table is None
    (reply,) = desk_replies(sim, monkeypatch, table_request('Seconds="1"'), 1)
    assert reply.metadata["Error"] == (
        "GetStateTable: no state table (configure state_table.seconds)"
    )


def test_two_state_tables_are_two_handled_requests_each_reply_stamped(monkeypatch):
    with SimRobot(ROOT / "configs" / "collab" / "slave.yaml") as sim:
        sim.step(20)
        for n in (1, 2):
            array, reply = desk_replies(sim, monkeypatch, table_request('Seconds="0.01"'), 2)
            assert reply.metadata["Status"] == "SUCCESS"
            assert reply.timestamp == pytest.approx(sim.clock.wall_time(), abs=0.01)
            assert reply.timestamp > 1e9 and array.timestamp > 1e9
            assert sim.robot.operators.counters()["handled"] == n


def test_a_controller_command_gets_the_time_and_an_ok_when_it_says_nothing(sim, monkeypatch):
    seen: list = []

    def on_command(req, now):
        seen.append((req.name, now))
        return None

    monkeypatch.setattr(sim.robot.controller, "on_command", on_command)
    out: list[igtl.Message] = []
    monkeypatch.setattr(sim.robot.interfaces, "reply", lambda item, reply: out.append(reply))
    sim.step(3)
    handle(sim, igtl.CommandMessage(command_id=1, command_name="Home", device_name="x"))
    assert seen == [("Home", sim.now)]
    (reply,) = out
    assert reply.metadata == {"Status": "SUCCESS", "Message": "OK"}


def test_get_status_carries_the_code_of_the_state(sim):
    get = igtl.REGISTRY["GET_STATUS"]
    for event, state, code in (
        ("estop", "ESTOP", igtl.StatusCode.PANICK_MODE),
        ("reset", "READY", igtl.StatusCode.OK),
    ):
        sim.robot.state_machine.request(event, "test")
        (reply,) = answers(sim, get(type_name="GET_STATUS", device_name="S", header_version=2))
        assert (reply.code, reply.error_name) == (int(code), state)


def test_the_statistics_of_a_collaboration_robot_name_its_owner_streams_and_table():
    from types import SimpleNamespace

    with SimRobot(ROOT / "configs" / "collab" / "slave.yaml") as sim:
        sim.step(5)
        r = sim.robot
        assert r.collab is not None and r.state_table is not None
        snap = r.snapshot()
        assert snap["owner"] == "mentor"
        assert snap["collaboration"] == r.collab.stats()
        assert snap["loss_by_stream"] == {n: m.counters() for n, m in r.streams.monitors.items()}
        assert set(snap["loss_by_stream"]) == {"mentor", "trainee"}
        assert snap["state_table"] == r.state_table.stats() and snap["state_table"]
        # a supervisor thread (a real-time daemon) reports itself there
        r.supervisor_thread = SimpleNamespace(report={"checks": 7})  # type: ignore[assignment]
        try:
            assert r.snapshot()["supervisor"]["thread"] == {"checks": 7}
        finally:
            r.supervisor_thread = None


def test_handover_takes_its_target_in_either_spelling():
    with SimRobot(ROOT / "configs" / "collab" / "slave.yaml") as sim:
        op = sim.peer("operator")
        sim.step()
        cid = op.send_command("Handover", '<Command Name="Handover" to="trainee"/>')
        sim.step()
        reply = op.reply_to(cid)
        assert reply is not None and reply.metadata["Status"] == "SUCCESS"
        assert reply.metadata["Message"].startswith("control mentor -> trainee (by ")
        assert sim.robot.collab.owner == "trainee"
        cid = op.send_command("Handover", '<Command Name="Handover" To="mentor"/>')
        sim.step()
        assert op.reply_to(cid).metadata["Message"].startswith("control trainee -> mentor (by ")


def test_the_log_names_each_refusal_and_lost_reply_at_most_five_a_second(sim, monkeypatch, caplog):
    """An operator reads the log: a refused request is logged with its interface, type, peer
    and reason, at most five a second (a flood of bad commands must not flood the log); a
    reply that could not be sent, now or later, with its interface, peer and error."""
    import logging

    from igtl.transport.common import Peer
    from occ.net.commands import Deferred
    from occ.errors import CommandError
    from occ.net.interfaces import Inbound

    def refuse(item, now):
        raise CommandError("fixture 'wall' has no normal")

    monkeypatch.setattr(sim.robot.controller, "on_input", refuse)
    out: list[igtl.Message] = []
    monkeypatch.setattr(sim.robot.interfaces, "reply", lambda item, reply: out.append(reply))
    caplog.set_level(logging.WARNING, logger="occ.core.robot")
    handle(sim, igtl.StringMessage("wall", device_name="VF"))
    for n in range(6):
        handle(sim, igtl.CommandMessage(command_id=n, command_name="NoSuchThing", device_name="x"))
    why = out[-1].metadata["Error"]
    assert [r.getMessage() for r in caplog.records] == [
        "operator: refused STRING from 127.0.0.1:5: fixture 'wall' has no normal"
    ] + [f"operator: refused COMMAND from 127.0.0.1:5: {why}"] * 4
    assert sim.robot.operators.counters()["refused"] == 7

    caplog.clear()
    pending: list[Deferred] = []

    def on_command(req, now):
        pending.append(Deferred())
        return pending[-1]

    monkeypatch.setattr(sim.robot.controller, "on_command", on_command)
    monkeypatch.setattr(
        sim.robot.interfaces, "reply", lambda item, reply: (_ for _ in ()).throw(OSError("gone"))
    )
    peer = Peer(1, ("127.0.0.1", 5))
    msg = igtl.CommandMessage(command_id=9, command_name="GetState", device_name="x")
    sim.robot.operators.handle(Inbound("operator", peer, msg, sim.now), sim.now)
    msg = igtl.CommandMessage(command_id=10, command_name="Plan", device_name="x")
    sim.robot.operators.handle(Inbound("operator", peer, msg, sim.now), sim.now)
    pending[0].resolve("planned")
    assert [r.getMessage() for r in caplog.records] == [
        f"operator: reply to {peer} could not be sent: gone"
    ] * 2


def test_every_robot_command_in_the_table_is_answered_by_its_role_and_thread() -> None:
    """ROBOT_COMMANDS (occ/net/commands.py) is the one list: a viewer may ask the ``viewer``
    commands and is refused the others by its interface; every command gets an answer (the
    worker's ones from the worker thread)."""
    from occ.net.commands import ROBOT_COMMANDS

    with SimRobot(SLAVE) as sim:
        viewer = sim.peer("slicer")
        sim.step(3)
        for key, spec in ROBOT_COMMANDS.items():
            cid = viewer.send_command(spec.name)
            sim.step(1)
            reply = wait_until(lambda c=cid: viewer.reply_to(c), timeout=5.0)
            assert reply is not None, spec.name
            refused = reply.metadata.get("Status") != "SUCCESS"
            if spec.role == "operator":
                assert refused and "a viewer may query but not command" in str(
                    reply.metadata.get("Error", "")
                ), (key, reply.metadata)
            elif spec.name != "GetStateTable":  # the slave has no table: a clear refusal
                assert not refused, (key, reply.metadata)
        assert sim.robot.state is RobotState.READY  # nothing a viewer sent changed anything


def test_a_pose_on_the_command_queue_reaches_the_controller_as_a_sample(sim, monkeypatch):
    """A TRANSFORM routed to the command queue (a Base, a fixture's pose) is given to the
    controller as the typed sample a stream would give: its sender, its device, its pose and
    its arrival time, with the loop's time; never as a discrete input."""
    from igtl.transport.common import Peer
    from occ.net.interfaces import Inbound

    got: list = []
    monkeypatch.setattr(sim.robot.controller, "on_sample", lambda s, now: got.append((s, now)))
    monkeypatch.setattr(sim.robot.controller, "on_input", lambda *a: got.append(("input", a)))
    sim.step(3)
    m = np.eye(4)
    m[:3, 3] = (1.0, 2.0, 3.0)
    msg = igtl.TransformMessage.from_matrix(m, device_name="Base", header_version=2, message_id=9)
    peer = Peer(4, ("127.0.0.1", 7))
    item = Inbound("operator", peer, msg, sim.now - 0.004)
    sim.robot.operators.handle(item, sim.now)
    ((sample, now),) = got
    assert now == sim.now
    assert (sample.interface, sample.peer, sample.device) == ("operator", peer, "Base")
    assert sample.position_mm == (1.0, 2.0, 3.0) and sample.kind == "TRANSFORM"
    assert sample.t_rx == sim.now - 0.004 and sample.seq == 9


def test_a_client_joining_a_latched_robot_is_told_the_alert_and_only_then(sim):
    """The greeting names the last alert in FAULT and ESTOP (what the operator must clear),
    not in a state that is not latched (an old alert is not the state's cause there)."""
    r = sim.robot
    r.alarms.last_alert = "driver tool: write failed"
    op = sim.peer("operator")
    sim.step()
    (hello,) = op.messages("STATUS")
    assert hello.status_message == "slave is READY"
    r.state_machine.request("fault", "test")
    r.alarms.last_alert = "driver tool: write failed"
    late = sim.peer("operator")
    sim.step()  # the FAULT's black box is dumped at the end of this tick: told too
    (hello, dumped) = late.messages("STATUS")
    assert dumped.error_name == "BLACKBOX"
    assert hello.status_message == "slave is FAULT: driver tool: write failed"
    r.alarms.last_alert = ""
    last = sim.peer("operator")
    sim.step()
    (hello,) = last.messages("STATUS")
    assert hello.status_message == "slave is FAULT"


def test_the_statistics_name_the_build_the_recording_and_the_hardware(sim):
    from occ import _native

    r = sim.robot
    snap = r.snapshot()
    assert snap["build"] == _native.BUILD and snap["build"]
    assert snap["recording"] == r.operators.recording.stats() and snap["recording"]
    assert snap["hardware"] == r.hardware.stats() and snap["hardware"]
    assert "collision" not in snap  # the slave checks no collisions (test_collision: one that does)


def test_recording_commands_reach_the_recording_control_by_name(sim):
    """StartRecording through the desk is the recording control's (occ/recording/control.py): a
    file name it refuses is refused to the asker with its reason, whatever the spelling."""
    op = sim.peer("operator")
    sim.step()
    for name in ("StartRecording", "startrecording "):
        cid = op.send_command(name, f'<Command Name="{name}" OutputFilename="../x"/>')
        sim.step()
        reply = op.reply_to(cid).metadata
        assert reply["Status"] == "FAIL" and reply["Error"].startswith(
            "StartRecording: OutputFilename must be a bare file name"
        ), reply
    cid = op.send_command("GetRecordingStatus")
    sim.step()
    assert op.reply_to(cid).metadata["Status"] == "SUCCESS"


def test_the_thread_column_dispatches_a_row(sim, monkeypatch):
    """The command table (occ/net/commands.py ROBOT_COMMANDS) is what dispatches: a row's
    handler runs on the loop thread; a ``loop`` row's text is the reply in that tick, a
    ``worker`` row's job runs on the worker thread, which sends the reply."""
    import threading

    import occ.net.operators as operators
    from occ.net.commands import success_reply
    from occ.net.commands import LOOP, WORKER, CommandSpec
    from occ_testkit.testing import wait_until

    ran: list[tuple[str, str]] = []

    def worker_row(desk, req, item, now):  # type: ignore[no-untyped-def]
        ran.append(("handler", threading.current_thread().name))

        def job() -> None:
            ran.append(("job", threading.current_thread().name))
            desk.port.reply(item, success_reply(req, "pong", timestamp=0.0))

        return job

    table = dict(operators.ROBOT_COMMANDS)
    table["ping"] = CommandSpec("Ping", "operator", WORKER, "a test row", worker_row, busy="x")
    table["echo"] = CommandSpec("Echo", "operator", LOOP, "a test row", lambda *a: "echoed")
    monkeypatch.setattr(operators, "ROBOT_COMMANDS", table)
    op = sim.peer("operator")
    sim.step(2)
    cid = op.send_command("Echo")
    sim.step(1)
    assert op.reply_to(cid).metadata["Message"] == "echoed"
    loop = threading.current_thread().name
    cid = op.send_command("Ping")
    sim.step(1)
    reply = wait_until(lambda: op.reply_to(cid), timeout=5.0)
    assert reply is not None and reply.metadata["Message"] == "pong"
    assert ran == [("handler", loop), ("job", f"occ-{sim.robot.name}-report")]
