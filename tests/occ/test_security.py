"""Who may command the robot, seen from the network: every kind of message a viewer, a data
link's peer or a peer that is not allowed can send, over TCP and UDP, on unsigned and on signed
(``auth_key_file``) interfaces (docs/SAFETY.md, SR-SEC-1..5; issue 29).

The slave of configs/slave.yaml runs on a SimClock, ticked by the test; its interfaces are real
sockets on 127.0.0.1 (ephemeral ports). The peers are plain sockets bound to 127.0.0.1 or
127.0.0.2 (both loopback: an operator address and another host, without leaving the machine),
reading what the daemon sends back with igtl's own decoder. Each check is what the peer gets
back (a reply, its form and text, or nothing), what the daemon counted, and the robot's state.

"Nothing came back" is proved without waiting on a clock: after the message under test the
peer sends a request that is always answered (a *marker*) on the same socket; replies to one
peer leave in order, so a reply to the message under test would come before the marker's.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import socket
from collections.abc import Callable, Iterator
from pathlib import Path
from xml.sax.saxutils import quoteattr

import pytest

import igtl
from igtl.auth import HMAC_KEY, sign, verify
from occ.clock import SimClock
from occ.net.commands import ROBOT_COMMANDS
from occ.core.loader import parse_config
from occ.core.robot import Robot, build_robot
from occ.core.safety import RobotState
from occ_testkit.testing import wait_until

ROOT = Path(__file__).resolve().parents[2]
KEY = b"the operators' shared key, 32 b."
WRONG_KEY = b"another key of at least 16 bytes"
OPERATOR_HOST = "127.0.0.2"  # in the operators list of the shared interfaces
OTHER_HOST = "127.0.0.1"  # allowed, not an operator there
UNKNOWN_HOST = "127.0.0.3"  # in no interface's allowed_peers
#: how long to wait for a reply on loopback (scripts/mutate shortens it: a killed mutant is
#: often one whose reply never comes, and each would cost the whole wait)
WAIT_S = float(os.environ.get("OCC_SECURITY_WAIT_S", "10"))

INTERFACES = """
interfaces:
  - {name: tview, transport: tcp-server, host: 127.0.0.1, port: 0, role: viewer}
  - {name: top, transport: tcp-server, host: 127.0.0.1, port: 0, role: operator,
     operators: [127.0.0.2], allowed_peers: [127.0.0.1, 127.0.0.2],
     inputs: [{type: POINT, queue: command, depth: 4}]}
  - {name: tlink, transport: tcp-server, host: 127.0.0.1, port: 0}
  - {name: tkey, transport: tcp-server, host: 127.0.0.1, port: 0, role: operator,
     auth_key_file: KEYFILE}
  - {name: uview, transport: udp, host: 127.0.0.1, port: 0, role: viewer}
  - {name: uop, transport: udp, host: 127.0.0.1, port: 0, role: operator,
     operators: [127.0.0.2], allowed_peers: [127.0.0.1, 127.0.0.2]}
  - {name: ulink, transport: udp, host: 127.0.0.1, port: 0}
  - {name: ukey, transport: udp, host: 127.0.0.1, port: 0, role: operator,
     auth_key_file: KEYFILE}
  - name: master
    transport: udp
    host: 127.0.0.1
    port: 0
    auth_key_file: KEYFILE
    inputs: [{type: POSITION, queue: stream, depth: 10}]
    outputs: [{type: POSITION, device: SlaveTip, source: teleop-return, rate_hz: 500}]
  - {name: feed, transport: udp, host: 127.0.0.1, port: 0, kernel_filter: false,
     inputs: [{type: POSITION, device: Master, queue: stream, depth: 10}],
     outputs: [{type: TRANSFORM, device: Tip, source: tip, rate_hz: 1000}]}
