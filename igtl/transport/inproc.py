"""OpenIGTLink inside one process: :class:`InprocTransport`, the network's ``virtual`` bus.

As python-can's ``virtual`` interface lets a whole CAN stack run without hardware, this
transport lets a daemon and its peers (tests, simulations, tools) talk OpenIGTLink without
sockets. Endpoints that name the same *channel* (any string) in one process are connected to
each other, in both directions: start two and each sees the other connect (``on_connect``),
stop one and the other sees it leave (``on_disconnect``). A *listening* endpoint (the default,
``listen=True``: a daemon's interface) connects to every endpoint on the channel; a client
(``listen=False``) only to the listening ones, so two clients of one daemon never hear each
other, as two TCP clients of one server do not. Two listeners connect to each other (two
daemons in one process, like a UDP pair).

Every message goes through the real codec: ``send`` packs it in the sender's thread (a bad
message raises ``ValueError`` there, as on TCP) and the receiver decodes the bytes with
:func:`igtl.unpack` (CRC checked unless ``crc_check=False``, ``max_body_size`` enforced), so a
receiver sees exactly what the wire would carry: a message packed as version 1 arrives without
metadata or message ID. Bytes are sent as they are; each ``send`` carries exactly one message
(as a UDP datagram does), so a test can hand a receiver malformed bytes. Decode errors are
counted (``peer.malformed``), passed to ``on_error(peer, err)`` and logged (rate-limited);
nothing is raised into the sender.

Header versions. Each endpoint announces ``header_version`` to the endpoints it meets: a peer
starts at that version (``peer.header_version``) and is raised, as on TCP, by the highest
version it sends. With ``negotiate=True`` (the default: a daemon's interface serving clients,
as :class:`~igtl.transport.TCPServer` does) every message is packed in the recipient's version;
with ``negotiate=False`` (a client, or a datagram sender) in its own. A peer announcing 1 is
therefore a client like an old Slicer that never sent v2; a peer announcing 2 one that did.

Delivery is synchronous, hence deterministic for simulated-time tests: when ``send`` returns,
every recipient's ``on_message`` has run (on the sender's thread; keep callbacks quick, as on
every transport). A message sent from inside a callback (a reply) is delivered after that
callback returns, before the outermost ``send`` returns: delivery never recurses, order is
kept, and a callback never runs inside another callback of the same thread. Callbacks of one
endpoint never run concurrently (a lock per endpoint stands in for the I/O thread). There is
no I/O thread: ``thread`` is None, ``poll()`` has nothing to do.

``send(msg, peer=None) -> int`` as on every transport: ``peer`` None sends to every connected
endpoint of the channel, a :class:`Peer` (or its id) to that one; the result is the number of
peers it was handed to (0: nobody connected, or that peer has gone).

Admission. ``address`` is the endpoint's (host, port) as its peers see it (stream ownership and
access lists use it); the default poses as a loopback client with a port unique in the process.
An address already on the channel is refused at ``start()`` (``OSError`` EADDRINUSE, as a bound
port is). An endpoint whose ``allowed_peers`` excludes the newcomer's host, or that has
``max_peers`` peers already, does not connect to it and counts it (``denied``, ``rejected``).
"""

from __future__ import annotations

import errno
import itertools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from .. import wire
from ..codec import unpack
from ..errors import DecodeError
from ..messages.base import Message
from .common import (
    PEER_COUNTERS,
    AccessList,
    CallbackGuard,
    IdCounter,
    Inbox,
    Peer,
    addr_text,
    encode,
)

log = logging.getLogger("igtl.transport.inproc")

OnMessage = Callable[[Peer, Message], Any]
OnPeer = Callable[[Peer], Any]
OnDisconnect = Callable[[Peer, str], Any]
OnError = Callable[["Peer | None", BaseException], Any]
Sendable = Message | bytes | bytearray | memoryview

# channel name -> its started endpoints, in joining order
_channels: dict[str, list[InprocTransport]] = {}
_channels_lock = threading.Lock()
# default addresses: a loopback "port" no other endpoint of this process was given
_next_port = itertools.count(49152)

_local = threading.local()


def _dispatch(fn: Callable[..., None], *args: Any) -> None:
    """Run ``fn(*args)`` now, or, when called from inside a delivery on this thread, right
    after that delivery: a reply sent by a callback must neither recurse nor overtake."""
    pending: deque[tuple[Callable[..., None], tuple[Any, ...]]] | None = getattr(
        _local, "pending", None
    )
    if pending is not None:
        pending.append((fn, args))
        return
    pending = _local.pending = deque([(fn, args)])
    try:
        while pending:
            f, a = pending.popleft()
            f(*a)
    finally:
        _local.pending = None


@dataclass(slots=True)
class _Link:
    """One direction of a connection: what this endpoint knows of ``remote``."""

    peer: Peer  # the remote endpoint as seen from here (counters, header version)
    remote: InprocTransport


