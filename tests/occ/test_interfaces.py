"""occ/interfaces.py: the queues that feed the loop, who owns a stream, and what each interface
counts. Queues are tested alone; routing over in-process interfaces (occ.testing.SimRobot),
where a peer's address is chosen, so ownership is exact.

Several of these were written to catch faults the other tests let through (mutation testing,
docs/VERIFICATION.md): a queue's bound off by one, a count that counts twice, an owner that
is not restored on Reset.
"""

from __future__ import annotations

from pathlib import Path

import pytest

import igtl
from igtl.transport.common import Peer
from occ.interfaces import CommandQueue, Inbound, StreamQueue, is_operator_request
from occ.testing import SimRobot

ROOT = Path(__file__).resolve().parents[2]
SLAVE = ROOT / "configs" / "slave.yaml"


def inbound(i: int) -> Inbound:
    return Inbound("master", Peer(1, ("127.0.0.1", 9)), igtl.StatusMessage(code=i), float(i))


# -------------------------------------------------------------------------------- queues
def test_a_stream_queue_drops_its_oldest_and_keeps_them_for_accounting():
    q = StreamQueue(depth=3, overflow_depth=2)
    items = [inbound(i) for i in range(7)]
    for it in items[:3]:
        assert q.put(it) is True
    assert len(q) == 3 and q.dropped == 0 and q.received == 3  # exactly full: nothing lost
    assert q.put(items[3]) is True
    assert q.dropped == 1 and q.overflow_lost == 0 and len(q) == 3
    assert q.put(items[4]) is True
    assert q.dropped == 2 and q.overflow_lost == 0  # the overflow queue is exactly full
    assert q.put(items[5]) is True
    assert q.dropped == 3 and q.overflow_lost == 1  # now one is forgotten
    assert q.put(items[6]) is True
    assert (q.received, q.dropped, q.overflow_lost) == (7, 4, 2)
    assert q.drain() == items[4:7] and len(q) == 0 and q.drain() == []
    assert q.drain_overflow() == items[2:4] and q.drain_overflow() == []


def test_a_command_queue_refuses_when_full_and_drains_in_order():
    q = CommandQueue(depth=2)
    a, b, c = inbound(1), inbound(2), inbound(3)
    assert q.put(a) is True and q.put(b) is True
    assert q.put(c) is False  # exactly full: refused, the caller answers
    assert (q.received, q.refused, len(q)) == (2, 1, 2)
    assert q.put(c) is False and q.refused == 2
    assert q.drain(limit=0) == []
    assert q.drain(limit=1) == [a] and len(q) == 1
    assert q.put(c) is True and q.received == 3
    assert q.drain() == [b, c] and q.drain(limit=5) == []


def test_what_is_an_operator_request():
    raw = igtl.RawMessage
    assert is_operator_request(igtl.CommandMessage(command_name="Run"))
    for t in ("GET_STATUS", "STT_TDATA", "STP_TDATA"):
        assert is_operator_request(raw(type_name=t))
    assert is_operator_request(igtl.StringMessage("Run", device_name="CMD_1"))
    assert not is_operator_request(igtl.StringMessage("Run", device_name="Note"))
    assert not is_operator_request(igtl.StatusMessage(device_name="CMD_1"))
    assert not is_operator_request(raw(type_name="RTS_TDATA"))


# ------------------------------------------------------------------------------- routing
@pytest.fixture
def sim():
    with SimRobot(SLAVE) as s:
        yield s


def position(seq: int, device: str = "Master") -> igtl.Message:
    return igtl.PositionMessage(
        (0.0, 50.0, 270.0),
        (0.0, 0.0, 0.0, 1.0),
        24,
        device_name=device,
        header_version=2,
        message_id=seq,
        metadata={"run": "1", "clutch": "0"},
    )


@pytest.mark.req("SR-OWN-1")
def test_the_first_sender_owns_the_stream_and_others_are_counted(sim):
    iface = sim.robot.interfaces["master"]
    assert iface.stream_owner is None and iface.configured_source is None
    owner = sim.peer("master", address=("127.0.0.1", 4000))
    other = sim.peer("master", address=("127.0.0.1", 4002))
    same_host = sim.peer("master", address=("127.0.0.1", 4001))
    sim.clock.set(0.25)
    owner.send(position(1))
    assert iface.stream_owner == ("127.0.0.1", 4000)
    other.send(position(2))
    same_host.send(position(3))
    other.send(position(4))
    owner.send(position(5))
    q = iface.streams["POSITION"]
    got = q.drain()
    assert [m.msg.message_id for m in got] == [1, 5]
    assert all(m.t_rx == 0.25 and m.interface == "master" for m in got)
    st = iface.stats()
    assert st["foreign"] == 3 and st["received"] == 5
    assert st["stream_owner"] == ["127.0.0.1", 4000]
    assert st["streams"] == {"POSITION": {"received": 2, "dropped": 0}}
    # an operator's Reset releases it: the next sender owns it
    iface.release_stream()
    assert iface.stream_owner is None and iface.stats()["stream_owner"] is None
    other.send(position(6))
    assert iface.stream_owner == ("127.0.0.1", 4002)
    assert [m.msg.message_id for m in q.drain()] == [6]


