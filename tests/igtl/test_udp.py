"""igtl.transport.udp over 127.0.0.1 with ephemeral ports (no sleeps; bounded waits)."""

from __future__ import annotations

import socket
import struct
import threading
import time
from typing import Any

import pytest

import igtl
from igtl import rtp, wire
from igtl.errors import CRCError, DecodeError
from igtl.transport import Peer, UDPEndpoint

WAIT = 5.0


class Recorder:
    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.messages: list[tuple[Peer, igtl.Message]] = []
        self.errors: list[tuple[Peer | None, BaseException]] = []

    def on_message(self, peer: Peer, msg: igtl.Message) -> None:
        with self.cond:
            self.messages.append((peer, msg))
            self.cond.notify_all()

    def on_error(self, peer: Peer | None, exc: BaseException) -> None:
        with self.cond:
            self.errors.append((peer, exc))
            self.cond.notify_all()

    def wait(self, predicate: Any, timeout: float = WAIT) -> bool:
        with self.cond:
            return self.cond.wait_for(predicate, timeout)


@pytest.fixture
def stack():
    started: list[Any] = []

    def start(obj: Any) -> Any:
        started.append(obj)
        return obj.start()

    yield start
    for obj in reversed(started):
        obj.stop()


def raw_udp(host: str = "127.0.0.1") -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind((host, 0))
    sock.settimeout(WAIT)
    return sock


def test_round_trip_both_ways(stack):
    rec = Recorder()
    a = stack(UDPEndpoint(on_message=rec.on_message))
    b = stack(UDPEndpoint(remote=a.address))
    assert a.address[1] != 0
    v1 = igtl.TransformMessage.from_position((1, 2, 3), device_name="Tip")
    v2 = igtl.StringMessage(string="hi", header_version=2, metadata={"k": "v"}, message_id=5)
    assert b.send(v1) and b.send(v2)
    assert rec.wait(lambda: len(rec.messages) == 2)
    (p1, m1), (p2, m2) = rec.messages
    assert p1 is p2 and p1.address == b.address
    assert m1.translation == (1.0, 2.0, 3.0) and m1.header_version == 1
    assert m2.pack() == v2.pack() and p1.header_version == 2 and p1.received == 2
    # Reply to the sender's address through the inbox API.
    assert a.send(igtl.StringMessage(string="back"), p1.address)
    got = b.receive(WAIT)
    assert got is not None and got[1].string == "back" and got[0].address == a.address
    assert b.receive(0) is None
    assert b.stats()["sent"] == 2 and a.stats()["received"] == 2 and a.stats()["sent"] == 1


def test_large_message_goes_through_rtp(stack):
    rec = Recorder()
    a = stack(UDPEndpoint(on_message=rec.on_message, rtp_payload=1300))
    b = stack(UDPEndpoint(remote=a.address, max_datagram=1400, rtp_payload=1300))
    big = igtl.StringMessage(string="y" * 20_000, device_name="big")  # v1: sent as v2
    # UDP may lose datagrams: allow a few bounded attempts (loopback practically never does).
    for attempt in range(3):
        assert b.send(big.replace(device_name=f"big{attempt}"))
        if rec.wait(lambda: len(rec.messages) >= 1, timeout=2.0):
            break
    msg = rec.messages[0][1]
    assert msg.string == big.string and msg.header_version == 2
    stats = a.stats()
    assert stats["reassembled"] >= 1 and stats["datagrams_received"] >= 16
    assert b.stats()["datagrams_sent"] >= 16


def test_message_over_64k_uses_default_rtp_payload(stack):
    rec = Recorder()
    a = stack(UDPEndpoint(on_message=rec.on_message))
    b = stack(UDPEndpoint(remote=a.address))
    content = bytes(range(256)) * 300  # 76.8 kB: no single datagram can carry it
    for attempt in range(3):
        msg = igtl.RawMessage(
            type_name="BLOB", content=content, header_version=2, message_id=attempt
        )
        assert b.send(msg)
        if rec.wait(lambda: len(rec.messages) >= 1, timeout=2.0):
            break
    assert rec.messages[0][1].content == content
    assert b.stats()["datagrams_sent"] % 9 == 0  # 76.8 kB / 8830 bytes per datagram


def test_rtp_true_wraps_every_message(stack):
    sink = raw_udp()
    ep = stack(UDPEndpoint(remote=sink.getsockname(), rtp=True, rtp_ssrc=42, rtp_payload_type=0))
    msg = igtl.StringMessage(string="small", message_id=3)
    assert ep.send(msg)
    data, _ = sink.recvfrom(65536)
    first, pt, _seq, _ts, ssrc = rtp.RTP_HEADER.unpack_from(data)
    assert (first, pt, ssrc) == (0x80, 0, 42)
    assert data[78:82] == b"\x00\x03\x00\x00"  # 16-bit id 3, unfragmented
    assert igtl.unpack(rtp.Reassembler().feed(data) or b"").string == "small"
    sink.close()
    with pytest.raises(ValueError):
        ep.send(msg.replace(message_id=70_000))  # the RTP scheme carries 16-bit ids only


