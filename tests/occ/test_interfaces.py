"""occ/net/interfaces.py: the queues that feed the loop, who owns a stream, and what each interface
counts. Queues are tested alone; routing over in-process interfaces (occ_testkit.testing.SimRobot),
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
from occ.net.interfaces import (
    CommandQueue,
    Inbound,
    StreamQueue,
    is_operator_request,
    rebuild_stream_item,
    stream_item,
)
from occ_testkit.testing import SimRobot

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


def _pose_items(msg: igtl.Message):
    """The same POSITION as the two kinds of wire a received message keeps: whole bytes (a
    datagram, ``igtl.unpack``) and the stream decoder's pieces (a TCP stream)."""
    data = msg.pack()
    whole = igtl.unpack(data)
    decoder = igtl.StreamDecoder()
    decoder.feed(data)
    (streamed,) = list(decoder)
    return whole, streamed


def test_a_stream_item_rebuilt_from_its_wire_is_the_one_the_interface_built():
    # the flight recorder keeps a stream item as its wire, its reception time and its peer, and
    # its writer rebuilds the item from them: the same sample, sender, interface and time
    peer = Peer(3, ("127.0.0.5", 40123))
    whole, streamed = _pose_items(position(7))
    assert isinstance(whole._wire, bytes)
    assert not isinstance(streamed._wire, bytes)  # the pieces, joined by the writer
    for msg in (whole, streamed):
        built = stream_item("master", peer, msg, 12.5)
        again = rebuild_stream_item("master", peer, msg._wire, 12.5)
        assert (again.interface, again.peer, again.t_rx) == ("master", peer, 12.5)
        assert again.msg.message_type == "POSITION"
        assert again.msg.device_name == "Master"
        assert again.msg.message_id == 7
        sample, want = again.event, built.event
        assert type(sample) is type(want)
        for name in want.__slots__:
            assert getattr(sample, name) == getattr(want, name), name
        assert (sample.interface, sample.peer, sample.t_rx, sample.seq) == ("master", peer, 12.5, 7)
        assert sample.position_mm == pytest.approx((0.0, 50.0, 270.0))


# ------------------------------------------------------------ transports built from the config
# The transport classes are replaced by a recorder: what matters here is the contract between
# the config and the transport (every setting handed over, in its unit), not any traffic.
class _Recorder:
    kind = "?"

    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs
        self.sent: list = []
        self.send_result = 1
        self.transport_stats: dict = {}
        self.address = ("127.0.0.1", 5555)
        self.peers: list = []
        self.thread = None
        self.events: list = []

    def start(self):
        self.events.append("start")

    def stop(self):
        self.events.append("stop")

    def send(self, msg, peer=None):
        self.sent.append((msg, peer))
        return self.send_result

    def stats(self):
        return dict(self.transport_stats)


class _Server(_Recorder):
    kind = "tcp-server"


class _Client(_Recorder):
    kind = "tcp-client"


class _Udp(_Recorder):
    kind = "udp"

    def pin_source(self, source):
        self.events.append(("pin", source))


@pytest.fixture
def fake_transports(monkeypatch):
    import occ.net.interfaces as mod

    monkeypatch.setattr(mod, "TCPServer", _Server)
    monkeypatch.setattr(mod, "TCPClient", _Client)
    monkeypatch.setattr(mod, "UDPEndpoint", _Udp)


def manager(*cfgs: dict, **kw):
    from occ.config import InterfaceConfig
    from occ.net.interfaces import InterfaceManager

    return InterfaceManager([InterfaceConfig(**c) for c in cfgs], clock_now=lambda: 1.5, **kw)


def _callbacks_are_the_interfaces(t, iface, *, peers: bool = True) -> None:
    assert t.kwargs.pop("on_message") == iface._on_message
    assert t.kwargs.pop("on_error") == iface._on_error
    if peers:
        assert t.kwargs.pop("on_connect") == iface._on_connect
        assert t.kwargs.pop("on_disconnect") == iface._on_disconnect


