"""igtl.transport.inproc: named channels, the real codec, synchronous delivery, no sockets."""

from __future__ import annotations

import errno
import itertools
import threading
from typing import Any

import pytest

import igtl
from igtl.errors import CRCError
from igtl.transport import InprocTransport, Peer
from igtl.transport.inproc import channel_endpoints

_names = itertools.count()


@pytest.fixture
def channel() -> str:
    return f"test-inproc-{next(_names)}"


class Log:
    def __init__(self) -> None:
        self.messages: list[tuple[Peer, igtl.Message]] = []
        self.connects: list[Peer] = []
        self.disconnects: list[tuple[Peer, str]] = []
        self.errors: list[tuple[Peer | None, BaseException]] = []

    def callbacks(self) -> dict[str, Any]:
        return {
            "on_message": lambda p, m: self.messages.append((p, m)),
            "on_connect": self.connects.append,
            "on_disconnect": lambda p, r: self.disconnects.append((p, r)),
            "on_error": lambda p, e: self.errors.append((p, e)),
        }


def test_endpoints_on_a_channel_connect_both_ways_and_deliver_at_once(channel: str) -> None:
    a_log, b_log = Log(), Log()
    a = InprocTransport(channel, address=("127.0.0.1", 1000), **a_log.callbacks()).start()
    b = InprocTransport(channel, negotiate=False, **b_log.callbacks()).start()
    assert [p.address for p in a_log.connects] == [b.address]
    assert [p.address for p in b_log.connects] == [("127.0.0.1", 1000)]
    assert channel_endpoints(channel) == [a.address, b.address]
    msg = igtl.StringMessage("hello", device_name="Greeting", header_version=2)
    assert b.send(msg) == 1  # delivered when send returns: no thread, no wait
    (peer, got), = a_log.messages
    assert got == igtl.unpack(msg.pack()) and peer is a.peers[0]
    assert peer.received == 1 and peer.header_version == 2  # raised by what it sent
    assert b.stats()["sent"] == 1 and a.stats()["received"] == 1
    b.stop()
    assert a_log.disconnects == [(peer, "closed by peer")]
    assert b_log.disconnects[0][1] == "stopped"
    assert a.peers == [] and a.send(msg) == 0
    a.stop()
    assert channel_endpoints(channel) == []


def test_replies_reach_only_the_peer_who_asked(channel: str) -> None:
    def answer(peer: Peer, msg: igtl.Message) -> None:
        server.send(igtl.StringMessage(f"re: {msg.string}", device_name="Answer"), peer)

    server = InprocTransport(channel, on_message=answer).start()
    logs = [Log(), Log(), Log()]
    clients = [InprocTransport(channel, listen=False, **log.callbacks()).start() for log in logs]
    assert clients[1].send(igtl.StringMessage("one", device_name="Q")) == 1
    # the other clients hear nothing: clients connect to listeners only
    assert [m.string for _, m in logs[1].messages] == ["re: one"]
    assert logs[0].messages == [] and logs[2].messages == []
    assert server.send(igtl.StringMessage("all", device_name="B")) == 3
    assert all(log.messages[-1][1].string == "all" for log in logs)
    for ep in (*clients, server):
        ep.stop()


def test_a_reply_from_a_callback_is_delivered_after_it_in_order(channel: str) -> None:
    order: list[str] = []

    def server_rx(peer: Peer, msg: igtl.Message) -> None:
        order.append(f"server got {msg.string}")
        server.send(igtl.StringMessage("ack", device_name="A"), peer)
        order.append("server callback done")

    server = InprocTransport(channel, on_message=server_rx).start()
    client = InprocTransport(
        channel, on_message=lambda p, m: order.append(f"client got {m.string}")
    ).start()
    client.send(igtl.StringMessage("q", device_name="Q"))
    assert order == ["server got q", "server callback done", "client got ack"]
    client.stop()
    server.stop()