"""


def _config_text(keyfile: Path, interfaces: str = INTERFACES) -> str:
    text = (ROOT / "configs" / "slave.yaml").read_text()
    head, _, rest = text.partition("interfaces:")
    _, _, tail = rest.partition("\nsafety:")
    return head + interfaces.lstrip("\n").replace("KEYFILE", str(keyfile)) + "safety:" + tail


@pytest.fixture
def robot(tmp_path: Path) -> Iterator[Robot]:
    keyfile = tmp_path / "link.key"
    keyfile.write_text(KEY.decode() + "\n")
    cfg = parse_config(_config_text(keyfile), base_dir=ROOT / "configs")
    r = build_robot(cfg, clock=SimClock())
    r.configure()
    r.activate()
    try:
        yield r
    finally:
        r.shutdown()


_TICKS = [0]


def tick(robot: Robot, n: int = 1) -> None:
    for _ in range(n):
        _TICKS[0] += 1
        robot.tick(robot.clock.now(), _TICKS[0])
        robot.clock.advance(0.001)  # type: ignore[attr-defined]


class Peer:
    """A client of one interface from ``host``: a TCP connection or a UDP socket; ``key`` signs
    what it sends. ``got`` collects what the daemon sends to it, decoded."""

    def __init__(self, robot: Robot, iface: str, host: str, key: bytes | None = None) -> None:
        self.robot = robot
        self.iface = robot.interfaces[iface]
        self.key = key
        self.udp = self.iface.cfg.transport == "udp"
        addr = self.iface.address
        assert addr is not None
        self.dest = ("127.0.0.1", addr[1])
        if self.udp:
            self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.sock.bind((host, 0))
        else:
            self.sock = socket.create_connection(self.dest, timeout=5.0, source_address=(host, 0))
            self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.sock.setblocking(False)
        self.decoder = igtl.StreamDecoder()
        self.got: list[igtl.Message] = []
        self.closed = False
        self._id = 0

    def send(self, msg: igtl.Message, *, raw: bool = False) -> None:
        if self.key is not None and not raw:
            msg = sign(msg, self.key)
        data = msg.pack()
        if self.udp:
            self.sock.sendto(data, self.dest)
        else:
            self.sock.sendall(data)

    def read(self) -> None:
        while True:
            try:
                data = self.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self.closed = True
                return
            if not data:
                if not self.udp:
                    self.closed = True
                return
            if self.udp:
                self.got.append(igtl.unpack(data))
            else:
                self.decoder.feed(data)
                self.got.extend(self.decoder)

    def next_id(self) -> int:
        self._id += 1
        return 7000 + self._id

    def await_reply(self, mid: int) -> igtl.Message:
        """Tick the robot until the reply that echoes message ID ``mid`` comes back."""
        found: list[igtl.Message] = []

        def step() -> bool:
            tick(self.robot)
            self.read()
            found[:] = [m for m in self.got if m.message_id == mid]
            return bool(found)

        assert wait_until(step, timeout=WAIT_S), (
            f"no reply to {mid}; got {[(m.message_type, m.message_id) for m in self.got]}"
        )
        return found[0]

    def close(self) -> None:
        self.sock.close()


def until(robot: Robot, cond: Callable[[], object]) -> bool:
    """Tick the robot (it polls its UDP streams in its tick) until ``cond`` holds."""

    def step() -> object:
        tick(robot)
        return cond()

    return bool(wait_until(step, timeout=WAIT_S))


def command(name: str, mid: int, text: str = "") -> igtl.Message:
    return igtl.CommandMessage(
        command_id=mid, command_name=name, command=text, header_version=2, message_id=mid
    )


def string_command(name: str, mid: int) -> igtl.Message:
    """A PLUS-style request: STRING ``CMD_<id>`` holding ``<Command Name="..."/>``."""
    return igtl.StringMessage(
        f'<Command Name="{name}" />', device_name=f"CMD_{mid}", header_version=2, message_id=mid
    )


def query(mtype: str, mid: int) -> igtl.Message:
    return igtl.REGISTRY[mtype](type_name=mtype, header_version=2, message_id=mid)


def ask(peer: Peer, msg: igtl.Message) -> list[igtl.Message]:
    """Send ``msg``, then a marker (GET_STATUS, always answered: by the state, or by a refusal);
    return everything that came back before the marker's answer, which is ``peer.got[-1]``."""
    peer.got.clear()
    peer.send(msg)
    marker = peer.next_id()
    peer.send(query("GET_STATUS", marker))
    peer.await_reply(marker)
    before = []
    for m in peer.got:
        if m.message_id == marker and m.message_type == "STATUS":
            break
        before.append(m)
    # the greeting and the state STATUS pushed to every viewer and operator (message ID 0) are
    # no answer
    return [m for m in before if m.message_type != "STATUS" or m.message_id != 0]


def answer_to(peer: Peer, msg: igtl.Message) -> igtl.Message:
    """The one reply to ``msg`` (asserted: exactly one, echoing its message ID)."""
    got = [m for m in ask(peer, msg) if m.message_id == msg.message_id]
    assert len(got) == 1, [(m.message_type, m.message_id) for m in got]
    return got[0]


def reply_to(peer: Peer, msg: igtl.Message) -> igtl.Message:
    """The reply to ``msg``, however late (GetStats is answered by the worker thread)."""
    peer.got.clear()
    peer.send(msg)
    return peer.await_reply(msg.message_id)


def _status(reply: igtl.Message) -> str:
    return str(reply.metadata.get("Status", ""))


# the commands that change the robot or its controller, and those that only read
ACTING = sorted(c.name for c in ROBOT_COMMANDS.values() if c.role == "operator") + [
    "Clutch",
    "ClearFixtures",
    "Select",
    "Toggle",
    "NoSuchCommand",
]
READING = ["GetState", "GetStats", "GetRecordingStatus"]
#: the queries (GET_, STT_, STP_) and the type of their answer
QUERIES = {
    "GET_STATUS": "STATUS",
    "GET_CAPABIL": "CAPABILITY",
    "GET_TRANS": "TRANSFORM",
    "STT_TDATA": "RTS_TDATA",
    "STP_TDATA": "RTS_TDATA",
}


# a viewer: a viewer interface, or a host not in the operators list of an operator interface
VIEWERS = [("tview", OTHER_HOST), ("uview", OTHER_HOST), ("top", OTHER_HOST), ("uop", OTHER_HOST)]


@pytest.mark.req("SR-SEC-1")
@pytest.mark.parametrize(("iface", "host"), VIEWERS)
def test_a_viewer_may_read_and_is_refused_every_command_that_acts(
    robot: Robot, iface: str, host: str, caplog: pytest.LogCaptureFixture
) -> None:
    peer = Peer(robot, iface, host)
    counters = robot.interfaces[iface].counters
    caplog.set_level(logging.WARNING, logger="occ.net.interfaces")
    try:
        refused = 0
        for name in ACTING + ["enable", " Run ", "ESTOP", "getstate now"]:
            mid = peer.next_id()
            reply = answer_to(peer, command(name, mid))
            assert reply.message_type == "RTS_COMMAND" and _status(reply) == "FAIL", name
            assert reply.metadata["Error"] == (
                f"{name.strip()}: a viewer may query but not command the robot; "
                "send commands to an operator interface"
            )
            mid = peer.next_id()
            ack = answer_to(peer, string_command(name.strip(), mid))
            assert ack.message_type == "STRING" and ack.device_name == f"ACK_{mid}"
            assert "a viewer may query but not command the robot" in ack.string
            if not refused:  # the log names the interface, the message, the peer, the why
                port = peer.sock.getsockname()[1]
                assert [r.getMessage() for r in caplog.records] == [
                    f"{iface}: refused COMMAND '' from {host}:{port}: {reply.metadata['Error']}",
                    f"{iface}: refused STRING 'CMD_{mid}' from {host}:{port}: "
                    + reply.metadata["Error"],
                ]
            refused += 2
            assert robot.state is RobotState.READY
        assert counters.refused == refused
        for name in READING + ["getstate", " GETSTATS "]:
            mid = peer.next_id()
            reply = reply_to(peer, command(name, mid))
            assert _status(reply) == "SUCCESS", (name, reply.metadata)
            mid = peer.next_id()
            ack = reply_to(peer, string_command(name.strip(), mid))
            assert 'Status="SUCCESS"' in ack.string, ack.string
        # the state table is a viewer's to read (this robot keeps none: the desk says so)
        table = reply_to(peer, command("GetStateTable", peer.next_id()))
        assert table.metadata["Error"] == (
            "GetStateTable: no state table (configure state_table.seconds)"
        )
        # every query is a viewer's to ask (a type the robot does not serve is answered so)
        for mtype, answer in QUERIES.items():
            mid = peer.next_id()
            got = ask(peer, query(mtype, mid))
            assert [m.message_type for m in got] == [answer], (mtype, got)
            reply = got[0]
            if mtype == "GET_STATUS":
                assert "state=READY" in reply.status_message
        assert counters.refused == refused  # reading refused nothing
        assert robot.state is RobotState.READY
    finally:
        peer.close()


