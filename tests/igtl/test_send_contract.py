"""Every transport's ``send(msg, peer=None) -> int``, back to back (python-can's back2back test):
a daemon-side endpoint answers each request to the peer that sent it, whatever the transport.

TCP and UDP run on 127.0.0.1 with ephemeral ports, synchronised by a Condition (never a sleep);
the in-process transport delivers before ``send`` returns.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import pytest

import igtl
from igtl.transport import InprocTransport, Peer, TCPClient, TCPServer, UDPEndpoint

WAIT = 5.0
_channels = itertools.count()


class Inbox:
    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.got: list[str] = []

    def __call__(self, peer: Peer, msg: igtl.Message) -> None:
        with self.cond:
            self.got.append(msg.string)
            self.cond.notify_all()

    def wait(self, n: int) -> list[str]:
        with self.cond:
            assert self.cond.wait_for(lambda: len(self.got) >= n, WAIT), self.got
            return list(self.got)


Pair = tuple[Any, list[Any]]  # the daemon-side endpoint and its clients


@contextmanager
def tcp(answer: Callable[[Peer, igtl.Message], None], inboxes: list[Inbox]) -> Iterator[Pair]:
    server = TCPServer("127.0.0.1", 0, on_message=answer).start()
    clients = [TCPClient("127.0.0.1", server.address[1], on_message=i).start() for i in inboxes]
    try:
        assert all(c.wait_connected(WAIT) for c in clients)
        assert server.wait_for_peers(len(clients), WAIT)
        yield server, clients
    finally:
        for ep in (*clients, server):
            ep.stop()


@contextmanager
def udp(answer: Callable[[Peer, igtl.Message], None], inboxes: list[Inbox]) -> Iterator[Pair]:
    server = UDPEndpoint("127.0.0.1", 0, on_message=answer).start()
    clients = [
        UDPEndpoint("127.0.0.1", 0, remote=server.address, on_message=i).start() for i in inboxes
    ]
    try:
        yield server, clients
    finally:
        for ep in (*clients, server):
            ep.stop()


@contextmanager
def inproc(answer: Callable[[Peer, igtl.Message], None], inboxes: list[Inbox]) -> Iterator[Pair]:
    channel = f"contract-{next(_channels)}"
    server = InprocTransport(channel, on_message=answer).start()
    clients = [
        InprocTransport(channel, listen=False, negotiate=False, on_message=i).start()
        for i in inboxes
    ]
    try:
        yield server, clients
    finally:
        for ep in (*clients, server):
            ep.stop()


@pytest.mark.parametrize("make", [tcp, udp, inproc], ids=["tcp", "udp", "inproc"])
def test_a_reply_reaches_the_peer_who_asked(make: Any) -> None:
    holder: dict[str, Any] = {}
    results: list[int] = []

    def answer(peer: Peer, msg: igtl.Message) -> None:
        reply = igtl.StringMessage(f"re: {msg.string}", device_name="Answer")
        results.append(holder["server"].send(reply, peer))

    inboxes = [Inbox(), Inbox()]
    with make(answer, inboxes) as (server, clients):
        holder["server"] = server
        for i, client in enumerate(clients):
            n = client.send(igtl.StringMessage(f"q{i}", device_name="Q"))
            assert isinstance(n, int) and n == 1
        assert inboxes[0].wait(1) == ["re: q0"]
        assert inboxes[1].wait(1) == ["re: q1"]
        # the server's thread records send()'s result just after the reply left: the reply
        # can reach its client first
        deadline = time.monotonic() + 5.0
        while len(results) < 2 and time.monotonic() < deadline:
            time.sleep(0.001)
        assert results == [1, 1]
        # a peer the endpoint does not know: nothing sent, 0 (never an exception); UDP has no
        # connections, so any address is a destination there
        if make is not udp:
            stranger = Peer(12345, ("127.0.0.1", 9))
            assert server.send(igtl.StringMessage("x", device_name="X"), stranger) == 0
            assert clients[0].send(igtl.StringMessage("y", device_name="Y"), stranger) == 0