@pytest.mark.req("SR-OWN-1")
def test_a_configured_source_owns_the_stream_from_the_start_and_after_reset():
    import yaml

    data = yaml.safe_load(SLAVE.read_text())
    for i in data["interfaces"]:
        if i["name"] == "master":
            i["stream_source"] = "127.0.0.1:7000"
    with SimRobot(data) as sim:
        iface = sim.robot.interfaces["master"]
        assert iface.stream_owner == iface.configured_source == ("127.0.0.1", 7000)
        first = sim.peer("master", address=("127.0.0.1", 4000))
        first.send(position(1))  # first, but not the configured source
        assert iface.stream_owner == ("127.0.0.1", 7000) and iface.stats()["foreign"] == 1
        sim.peer("master", address=("127.0.0.1", 7000)).send(position(2))
        assert [m.msg.message_id for m in iface.streams["POSITION"].drain()] == [2]
        iface.release_stream()
        assert iface.stream_owner == ("127.0.0.1", 7000)


def test_pinning_follows_the_owner_unless_the_kernel_filter_is_off(sim, monkeypatch):
    iface = sim.robot.interfaces["master"]
    pins: list = []
    monkeypatch.setattr(
        type(iface.transport), "pin_source", lambda self, src: pins.append(src), raising=False
    )
    sim.peer("master", address=("127.0.0.1", 4000)).send(position(1))
    assert pins == [("127.0.0.1", 4000)]
    iface.release_stream()
    assert pins == [("127.0.0.1", 4000), None]
    iface.release_stream()  # nothing to release: no second unpin
    assert pins == [("127.0.0.1", 4000), None]
    # an interface without stream inputs never pins
    sim.robot.interfaces["operator"]._pin(("127.0.0.1", 4000))
    assert len(pins) == 2
    monkeypatch.setattr(iface, "cfg", iface.cfg.model_copy(update={"kernel_filter": False}))
    iface.release_stream()
    assert len(pins) == 2
    sim.peer("master", address=("127.0.0.1", 4005)).send(position(2))
    assert iface.stream_owner == ("127.0.0.1", 4005) and len(pins) == 2


def test_a_stream_input_takes_only_its_device(monkeypatch):
    import yaml

    data = yaml.safe_load(SLAVE.read_text())
    for i in data["interfaces"]:
        if i["name"] == "master":
            i["inputs"][0]["device"] = "Master"
    with SimRobot(data) as sim:
        iface = sim.robot.interfaces["master"]
        peer = sim.peer("master", address=("127.0.0.1", 4000))
        peer.send(position(1, device="Other"))
        assert iface.stream_owner is None and len(iface.streams["POSITION"]) == 0
        assert iface.stats()["unexpected"] == 1
        peer.send(position(2, device="Master"))
        assert [m.msg.message_id for m in iface.streams["POSITION"].drain()] == [2]


def test_what_an_interface_counts(sim):
    op_iface = sim.robot.interfaces["operator"]
    op = sim.peer("operator")
    op.send(igtl.StatusMessage(device_name="keepalive"))
    op.send(igtl.StatusMessage(device_name="keepalive"))
    op.send(igtl.TransformMessage(device_name="Stray"))
    op.send(igtl.TransformMessage(device_name="Stray"))
    op.send(igtl.RawMessage(type_name="FOO", device_name="x"))
    op.send_command("")  # refused: no command name
    st = op_iface.stats()
    assert st["received"] == 6 and st["keepalive"] == 2 and st["unexpected"] == 3
    assert op_iface.counters.unexpected_types == {"TRANSFORM", "FOO"}
    assert st["refused"] == 1 and st["foreign"] == 0 and st["unauthenticated"] == 0
    assert st["transport"] == "inproc" and st["role"] == "operator"
    assert st["stream_owner"] is None and st["streams"] == {} and st["peers"] == 1
    assert st["address"] == list(op_iface.address)
    assert st["malformed"] == 0
    assert st["dropped"] == int(op_iface.transport.stats().get("dropped", 0)) + (
        op_iface.counters.send_dropped
    )
    sim.step()  # the greeting STATUS went out: sent counts outputs, replies are not outputs
    assert op_iface.stats()["sent"] >= 1


def test_a_full_command_queue_answers_busy(sim):
    op = sim.peer("operator")
    q = sim.robot.interfaces.commands
    for _ in range(q.depth):
        op.send_command("GetState")
    op.send_command("Run")
    assert q.refused == 1 and len(q) == q.depth
    busy = [m for m in op.messages("RTS_COMMAND") if m.metadata.get("Status") == "FAIL"]
    assert [m.metadata["Error"] for m in busy] == ["command queue full"]
    assert sim.robot.interfaces["operator"].stats()["refused"] == 1