def test_a_tcp_server_gets_every_setting_of_its_config(fake_transports):
    m = manager(
        dict(
            name="ops",
            transport="tcp-server",
            host="127.0.0.2",
            port=5000,
            allowed_peers=["127.0.0.1", "10.0.0.0/8"],
            role="operator",
            operators=["10.0.0.5"],
            operator_slots=2,
            max_clients=5,
            send_queue=33,
            idle_timeout_s=7.5,
            message_timeout_s=3.0,
            send_stall_timeout_s=2.5,
            unread_limit_kib=20,
            max_body_kib=100,
        )
    )
    iface = m["ops"]
    t = iface.transport
    assert isinstance(t, _Server)
    _callbacks_are_the_interfaces(t, iface)
    assert t.args == ("127.0.0.2", 5000)
    assert t.kwargs == dict(
        negotiate=True,
        allowed_peers=["127.0.0.1/32", "10.0.0.0/8"],
        max_clients=5,
        send_queue=33,
        idle_timeout=7.5,
        message_timeout=3.0,
        send_stall_timeout=2.5,
        unread_limit=20 * 1024,
        max_buffered=8192 * 1024,  # at least 8 MiB
        max_body_size=100 * 1024,
        reserved_slots=2,
        privileged_peers=["10.0.0.5/32"],
        name="igtl-ops",
    )


@pytest.mark.parametrize(
    ("body_kib", "buffered_kib", "want_kib"),
    [
        (4096, None, 8192),  # twice the body is exactly 8 MiB
        (4097, None, 8194),  # just over: twice the body
        (100, 300, 300),  # configured
    ],
)
def test_a_tcp_servers_buffer_budget(fake_transports, body_kib, buffered_kib, want_kib):
    m = manager(
        dict(
            name="s",
            transport="tcp-server",
            port=0,
            max_body_kib=body_kib,
            max_buffered_kib=buffered_kib,
        )
    )
    kw = m["s"].transport.kwargs
    assert kw["max_buffered"] == want_kib * 1024 and kw["max_body_size"] == body_kib * 1024
    # no operators list: no reserved slots, no privileged peers, default settings passed on
    assert kw["reserved_slots"] == 0 and kw["privileged_peers"] is None
    assert kw["idle_timeout"] is None and kw["allowed_peers"] == ["127.0.0.1/32"]


def test_a_keyed_tcp_server_does_not_negotiate_the_header_version(fake_transports, tmp_path):
    (tmp_path / "k").write_text("a shared key for the master link\n")
    m = manager(dict(name="s", transport="tcp-server", port=0, auth_key_file=tmp_path / "k"))
    assert m["s"].transport.kwargs["negotiate"] is False
    assert m["s"].auth_key == b"a shared key for the master link"


def test_a_tcp_client_gets_its_remote_and_limits(fake_transports):
    m = manager(
        dict(
            name="up",
            transport="tcp-client",
            remote="[::1]:7001",
            send_queue=12,
            max_body_kib=64,
        )
    )
    iface = m["up"]
    t = iface.transport
    assert isinstance(t, _Client)
    _callbacks_are_the_interfaces(t, iface)
    assert t.args == ("::1", 7001)
    assert t.kwargs == dict(send_queue=12, max_body_size=64 * 1024, name="igtl-up")