@pytest.mark.req("SR-SEC-1")
@pytest.mark.parametrize("iface", ["top", "uop"])
def test_an_operator_address_commands_where_other_hosts_only_read(robot: Robot, iface: str) -> None:
    op, other = Peer(robot, iface, OPERATOR_HOST), Peer(robot, iface, OTHER_HOST)
    try:
        assert _status(answer_to(other, command("Enable", other.next_id()))) == "FAIL"
        assert robot.state is RobotState.READY
        mid = op.next_id()
        reply = reply_to(op, command("Enable", mid))
        assert _status(reply) == "SUCCESS" and robot.state is RobotState.ENABLED
        ack = reply_to(op, string_command("Run", op.next_id()))
        assert 'Status="SUCCESS"' in ack.string and robot.state is RobotState.RUNNING
        # the operator sees every statistic; the other host, a viewer, not the stream's
        # source or its next sequence number (SR-ROLE-1)
        full = reply_to(op, command("GetStats", op.next_id())).metadata["Message"]
        seen = reply_to(other, command("GetStats", other.next_id())).metadata["Message"]
        assert '"stream_owner"' in full and '"stream_owner"' not in seen
        # a name the robot does not know goes on to its controller (the slave's has none)
        unknown = reply_to(op, command("Clutch", op.next_id()))
        assert unknown.metadata["Error"] == "unknown command 'Clutch'"
        assert _status(answer_to(other, command("Stop", other.next_id()))) == "FAIL"
        assert robot.state is RobotState.RUNNING
        assert robot.interfaces[iface].counters.refused == 2
    finally:
        op.close()
        other.close()


@pytest.mark.req("SR-SEC-2")
@pytest.mark.parametrize("iface", ["tlink", "ulink"])
def test_a_data_link_refuses_every_request_with_access_denied(robot: Robot, iface: str) -> None:
    peer = Peer(robot, iface, OTHER_HOST)
    why = f"interface {iface} is a data link: it takes no requests"
    counters = robot.interfaces[iface].counters
    try:
        n = 0
        for name in ["Enable", "GetState", "GetStats"]:
            reply = answer_to(peer, command(name, peer.next_id()))
            assert reply.message_type == "RTS_COMMAND" and reply.metadata["Error"] == why
            mid = peer.next_id()
            ack = answer_to(peer, string_command(name, mid))
            assert ack.device_name == f"ACK_{mid}" and why in ack.string
            n += 4  # each with its marker
        for mtype in QUERIES:
            got = ask(peer, query(mtype, peer.next_id()))
            assert len(got) == 1, got
            reply = got[0]
            if mtype.startswith("GET_"):
                assert reply.message_type == "STATUS"
                assert reply.code == igtl.StatusCode.ACCESS_DENIED
                assert reply.error_name == "ACCESS_DENIED" and reply.status_message == why
            else:  # (an RTS_ reply does not echo the message ID: only one is here)
                assert reply.message_type == "RTS_TDATA"
            n += 2
        assert counters.refused == counters.received == n
        assert robot.state is RobotState.READY
    finally:
        peer.close()


#: messages that are no request: never answered, never acted on where no input takes them
NOT_REQUESTS = [
    igtl.TransformMessage.from_matrix(
        [[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]],
        device_name="Tip",
        header_version=2,
    ),
    igtl.PositionMessage(
        (1.0, 2.0, 3.0),
        (0.0, 0.0, 0.0, 1.0),
        24,
        device_name="Master",
        header_version=2,
        message_id=5,
        metadata={"run": "1", "clutch": "0"},
    ),
    igtl.StringMessage('<Command Name="Enable" />', device_name="Enable", header_version=2),
    igtl.StringMessage("Enable", device_name="cmd_1", header_version=2),
]


@pytest.mark.req("SR-SEC-2")
@pytest.mark.parametrize("iface", ["tview", "uview", "top", "uop", "tlink", "ulink"])
def test_what_is_no_request_is_counted_and_never_acted_on(robot: Robot, iface: str) -> None:
    peer = Peer(robot, iface, OPERATOR_HOST if iface in ("top", "uop") else OTHER_HOST)
    counters = robot.interfaces[iface].counters
    try:
        for msg in NOT_REQUESTS:
            assert ask(peer, msg) == []
        keepalive = igtl.StatusMessage(code=igtl.StatusCode.OK, header_version=2, message_id=9)
        assert ask(peer, keepalive) == []
        assert counters.unexpected == len(NOT_REQUESTS)
        assert counters.unexpected_types == {"TRANSFORM", "POSITION", "STRING"}
        assert counters.keepalive == 1 and counters.unauthenticated == 0
        assert robot.state is RobotState.READY
        assert robot.interfaces["master"].counters.received == 0
    finally:
        peer.close()


def _retag(msg: igtl.Message, tag: str) -> igtl.Message:
    return dataclasses.replace(msg, metadata={**msg.metadata, HMAC_KEY: tag})