def channel_endpoints(channel: str) -> list[tuple[str, int]]:
    """The addresses of the endpoints started on ``channel`` (for diagnostics and tests)."""
    with _channels_lock:
        return [ep.address for ep in _channels.get(channel, [])]


class InprocTransport:
    """An OpenIGTLink endpoint on a named in-process channel (see the module docstring)."""

    def __init__(
        self,
        channel: str,
        *,
        address: tuple[str, int] | None = None,
        header_version: int = 1,
        negotiate: bool = True,
        listen: bool = True,
        on_message: OnMessage | None = None,
        on_connect: OnPeer | None = None,
        on_disconnect: OnDisconnect | None = None,
        on_error: OnError | None = None,
        allowed_peers: list[str] | None = None,
        max_peers: int = 16,
        receive_queue: int = 1024,
        max_body_size: int = wire.DEFAULT_MAX_BODY_SIZE,
        crc_check: bool = True,
        name: str = "igtl-inproc",
    ) -> None:
        if not channel:
            raise ValueError("channel must be a non-empty name")
        if header_version not in (1, 2):
            raise ValueError(f"header_version must be 1 or 2, got {header_version}")
        if max_peers < 1:
            raise ValueError(f"max_peers must be >= 1, got {max_peers}")
        self.channel = channel
        self.address: tuple[str, int] = (
            (str(address[0]), int(address[1])) if address else ("127.0.0.1", next(_next_port))
        )
        self.header_version = header_version
        self.negotiate = negotiate
        self.listen = listen
        self.on_message = on_message
        self.on_connect = on_connect
        self.on_disconnect = on_disconnect
        self.on_error = on_error
        self.max_peers = max_peers
        self.name = name
        self._access = AccessList(allowed_peers)
        self._max_body = max_body_size
        self._crc_check = crc_check
        self._inbox = Inbox(receive_queue)
        self._guard = CallbackGuard(name)
        self._next_id = IdCounter()
        # Published copy-on-write under _channels_lock; senders read them without a lock.
        self._links: dict[int, _Link] = {}  # by our Peer id
        self._by_remote: dict[int, _Link] = {}  # by id() of the remote endpoint
        self._rx_lock = threading.Lock()
        self._state = "new"  # new -> started -> stopped
        self._closed_totals = dict.fromkeys(PEER_COUNTERS, 0)
        self._connections = 0
        self._denied = 0
        self._rejected = 0
        self._unrouted = 0  # sends to a peer that is not (or no longer) connected

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> InprocTransport:
        """Join the channel and connect to every endpoint already on it."""
        met: list[tuple[InprocTransport, _Link, _Link]] = []
        with _channels_lock:
            if self._state != "new":
                raise RuntimeError(f"{self.name}: start() may be called once")
            members = _channels.setdefault(self.channel, [])
            if any(ep.address == self.address for ep in members):
                raise OSError(
                    errno.EADDRINUSE,
                    f"{self.name}: {addr_text(self.address)} is already on channel "
                    f"{self.channel!r}",
                )
            self._state = "started"
            for other in members:
                if not (self.listen or other.listen):
                    continue  # two clients
                if not (other._admits(self) and self._admits(other)):
                    continue
                mine = _Link(Peer(self._next_id(), other.address), other)
                mine.peer.header_version = other.header_version
                theirs = _Link(Peer(other._next_id(), self.address), self)
                theirs.peer.header_version = self.header_version
                self._attach(mine)
                other._attach(theirs)
                met.append((other, mine, theirs))
            members.append(self)
        log.info("%s: on channel %r as %s", self.name, self.channel, addr_text(self.address))
        for other, mine, theirs in met:
            # the endpoint already there hears of us first, as a server accepts a client
            _dispatch(other._notify, other.on_connect, theirs.peer)
            _dispatch(self._notify, self.on_connect, mine.peer)
        return self

    def stop(self, timeout: float = 2.0) -> None:
        """Leave the channel: every peer sees this endpoint disconnect. Safe twice, or before
        start. ``timeout`` is accepted for the shared signature; there is nothing to wait for."""
        left: list[_Link] = []
        gone: list[tuple[InprocTransport, _Link]] = []
        with _channels_lock:
            if self._state != "started":
                self._state = "stopped"
                return
            self._state = "stopped"
            members = _channels.get(self.channel, [])
            if self in members:
                members.remove(self)
            if not members:
                _channels.pop(self.channel, None)
            for link in self._links.values():
                theirs = link.remote._detach(self)
                self._forget(link)
                left.append(link)
                if theirs is not None:
                    gone.append((link.remote, theirs))
            self._links = {}
            self._by_remote = {}
        # callbacks run outside the channel lock: one may start or stop another endpoint
        for remote, theirs in gone:
            _dispatch(remote._notify, remote.on_disconnect, theirs.peer, "closed by peer")
        for link in left:
            _dispatch(self._notify, self.on_disconnect, link.peer, "stopped")
        log.info("%s: left channel %r", self.name, self.channel)

    def __enter__(self) -> InprocTransport:
        if self._state == "new":
            self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def thread(self) -> None:
        """No I/O thread: delivery runs on the sender's thread."""
        return None

    @property
    def started(self) -> bool:
        return self._state == "started"

    # ------------------------------------------------------------------ public, any thread
    @property
    def peers(self) -> list[Peer]:
        """The connected endpoints (a snapshot)."""
        return [link.peer for link in self._links.values()]

    def send(self, msg: Sendable, peer: Peer | int | None = None) -> int:
        """Pack ``msg`` and deliver it to ``peer`` (Peer or id), or to every connected
        endpoint (None); returns how many it was handed to. The recipients' callbacks have run
        when this returns (unless called from a callback: module docstring)."""
        if not isinstance(msg, (Message, bytes, bytearray, memoryview)):
            raise TypeError(f"can only send igtl Message or bytes, not {type(msg).__name__}")
        links = self._links
        targets: Any
        if peer is None:
            targets = links.values()
        else:
            link = links.get(peer if isinstance(peer, int) else peer.id)
            if link is None:
                self._unrouted += 1
                return 0
            targets = (link,)
        negotiate = self.negotiate and isinstance(msg, Message)
        packed: dict[int | None, bytes] = {}
        count = 0
        for link in targets:
            version = link.peer.header_version if negotiate else None
            data = packed.get(version)
            if data is None:
                data = packed[version] = encode(msg, version)
            link.peer.sent += 1
            _dispatch(link.remote._receive, self, data)
            count += 1
        return count

    def receive(self, timeout: float | None = None) -> tuple[Peer, Message] | None:
        """Next (peer, message) from the inbox, or None after ``timeout`` seconds (None: wait)."""
        if self.on_message is not None:
            raise RuntimeError("on_message is set, so messages never reach receive()")
        return self._inbox.get(timeout)

    def poll(self, limit: int = 64, on_message: OnMessage | None = None) -> int:
        """Nothing is ever waiting: delivery is synchronous. Returns 0 (for loops that poll)."""
        return 0

    def stats(self) -> dict[str, Any]:
        peers = self.peers
        out: dict[str, Any] = dict(self._closed_totals)
        for p in peers:
            for name in PEER_COUNTERS:
                out[name] += getattr(p, name)
        out.update(
            channel=self.channel,
            connections=self._connections,
            clients=len(peers),
            denied=self._denied,
            rejected=self._rejected,
            unrouted=self._unrouted,
            receive_dropped=self._inbox.dropped,
            callback_errors=self._guard.errors,
            peers=[p.as_dict() for p in peers],
        )
        return out

    def __repr__(self) -> str:
        return (
            f"InprocTransport({self.channel!r}, address={addr_text(self.address)}, "
            f"{self._state}, peers={len(self._links)})"
        )

    # ------------------------------------------------------------------ internals
    def _admits(self, other: InprocTransport) -> bool:
        """Called under _channels_lock when ``other`` and this endpoint meet."""
        if not self._access.allows(other.address[0]):
            self._denied += 1
            log.warning("%s: %s denied (not in allowed_peers)", self.name, addr_text(other.address))
            return False
        if len(self._links) >= self.max_peers:
            self._rejected += 1
            log.warning(
                "%s: %s rejected (max_peers=%d reached)",
                self.name,
                addr_text(other.address),
                self.max_peers,
            )
            return False
        return True

    def _attach(self, link: _Link) -> None:
        links = dict(self._links)
        links[link.peer.id] = link
        by_remote = dict(self._by_remote)
        by_remote[id(link.remote)] = link
        self._links, self._by_remote = links, by_remote
        self._connections += 1

    def _detach(self, remote: InprocTransport) -> _Link | None:
        by_remote = dict(self._by_remote)
        link = by_remote.pop(id(remote), None)
        if link is None:
            return None
        links = dict(self._links)
        links.pop(link.peer.id, None)
        self._links, self._by_remote = links, by_remote
        self._forget(link)
        return link

    def _forget(self, link: _Link) -> None:
        for name in PEER_COUNTERS:
            self._closed_totals[name] += getattr(link.peer, name)

    def _notify(self, callback: Callable[..., Any] | None, *args: Any) -> None:
        with self._rx_lock:
            self._guard(callback, *args)

    def _receive(self, sender: InprocTransport, data: bytes) -> None:
        link = self._by_remote.get(id(sender))
        if link is None:  # we left (or refused it) between its send and this delivery
            return
        peer = link.peer
        with self._rx_lock:
            peer.last_received = time.monotonic()
            try:
                msg = unpack(data, crc_check=self._crc_check, max_body_size=self._max_body)
            except DecodeError as err:
                peer.malformed += 1
                if peer.log_limit.allow():
                    log.warning(
                        "%s: malformed message from %s: %s",
                        self.name,
                        addr_text(peer.address),
                        err,
                    )
                self._guard(self.on_error, peer, err)
                return
            peer.received += 1
            if msg.header_version > peer.header_version:
                peer.note_version(msg.header_version)
            if self.on_message is not None:
                self._guard(self.on_message, peer, msg)
            else:
                self._inbox.put((peer, msg))