def test_udp_endpoints_from_the_config(fake_transports):
    stream = [{"type": "POSITION", "queue": "stream", "depth": 3}]
    m = manager(
        # a receiver polled by the loop
        dict(name="rx", transport="udp", host="127.0.0.3", port=6000, inputs=stream),
        # a pure sender: connected to its remote
        dict(name="tx", transport="udp", port=0, remote="127.0.0.4:6001", max_body_kib=8),
        # inputs and a remote: not connected
        dict(name="both", transport="udp", port=0, remote="127.0.0.4:6002", inputs=stream),
        # command inputs only: nothing to poll
        dict(
            name="cmd",
            transport="udp",
            port=0,
            allowed_peers=["10.1.0.0/16"],
            inputs=[{"type": "STRING", "queue": "command"}],
        ),
        poll_streams=True,
    )
    rx = m["rx"].transport
    assert isinstance(rx, _Udp)
    _callbacks_are_the_interfaces(rx, m["rx"], peers=False)
    assert rx.args == ("127.0.0.3", 6000)
    assert rx.kwargs == dict(
        remote=None,
        allowed_peers=["127.0.0.1/32"],
        max_body_size=1024 * 1024,
        polled=True,
        connect_remote=False,
        name="igtl-rx",
    )
    tx = m["tx"].transport.kwargs
    assert tx["remote"] == ("127.0.0.4", 6001) and tx["connect_remote"] is True
    assert tx["polled"] is False and tx["max_body_size"] == 8 * 1024
    both = m["both"].transport.kwargs
    assert both["remote"] == ("127.0.0.4", 6002) and both["connect_remote"] is False
    assert both["polled"] is True
    cmd = m["cmd"]
    assert cmd.transport.kwargs["polled"] is False
    assert cmd.transport.kwargs["allowed_peers"] == ["10.1.0.0/16"]
    assert cmd.command_inputs == {"STRING"} and cmd.streams == {}


def test_streams_are_not_polled_unless_asked(fake_transports):
    stream = [{"type": "POSITION", "queue": "stream", "depth": 3}]
    m = manager(dict(name="rx", transport="udp", port=0, inputs=stream))
    assert m["rx"].transport.kwargs["polled"] is False and m["rx"].poll_streams is False
    assert m["rx"].streams["POSITION"].depth == 3


def test_an_unknown_transport_is_named_in_the_error(fake_transports):
    from types import SimpleNamespace

    from occ.net.interfaces import Interface

    cfg = manager(dict(name="x", transport="udp", port=0))["x"].cfg
    bad = SimpleNamespace(**{**dict(cfg), "transport": "carrier-pigeon"})
    with pytest.raises(ValueError, match="unknown transport 'carrier-pigeon'"):
        Interface(bad, manager(), clock_now=lambda: 0.0)


def test_a_default_queue_depth():
    assert StreamQueue().depth == 10 and CommandQueue().depth == 64
    assert StreamQueue().evicted.maxlen == 4096
    assert manager().commands.depth == 64


def test_send_counts_outputs_and_drops_and_passes_the_peer_on(fake_transports):
    m = manager(dict(name="s", transport="tcp-server", port=0))
    iface = m["s"]
    t = iface.transport
    msg, peer = igtl.StatusMessage(device_name="a"), Peer(7, ("127.0.0.1", 9))
    assert iface.send(msg) == 1 and iface.send(msg, peer) == 1
    assert t.sent == [(msg, None), (msg, peer)]  # unkeyed: sent as it is
    t.send_result = 3
    assert iface.send(msg) == 3
    t.send_result = 0
    assert iface.send(msg) == 0 and iface.send(msg) == 0
    assert (iface.counters.sent, iface.counters.send_dropped) == (3, 2)
    st = iface.stats()
    assert st["sent"] == 3 and st["dropped"] == 2  # the transport reports neither
    # outputs that may have nowhere to go are those of a link sending to its stream's owner
    # (a udp link without a remote); a server's always have its clients: no such count
    assert "no_destination" not in st
    # a reply is not an output: not counted, True only when queued
    assert iface.send_to_peer(msg, peer) is False
    t.send_result = 1
    assert iface.send_to_peer(msg, peer) is True and t.sent[-1] == (msg, peer)
    assert (iface.counters.sent, iface.counters.send_dropped) == (3, 2)


def test_a_keyed_interface_signs_what_it_sends(fake_transports, tmp_path):
    from igtl.auth import verify

    key = b"a shared key for the master link"
    (tmp_path / "k").write_text(key.decode() + "\n")
    m = manager(dict(name="s", transport="udp", port=0, auth_key_file=tmp_path / "k"))
    iface, peer = m["s"], Peer(7, ("127.0.0.1", 9))
    iface.send(igtl.StatusMessage(device_name="a", header_version=2), peer)
    iface.send_to_peer(igtl.StatusMessage(device_name="b", header_version=2), peer)
    (a, pa), (b, pb) = iface.transport.sent
    assert verify(a, key) == "" and verify(b, key) == "" and pa is pb is peer
    assert a.device_name == "a" and b.device_name == "b"


