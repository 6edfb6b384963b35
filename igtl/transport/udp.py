"""OpenIGTLink over UDP: :class:`UDPEndpoint`, one message per datagram, RTP for large ones.

Sending happens in the caller's thread on a non-blocking socket: ``send`` never waits. A full
socket buffer drops the message (counted in ``dropped``, ``send`` returns 0); any other
socket error is counted in ``send_errors``. A packed message longer than ``max_datagram`` (or
every message, with ``rtp=True``) goes out with the reference library's RTP fragmentation
(:mod:`igtl.rtp`, ``rtp_payload`` bytes of RTP payload per datagram); since that scheme needs
header version 2, such a message is packed as v2. Its message ID must be below 2**16.

Receiving runs on the endpoint's I/O thread. A datagram whose first byte is 0x80 (an RTP header;
an OpenIGTLink header starts with 0x00) goes to a per-sender :class:`igtl.rtp.Reassembler`
(incomplete messages expire after ``reassembly_timeout`` seconds; memory is capped); any other
datagram must be exactly one complete message. Decoding uses :func:`igtl.unpack` (CRC checked
unless ``crc_check=False``). Every bad datagram or reassembly error is counted (``malformed``,
per peer and in total), passed to ``on_error(peer, err)`` and logged as a rate-limited WARNING;
nothing is ever raised into the receive loop. Datagrams from senders outside ``allowed_peers``
are dropped and counted (``denied``). Messages go to ``on_message(peer, msg)`` when set, else to
a bounded inbox read with ``receive(timeout)`` (full: oldest dropped, ``receive_dropped``).

A :class:`~igtl.transport.common.Peer` is kept per remote address (at most ``max_peers``, the
least recently created is forgotten first); ``peer.header_version`` is the highest version it
sent, as on TCP.
"""

from __future__ import annotations

import errno
import logging
import os
import select
import selectors
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

from .. import rtp as _rtp
from .. import wire
from ..codec import unpack
from ..errors import DecodeError
from ..messages.base import Message
from .common import (
    PEER_COUNTERS,
    AccessList,
    CallbackGuard,
    HostLogLimits,
    IdCounter,
    Inbox,
    IOThreadOwner,
    Peer,
    RateLimit,
    Waker,
    addr_text,
    encode,
)

log = logging.getLogger("igtl.transport.udp")

OnMessage = Callable[[Peer, Message], Any]
OnError = Callable[["Peer | None", BaseException], Any]
Sendable = Message | bytes | bytearray | memoryview

MAX_UDP_PAYLOAD = 65507  # IPv4: 65535 - 20 (IP) - 8 (UDP)
_RECV_BATCH = 64  # datagrams read per readiness event before looking at the selector again


def _disconnect(sock: socket.socket) -> None:
    """Dissolve a UDP socket's association (connect to AF_UNSPEC, which Python's
    ``connect`` cannot express): it takes datagrams from anyone again."""
    import ctypes
    import ctypes.util

    libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
    unspec = (ctypes.c_ubyte * 16)()  # sa_family_t 0 = AF_UNSPEC, the rest ignored
    if libc.connect(sock.fileno(), unspec, ctypes.sizeof(unspec)) != 0:
        err = ctypes.get_errno()
        raise OSError(err, os.strerror(err))