def _forgeries(msg: igtl.Message) -> dict[str, igtl.Message]:
    """``msg`` as a peer without the key could send it."""
    signed = sign(msg, KEY)
    tag = signed.metadata[HMAC_KEY]
    other = sign(dataclasses.replace(msg, message_id=msg.message_id + 1), KEY)
    if isinstance(msg, igtl.CommandMessage):
        # a signed harmless request with the command changed after signing
        harmless = sign(dataclasses.replace(msg, command_name="GetState"), KEY)
        altered = dataclasses.replace(harmless, command_name=msg.command_name)
    elif isinstance(msg, igtl.StringMessage):
        harmless = sign(dataclasses.replace(msg, string='<Command Name="GetState" />'), KEY)
        altered = dataclasses.replace(harmless, string=msg.string)
    else:
        altered = dataclasses.replace(signed, device_name="Forged")
    v1 = dataclasses.replace(msg, header_version=1, message_id=0, metadata={})
    return {
        "unsigned": msg,
        "wrong key": sign(msg, WRONG_KEY),
        "altered after signing": altered,
        "truncated tag": _retag(signed, tag[:31]),
        "half a tag": _retag(signed, tag[:16]),
        "empty tag": _retag(signed, ""),
        "upper-case tag": _retag(signed, tag.upper()),
        "another message's tag": _retag(signed, other.metadata[HMAC_KEY]),
        "non-ASCII tag": _retag(signed, "é" * 32),
        "header version 1": v1,
    }


@pytest.mark.req("SR-SEC-3")
@pytest.mark.parametrize("iface", ["tkey", "ukey"])
def test_a_signed_link_answers_nothing_without_a_valid_tag_and_signs_its_answers(
    robot: Robot, iface: str
) -> None:
    peer = Peer(robot, iface, OTHER_HOST, key=KEY)
    counters = robot.interfaces[iface].counters
    try:
        n = 0
        for make in (
            lambda mid: command("Enable", mid),
            lambda mid: string_command("Enable", mid),
            lambda mid: query("GET_STATUS", mid),
        ):
            for what, forged in _forgeries(make(peer.next_id())).items():
                peer.got.clear()
                peer.send(forged, raw=True)
                marker = peer.next_id()
                peer.send(query("GET_STATUS", marker))
                peer.await_reply(marker)
                answers = [m for m in peer.got if m.message_id != marker and m.message_id != 0]
                assert answers == [], what
                n += 1
                assert counters.unauthenticated == n, what
                assert robot.state is RobotState.READY, what
        assert counters.refused == 0
        # and with the key: obeyed, and every answer carries a valid tag
        reply = reply_to(peer, command("Enable", peer.next_id()))
        assert _status(reply) == "SUCCESS" and robot.state is RobotState.ENABLED
        assert verify(reply, KEY) == "" and verify(reply, WRONG_KEY) == "wrong HMAC"
        assert all(verify(m, KEY) == "" for m in peer.got)
        assert counters.unauthenticated == n
    finally:
        peer.close()


@pytest.mark.req("SR-SEC-3")
def test_a_signed_stream_takes_only_samples_with_a_valid_tag(robot: Robot) -> None:
    iface = robot.interfaces["master"]
    sample = igtl.PositionMessage(
        (0.0, 50.0, 270.0),
        (0.0, 0.0, 0.0, 1.0),
        24,
        device_name="Master",
        header_version=2,
        message_id=1,
        metadata={"run": "1", "clutch": "0"},
    )
    peer = Peer(robot, "master", OTHER_HOST)
    try:
        forged = _forgeries(sample)
        for msg in forged.values():
            peer.send(msg)
        assert until(robot, lambda: iface.counters.received == len(forged))
        assert iface.counters.unauthenticated == len(forged)
        assert iface.stats()["streams"]["POSITION"]["received"] == 0
        assert iface.stream_owner is None  # a forger does not become the stream's owner
        peer.send(sign(sample, KEY))
        assert until(robot, lambda: iface.stats()["streams"]["POSITION"]["received"] == 1)
        assert iface.stream_owner == peer.sock.getsockname()
        assert iface.counters.unauthenticated == len(forged)
    finally:
        peer.close()


@pytest.mark.req("SR-SEC-4")
@pytest.mark.parametrize("iface", ["tview", "top", "tlink", "tkey"])
def test_an_unknown_host_is_told_access_denied_and_closed_over_tcp(
    robot: Robot, iface: str
) -> None:
    transport = robot.interfaces[iface].transport
    sock = socket.create_connection(
        ("127.0.0.1", robot.interfaces[iface].address[1]),  # type: ignore[index]
        timeout=WAIT_S,
        source_address=(UNKNOWN_HOST, 0),
    )
    try:
        try:
            sock.sendall(command("Enable", 1).pack() + sign(command("Run", 2), KEY).pack())
        except OSError:
            pass  # closed already
        data = b""
        while True:
            try:
                chunk = sock.recv(65536)
            except OSError:
                break
            if not chunk:
                break
            data += chunk
        got = igtl.unpack(data)  # exactly one message, then the end of the stream
        assert got.message_type == "STATUS" and got.code == igtl.StatusCode.ACCESS_DENIED
        assert got.status_message == "connection not allowed"
        assert wait_until(lambda: transport.stats()["denied"] == 1, timeout=WAIT_S)
        tick(robot, 20)
        assert robot.interfaces[iface].counters.received == 0
        assert robot.interfaces[iface].stats()["denied"] == 1
        assert robot.state is RobotState.READY
    finally:
        sock.close()


@pytest.mark.req("SR-SEC-4")
@pytest.mark.parametrize("iface", ["uview", "uop", "ulink", "ukey", "master"])
def test_an_unknown_host_gets_nothing_over_udp(robot: Robot, iface: str) -> None:
    stranger = Peer(robot, iface, UNKNOWN_HOST)
    messages = [
        command("Enable", 1),
        sign(command("Run", 2), KEY),
        query("GET_STATUS", 3),
        sign(NOT_REQUESTS[1], KEY),
    ]
    try:
        for msg in messages:
            stranger.send(msg)
        assert until(robot, lambda: robot.interfaces[iface].stats()["denied"] == len(messages))
        tick(robot, 20)
        stranger.read()
        assert stranger.got == []
        assert robot.interfaces[iface].counters.received == 0
        assert robot.interfaces[iface].stream_owner is None
        assert robot.state is RobotState.READY
    finally:
        stranger.close()