def test_stats_take_the_transports_counts_when_it_has_them(fake_transports):
    stream = [{"type": "POSITION", "queue": "stream", "depth": 1}]
    m = manager(dict(name="rx", transport="udp", port=0, inputs=stream))
    iface = m["rx"]
    t = iface.transport
    st = iface.stats()
    assert (st["sent"], st["dropped"], st["malformed"]) == (0, 0, 0)
    assert not any(k in st for k in ("denied", "over_budget", "refused_by_remote"))
    assert st["no_destination"] == 0  # a udp link without a remote: it sends to its owner
    iface.counters.sent, iface.counters.send_dropped, iface.counters.malformed = 4, 1, 2
    assert (iface.stats()["sent"], iface.stats()["malformed"]) == (4, 2)
    q = iface.streams["POSITION"]
    for i in range(3):
        q.put(inbound(i))  # two pushed out
    t.peers = [object(), object()]
    t.transport_stats = {
        "sent": 10,
        "dropped": 5,
        "malformed": 6,
        "over_budget": 1,
        "denied": 2,
        "rejected": 3,
        "idle_closed": 4,
        "slow_message_closed": 5,
        "evicted_not_reading": 6,
        "refused_by_remote": 7,
        "other": 99,
    }
    st = iface.stats()
    assert st["sent"] == 10 and st["malformed"] == 6
    assert st["dropped"] == 5 + 1 + 2  # transport + send queue + stream overflow
    assert st["streams"] == {"POSITION": {"received": 3, "dropped": 2}}
    assert {k: st[k] for k in ("over_budget", "denied", "rejected", "idle_closed")} == {
        "over_budget": 1,
        "denied": 2,
        "rejected": 3,
        "idle_closed": 4,
    }
    assert (st["slow_message_closed"], st["evicted_not_reading"]) == (5, 6)
    assert st["refused_by_remote"] == 7 and "other" not in st
    assert st["peers"] == 2 and st["address"] == [
        "127.0.0.1",
        5555,
    ]
    t.address = None
    t.peers = None
    st = iface.stats()
    assert st["address"] is None and st["peers"] == 0
    assert st["transport"] == "udp" and st["role"] == "none"


def _log(caplog) -> list[tuple[str, str]]:
    return [(r.levelname, r.getMessage()) for r in caplog.records if r.name == "occ.net.interfaces"]


