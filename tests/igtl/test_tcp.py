"""igtl.transport.tcp over 127.0.0.1 with ephemeral ports.

Synchronisation is by callbacks feeding a Condition (never by sleeping); every wait has a
timeout and every traffic loop a bound.
"""

from __future__ import annotations

import socket
import statistics
import struct
import threading
import time
from dataclasses import dataclass
from typing import Any, ClassVar

import pytest

import igtl
from igtl import wire
from igtl.errors import CRCError, DecodeError, TransportError
from igtl.transport import Peer, TCPClient, TCPServer
from occ_testkit.testing import wait_until as _wait

WAIT = 5.0


class Recorder:
    """Callbacks that record into lists under one Condition, and a way to wait on them."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.messages: list[tuple[Peer, igtl.Message]] = []
        self.connects: list[Peer] = []
        self.disconnects: list[tuple[Peer, str]] = []
        self.errors: list[tuple[Peer | None, BaseException]] = []

    def _add(self, items: list[Any], item: Any) -> None:
        with self.cond:
            items.append(item)
            self.cond.notify_all()

    def on_message(self, peer: Peer, msg: igtl.Message) -> None:
        self._add(self.messages, (peer, msg))

    def on_connect(self, peer: Peer) -> None:
        self._add(self.connects, peer)

    def on_disconnect(self, peer: Peer, reason: str) -> None:
        self._add(self.disconnects, (peer, reason))

    def on_error(self, peer: Peer | None, exc: BaseException) -> None:
        self._add(self.errors, (peer, exc))

    def callbacks(self, *names: str) -> dict[str, Any]:
        names = names or ("on_message", "on_connect", "on_disconnect", "on_error")
        return {n: getattr(self, n) for n in names}

    def wait(self, predicate: Any, timeout: float = WAIT) -> bool:
        with self.cond:
            return self.cond.wait_for(predicate, timeout)

    def wait_messages(self, n: int, timeout: float = WAIT) -> list[igtl.Message]:
        assert self.wait(lambda: len(self.messages) >= n, timeout), (
            f"got {len(self.messages)} of {n} messages"
        )
        return [m for _, m in self.messages]


@pytest.fixture
def stack():
    """Start transports through this and they are stopped after the test, even on failure."""
    started: list[Any] = []

    def start(obj: Any) -> Any:
        started.append(obj)
        return obj.start()

    yield start
    for obj in reversed(started):
        obj.stop()


def raw_connect(address: tuple[str, int], rcvbuf: int | None = None) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    if rcvbuf:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    sock.settimeout(WAIT)
    sock.connect(address)
    return sock


def read_until_eof(sock: socket.socket, limit: int = 1 << 20) -> bytes:
    """Everything the server sends until it closes (a reset counts as the end too)."""
    data = b""
    try:
        while len(data) < limit:
            chunk = sock.recv(65536)
            if not chunk:
                break
            data += chunk
    except ConnectionResetError:
        pass
    return data


def text(s: str, **kw: Any) -> igtl.StringMessage:
    return igtl.StringMessage(string=s, **kw)


def connect_named(stack: Any, server: TCPServer, server_rec: Recorder, names: list[str]):
    """Clients that announce their name, so the test knows which server Peer is which."""
    clients = {}
    for name in names:
        rec = Recorder()
        client = stack(TCPClient(*server.address, **rec.callbacks()))
        assert client.wait_connected(WAIT)
        clients[name] = (client, rec)
        client.send(text(name, device_name="hello"))
    server_rec.wait_messages(len(names))
    peers = {m.string: p for p, m in server_rec.messages if m.device_name == "hello"}
    return clients, peers


# ------------------------------------------------------------------------- basic traffic
def test_send_to_one_and_to_all(stack):
    srec = Recorder()
    server = stack(TCPServer(port=0, **srec.callbacks()))
    assert server.address[1] != 0
    clients, peers = connect_named(stack, server, srec, ["a", "b", "c"])
    assert server.wait_for_peers(3, WAIT) and len(server.peers) == 3
    assert len({p.id for p in server.peers}) == 3

    assert server.send(text("to b"), peers["b"]) == 1
    assert server.send(text("to c"), peers["c"].id) == 1
    assert server.send(text("to all")) == 3
    assert server.send(text("nobody"), 987654) == 0

    assert [m.string for m in clients["a"][1].wait_messages(1)] == ["to all"]
    assert [m.string for m in clients["b"][1].wait_messages(2)] == ["to b", "to all"]
    assert [m.string for m in clients["c"][1].wait_messages(2)] == ["to c", "to all"]
    # ``sent`` is counted by the I/O thread just after the write; one more round trip through
    # that thread makes sure it has been counted.
    clients["a"][0].send(text("sync"))
    srec.wait_messages(4)
    stats = server.stats()
    assert stats["received"] == 4 and stats["clients"] == 3 and stats["connections"] == 3
    assert stats["sent"] == 5 and stats["malformed"] == 0 and len(stats["peers"]) == 3
    assert clients["a"][0].stats()["received"] == 1


def test_inbox_receive_and_client_peer(stack):
    server = stack(TCPServer(port=0))
    client = stack(TCPClient(*server.address))
    assert client.wait_connected(WAIT) and server.wait_for_peers(1, WAIT)
    assert client.peer is not None and client.peer.address == server.address
    assert client.send(igtl.TransformMessage.from_position((1, 2, 3), device_name="Tip"))
    got = server.receive(timeout=WAIT)
    assert got is not None
    peer, msg = got
    assert peer is server.peers[0] and msg.translation == (1.0, 2.0, 3.0)
    assert server.receive(timeout=0) is None
    server.send(text("back"))
    got = client.receive(timeout=WAIT)
    assert got is not None and got[1].string == "back" and got[0] is client.peer


def test_stream_split_byte_by_byte(stack):
    srec = Recorder()
    server = stack(TCPServer(port=0, **srec.callbacks("on_message")))
    data = text("split", device_name="d").pack() + text("x" * 300).pack(2)
    with raw_connect(server.address) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for i in range(len(data)):
            sock.sendall(data[i : i + 1])
        msgs = srec.wait_messages(2)
    assert msgs[0].string == "split" and msgs[1].string == "x" * 300


# ------------------------------------------------------------------------- negotiation
@dataclass(frozen=True, slots=True)
class CountingString(igtl.StringMessage):
    """A STRING that counts how often it is packed (receivers decode a plain StringMessage)."""

    packs: ClassVar[list[int]] = []

    def pack_content(self) -> bytes:
        CountingString.packs.append(1)
        return igtl.StringMessage.pack_content(self)


def test_per_client_header_version_negotiation(stack):
    srec = Recorder()
    server = stack(TCPServer(port=0, **srec.callbacks()))
    clients, peers = connect_named(stack, server, srec, ["old1", "old2", "new"])
    assert all(p.header_version == 1 for p in peers.values())

    # "new" speaks v2 (like Slicer's first STATUS); the others stay on v1.
    clients["new"][0].send(igtl.StatusMessage(header_version=2, metadata={"dummy": "dummy"}))
    srec.wait_messages(4)
    assert peers["new"].header_version == 2
    assert peers["old1"].header_version == peers["old2"].header_version == 1

    CountingString.packs.clear()
    msg = CountingString(string="pose", header_version=2, metadata={"Status": "OK"}, message_id=9)
    assert server.send(msg) == 3
    assert len(CountingString.packs) == 2  # once per header version, not once per client

    (new_msg,) = clients["new"][1].wait_messages(1)
    assert new_msg.header_version == 2 and dict(new_msg.metadata) == {"Status": "OK"}
    assert new_msg.message_id == 9
    for name in ("old1", "old2"):
        (old_msg,) = clients[name][1].wait_messages(1)
        assert old_msg.header_version == 1 and dict(old_msg.metadata) == {}
        assert old_msg.string == "pose"

    # A v1 message to a v2 client goes out as v2.
    server.send(text("plain"), peers["new"])
    assert clients["new"][1].wait_messages(2)[1].header_version == 2


def test_negotiate_false_sends_each_message_in_its_own_version(stack):
    server = stack(TCPServer(port=0, negotiate=False))
    rec = Recorder()
    client = stack(TCPClient(*server.address, **rec.callbacks("on_message")))
    assert client.wait_connected(WAIT) and server.wait_for_peers(1, WAIT)
    server.send(text("v2", header_version=2, metadata={"a": "b"}))
    assert rec.wait_messages(1)[0].header_version == 2


# ------------------------------------------------------------------------- slow client
def test_slow_client_loses_its_oldest_data_and_never_blocks_the_sender(stack):
    """A client that never reads fills the kernel buffers, then its queue drops its oldest
    messages, counted. The fast client gets everything, in order, and send() stays fast."""
    queue = 16
    server = stack(TCPServer(port=0, send_queue=queue))
    slow = raw_connect(server.address, rcvbuf=4096)  # small window, never read (until the end)
    assert server.wait_for_peers(1, WAIT)
    (slow_peer,) = server.peers
    rec = Recorder()
    stack(TCPClient(*server.address, **rec.callbacks("on_message")))
    assert server.wait_for_peers(2, WAIT)
    fast_peer = next(p for p in server.peers if p is not slow_peer)

    payload = bytes(128 * 1024)
    durations: list[float] = []
    sent = 0
    max_messages = 600  # bound: 77 MB; dropping usually starts after ~5 MB (kernel buffers)
    try:
        while sent < max_messages and slow_peer.dropped < 20:
            msg = igtl.RawMessage(type_name="BLOB", content=sent.to_bytes(4, "big") + payload)
            t0 = time.perf_counter()
            assert server.send(msg) == 2
            durations.append(time.perf_counter() - t0)
            sent += 1
            if sent % (queue // 2) == 0:  # keep the fast client's queue below its limit
                assert rec.wait(lambda n=sent: len(rec.messages) >= n - queue // 2)
        got = rec.wait_messages(sent)
        assert [int.from_bytes(m.content[:4], "big") for m in got] == list(range(sent))
        assert slow_peer.dropped >= 20 and fast_peer.dropped == 0
        assert server.stats()["dropped"] == slow_peer.dropped

        # Now drain the slow client: it gets exactly what was not dropped, oldest ones missing,
        # newest ones present, in order.
        slow.settimeout(WAIT)
        decoder = igtl.StreamDecoder()
        indices: list[int] = []
        expected = sent - slow_peer.dropped
        while len(indices) < expected:
            chunk = slow.recv(1 << 20)
            assert chunk, "server closed the slow client"
            decoder.feed(chunk)
            indices.extend(int.from_bytes(m.content[:4], "big") for m in decoder)
        assert len(indices) == expected == sent - slow_peer.dropped
        assert indices == sorted(indices) and indices[-1] == sent - 1
        assert indices[-queue:] == list(range(sent - queue, sent))  # the newest survive
    finally:
        slow.close()

    # send() is an enqueue: its cost does not grow once the slow client is saturated.
    early = statistics.median(durations[:queue])
    late = statistics.median(durations[-queue:])
    assert max(durations) < 1.0
    assert late < 20 * early + 0.002, (early, late)


# ------------------------------------------------------------------------- garbage
def _bad_crc(msg: igtl.Message) -> bytes:
    data = bytearray(msg.pack())
    data[50:58] = struct.pack(">Q", wire.HEADER.unpack_from(data)[5] ^ 1)
    return bytes(data)


def test_recoverable_garbage_is_counted_and_connection_kept(stack):
    srec = Recorder()
    server = stack(TCPServer(port=0, **srec.callbacks()))
    with raw_connect(server.address) as sock:
        sock.sendall(_bad_crc(text("bad")) + text("good").pack())
        msgs = srec.wait_messages(1)
        assert msgs[0].string == "good"
        assert srec.wait(lambda: len(srec.errors) == 1)
        peer, err = srec.errors[0]
        assert isinstance(err, CRCError) and err.recoverable
        assert peer is not None and peer.malformed == 1 and peer.received == 1
        assert peer in server.peers and srec.disconnects == []
        # Still usable in both directions.
        assert server.send(text("still here"), peer) == 1
        sock.settimeout(WAIT)
        dec = igtl.StreamDecoder()
        while not (got := list(dec)):
            dec.feed(sock.recv(4096))
        assert got[0].string == "still here"
    assert server.stats()["malformed"] == 1


@pytest.mark.parametrize(
    "garbage",
    [
        struct.pack(">H12s20sQQQ", 7, b"STRING", b"", 0, 4, 0) + bytes(4),  # unknown version
        struct.pack(">H12s20sQQQ", 1, b"IMAGE", b"", 0, 1 << 40, 0),  # 1 TiB body announced
        b"GET / HTTP/1.1\r\nHost: robot\r\n\r\n" + bytes(64),  # a confused web client
    ],
    ids=["bad-version", "huge-body", "http"],
)
def test_unrecoverable_garbage_closes_only_that_connection(stack, garbage, caplog):
    srec = Recorder()
    server = stack(TCPServer(port=0, **srec.callbacks()))
    crec = Recorder()
    good = stack(TCPClient(*server.address, reconnect=False, **crec.callbacks()))
    assert good.wait_connected(WAIT) and server.wait_for_peers(1, WAIT)
    with raw_connect(server.address) as sock:
        assert server.wait_for_peers(2, WAIT)
        sock.sendall(garbage)
        read_until_eof(sock)  # the server closes it
    assert srec.wait(lambda: len(srec.disconnects) == 1)
    peer, reason = srec.disconnects[0]
    assert reason.startswith("protocol error")
    assert len(srec.errors) == 1 and isinstance(srec.errors[0][1], DecodeError)
    assert not srec.errors[0][1].recoverable and peer.malformed == 1
    assert f"{peer.address[0]}:{peer.address[1]}" in caplog.text
    # The other client is untouched.
    assert good.connected and len(server.peers) == 1
    assert server.send(text("hello")) == 1
    assert crec.wait_messages(1)[0].string == "hello"
    assert server.stats()["malformed"] == 1


def test_truncated_message_at_disconnect_is_reported(stack):
    srec = Recorder()
    server = stack(TCPServer(port=0, **srec.callbacks()))
    with raw_connect(server.address) as sock:
        sock.sendall(text("cut").pack()[:-2])
    assert srec.wait(lambda: len(srec.disconnects) == 1)
    assert srec.disconnects[0][1] == "closed by peer"
    assert isinstance(srec.errors[0][1], igtl.TruncatedMessageError)


def test_callback_exceptions_are_counted_and_harmless(stack, caplog):
    calls = []
    done = threading.Event()

    def explode(peer: Peer, msg: igtl.Message) -> None:
        calls.append(msg)
        if len(calls) == 2:
            done.set()
        raise RuntimeError("user bug")

    server = stack(TCPServer(port=0, on_message=explode, on_connect=lambda p: 1 / 0))
    client = stack(TCPClient(*server.address))
    assert client.wait_connected(WAIT)
    client.send(text("1"))
    client.send(text("2"))
    assert done.wait(WAIT)
    assert server.stats()["callback_errors"] >= 3  # on_connect + two on_message
    assert "user bug" in caplog.text
    server.send(text("alive"))
    assert client.receive(WAIT) is not None


# ------------------------------------------------------------------------- admission
def test_allowed_peers_denies_with_status_access_denied(stack, caplog):
    srec = Recorder()
    server = stack(TCPServer(port=0, allowed_peers=["10.0.0.0/8"], **srec.callbacks()))
    with raw_connect(server.address) as sock:
        local = sock.getsockname()
        data = read_until_eof(sock)
    msg = igtl.unpack(data)
    assert isinstance(msg, igtl.StatusMessage)
    assert msg.code == igtl.StatusCode.ACCESS_DENIED == 5 and msg.error_name == "ACCESS_DENIED"
    stats = server.stats()
    assert stats["denied"] == 1 and stats["clients"] == 0 and srec.connects == []
    assert f"127.0.0.1:{local[1]}" in caplog.text


def test_allowed_peers_admits_matching_address(stack):
    server = stack(TCPServer(port=0, allowed_peers=["192.168.0.0/16", "127.0.0.1"]))
    client = stack(TCPClient(*server.address))
    assert client.wait_connected(WAIT) and server.wait_for_peers(1, WAIT)


def test_max_clients_rejects_the_excess(stack, caplog):
    srec = Recorder()
    server = stack(TCPServer(port=0, max_clients=1, **srec.callbacks()))
    first = stack(TCPClient(*server.address))
    assert first.wait_connected(WAIT) and server.wait_for_peers(1, WAIT)
    with raw_connect(server.address) as sock:
        assert read_until_eof(sock) == b""
    stats = server.stats()
    assert stats["rejected"] == 1 and stats["clients"] == 1 and stats["connections"] == 2
    assert "max_clients" in caplog.text
    assert first.connected and server.send(text("x")) == 1
    assert first.receive(WAIT) is not None


def test_idle_timeout_closes_silent_clients(stack):
    srec = Recorder()
    server = stack(TCPServer(port=0, idle_timeout=0.2, **srec.callbacks()))
    with raw_connect(server.address) as sock:
        t0 = time.monotonic()
        assert read_until_eof(sock) == b""
        elapsed = time.monotonic() - t0
    assert srec.wait(lambda: len(srec.disconnects) == 1)
    assert srec.disconnects[0][1] == "idle timeout"
    assert 0.15 < elapsed < WAIT


# ------------------------------------------------------------------------- client
def test_client_reconnects_after_server_restart(stack):
    srec1 = Recorder()
    server1 = stack(TCPServer(port=0, **srec1.callbacks("on_message")))
    port = server1.address[1]
    crec = Recorder()
    client = stack(TCPClient("127.0.0.1", port, backoff=(0.02, 0.1), **crec.callbacks()))
    assert crec.wait(lambda: len(crec.connects) == 1)
    assert client.send(text("one"))
    srec1.wait_messages(1)

    server1.stop()
    assert crec.wait(lambda: len(crec.disconnects) == 1)
    assert crec.disconnects[0][1] == "closed by peer"
    assert not client.connected
    assert client.send(text("lost")) == 0
    assert client.stats()["dropped"] >= 1

    srec2 = Recorder()
    server2 = stack(TCPServer(port=port, **srec2.callbacks("on_message")))
    assert crec.wait(lambda: len(crec.connects) == 2), client.stats()
    assert client.wait_connected(WAIT) and server2.wait_for_peers(1, WAIT)
    assert client.send(text("two"))
    assert [m.string for m in srec2.wait_messages(1)] == ["two"]
    stats = client.stats()
    # every refused attempt while the server was down is counted and reported, one for one
    refused = [err for peer, err in crec.errors if peer is None]
    assert all(isinstance(err, TransportError) for err in refused)
    assert stats["connects"] == 2 and stats["connect_failures"] == len(refused)
    assert crec.connects[0] is not crec.connects[1]


def test_client_stop_while_connecting_is_prompt(stack):
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    listener.close()  # nothing listens there now: connects fail, client backs off
    rec = Recorder()
    client = TCPClient("127.0.0.1", port, backoff=(1.0, 1.0), **rec.callbacks("on_error")).start()
    assert rec.wait(lambda: len(rec.errors) == 1)  # the refused attempt is reported
    peer, err = rec.errors[0]
    assert peer is None and isinstance(err, TransportError) and not client.connected
    assert client.stats()["connect_failures"] == 1
    t0 = time.monotonic()
    client.stop()
    assert time.monotonic() - t0 < 1.0
    client.stop()  # twice is fine
    assert client.send(text("x")) == 0


def test_context_managers_and_double_stop():
    with TCPServer(port=0) as server, TCPClient(*server.address) as client:
        assert client.wait_connected(WAIT)
    server.stop()
    client.stop()
    assert server.peers == [] and server.send(text("x")) == 0


def test_bind_error_raises_in_start():
    with TCPServer(port=0) as server:
        other = TCPServer(port=server.address[1])
        with pytest.raises(OSError):
            other.start()
        other.stop()


def test_bad_arguments():
    with pytest.raises(ValueError):
        TCPServer(port=0, max_clients=0)
    with pytest.raises(ValueError):
        TCPServer(port=0, allowed_peers=["not an ip"])
    with pytest.raises(TypeError):
        TCPServer(port=0, allowed_peers="10.0.0.0/8")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        TCPClient("127.0.0.1", 1, backoff=(0, 1))
    with TCPServer(port=0) as server:
        with pytest.raises(TypeError):
            server.send(object())  # type: ignore[arg-type]
        with pytest.raises(RuntimeError):
            server.start()


def test_server_can_disconnect_one_client(stack):
    srec = Recorder()
    server = stack(TCPServer(port=0, **srec.callbacks("on_disconnect")))
    crec = Recorder()
    stack(TCPClient(*server.address, reconnect=False, **crec.callbacks()))
    assert server.wait_for_peers(1, WAIT)
    server.disconnect(server.peers[0], reason="operator request")
    assert srec.wait(lambda: len(srec.disconnects) == 1)
    assert srec.disconnects[0][1] == "operator request"
    assert crec.wait(lambda: len(crec.disconnects) == 1)
    assert crec.disconnects[0][1] == "closed by peer"


def test_a_client_trickling_a_message_is_closed_and_its_slot_freed() -> None:
    with TCPServer("127.0.0.1", 0, max_clients=1, message_timeout=0.3) as server:
        slow = socket.create_connection(server.address)
        data = igtl.StringMessage("hello", device_name="x").pack()
        slow.sendall(data[:10])  # a header begun, never finished (slowloris)
        assert server.wait_for_peers(1)
        assert _wait(lambda: server.stats()["slow_message_closed"] == 1)
        assert _wait(lambda: server.stats()["clients"] == 0)
        # the slot is free again for a real client
        with TCPClient(*server.address, reconnect=False) as client:
            assert client.wait_connected(5.0)
        slow.close()


def test_a_client_that_never_reads_is_evicted() -> None:
    with TCPServer("127.0.0.1", 0, send_stall_timeout=0.3, send_queue=4) as server:
        deaf = socket.create_connection(server.address)
        deaf.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        assert server.wait_for_peers(1)
        big = igtl.StringMessage("x" * 60000, device_name="x")
        # keep sending until its socket stops taking data, then it must go
        assert _wait(lambda: server.send(big) == 0 or server.stats()["evicted_not_reading"] == 1)
        assert _wait(lambda: server.stats()["evicted_not_reading"] == 1)
        assert server.stats()["clients"] == 0
        deaf.close()


@pytest.mark.parametrize("rcvbuf", [None, 2048])
def test_a_client_that_never_reads_a_slow_stream_is_evicted_and_a_reader_is_not(
    rcvbuf: int | None,
) -> None:
    """A pose stream of a few kB/s never blocks our writes (kernel buffers hold minutes of
    it); the client's shrinking receive window shows it does not read. A client that reads
    the same stream keeps its slot."""
    with TCPServer(
        "127.0.0.1", 0, send_stall_timeout=0.3, unread_limit=8 * 1024
    ) as server:
        deaf = socket.socket()
        if rcvbuf:  # a tiny buffer: its window closes, our bytes wait unsent
            deaf.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        deaf.connect(server.address)
        got: list[igtl.Message] = []
        reader = TCPClient(*server.address, reconnect=False, on_message=lambda p, m: got.append(m))
        reader.start()
        assert server.wait_for_peers(2)
        pose = igtl.StringMessage("p" * 1000, device_name="Tip")
        sent = 0
        deadline = time.monotonic() + 20.0
        while server.stats()["evicted_not_reading"] == 0 and time.monotonic() < deadline:
            server.send(pose)
            sent += 1
            time.sleep(0.005)
        stats = server.stats()
        assert stats["evicted_not_reading"] == 1, f"not evicted after {sent} messages"
        assert stats["clients"] == 1 and reader.connected
        assert _wait(lambda: len(got) >= sent - 5)  # the reader kept up and stays
        reader.stop()
        deaf.close()


def test_a_reader_that_got_one_big_answer_and_is_sent_nothing_more_keeps_its_slot(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """After a big answer read at once, a client that sends nothing may leave us a stale,
    shrunken window (its next ACK would reopen it; measured here after three 40 kB answers:
    7 kB "unread" though all was read): without further sends that is no proof it does not
    read (the staff console was closed every 10-40 s after a GetStats answer). The kernel's
    window is replaced by that stale reading, so the test does not depend on ACK timing."""
    with TCPServer("127.0.0.1", 0, send_stall_timeout=0.2, unread_limit=4 * 1024) as server:
        got: list[igtl.Message] = []
        reader = TCPClient(*server.address, reconnect=False, on_message=lambda p, m: got.append(m))
        reader.start()
        assert server.wait_for_peers(1)
        server.send(igtl.StringMessage("s" * 40000, device_name="Stats"))
        assert _wait(lambda: len(got) == 1)
        from igtl.transport.common import Connection

        monkeypatch.setattr(Connection, "unread_bytes", lambda self: (7168, 0))
        time.sleep(1.0)  # five stall periods with nothing more sent
        assert server.stats()["evicted_not_reading"] == 0 and reader.connected
        # the same reading while we go on sending: now it is evidence
        deadline = time.monotonic() + 5.0
        while server.stats()["evicted_not_reading"] == 0 and time.monotonic() < deadline:
            server.send(igtl.StringMessage("p", device_name="Tip"))
            time.sleep(0.02)
        assert server.stats()["evicted_not_reading"] == 1
        reader.stop()


def test_incomplete_messages_over_all_clients_stay_within_the_budget() -> None:
    """Each client just under the body limit, together over the interface's budget: the one
    that goes over is closed and counted; the others are untouched."""
    with TCPServer("127.0.0.1", 0, max_body_size=1 << 20, max_buffered=3 << 19) as server:
        body = 1 << 19  # 512 KiB each: two fit in 1.5 MiB, the third does not
        header = igtl.wire.pack_header(1, "STRING", "x", 0, b"\0" * body)
        socks = [socket.create_connection(server.address) for _ in range(3)]
        try:
            assert server.wait_for_peers(3)
            for s in socks[:2]:
                s.sendall(header + b"\0" * (body - 10))
            assert _wait(lambda: sum(1 for p in server.peers) == 3)
            socks[2].sendall(header + b"\0" * (body - 10))
            assert _wait(lambda: server.stats()["over_budget"] == 1)
            assert server.stats()["clients"] == 2
        finally:
            for s in socks:
                s.close()


def test_transport_threads_carry_their_names_in_the_os() -> None:
    """`top -H` and py-spy show which thread is which (Python 3.11 names threads only for
    itself): the I/O thread of a server named igtl-x is `x` in /proc."""
    import os
    from pathlib import Path

    with TCPServer("127.0.0.1", 0, name="igtl-viewer") as server:
        thread = server.thread
        assert thread is not None and thread.native_id is not None
        comm = Path(f"/proc/{os.getpid()}/task/{thread.native_id}/comm")
        if not comm.exists():
            pytest.skip("no /proc on this platform")
        assert _wait(lambda: comm.read_text().strip() == "viewer")