@pytest.mark.req("SR-SEC-1")
def test_state_changes_reach_viewers_and_operators_not_data_links(robot: Robot) -> None:
    """What the robot does is every viewer's and operator's business (signed where the
    interface is keyed); a data link's peers are told nothing."""
    viewer = Peer(robot, "tview", OTHER_HOST)
    link = Peer(robot, "tlink", OTHER_HOST)
    keyed = Peer(robot, "tkey", OTHER_HOST, key=KEY)
    op = Peer(robot, "top", OPERATOR_HOST)
    try:
        for p in (viewer, link, keyed, op):
            assert until(
                robot,
                lambda p=p: (p.read(), robot.interfaces[p.iface.name].stats()["peers"])[1] == 1,
            )
        assert _status(reply_to(op, command("Enable", op.next_id()))) == "SUCCESS"

        def pushed(p: Peer) -> list[igtl.Message]:
            p.read()
            return [m for m in p.got if m.message_type == "STATUS" and m.error_name == "ENABLED"]

        for p in (viewer, keyed, op):
            assert until(robot, lambda p=p: pushed(p)), p.iface.name
        assert all(verify(m, KEY) == "" for m in pushed(keyed))
        # the link: a request sent now is refused on the same connection after any push
        # of the Enable would have been sent (one connection, in order): none came
        mid = link.next_id()
        link.send(query("GET_CAPABIL", mid))
        assert link.await_reply(mid).code == igtl.StatusCode.ACCESS_DENIED
        assert pushed(link) == [] and [m for m in link.got if m.message_id == 0] == []
    finally:
        for p in (viewer, link, keyed, op):
            p.close()


@pytest.mark.req("SR-SEC-2")
@pytest.mark.parametrize(
    ("role", "extra"),
    [
        ("viewer", ""),
        ("none", ""),
        ("operator", ", operators: [127.0.0.2], allowed_peers: [127.0.0.1, 127.0.0.2]"),
    ],
)
@pytest.mark.parametrize("listed", ["COMMAND", "STRING"])
def test_listing_a_request_type_as_an_input_does_not_lift_the_role_check(
    tmp_path: Path, role: str, extra: str, listed: str
) -> None:
    """A config that lists COMMAND or STRING among an interface's inputs (a controller that
    wants them) must not turn its viewers, or a data link's peers, into operators."""
    keyfile = tmp_path / "link.key"
    keyfile.write_text(KEY.decode() + "\n")
    text = _config_text(keyfile).replace(
        "  - {name: tview, transport: tcp-server, host: 127.0.0.1, port: 0, role: viewer}",
        "  - {name: tview, transport: tcp-server, host: 127.0.0.1, port: 0, "
        f"role: {role}{extra},\n     inputs: [{{type: {listed}, queue: command, depth: 4}}]}}",
    )
    r = build_robot(parse_config(text, base_dir=ROOT / "configs"), clock=SimClock())
    r.configure()
    r.activate()
    peer = Peer(r, "tview", OTHER_HOST)
    try:
        msg = command("Enable", 5) if listed == "COMMAND" else string_command("Enable", 5)
        got = ask(peer, msg)
        assert len(got) == 1, got
        why = (
            "interface tview is a data link: it takes no requests"
            if role == "none"
            else "Enable: a viewer may query but not command the robot; send commands to an "
            "operator interface"
        )
        if listed == "COMMAND":
            assert got[0].metadata["Error"] == why
        else:
            assert f"Error={quoteattr(why)}" in got[0].string
        assert r.state is RobotState.READY
        # on a data link the marker is refused too; elsewhere the desk answered it, only it
        assert r.interfaces["tview"].counters.refused == (2 if role == "none" else 1)
        assert r.operators.handled == (0 if role == "none" else 1)
    finally:
        peer.close()
        r.shutdown()


@pytest.mark.req("SR-SEC-5")
def test_a_replayed_signed_sample_is_a_duplicate_never_applied(robot: Robot) -> None:
    """The tag proves who made a sample, not when: the same signed bytes sent again pass the
    tag check and are refused by the sequence check (SR-SEQ-1) as a duplicate."""
    monitor = robot.streams.monitor
    assert monitor is not None
    iface = robot.interfaces["master"]
    peer = Peer(robot, "master", OTHER_HOST, key=KEY)

    def sample(seq: int) -> igtl.Message:
        return igtl.PositionMessage(
            (0.0, 50.0, 270.0),
            (0.0, 0.0, 0.0, 1.0),
            24,
            device_name="Master",
            header_version=2,
            message_id=seq,
            metadata={"run": "1", "clutch": "0"},
        )

    try:
        first, second = sign(sample(1), KEY), sign(sample(2), KEY)
        for msg in (first, second, second, first):
            peer.send(msg, raw=True)
        assert until(robot, lambda: monitor.counters()["received"] == 4)
        counts = monitor.counters()
        assert (counts["accepted"], counts["duplicates"], counts["lost_total"]) == (2, 2, 0)
        assert iface.counters.unauthenticated == 0
    finally:
        peer.close()


def _pose(seq: int, device: str = "Master") -> igtl.Message:
    return igtl.PositionMessage(
        (0.0, 50.0, 270.0),
        (0.0, 0.0, 0.0, 1.0),
        24,
        device_name=device,
        header_version=2,
        message_id=seq,
        metadata={"run": "1", "clutch": "0"},
    )