def test_the_log_tells_an_operator_what_each_interface_did(fake_transports, caplog, tmp_path):
    caplog.set_level("DEBUG", logger="occ.net.interfaces")
    stream = [{"type": "POSITION", "queue": "stream", "depth": 5}]
    m = manager(
        dict(name="ops", transport="tcp-server", port=0, role="viewer"),
        dict(name="link", transport="udp", port=0, inputs=stream),
    )
    seen = []
    m.on_connect(lambda iface, peer: seen.append((iface.name, peer.address)))

    def broken(iface, peer):
        raise RuntimeError("listener bug")

    m.on_connect(broken)
    m.on_connect(lambda iface, peer: seen.append("next listener"))
    m.start()
    assert m["ops"].transport.events == ["start"]
    ops, link = m["ops"].transport.kwargs, m["link"].transport.kwargs
    a, b = Peer(1, ("10.0.0.5", 4000)), Peer(2, ("10.0.0.6", 4001))
    ops["on_connect"](a)
    assert seen == [("ops", ("10.0.0.5", 4000)), "next listener"]
    ops["on_disconnect"](a, "idle")
    ops["on_error"](a, ValueError("bad CRC"))
    ops["on_error"](None, ValueError("short header"))
    assert m["ops"].counters.malformed == 2 and m["ops"].stats()["malformed"] == 2
    ops["on_message"](a, igtl.RawMessage(type_name="FOO", device_name="x"))
    ops["on_message"](b, igtl.RawMessage(type_name="FOO", device_name="y"))  # logged once
    ops["on_message"](a, igtl.CommandMessage(command_name="Run", device_name="C"))
    link["on_message"](a, position(1))
    link["on_message"](b, position(2))
    link["on_message"](a, position(3))
    assert [i.msg.message_id for i in m["link"].streams["POSITION"].drain()] == [1, 3]
    m["link"].transport.stop = lambda: (_ for _ in ()).throw(OSError("socket gone"))
    m.stop()
    assert m["ops"].transport.events == ["start", "stop"]  # stopped despite the other's error
    assert _log(caplog) == [
        ("INFO", "interface ops: tcp-server on ('127.0.0.1', 5555)"),
        ("INFO", "interface link: udp on ('127.0.0.1', 5555)"),
        ("INFO", "ops: 10.0.0.5:4000 connected"),
        ("ERROR", "connect listener failed"),
        ("INFO", "ops: 10.0.0.5:4000 disconnected (idle)"),
        ("DEBUG", "ops: malformed message from 10.0.0.5:4000: bad CRC"),
        ("DEBUG", "ops: malformed message from ?: short header"),
        ("INFO", "ops: ignoring unexpected FOO from 10.0.0.5:4000 (counted)"),
        (
            "WARNING",
            "ops: refused COMMAND 'C' from 10.0.0.5:4000: Run: a viewer may query but not "
            "command the robot; send commands to an operator interface",
        ),
        ("INFO", "link: stream owned by 10.0.0.5:4000"),
        (
            "WARNING",
            "link: refused POSITION from 10.0.0.6:4001: the stream belongs to 10.0.0.5:4000",
        ),
        ("ERROR", "interface link: error while stopping"),
    ]
    # the refusal went back to the asker, with its code
    (reply, peer), *_ = [s for s in m["ops"].transport.sent]
    assert peer is a and reply.message_type == "RTS_COMMAND"
    assert "viewer may query" in reply.metadata["Error"]


def test_refusals_are_logged_at_most_five_a_second(fake_transports, caplog, tmp_path):
    caplog.set_level("DEBUG", logger="occ.net.interfaces")
    key = b"a shared key for the master link"
    (tmp_path / "k").write_text(key.decode() + "\n")
    stream = [{"type": "POSITION", "queue": "stream", "depth": 5}]
    m = manager(
        dict(name="link", transport="udp", port=0, inputs=stream, auth_key_file=tmp_path / "k")
    )
    on_message = m["link"].transport.kwargs["on_message"]
    a = Peer(1, ("10.0.0.5", 4000))
    for i in range(7):
        on_message(a, position(i))
    assert m["link"].counters.unauthenticated == 7
    assert _log(caplog) == [("WARNING", "link: refused POSITION from 10.0.0.5:4000: no HMAC")] * 5


def test_a_viewer_with_a_malformed_request_is_told_illegal_instruction(fake_transports):
    m = manager(dict(name="ops", transport="tcp-server", port=0, role="viewer"))
    on_message = m["ops"].transport.kwargs["on_message"]
    a = Peer(1, ("10.0.0.5", 4000))
    on_message(a, igtl.StringMessage("<Command Name=", device_name="CMD_4"))
    on_message(a, igtl.REGISTRY["GET_STATUS"](type_name="GET_STATUS", device_name="Q"))
    ack = m["ops"].transport.sent[0][0]
    assert ack.device_name == "ACK_4" and 'Status="FAIL"' in ack.string
    # a query is queued, whatever the role
    (item,) = m.commands.drain()
    assert item.role == "viewer" and item.request.kind == "query"


def test_an_interface_pins_its_configured_source_when_it_starts(fake_transports):
    stream = [{"type": "POSITION", "queue": "stream", "depth": 5}]
    m = manager(
        dict(name="pinned", transport="udp", port=0, inputs=stream, stream_source="127.0.0.1:7000"),
        dict(name="free", transport="udp", port=0, inputs=stream),
    )
    m.start()
    assert m["pinned"].transport.events == ["start", ("pin", ("127.0.0.1", 7000))]
    assert m["free"].transport.events == ["start"]  # the first sender will own it