def test_the_manager_broadcasts_to_viewers_and_operators_only(sim):
    viewer, op = sim.peer("slicer"), sim.peer("operator")
    master = sim.peer("master", address=("127.0.0.1", 4000))
    sim.robot.interfaces.broadcast_operators(igtl.StatusMessage(device_name="Bcast"))
    assert len(viewer.messages("STATUS", "Bcast")) == 1
    assert len(op.messages("STATUS", "Bcast")) == 1
    assert master.messages("STATUS", "Bcast") == []
    assert [i.name for i in sim.robot.interfaces.operator_interfaces()] == ["operator"]
    assert set(sim.robot.interfaces.stats()) == {"slicer", "operator", "master"}


@pytest.mark.req("SR-AUTH-1")
def test_a_keyed_link_takes_only_signed_samples_and_counts_the_rest(tmp_path):
    import yaml

    from igtl.auth import sign

    key = "a shared key for the master link"
    (tmp_path / "link.key").write_text(key + "\n")
    data = yaml.safe_load(SLAVE.read_text())
    for i in data["interfaces"]:
        if i["name"] == "master":
            i["auth_key_file"] = str(tmp_path / "link.key")
    with SimRobot(data) as sim:
        iface = sim.robot.interfaces["master"]
        peer = sim.peer("master", address=("127.0.0.1", 4000))
        peer.send(position(1))  # unsigned
        peer.send(sign(position(2), b"the wrong key, 16 bytes+"))
        assert iface.stream_owner is None  # a refused sample does not take the stream
        peer.send(sign(position(3), key.encode()))
        assert [m.msg.message_id for m in iface.streams["POSITION"].drain()] == [3]
        st = iface.stats()
        assert st["unauthenticated"] == 2 and st["received"] == 3 and st["foreign"] == 0


@pytest.mark.req("SR-ROUTE-1")
def test_refusals_reach_the_asker_with_code_and_reason(sim):
    viewer = sim.peer("slicer")
    viewer.send_command("Run")
    (reply,) = [m for m in viewer.messages("RTS_COMMAND")]
    assert reply.metadata["Error"] == (
        "Run: a viewer may query but not command the robot; send commands to an operator interface"
    )
    viewer.send(igtl.StringMessage("<Command Name=", device_name="CMD_4"))
    (ack,) = viewer.messages("STRING", "ACK_4")
    assert 'Status="FAIL"' in ack.string and "malformed XML command" in ack.string
    link = sim.peer("master", address=("127.0.0.1", 4000))
    link.send(igtl.REGISTRY["GET_STATUS"](type_name="GET_STATUS", device_name="Q"))
    (denied,) = link.messages("STATUS", "Q")
    assert denied.code == int(igtl.StatusCode.ACCESS_DENIED)
    assert denied.status_message == "interface master is a data link: it takes no requests"
    q = sim.robot.interfaces.commands
    for _ in range(q.depth):
        viewer.send_command("GetState")
    viewer.send(igtl.REGISTRY["GET_STATUS"](type_name="GET_STATUS", device_name="Full"))
    (busy,) = viewer.messages("STATUS", "Full")
    assert busy.code == int(igtl.StatusCode.BUSY) and busy.status_message == "command queue full"
    assert sim.robot.interfaces["slicer"].stats()["refused"] == 3
    # what is queued carries its parsed request and the sender's role
    item = q.drain(limit=1)[0]
    assert item.request is not None and item.request.name == "GetState"
    assert item.role == "viewer"


def test_replies_say_whether_they_went_out(sim):
    op = sim.peer("operator")
    op.send_command("GetState")
    item = sim.robot.interfaces.commands.drain()[0]
    assert sim.robot.interfaces.reply(item, igtl.StatusMessage(device_name="r")) is True
    op.close()
    assert sim.robot.interfaces.reply(item, igtl.StatusMessage(device_name="r")) is False


def test_replies_on_a_keyed_link_are_signed(tmp_path):
    import yaml

    from igtl.auth import sign, verify

    key = b"a shared key for the master link"
    (tmp_path / "link.key").write_text(key.decode() + "\n")
    data = yaml.safe_load(SLAVE.read_text())
    for i in data["interfaces"]:
        if i["name"] == "master":
            i["auth_key_file"] = str(tmp_path / "link.key")
    with SimRobot(data) as sim:
        peer = sim.peer("master", address=("127.0.0.1", 4000))
        get = igtl.REGISTRY["GET_STATUS"](type_name="GET_STATUS", device_name="Q", header_version=2)
        peer.send(sign(get, key))
        (denied,) = peer.messages("STATUS", "Q")
        assert verify(denied, key) == ""


def test_an_ipv6_stream_source_and_the_operators_list():
    import yaml

    data = yaml.safe_load(SLAVE.read_text())
    for i in data["interfaces"]:
        if i["name"] == "master":
            i["stream_source"] = "[::1]:7000"
        if i["name"] == "operator":
            i["operators"] = ["10.0.0.5"]
    with SimRobot(data) as sim:
        assert sim.robot.interfaces["master"].configured_source == ("::1", 7000)
        op = sim.robot.interfaces["operator"]
        assert op.peer_role(Peer(1, ("10.0.0.5", 4000))) == "operator"
        assert op.peer_role(Peer(2, ("10.0.0.6", 4000))) == "viewer"
        assert sim.robot.interfaces["slicer"].peer_role(Peer(3, ("10.0.0.5", 1))) == "viewer"