@pytest.mark.req("SR-SEC-4", "SR-OWN-1")
def test_a_second_sender_cannot_feed_a_stream_it_does_not_own(robot: Robot) -> None:
    """The first sender owns a stream; another allowed host's samples are refused: dropped by
    the kernel where the socket is pinned to the owner (``kernel_filter``, the default), counted
    ``foreign`` where it is not. A device other than the input's is no sample."""
    pinned, open_ = robot.interfaces["master"], robot.interfaces["feed"]
    owner = Peer(robot, "master", OTHER_HOST, key=KEY)
    # another sender on the same (allowed) host: another port
    intruder = Peer(robot, "master", OTHER_HOST, key=KEY)
    owner2 = Peer(robot, "feed", OTHER_HOST)
    intruder2 = Peer(robot, "feed", OTHER_HOST)
    try:
        owner.send(_pose(1))
        owner2.send(_pose(1))
        assert until(robot, lambda: pinned.stream_owner and open_.stream_owner)
        assert pinned.stream_owner == owner.sock.getsockname()
        assert open_.stream_owner == owner2.sock.getsockname()
        for seq in (2, 3, 4):
            intruder.send(_pose(seq))
            intruder2.send(_pose(seq))
        owner.send(_pose(2))
        owner2.send(_pose(2))
        owner2.send(_pose(3, device="Other"))
        assert until(robot, lambda: open_.counters.received == 6 and pinned.counters.received == 2)
        # the pinned socket never delivered the intruder's datagrams; the open one refused them
        assert (pinned.counters.received, pinned.counters.foreign) == (2, 0)
        assert (open_.counters.foreign, open_.counters.unexpected) == (3, 1)
        assert open_.counters.unexpected_types == {"POSITION"}
        assert pinned.stats()["streams"]["POSITION"]["received"] == 2
        assert open_.stats()["streams"]["POSITION"]["received"] == 2
        monitor = robot.streams.monitor
        assert monitor is not None
        assert until(robot, lambda: monitor.counters()["accepted"] == 2)
        assert monitor.counters()["received"] == 2
    finally:
        for p in (owner, intruder, owner2, intruder2):
            p.close()


@pytest.mark.req("SR-SEC-1")
@pytest.mark.parametrize("iface", ["top", "uop"])
def test_a_malformed_request_is_refused_with_its_reason_and_a_full_queue_says_busy(
    robot: Robot, iface: str
) -> None:
    op = Peer(robot, iface, OPERATOR_HOST)
    counters = robot.interfaces[iface].counters
    try:
        mid = op.next_id()
        bad = igtl.StringMessage(
            '<Command Name="Enable"', device_name=f"CMD_{mid}", header_version=2, message_id=mid
        )
        ack = answer_to(op, bad)
        assert ack.device_name == f"ACK_{mid}"
        assert 'Error="malformed XML command: unclosed token' in ack.string, ack.string
        nameless = answer_to(op, command("", op.next_id()))
        assert nameless.metadata["Error"] == "COMMAND without a command name"
        assert counters.refused == 2 and robot.state is RobotState.READY
        # the command queue holds 64; the loop does not tick while 70 arrive: the 6 past it
        # are refused at once (a query's STATUS says BUSY), none is lost without its sender
        # knowing
        queue = robot.interfaces.commands
        before, received = queue.received, counters.received
        ids = [op.next_id() for _ in range(70)]
        for n, i in enumerate(ids):
            op.send(command("GetState", i) if n < 67 else query("GET_STATUS", i))
        assert wait_until(lambda: counters.received == received + 70, timeout=WAIT_S)
        assert queue.received - before == 64 and queue.refused == 6
        assert wait_until(lambda: (op.read(), len(op.got) >= 6)[1], timeout=WAIT_S)
        full = [m for m in op.got if m.message_id in ids[64:]]
        assert [m.message_id for m in full] == ids[64:]
        assert [m.metadata["Error"] for m in full[:3]] == ["command queue full"] * 3
        assert [(m.code, m.error_name, m.status_message) for m in full[3:]] == [
            (igtl.StatusCode.BUSY, "BUSY", "command queue full")
        ] * 3
        assert counters.refused == 2 + 6
        # and the 64 queued are answered once the loop runs
        answered: set[int] = set()

        def replies() -> bool:
            op.read()
            answered.update(m.message_id for m in op.got if m.message_id in ids[:64])
            return len(answered) == 64

        assert until(robot, replies)
    finally:
        op.close()


@pytest.mark.req("SR-SEC-2")
def test_keepalives_are_counted_and_a_listed_input_is_taken_not_unexpected(robot: Robot) -> None:
    op = Peer(robot, "top", OPERATOR_HOST)
    viewer = Peer(robot, "top", OTHER_HOST)
    counters = robot.interfaces["top"].counters
    queue = robot.interfaces.commands
    try:
        for _ in range(3):
            assert ask(op, igtl.StatusMessage(code=1, header_version=2, message_id=3)) == []
        assert counters.keepalive == 3
        before = queue.received
        point = igtl.PointMessage(header_version=2, message_id=11)
        assert ask(viewer, point) == []  # a declared input: taken whatever the role
        assert queue.received - before == 2  # the point and the marker
        assert counters.unexpected == 0 and counters.refused == 0
    finally:
        op.close()
        viewer.close()


@pytest.mark.req("SR-SEC-3")
def test_the_return_channel_goes_signed_to_the_streams_owner_only(robot: Robot) -> None:
    """A master link's outputs (the slave's tip) go to the stream's owner, signed; before any
    master streamed there they have nowhere to go and are counted."""
    iface = robot.interfaces["master"]
    robot.state_machine.request("enable", "test")
    robot.state_machine.request("run", "test")
    tick(robot, 5)
    assert iface.counters.sent == 0  # one tip per sample: nobody streamed yet
    owner = Peer(robot, "master", OTHER_HOST, key=KEY)
    other = Peer(robot, "master", OTHER_HOST, key=KEY)
    try:
        seq = [0]

        def following() -> bool:
            # a sample a tick (at most 500: bounded), until the tip says the slave follows
            if seq[0] < 500:
                seq[0] += 1
                owner.send(_pose(seq[0]))
            owner.read()
            return any(m.metadata.get("following") == "1" for m in owner.got)

        assert until(robot, following)
        assert until(robot, lambda: (owner.read(), len(owner.got) >= 10)[1])
        assert {m.device_name for m in owner.got} == {"SlaveTip"}
        assert all(verify(m, KEY) == "" for m in owner.got)
        assert iface.counters.no_destination == 0 and iface.counters.sent >= 10
        assert iface.counters.send_dropped == 0
        assert iface.stats()["no_destination"] == iface.counters.no_destination
        other.send(_pose(9))  # dropped by the kernel: the socket is pinned to the owner
        tick(robot, 20)
        other.read()
        assert other.got == [] and iface.counters.received == seq[0]
    finally:
        owner.close()
        other.close()