def test_garbage_datagrams_are_counted_never_raised(stack, caplog):
    rec = Recorder()
    a = stack(UDPEndpoint(on_message=rec.on_message, on_error=rec.on_error))
    good = igtl.StringMessage(string="ok").pack()
    bad_crc = bytearray(good)
    bad_crc[-1] ^= 0xFF
    fragments = rtp.fragment(igtl.StringMessage(string="z" * 3000).pack(2), payload_length=1000)
    with raw_udp() as sock:
        lone_middle_fragment = fragments[1]
        for junk in (
            b"hello",
            bytes(bad_crc),
            good + b"trailing",
            b"\x80" + bytes(100),
            lone_middle_fragment,
        ):
            sock.sendto(junk, a.address)
        sock.sendto(good, a.address)
        assert rec.wait(lambda: len(rec.messages) == 1)
        sender = sock.getsockname()
    assert rec.messages[0][1].string == "ok"
    errors = [e for _, e in rec.errors]
    assert len(errors) == 4 and all(isinstance(e, DecodeError) for e in errors)
    assert any(isinstance(e, CRCError) for e in errors)
    stats = a.stats()
    assert stats["malformed"] == 4 and stats["received"] == 1
    assert stats["reassembly_pending"] == 1  # the lone middle fragment waits (and will expire)
    assert f"127.0.0.1:{sender[1]}" in caplog.text


def test_allowed_peers_filters_senders(stack):
    rec = Recorder()
    a = stack(UDPEndpoint(on_message=rec.on_message, allowed_peers=["127.0.0.2/32"]))
    with raw_udp("127.0.0.1") as denied, raw_udp("127.0.0.2") as allowed:
        denied.sendto(igtl.StringMessage(string="no").pack(), a.address)
        allowed.sendto(igtl.StringMessage(string="yes").pack(), a.address)
        assert rec.wait(lambda: len(rec.messages) == 1)
    assert rec.messages[0][1].string == "yes"
    stats = a.stats()
    assert stats["denied"] == 1 and stats["received"] == 1


def test_full_socket_buffer_drops_without_blocking(stack):
    ep = stack(UDPEndpoint(remote=("127.0.0.1", 9)))
    calls = []

    def full(data: bytes, addr: Any) -> int:
        calls.append(addr)
        raise BlockingIOError(11, "Resource temporarily unavailable")

    ep._sendto = full  # simulate a full send buffer on the non-blocking socket
    msg = igtl.TransformMessage()
    t0 = time.perf_counter()
    results = [ep.send(msg) for _ in range(100)]
    elapsed = time.perf_counter() - t0
    assert results == [False] * 100 and len(calls) == 100
    stats = ep.stats()
    assert stats["dropped"] == 100 and stats["sent"] == 0
    assert ep.peers[0].dropped == 100
    assert elapsed < 2.0  # returns at once: nothing waits for buffer space


def test_socket_errors_are_counted(stack):
    ep = stack(UDPEndpoint(remote=("127.0.0.1", 9)))

    def broken(data: bytes, addr: Any) -> int:
        raise OSError(90, "Message too long")

    ep._sendto = broken
    assert ep.send(igtl.TransformMessage()) == 0
    assert ep.stats()["send_errors"] == 1


def test_send_needs_a_destination_and_a_started_endpoint():
    ep = UDPEndpoint()
    with pytest.raises(ValueError):
        ep.send(igtl.TransformMessage())
    assert ep.send(igtl.TransformMessage(), ("127.0.0.1", 9)) == 0  # not started
    assert ep.stats()["dropped"] == 1
    ep.stop()
    ep.stop()


def test_context_manager_and_receive_with_callback_set():
    with UDPEndpoint(on_message=lambda p, m: None) as ep:
        assert ep.address[1] != 0
        with pytest.raises(RuntimeError):
            ep.receive(0)
    assert ep.send(igtl.TransformMessage(), ("127.0.0.1", 9)) == 0


def test_bad_arguments():
    with pytest.raises(ValueError):
        UDPEndpoint(max_datagram=70_000)
    with pytest.raises(ValueError):
        UDPEndpoint(rtp_payload=50)


def test_rtp_wire_constants_match_the_reference():
    assert rtp.PREFIX_SIZE == wire.HEADER_SIZE + wire.EXT_HEADER_SIZE == 70
    assert struct.calcsize(">BBHII") == rtp.RTP_HEADER_SIZE == 12