class UDPEndpoint(IOThreadOwner):
    """A UDP socket speaking OpenIGTLink (see the module docstring)."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        remote: tuple[str, int] | None = None,
        on_message: OnMessage | None = None,
        on_error: OnError | None = None,
        allowed_peers: list[str] | None = None,
        max_datagram: int = MAX_UDP_PAYLOAD,
        rtp: bool = False,
        rtp_payload: int = _rtp.DEFAULT_PAYLOAD_LENGTH,
        rtp_payload_type: int = _rtp.DEFAULT_PAYLOAD_TYPE,
        rtp_ssrc: int | None = None,
        reassembly_timeout: float = 1.0,
        max_peers: int = 1024,
        receive_queue: int = 1024,
        rcvbuf: int | None = None,
        max_body_size: int = wire.DEFAULT_MAX_BODY_SIZE,
        crc_check: bool = True,
        polled: bool = False,
        connect_remote: bool = False,
        name: str = "igtl-udp",
    ) -> None:
        self._check_sizes(max_datagram, rtp_payload, rtp_payload_type)
        self.host = host
        self.port = port
        self.remote = remote
        #: connect the socket to ``remote``: the kernel then reports a remote that nobody
        #: listens on (ICMP port unreachable) as ECONNREFUSED on the next send, which is
        #: counted (``refused_by_remote``) and logged; only ``remote`` is heard from
        self.connect_remote = connect_remote
        self._refused_by_remote = 0
        self._refused_logged = -1e9
        self._ready: Any = None  # poll(2) of the socket, for a polled endpoint (see poll())
        #: the only sender the kernel lets through (:meth:`pin_source`), or None: anyone
        self.source: tuple[str, int] | None = None
        self.on_message = on_message
        self.on_error = on_error
        self.max_datagram = max_datagram
        self.rtp = rtp
        self.rtp_payload = rtp_payload
        self.rtp_payload_type = rtp_payload_type
        self.rtp_ssrc = (
            int.from_bytes(os.urandom(4), "big") if rtp_ssrc is None else rtp_ssrc & 0xFFFFFFFF
        )
        self.max_peers = max_peers
        self.rcvbuf = rcvbuf
        #: received only by the owner's :meth:`poll` (e.g. a control loop, once per tick): the
        #: I/O thread does not wake for every datagram
        self.polled = polled
        self.name = name
        self.address: tuple[str, int] = (host, port)
        self._init_decoding(
            allowed_peers, crc_check, max_body_size, reassembly_timeout, receive_queue
        )
        self._init_io()
        self._init_counters()

    @staticmethod
    def _check_sizes(max_datagram: int, rtp_payload: int, rtp_payload_type: int) -> None:
        """ValueError for a datagram size, RTP payload size or RTP payload type out of range."""
        if not 1 <= max_datagram <= MAX_UDP_PAYLOAD:
            raise ValueError(f"max_datagram must be 1..{MAX_UDP_PAYLOAD}, got {max_datagram}")
        if not _rtp.PREFIX_SIZE < rtp_payload <= MAX_UDP_PAYLOAD - _rtp.RTP_HEADER_SIZE:
            raise ValueError(f"rtp_payload must be 71..{MAX_UDP_PAYLOAD - 12}, got {rtp_payload}")
        if not 0 <= rtp_payload_type <= 0x7F:
            raise ValueError(f"rtp_payload_type must be 0..127, got {rtp_payload_type}")

    def _init_decoding(
        self,
        allowed_peers: list[str] | None,
        crc_check: bool,
        max_body_size: int,
        reassembly_timeout: float,
        receive_queue: int,
    ) -> None:
        """Who may send, the decoding limits, RTP reassembly, the inbox, the callback guard."""
        self._access = AccessList(allowed_peers)
        self._crc_check = crc_check
        self._max_body = max_body_size
        self._reassembler = _rtp.Reassembler(
            timeout=reassembly_timeout, max_body_size=max_body_size
        )
        self._inbox = Inbox(receive_queue)
        self._guard = CallbackGuard(self.name)

    def _init_io(self) -> None:
        """The peers, the RTP sequence, the socket (bound by :meth:`start`), the I/O thread,
        the receive buffer and the log rate limits."""
        self._next_id = IdCounter()
        self._peers: dict[Any, Peer] = {}
        self._peers_lock = threading.Lock()
        self._seq = int.from_bytes(os.urandom(2), "big")
        self._seq_lock = threading.Lock()
        self._sock: socket.socket | None = None
        self._sendto: Callable[[bytes, Any], int] | None = None
        self._waker = Waker()
        self._sel = selectors.DefaultSelector()
        self._init_io_thread()
        self._rx_lock = threading.Lock()  # one reader at a time: the I/O thread or poll()
        self._denied_log = RateLimit()
        self._log_limits = HostLogLimits()
        self._error_log = RateLimit()
        self._rxbuf = bytearray(65536)
        self._rxview = memoryview(self._rxbuf)
        #: the pinned source once its socket's queue was seen empty after the connect
        self._clean_source: tuple[str, int] | None = None

    def _init_counters(self) -> None:
        """Endpoint-wide counters (per-peer ones live on the Peers)."""
        self._sent = 0
        self._dropped = 0
        self._send_errors = 0
        self._datagrams_sent = 0
        self._datagrams_received = 0
        self._denied = 0
        self._receive_errors = 0
        self._forgotten = dict.fromkeys(PEER_COUNTERS, 0)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> UDPEndpoint:
        """Bind (errors raise here) and start the receive thread."""
        with self._state_lock:
            if self._thread is not None or self._stopped:
                raise RuntimeError(f"{self.name}: start() may be called once")
            family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
            sock = socket.socket(family, socket.SOCK_DGRAM)
            try:
                if self.rcvbuf:
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.rcvbuf)
                sock.bind((self.host, self.port))
                sock.setblocking(False)
            except OSError:
                sock.close()
                raise
            self._sock = sock
            self._sendto = sock.sendto
            if self.connect_remote and self.remote is not None:
                try:
                    sock.connect(self.remote)
                except OSError as err:
                    log.warning("%s: cannot connect to %s: %s", self.name, self.remote, err)
            if self.polled and hasattr(select, "poll"):
                poller = select.poll()
                poller.register(sock, select.POLLIN)
                self._ready = poller.poll
            self.address = sock.getsockname()[:2]
            if not self.polled:
                self._sel.register(sock, selectors.EVENT_READ, "sock")
            self._sel.register(self._waker.r, selectors.EVENT_READ, "wake")
            self._launch()
        log.info("%s: bound to %s", self.name, addr_text(self.address))
        return self

    def _on_stopping(self) -> None:
        self._sendto = None

    def _release(self) -> None:
        self._sel.close()
        self._waker.close()
        if self._sock is not None:
            self._sock.close()

    # ------------------------------------------------------------------ public, any thread
    @property
    def peers(self) -> list[Peer]:
        with self._peers_lock:
            return list(self._peers.values())

    def send(self, msg: Sendable, peer: Peer | tuple[str, int] | None = None) -> int:
        """Send ``msg`` to ``peer`` (a Peer, e.g. the sender of a request, or a (host, port)
        address; default ``remote``) without blocking. Returns 1, or 0 (counted) when the
        socket buffer is full or the socket fails; ValueError for a message that cannot be
        sent (no destination, RTP limits)."""
        if peer is None:
            dest = self.remote
        elif isinstance(peer, Peer):
            dest = peer.address
        else:
            dest = (peer[0], peer[1])
        if dest is None:
            raise ValueError("no destination: pass peer or construct with remote=(host, port)")
        if self.rtp and isinstance(msg, Message):
            data = msg.pack(2)
        else:
            data = encode(msg)
        if self.rtp or len(data) > self.max_datagram:
            datagrams = self._fragment(msg, data)
        else:
            datagrams = [data]
        peer = self._peer_for(dest)
        sendto = self._sendto
        if sendto is None:  # not started, or stopped
            self._dropped += 1
            peer.dropped += 1
            return 0
        try:
            for datagram in datagrams:
                sendto(datagram, dest)
                self._datagrams_sent += 1
        except (BlockingIOError, InterruptedError):
            # Socket buffer full: the 1 kHz caller must not wait, so this message is lost.
            self._dropped += 1
            peer.dropped += 1
            return 0
        except OSError as err:
            self._send_errors += 1
            peer.dropped += 1
            if err.errno == errno.ECONNREFUSED:
                self._remote_refused()
            elif self._error_log.allow():
                log.warning("%s: send to %s failed: %s", self.name, addr_text(dest), err)
            return 0
        self._sent += 1
        peer.sent += 1
        return 1

    def _remote_refused(self) -> None:
        self._refused_by_remote += 1
        now = time.monotonic()
        if now - self._refused_logged >= 10.0:  # a 500 Hz stream: say it, not 500 times a second
            self._refused_logged = now
            where = addr_text(self.remote) if self.remote is not None else "the remote"
            log.warning(
                "%s: nobody is listening on %s (datagrams refused; %d so far)",
                self.name,
                where,
                self._refused_by_remote,
            )

    def pin_source(self, address: tuple[str, int] | None) -> bool:
        """Take datagrams from ``address`` only, or again from anyone (None).

        The socket is connected to ``address``: the kernel then drops every other sender's
        datagrams before they reach the socket buffer, so a flood from another port or host
        can neither cost us a read nor push the pinned sender's datagrams out of a full buffer
        (they are not counted here: the kernel counts them as ``NoPorts`` in /proc/net/snmp).
        Sending to other addresses still works. Returns False (logged) where it cannot be
        done; the caller's own filtering then still applies.
        """
        sock = self._sock
        if sock is None:
            return False
        self._clean_source = None  # until the queue is seen empty under the new pin
        try:
            if address is None:
                _disconnect(sock)
                if sock.getsockname()[1] != self.address[1]:
                    # an ephemeral port (bound as 0) is released by the disconnect: take it back
                    sock.bind(self.address)
            else:
                sock.connect((address[0], address[1]))
        except OSError as err:
            log.warning("%s: cannot pin the source to %s: %s", self.name, address, err)
            return False
        self.source = (address[0], address[1]) if address is not None else None
        log.info("%s: datagrams taken from %s only", self.name, address or "anyone")
        return True

    def receive(self, timeout: float | None = None) -> tuple[Peer, Message] | None:
        """Next (peer, message), or None after ``timeout`` seconds (None: wait)."""
        if self.on_message is not None:
            raise RuntimeError("on_message is set, so messages never reach receive()")
        return self._inbox.get(timeout)

    def stats(self) -> dict[str, Any]:
        peers = self.peers
        totals = dict(self._forgotten)
        for peer in peers:
            for name in PEER_COUNTERS:
                totals[name] += getattr(peer, name)
        reasm = self._reassembler
        return {
            "received": totals["received"],
            "sent": self._sent,
            "dropped": self._dropped,
            "send_errors": self._send_errors,
            "malformed": totals["malformed"],
            "denied": self._denied,
            "refused_by_remote": self._refused_by_remote,
            "receive_errors": self._receive_errors,
            "datagrams_sent": self._datagrams_sent,
            "datagrams_received": self._datagrams_received,
            "reassembled": reasm.completed,
            "reassembly_expired": reasm.expired,
            "reassembly_evicted": reasm.evicted,
            "reassembly_pending": reasm.pending,
            "receive_dropped": self._inbox.dropped,
            "callback_errors": self._guard.errors,
            "peers": [p.as_dict() for p in peers],
        }

    # ------------------------------------------------------------------ internals
    def _fragment(self, msg: Sendable, data: bytes) -> list[bytes]:
        if data[:2] != b"\x00\x02":
            if not isinstance(msg, Message):
                raise ValueError("RTP needs a header-version-2 message; these bytes are not one")
            data = msg.pack(2)
        chunk = self.rtp_payload - _rtp.PREFIX_SIZE
        count = max(1, -(-(len(data) - _rtp.PREFIX_SIZE) // chunk))
        with self._seq_lock:
            seq = self._seq
            self._seq = (seq + count) & 0xFFFF
        return _rtp.fragment(
            data,
            seq_start=seq,
            payload_type=self.rtp_payload_type,
            ssrc=self.rtp_ssrc,
            payload_length=self.rtp_payload,
        )

    def _peer_for(self, address: Any) -> Peer:
        key = (address[0], address[1])
        peer = self._peers.get(key)
        if peer is not None:
            return peer
        with self._peers_lock:
            peer = self._peers.get(key)
            if peer is None:
                while len(self._peers) >= self.max_peers:
                    old = self._peers.pop(next(iter(self._peers)))
                    for name in PEER_COUNTERS:
                        self._forgotten[name] += getattr(old, name)
                # the log budget is per host: a sender hopping ports gets no fresh one
                peer = Peer(self._next_id(), key, self._log_limits.get(str(key[0])))
                self._peers[key] = peer
        return peer

    def _thread_main(self) -> None:
        try:
            self._run()
        except Exception:  # pragma: no cover - a bug; keep the cause visible
            log.exception("%s: I/O thread failed", self.name)
        finally:
            self._release()
            log.info("%s: stopped", self.name)

    def _run(self) -> None:
        reasm = self._reassembler
        tick = min(reasm.timeout / 4, 0.25)
        while self._running:
            for key, _mask in self._sel.select(tick):
                if key.data == "wake":
                    self._waker.drain()
                else:
                    self._read_batch()
            if reasm.pending:
                with self._rx_lock:  # poll() may be feeding the reassembler
                    reasm.expire()

    def poll(self, limit: int = 64, on_message: OnMessage | None = None) -> int:
        """Receive and deliver the datagrams already waiting, on the calling thread; never blocks.

        For a periodic loop that wants a sample the moment it ticks: the I/O thread delivers
        datagrams as they arrive, but in a Python process it cannot while another thread holds
        the interpreter (a loop spinning before its deadline does). The two readers take turns
        datagram by datagram (a lock keeps delivery in arrival order); if the I/O thread is
        busy delivering, poll returns 0 and leaves the rest to it. Returns the number delivered.

        ``on_message``: the messages this call reads go to it instead of the endpoint's own
        callback, and unguarded: its exceptions reach the caller of ``poll`` (a loop that handles
        what it polled at once, and its own errors). Bad datagrams are counted and reported as
        always (``on_error``).
        """
        if self._sock is None or not self._running:
            return 0
        ready = self._ready
        done = 0
        for _ in range(limit):
            # ask first: an empty receive raises, and the exception costs a 1 kHz loop more
            # (about 14 us cold here) than the poll(2) that tells the same (about 6 us)
            if ready is not None and not ready(0):
                if self._clean_source is None and self.source is not None:
                    self._clean_source = self.source  # queue empty since the pin: see below
                return done
            if not self._rx_lock.acquire(blocking=False):
                return done
            try:
                if not self._receive_one(on_message):
                    return done
            finally:
                self._rx_lock.release()
            done += 1
        return done

    def _read_batch(self) -> None:
        for _ in range(_RECV_BATCH):
            if not self._running:
                return
            with self._rx_lock:
                if not self._receive_one():
                    return

    def _receive_one(self, deliver: OnMessage | None = None) -> bool:
        """Read one datagram and deliver it (to ``deliver``, unguarded, when given); False when
        none is waiting (or on an error)."""
        sock = self._sock
        if sock is None:
            return False
        buf = self._rxbuf
        source = self._clean_source
        try:
            if source is not None:
                # connected to one sender and its queue seen empty since: every datagram is
                # that sender's, so skip the address the kernel would build per datagram
                n = sock.recv_into(buf)
                address = source
            else:
                n, address = sock.recvfrom_into(buf)
        except (BlockingIOError, InterruptedError):
            if self.source is not None and self._clean_source is None:
                # datagrams queued before the connect came from anyone; none are left now
                self._clean_source = self.source
            return False
        except OSError as err:  # e.g. ICMP errors reported on the socket
            if err.errno == errno.ECONNREFUSED:
                # a connected sender's remote is not listening: the kernel reports it to
                # whichever call comes first, this receive or the next send
                self._remote_refused()
                return False
            self._receive_errors += 1
            if self._error_log.allow():
                log.warning("%s: receive failed: %s", self.name, err)
            return False
        self._datagrams_received += 1
        self._datagram(bytes(self._rxview[:n]), address, deliver)
        return True

    def _datagram(self, data: bytes, address: Any, deliver: OnMessage | None = None) -> None:
        if not self._access.allows(address[0]):
            self._denied += 1
            if self._denied_log.allow():
                log.warning(
                    "%s: datagram from %s dropped (not in allowed_peers)",
                    self.name,
                    addr_text(address),
                )
            return
        peer = self._peer_for(address)
        peer.last_received = time.monotonic()
        try:
            if data[:1] == b"\x80":
                whole = self._reassembler.feed(data, (address[0], address[1]))
                if whole is None:
                    return
                data = whole
            msg = unpack(data, crc_check=self._crc_check, max_body_size=self._max_body)
        except DecodeError as err:
            peer.malformed += 1
            if peer.log_limit.allow():
                log.warning(
                    "%s: malformed datagram from %s: %s", self.name, addr_text(address), err
                )
            self._guard(self.on_error, peer, err)
            return
        peer.received += 1
        if msg.header_version > peer.header_version:
            peer.note_version(msg.header_version)
        if deliver is not None:
            deliver(peer, msg)
        elif self.on_message is not None:
            self._guard(self.on_message, peer, msg)
        else:
            self._inbox.put((peer, msg))