@pytest.mark.req("SR-SEC-4", "SR-OWN-1")
@pytest.mark.parametrize("kernel_filter", [True, False])
def test_a_configured_stream_source_is_the_only_sender_from_the_start(
    tmp_path: Path, kernel_filter: bool
) -> None:
    source = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    source.bind((OTHER_HOST, 0))
    port = source.getsockname()[1]
    keyfile = tmp_path / "link.key"
    keyfile.write_text(KEY.decode() + "\n")
    text = _config_text(keyfile).replace(
        "kernel_filter: false,",
        f"kernel_filter: {str(kernel_filter).lower()}, stream_source: '127.0.0.1:{port}',",
    )
    r = build_robot(parse_config(text, base_dir=ROOT / "configs"), clock=SimClock())
    r.configure()
    r.activate()
    iface = r.interfaces["feed"]
    first = Peer(r, "feed", OTHER_HOST)  # another port of the same host, sending first
    try:
        assert iface.stream_owner == (OTHER_HOST, port)
        first.send(_pose(1))
        source.sendto(_pose(2).pack(), ("127.0.0.1", iface.address[1]))  # type: ignore[index]
        assert until(r, lambda: iface.stats()["streams"]["POSITION"]["received"] == 1)
        tick(r, 20)
        # the first sender is no owner: refused (counted where the kernel does not filter)
        assert iface.stream_owner == (OTHER_HOST, port)
        assert iface.counters.foreign == (0 if kernel_filter else 1)
        assert iface.stats()["streams"]["POSITION"]["received"] == 1
    finally:
        first.close()
        source.close()
        r.shutdown()


@pytest.mark.req("SR-SEC-3")
def test_a_keyed_udp_link_with_a_remote_sends_to_it_signed(tmp_path: Path) -> None:
    """A UDP interface with a ``remote`` (a sender, as the master's stream is) sends its
    outputs there, each with a valid tag."""
    receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    receiver.bind((OTHER_HOST, 0))
    receiver.settimeout(WAIT_S)
    keyfile = tmp_path / "link.key"
    keyfile.write_text(KEY.decode() + "\n")
    text = _config_text(keyfile).replace(
        "interfaces:\n",
        "interfaces:\n"
        "  - {name: uout, transport: udp, host: 127.0.0.1, port: 0, auth_key_file: "
        f"{keyfile}, remote: '127.0.0.1:{receiver.getsockname()[1]}',\n"
        "     outputs: [{type: TRANSFORM, device: Tip, source: tip, rate_hz: 1000}]}\n",
        1,
    )
    r = build_robot(parse_config(text, base_dir=ROOT / "configs"), clock=SimClock())
    r.configure()
    r.activate()
    try:
        tick(r, 3)
        got = [igtl.unpack(receiver.recv(65536)) for _ in range(3)]
        assert [m.device_name for m in got] == ["Tip"] * 3
        assert all(verify(m, KEY) == "" for m in got)
        iface = r.interfaces["uout"]
        assert (iface.counters.sent, iface.counters.no_destination) == (3, 0)
    finally:
        receiver.close()
        r.shutdown()


@pytest.mark.req("SR-SEC-3")
def test_a_links_outputs_wait_for_its_owner_and_go_to_it_alone(robot: Robot) -> None:
    """A UDP link without ``remote`` sends to its stream's owner only; until a sender owns the
    stream its outputs have nowhere to go: counted (``no_destination``), sent to nobody."""
    iface = robot.interfaces["feed"]
    listener = Peer(robot, "feed", OTHER_HOST)  # a socket that never sent: owns nothing
    try:
        tick(robot, 7)
        assert iface.counters.no_destination == 7 and iface.counters.sent == 0
        assert iface.stats()["no_destination"] == 7
        owner = Peer(robot, "feed", OTHER_HOST)
        try:
            owner.send(_pose(1))
            assert until(robot, lambda: (owner.read(), len(owner.got) >= 3)[1])
            assert {(m.message_type, m.device_name) for m in owner.got} == {("TRANSFORM", "Tip")}
            assert iface.counters.sent >= 3
            listener.read()
            assert listener.got == []
        finally:
            owner.close()
    finally:
        listener.close()


def test_a_pose_listed_on_a_command_queue_reaches_the_controller_with_its_reception_time(
    tmp_path: Path,
) -> None:
    """A master's POSITION listed on a command queue (no loss monitor on it) still reaches the
    controller as a typed sample stamped when it arrived: the slave follows, nothing faults."""
    keyfile = tmp_path / "link.key"
    keyfile.write_text(KEY.decode() + "\n")
    listed = INTERFACES.replace(
        "    auth_key_file: KEYFILE\n    inputs: [{type: POSITION, queue: stream, depth: 10}]",
        "    inputs: [{type: POSITION, queue: command, depth: 10}]",
    )
    assert listed != INTERFACES
    text = _config_text(keyfile, listed).replace("loss: {enabled: true", "loss: {enabled: false")
    r = build_robot(parse_config(text, base_dir=ROOT / "configs"), clock=SimClock())
    r.configure()
    r.activate()
    r.state_machine.request("enable", "test")
    r.state_machine.request("run", "test")
    master = Peer(r, "master", OTHER_HOST)
    ctrl = r.controller.controllers[0]
    try:
        for seq in range(1, 6):
            master.send(_pose(seq))
        assert until(r, lambda: ctrl.samples == 5)
        tick(r, 10)
        assert r.state is RobotState.RUNNING
        assert isinstance(ctrl.last_sample_t, float)
    finally:
        master.close()
        r.shutdown()