def test_an_interface_made_alone_does_not_poll(fake_transports):
    from occ.net.interfaces import Interface

    stream = [{"type": "POSITION", "queue": "stream", "depth": 5}]
    m = manager(dict(name="rx", transport="udp", port=0, inputs=stream))
    iface = Interface(m["rx"].cfg, m, clock_now=lambda: 0.0)
    assert iface.poll_streams is False and iface.transport.kwargs["polled"] is False


def test_thread_priority_says_where_it_applied_and_why_not(fake_transports, monkeypatch):
    import os
    from types import SimpleNamespace

    calls = []

    def setscheduler(tid, policy, param):
        if tid == 13:
            raise PermissionError("not allowed")
        calls.append((tid, policy, param.sched_priority))

    monkeypatch.setattr(os, "sched_setscheduler", setscheduler, raising=False)
    m = manager(
        dict(name="a", transport="udp", port=0),
        dict(name="b", transport="udp", port=0),
        dict(name="c", transport="udp", port=0),
        dict(name="d", transport="udp", port=0),
    )
    m["a"].transport.thread = SimpleNamespace(native_id=11)
    m["b"].transport.thread = None  # not started: no thread
    m["c"].transport.thread = SimpleNamespace(native_id=13)
    m["d"].transport.thread = SimpleNamespace(native_id=14)
    assert m.set_thread_priority(40) == (
        "SCHED_FIFO 40 on a, d; refused for b (no thread), c (PermissionError)"
    )
    assert calls == [(11, os.SCHED_FIFO, 40), (14, os.SCHED_FIFO, 40)]
    assert manager(dict(name="a", transport="udp", port=0)).set_thread_priority(3) == (
        "SCHED_FIFO 3 on none; refused for a (no thread)"
    )
    one = manager(dict(name="a", transport="udp", port=0))
    one["a"].transport.thread = SimpleNamespace(native_id=11)
    assert one.set_thread_priority(5) == "SCHED_FIFO 5 on a"


def test_an_inproc_interface_gets_its_channel_and_limits(monkeypatch):
    import occ.net.interfaces as mod

    class _Inproc(_Recorder):
        kind = "inproc"

    monkeypatch.setattr(mod, "InprocTransport", _Inproc)
    m = manager(
        dict(
            name="sim",
            transport="inproc",
            channel="bench",
            host="127.0.0.9",
            port=1234,
            header_version=1,
            allowed_peers=["10.2.0.0/16"],
            max_clients=3,
            max_body_kib=7,
        ),
        dict(name="anon", transport="inproc", channel="c2", port=0),
    )
    iface = m["sim"]
    t = iface.transport
    _callbacks_are_the_interfaces(t, iface)
    assert t.args == ("bench",)
    assert t.kwargs == dict(
        address=("127.0.0.9", 1234),
        header_version=1,
        negotiate=True,
        allowed_peers=["10.2.0.0/16"],
        max_peers=3,
        max_body_size=7 * 1024,
        name="igtl-sim",
    )
    assert m["anon"].transport.kwargs["address"] is None  # port 0: no address of its own


def test_ipv6_peers_are_logged_by_host_and_port(fake_transports, caplog, tmp_path):
    """An IPv6 address arrives as a 4-tuple (host, port, flowinfo, scope): the log shows
    host:port (the Peer keeps those two)."""
    caplog.set_level("INFO", logger="occ.net.interfaces")
    (tmp_path / "k").write_text("a shared key for the master link\n")
    m = manager(
        dict(name="ops", transport="tcp-server", port=0, role="none"),
        dict(name="keyed", transport="udp", port=0, auth_key_file=tmp_path / "k"),
    )
    ops = m["ops"].transport.kwargs
    v6 = Peer(1, ("::1", 4000, 0, 0))
    ops["on_connect"](v6)
    ops["on_message"](v6, igtl.RawMessage(type_name="FOO", device_name="x"))
    ops["on_message"](v6, igtl.CommandMessage(command_name="Run", device_name="C"))
    ops["on_disconnect"](v6, "eof")
    m["keyed"].transport.kwargs["on_message"](v6, position(1))
    assert _log(caplog) == [
        ("INFO", "ops: ::1:4000 connected"),
        ("INFO", "ops: ignoring unexpected FOO from ::1:4000 (counted)"),
        (
            "WARNING",
            "ops: refused COMMAND 'C' from ::1:4000: interface ops is a data link: it takes "
            "no requests",
        ),
        ("INFO", "ops: ::1:4000 disconnected (eof)"),
        ("WARNING", "keyed: refused POSITION from ::1:4000: no HMAC"),
    ]