def test_poll_delivers_waiting_datagrams_once_in_order() -> None:
    got: list[int] = []
    rx = UDPEndpoint("127.0.0.1", 0, on_message=lambda peer, msg: got.append(msg.message_id)).start()
    tx = UDPEndpoint("127.0.0.1", 0, remote=rx.address).start()
    try:
        # with the reader lock taken (the I/O thread delivering), poll() returns at once
        with rx._rx_lock:
            for i in range(1, 6):
                assert tx.send(igtl.PositionMessage(header_version=2, message_id=i))
            assert rx.poll() == 0
        # then the caller and the I/O thread take turns: every datagram once, in arrival order
        end = time.monotonic() + 2.0
        while len(got) < 5 and time.monotonic() < end:
            rx.poll()
            time.sleep(0.001)
        assert got == [1, 2, 3, 4, 5]
    finally:
        tx.stop()
        rx.stop()
    assert rx.poll() == 0  # stopped: nothing delivered, no error


def test_access_list_verdicts_are_cached_bounded_and_right() -> None:
    from igtl.transport.common import AccessList

    acl = AccessList(["127.0.0.2/32", "10.0.0.0/8", "::1"])
    for _ in range(2):  # second round: from the cache
        assert acl.allows("127.0.0.2") and acl.allows("10.1.2.3") and acl.allows("::1")
        assert acl.allows("::ffff:10.9.9.9")  # IPv4-mapped IPv6
        assert not acl.allows("127.0.0.1") and not acl.allows("not-an-address")
        assert not acl.allows("fe80::1%lo")
    for i in range(5000):  # many senders: the cache stays bounded, verdicts stay right
        assert acl.allows(f"10.0.{i // 250}.{i % 250}")
        assert not acl.allows(f"11.0.{i // 250}.{i % 250}")
    assert len(acl._verdicts) <= 1024
    assert AccessList(None).allows("anything")


def test_pinned_source_is_the_only_sender_the_kernel_lets_through() -> None:
    rec = Recorder()
    ep = UDPEndpoint("127.0.0.1", 0, on_message=rec.on_message).start()
    master = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    master.bind(("127.0.0.1", 0))
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    msg = igtl.StringMessage("x", device_name="s").pack()
    try:
        assert ep.pin_source(master.getsockname())
        for _ in range(50):
            other.sendto(msg, ep.address)  # dropped by the kernel: never read, never counted
        master.sendto(msg, ep.address)
        assert rec.wait(lambda: len(rec.messages) == 1)
        assert rec.messages[0][0].address == master.getsockname()
        assert ep.stats()["datagrams_received"] == 1
        # still sends anywhere
        assert ep.send(igtl.StringMessage("y", device_name="s"), other.getsockname()) == 1
        assert other.recv(100)
        # released: anyone again
        assert ep.pin_source(None) and ep.source is None
        other.sendto(msg, ep.address)
        assert rec.wait(lambda: len(rec.messages) == 2)
    finally:
        ep.stop()
        master.close()
        other.close()


def test_datagrams_queued_before_the_pin_keep_their_own_sender() -> None:
    """A pinned socket reads without asking the sender's address only once its queue was seen
    empty after the connect: a datagram another host queued before the pin is still its own,
    never taken for the pinned sender's."""
    got: list[tuple[tuple[str, int], str]] = []
    ep = UDPEndpoint(
        "127.0.0.1", 0, polled=True, on_message=lambda p, m: got.append((p.address, m.device_name))
    ).start()
    master = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    master.bind(("127.0.0.1", 0))
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other.bind(("127.0.0.1", 0))
    try:
        other.sendto(igtl.StringMessage("x", device_name="other").pack(), ep.address)
        time.sleep(0.05)  # queued in the socket before the pin
        assert ep.pin_source(master.getsockname())
        master.sendto(igtl.StringMessage("x", device_name="master").pack(), ep.address)
        time.sleep(0.05)
        assert ep.poll() == 2
        assert got == [(other.getsockname(), "other"), (master.getsockname(), "master")]
        # the same poll then found the queue empty: later reads skip the address
        assert ep._clean_source == master.getsockname()
        master.sendto(igtl.StringMessage("x", device_name="master").pack(), ep.address)
        time.sleep(0.05)
        assert ep.poll() == 1 and got[-1] == (master.getsockname(), "master")
        assert ep.pin_source(None) and ep._clean_source is None
    finally:
        ep.stop()
        master.close()
        other.close()


def test_a_sender_hears_that_nobody_listens() -> None:
    """connect_remote: the kernel turns the ICMP 'port unreachable' of a remote nobody listens
    on into a refused send, counted and logged (the master learns there is no slave)."""
    closed = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    closed.bind(("127.0.0.1", 0))
    port = closed.getsockname()[1]
    closed.close()  # nobody on this port now
    ep = UDPEndpoint("127.0.0.1", 0, remote=("127.0.0.1", port), connect_remote=True).start()
    try:
        msg = igtl.StringMessage("x", device_name="s")
        deadline = time.monotonic() + WAIT
        while ep.stats()["refused_by_remote"] == 0 and time.monotonic() < deadline:
            ep.send(msg)
            time.sleep(0.01)  # the ICMP answer arrives after the send that caused it
        assert ep.stats()["refused_by_remote"] >= 1
    finally:
        ep.stop()