@pytest.mark.req("SR-SEC-1")
def test_a_pose_refused_on_a_stream_queue_is_answered_to_its_sender_alone() -> None:
    """The master of configs/master.yaml with its operators' TRANSFORM input on a stream queue:
    a TRANSFORM its controller refuses (a ``SlaveTip`` from an operator's connection) is
    answered to the client that sent it, never to the other clients."""
    text = (ROOT / "configs" / "master.yaml").read_text()
    text = text.replace(
        "{type: TRANSFORM, queue: command, depth: 16}",
        "{type: TRANSFORM, queue: stream, depth: 16}",
    ).replace("port: 18945", "port: 0")
    assert "{type: TRANSFORM, queue: stream" in text
    r = build_robot(parse_config(text, base_dir=ROOT / "configs"), clock=SimClock())
    r.configure()
    r.activate()
    sender, other = Peer(r, "operator", OTHER_HOST), Peer(r, "operator", OTHER_HOST)
    try:
        tip = igtl.TransformMessage.from_position(
            (0.0, 0.0, 0.0), device_name="SlaveTip", header_version=2, message_id=77
        )
        sender.send(tip)

        def refused() -> bool:
            sender.read()
            return any(
                m.message_type == "STATUS" and "is a slave's return stream" in m.status_message
                for m in sender.got
            )

        assert until(r, refused)
        tick(r, 20)
        other.read()
        assert [m for m in other.got if "return stream" in getattr(m, "status_message", "")] == []
    finally:
        sender.close()
        other.close()
        r.shutdown()


@pytest.mark.req("SR-SEC-7")
@pytest.mark.parametrize("iface", ["tkey", "ukey"])
def test_a_signed_request_is_obeyed_once_and_only_while_fresh(robot: Robot, iface: str) -> None:
    """A recorded signed Enable, sent again after the operator's Disable, must not power the
    robot: a repeat of a tag is a replay, and so is a request signed longer ago than the
    window (or ahead of the daemon's clock). Each is answered with why and counted."""
    import time

    peer = Peer(robot, iface, OTHER_HOST, key=KEY)
    counters = robot.interfaces[iface].counters
    try:
        enable = sign(command("Enable", peer.next_id()), KEY)  # stamped now, tagged
        assert _status(reply_to(peer, enable)) == "SUCCESS"
        assert robot.state is RobotState.ENABLED
        assert _status(reply_to(peer, command("Disable", peer.next_id()))) == "SUCCESS"
        assert robot.state is RobotState.READY
        replayed = answer_to(peer, enable)  # the same bytes again
        assert _status(replayed) == "FAIL"
        assert replayed.metadata["Error"] == (
            "COMMAND refused: a replay: this signed request was taken already"
        )
        assert robot.state is RobotState.READY and counters.replayed == 1
        now = time.time()
        for shift, tail in [
            (-60.0, " s ago (at most 30 s): a replay, or the clocks disagree"),
            (60.0, " s ahead of this clock (at most 30 s): the clocks disagree"),
        ]:
            msg = command("Enable", peer.next_id())
            stale = sign(dataclasses.replace(msg, timestamp=now + shift), KEY)
            reply = answer_to(peer, stale)
            err = reply.metadata["Error"]
            assert _status(reply) == "FAIL" and err.startswith("COMMAND refused: signed 60.")
            assert err.endswith(tail), err
            assert robot.state is RobotState.READY
        # a replayed query is answered in its own form: a STATUS that says access denied
        status = sign(query("GET_STATUS", peer.next_id()), KEY)
        assert answer_to(peer, status).code == igtl.StatusCode.OK
        again = answer_to(peer, status)
        assert again.code == igtl.StatusCode.ACCESS_DENIED
        assert again.status_message == (
            "GET_STATUS refused: a replay: this signed request was taken already"
        )
        assert counters.replayed == 4 and counters.unauthenticated == 0
        assert robot.interfaces[iface].stats()["replayed"] == 4
        # a fresh one is obeyed
        assert _status(reply_to(peer, command("Enable", peer.next_id()))) == "SUCCESS"
        assert robot.state is RobotState.ENABLED
    finally:
        peer.close()


@pytest.mark.req("SR-SEC-7")
def test_the_replay_window_is_the_interfaces_own(tmp_path: Path) -> None:
    """``auth_max_age_s`` sets the window: 5 s refuses a request signed 10 s ago, which the
    default 30 s takes."""
    import time

    keyfile = tmp_path / "link.key"
    keyfile.write_text(KEY.decode() + "\n")
    text = _config_text(
        keyfile,
        """
interfaces:
  - {name: short, transport: udp, host: 127.0.0.1, port: 0, role: operator,
     auth_key_file: KEYFILE, auth_max_age_s: 5}
  - {name: usual, transport: udp, host: 127.0.0.1, port: 0, role: operator,
     auth_key_file: KEYFILE}
  - {name: master, transport: udp, host: 127.0.0.1, port: 0,
     inputs: [{type: POSITION, queue: stream, depth: 10}]}
""",
    )
    r = build_robot(parse_config(text, base_dir=ROOT / "configs"), clock=SimClock())
    r.configure()
    r.activate()
    try:
        for name, code in [
            ("short", igtl.StatusCode.ACCESS_DENIED),
            ("usual", igtl.StatusCode.OK),
        ]:
            peer = Peer(r, name, OTHER_HOST, key=KEY)
            try:
                msg = query("GET_STATUS", peer.next_id())
                old = sign(dataclasses.replace(msg, timestamp=time.time() - 10.0), KEY)
                reply = answer_to(peer, old)
                assert reply.code == code, (name, reply.status_message)
                if name == "short":
                    assert reply.status_message.startswith("GET_STATUS refused: signed 10.")
                    assert reply.status_message.endswith(
                        " s ago (at most 5 s): a replay, or the clocks disagree"
                    )
            finally:
                peer.close()
    finally:
        r.shutdown()