def test_a_remote_by_host_name_keeps_its_name(fake_transports):
    m = manager(dict(name="up", transport="tcp-client", remote="XrayX.local:7001"))
    assert m["up"].transport.args == ("XrayX.local", 7001)


def test_a_key_file_is_read_as_utf8_whatever_the_locale(tmp_path):
    """A daemon started with an ASCII locale (LC_ALL=C, UTF-8 mode off) reads a key with
    non-ASCII characters as the other end does: in UTF-8."""
    import os
    import subprocess
    import sys

    (tmp_path / "k").write_text("clé partagée du lien maître\n", encoding="utf-8")
    code = (
        "import locale, sys\n"
        "from occ.config import InterfaceConfig\n"
        "from occ.net.interfaces import InterfaceManager\n"
        "assert locale.getpreferredencoding(False).lower() not in ('utf-8', 'utf8')\n"
        f"cfg = InterfaceConfig(name='k', transport='inproc', channel='c', port=0,"
        f" auth_key_file={str(tmp_path / 'k')!r})\n"
        "m = InterfaceManager([cfg], clock_now=lambda: 0.0)\n"
        "sys.stdout.write(m['k'].auth_key.hex())\n"
    )
    env = {**os.environ, "LC_ALL": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0"}
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, cwd=ROOT
    )
    assert out.returncode == 0, out.stderr
    assert bytes.fromhex(out.stdout) == "clé partagée du lien maître".encode()


def _points() -> igtl.PointMessage:
    el = igtl.PointElement(name="F-1", group="Fiducial", rgba=(255, 0, 0, 255), position=(1, 2, 3))
    return igtl.PointMessage(points=(el,), device_name="F", header_version=2)


def test_the_interface_decodes_what_it_routes_once_naming_who_sent_it_and_when() -> None:
    """Issue 39: an item the interface routes carries its typed event, made there once, with
    the interface's name, the sender and the reception time: a pose on its stream (a
    PoseSample), a discrete input on a stream queue, a discrete input of the command queue."""
    import yaml

    from occ.events import PointList
    from occ.samples import PoseSample

    cfg = yaml.safe_load(SLAVE.read_text(encoding="utf-8"))
    (master,) = [i for i in cfg["interfaces"] if i["name"] == "master"]
    master["inputs"].append({"type": "POINT", "queue": "stream", "depth": 10})
    (op,) = [i for i in cfg["interfaces"] if i["name"] == "operator"]
    op["inputs"] = [{"type": "POINT", "queue": "command", "depth": 4}]
    with SimRobot(cfg) as sim:
        sim.clock.set(0.5)
        iface = sim.robot.interfaces["master"]
        peer = Peer(7, ("127.0.0.1", 4000))
        item = iface.route(peer, position(1))
        assert isinstance(item, Inbound) and isinstance(item.event, PoseSample)
        sample = item.event
        assert (sample.interface, sample.peer, sample.t_rx, sample.seq) == ("master", peer, 0.5, 1)
        assert item.request is None and item.role == "operator"
        item = iface.route(peer, _points())
        assert isinstance(item, Inbound) and isinstance(item.event, PointList)
        ev = item.event
        assert (ev.interface, ev.peer, ev.t_rx, ev.device) == ("master", peer, 0.5, "F")
        # the command queue: decoded by the interface before it is queued
        ops = sim.robot.interfaces["operator"]
        asker = Peer(8, ("127.0.0.1", 4001))
        assert ops.route(asker, _points()) is None
        (queued,) = sim.robot.interfaces.commands.drain()
        assert isinstance(queued.event, PointList)
        ev = queued.event
        assert (ev.interface, ev.peer, ev.t_rx) == ("operator", asker, 0.5)