def test_negotiation_answers_each_peer_in_its_version(channel: str) -> None:
    server = InprocTransport(channel).start()
    old_log, new_log = Log(), Log()
    client: dict[str, Any] = {"listen": False, "negotiate": False}
    old = InprocTransport(channel, header_version=1, **client, **old_log.callbacks()).start()
    new = InprocTransport(channel, header_version=2, **client, **new_log.callbacks()).start()
    status = igtl.StatusMessage(code=1, device_name="S", header_version=2, metadata={"k": "v"})
    assert server.send(status) == 2
    assert old_log.messages[-1][1].header_version == 1 and old_log.messages[-1][1].metadata == {}
    assert new_log.messages[-1][1].metadata == {"k": "v"}
    old.send(igtl.StringMessage("now v2", device_name="S", header_version=2))
    server.send(status)
    assert old_log.messages[-1][1].metadata == {"k": "v"}
    # without negotiation every message goes in its own version, whatever the peer announced
    plain = InprocTransport(channel, negotiate=False).start()  # listens: meets the clients
    assert plain.send(status, plain.peers[1].id) == 1
    assert old_log.messages[-1][1].header_version == 2
    for ep in (old, new, plain, server):
        ep.stop()


def test_bad_bytes_are_counted_and_reported_never_raised_into_the_sender(channel: str) -> None:
    rx_log = Log()
    rx = InprocTransport(channel, **rx_log.callbacks()).start()
    tx = InprocTransport(channel).start()
    data = bytearray(igtl.StringMessage("x", device_name="S").pack())
    data[-1] ^= 0xFF
    assert tx.send(bytes(data)) == 1
    assert tx.send(b"\x00\x01garbage") == 1
    peer = rx.peers[0]
    assert peer.malformed == 2 and peer.received == 0 and not rx_log.messages
    assert isinstance(rx_log.errors[0][1], CRCError)
    with pytest.raises(TypeError):
        tx.send("text")  # type: ignore[arg-type]
    tx.stop()
    rx.stop()


def test_admission_address_in_use_access_list_and_limit(channel: str) -> None:
    server = InprocTransport(channel, allowed_peers=["127.0.0.1"], max_peers=1).start()
    with pytest.raises(OSError) as err:
        InprocTransport(channel, address=server.address).start()
    assert err.value.errno == errno.EADDRINUSE
    outsider = InprocTransport(channel, address=("10.1.2.3", 5)).start()
    first = InprocTransport(channel).start()
    second = InprocTransport(channel).start()
    assert [p.address for p in server.peers] == [first.address]
    stats = server.stats()
    assert stats["denied"] == 1 and stats["rejected"] == 1 and stats["clients"] == 1
    assert outsider.send(igtl.StringMessage("x", device_name="S")) == 2  # first and second
    for ep in (outsider, first, second, server):
        ep.stop()


def test_unknown_peer_inbox_lifecycle_and_stats(channel: str) -> None:
    rx = InprocTransport(channel).start()  # no on_message: the inbox
    tx = InprocTransport(channel).start()
    stranger = Peer(999, ("127.0.0.1", 1))
    assert tx.send(igtl.StringMessage("x", device_name="S"), stranger) == 0
    assert tx.stats()["unrouted"] == 1
    tx.send(igtl.StringMessage("y", device_name="S"))
    got = rx.receive(timeout=0)
    assert got is not None and got[1].string == "y" and rx.receive(timeout=0) is None
    assert rx.thread is None and rx.poll() == 0
    with pytest.raises(RuntimeError):
        rx.start()
    tx.stop()
    tx.stop()  # twice is fine
    stats = rx.stats()
    assert stats["received"] == 1 and stats["clients"] == 0 and stats["connections"] == 1
    rx.stop()
    with InprocTransport(channel) as ep:
        assert ep.started
    assert not ep.started
    never = InprocTransport(channel)
    never.stop()
    with pytest.raises(RuntimeError):
        never.start()
    with pytest.raises(ValueError):
        InprocTransport("")


def test_concurrent_senders_each_deliver_everything(channel: str) -> None:
    got: list[str] = []
    rx = InprocTransport(channel, on_message=lambda p, m: got.append(m.string)).start()
    senders = [InprocTransport(channel, negotiate=False).start() for _ in range(2)]

    def blast(ep: InprocTransport, tag: str) -> None:
        for i in range(300):
            ep.send(igtl.StringMessage(f"{tag}{i}", device_name="S"), ep.peers[0])

    threads = [threading.Thread(target=blast, args=(s, t)) for s, t in zip(senders, "ab", strict=True)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10.0)
    assert sorted(got) == sorted(f"{t}{i}" for t in "ab" for i in range(300))
    # each sender's messages arrive in its order
    assert [g for g in got if g[0] == "a"] == [f"a{i}" for i in range(300)]
    for ep in (*senders, rx):
        ep.stop()
