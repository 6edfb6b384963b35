"""Pieces shared by the transports: peers, access lists, the bounded inbox, the wake-up pipe,
one TCP connection's buffers, and callback guarding. Only transports import this module."""

from __future__ import annotations

import ipaddress
import itertools
import logging
import socket
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from typing import Any

from ..codec import StreamDecoder
from ..messages.base import Message

log = logging.getLogger("igtl.transport")

#: Bytes read per recv() call; also the most a write gathers from the queue per send() call.
IO_CHUNK = 256 * 1024

Address = tuple[Any, ...]  # (host, port) for IPv4, (host, port, flow, scope) for IPv6


class Peer:
    """One remote endpoint of a transport.

    Counters are plain integers (cheap to update, readable from any thread without locking):
    ``received`` messages decoded, ``sent`` messages wholly handed to the kernel, ``dropped``
    outgoing messages discarded (full send queue, full UDP socket buffer, still queued or partly
    written when the connection closed), ``malformed`` decode errors.
    ``header_version`` is the highest header version received from this peer, capped at 2; it
    starts at 1 and is the version a negotiating server answers in.
    """

    __slots__ = (
        "address",
        "connected_at",
        "dropped",
        "header_version",
        "id",
        "last_received",
        "log_limit",
        "malformed",
        "received",
        "sent",
    )

    def __init__(self, peer_id: int, address: Address, log_limit: RateLimit | None = None) -> None:
        self.id = peer_id
        self.address: tuple[str, int] = (str(address[0]), int(address[1]))
        self.header_version = 1
        self.received = 0
        self.sent = 0
        self.dropped = 0
        self.malformed = 0
        #: Wall-clock time (time.time()) of the connection, or of the first datagram for UDP.
        self.connected_at = time.time()
        #: Monotonic time of the last bytes received.
        self.last_received = time.monotonic()
        #: shared by every connection from the same host (:class:`HostLogLimits`), so a peer
        #: that reconnects in a loop cannot reset its own log budget
        self.log_limit = log_limit if log_limit is not None else RateLimit()

    def note_version(self, version: int) -> None:
        if version > self.header_version:
            self.header_version = min(version, 2)

    def as_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "address": f"{self.address[0]}:{self.address[1]}",
            "header_version": self.header_version,
            "received": self.received,
            "sent": self.sent,
            "dropped": self.dropped,
            "malformed": self.malformed,
            "connected_at": self.connected_at,
        }

    def __repr__(self) -> str:
        return (
            f"Peer(id={self.id}, address={self.address[0]}:{self.address[1]}, "
            f"v{self.header_version}, rx={self.received}, tx={self.sent}, "
            f"dropped={self.dropped}, malformed={self.malformed})"
        )


PEER_COUNTERS = ("received", "sent", "dropped", "malformed")


class RateLimit:
    """At most ``per_second`` events a second pass: so a peer flooding garbage cannot flood the
    log (every event is still counted and passed to on_error)."""

    __slots__ = ("_budget", "_window", "per_second", "suppressed")

    def __init__(self, per_second: int = 10) -> None:
        self.per_second = per_second
        self._budget = 0
        self._window = -1e9
        self.suppressed = 0

    def allow(self) -> bool:
        now = time.monotonic()
        if now - self._window >= 1.0:
            self._window = now
            self._budget = self.per_second
        if self._budget > 0:
            self._budget -= 1
            return True
        self.suppressed += 1
        return False


class HostLogLimits:
    """One :class:`RateLimit` per remote host, kept across connections (bounded, least
    recently used forgotten first): reconnecting does not buy a peer a fresh log budget, and a
    flood of connections from many addresses costs at most ``max_hosts`` entries."""

    __slots__ = ("_limits", "max_hosts", "per_second")

    def __init__(self, per_second: int = 10, max_hosts: int = 1024) -> None:
        self.per_second = per_second
        self.max_hosts = max_hosts
        self._limits: dict[str, RateLimit] = {}

    def get(self, host: str) -> RateLimit:
        limits = self._limits
        limit = limits.pop(host, None)
        if limit is None:
            limit = RateLimit(self.per_second)
            if len(limits) >= self.max_hosts:
                del limits[next(iter(limits))]
        limits[host] = limit  # most recently used last
        return limit

    @property
    def suppressed(self) -> int:
        return sum(limit.suppressed for limit in self._limits.values())


def should_log(peer: Peer | None) -> bool:
    return True if peer is None else peer.log_limit.allow()


class AccessList:
    """``allowed_peers``: IP addresses and CIDR networks, IPv4 or IPv6. ``None`` allows all."""

    def __init__(
        self, allowed: Iterable[str | ipaddress.IPv4Network | ipaddress.IPv6Network] | None
    ):
        if isinstance(allowed, str):
            raise TypeError("allowed_peers must be a list of addresses/networks, not one string")
        self.networks = (
            None
            if allowed is None
            else tuple(ipaddress.ip_network(a, strict=False) for a in allowed)
        )
        # verdicts by address text: parsing an address costs more than a 1 kHz loop polling
        # its stream should pay per datagram; bounded so that many senders cannot grow it
        self._verdicts: dict[str, bool] = {}

    def allows(self, host: str) -> bool:
        if self.networks is None:
            return True
        verdict = self._verdicts.get(host)
        if verdict is None:
            verdict = self._check(host)
            if len(self._verdicts) >= 1024:
                self._verdicts.clear()
            self._verdicts[host] = verdict
        return verdict

    def _check(self, host: str) -> bool:
        if self.networks is None:
            return True
        try:
            ip = ipaddress.ip_address(host.split("%", 1)[0])
        except ValueError:
            return False
        if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
            ip = ip.ipv4_mapped
        return any(ip in net for net in self.networks)


class Inbox:
    """Bounded queue of received (peer, message) for ``receive()``; full drops the oldest."""

    def __init__(self, size: int) -> None:
        if size < 1:
            raise ValueError(f"receive queue size must be >= 1, got {size}")
        self._items: deque[tuple[Peer, Message]] = deque()
        self._size = size
        self._cond = threading.Condition(threading.Lock())
        self.dropped = 0

    def put(self, item: tuple[Peer, Message]) -> None:
        with self._cond:
            if len(self._items) >= self._size:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self._cond.notify()

    def get(self, timeout: float | None) -> tuple[Peer, Message] | None:
        with self._cond:
            if not self._items:
                if timeout is not None and timeout <= 0:
                    return None
                self._cond.wait_for(lambda: bool(self._items), timeout)
                if not self._items:
                    return None
            return self._items.popleft()

    def __len__(self) -> int:
        return len(self._items)


class Waker:
    """A socket pair that lets any thread wake the I/O thread's selector, at most one byte in
    flight (a flag avoids a syscall per send when a wake-up is already pending)."""

    def __init__(self) -> None:
        self.r, self.w = socket.socketpair()
        self.r.setblocking(False)
        self.w.setblocking(False)
        self._pending = False

    def wake(self) -> None:
        if self._pending:
            return
        self._pending = True
        try:
            self.w.send(b"\0")
        except OSError:  # full (a wake-up is pending anyway) or closed during stop
            pass

    def drain(self) -> None:
        """Called by the I/O thread when ``r`` is readable, before it looks at the work queue.

        Order matters: empty the pipe first, then clear the flag. Clearing first would let a
        sender set the flag and write a byte that this recv then swallows, leaving the flag set
        with an empty pipe: every later wake() would be skipped and queued data would stall."""
        try:
            while self.r.recv(4096):
                pass
        except OSError:
            pass
        self._pending = False

    def close(self) -> None:
        self.r.close()
        self.w.close()


# struct tcp_info (linux/tcp.h): tcpi_snd_wnd, the peer's advertised window in bytes, is the
# 32-bit field at byte 228 (added in Linux 5.4), tcpi_notsent_bytes the one at byte 144; older
# kernels return a shorter struct.
_TCP_INFO = getattr(socket, "TCP_INFO", 11)
_SND_WND_OFFSET = 228
_NOTSENT_OFFSET = 144  # tcpi_notsent_bytes: queued, not yet sent (Linux 4.6 and later)
_TCP_INFO_LEN = 240


def name_native_thread(name: str) -> bool:
    """Give the calling thread ``name`` in the operating system too (``top -H``, ``ps -L``,
    py-spy show it; Python 3.11 names threads for itself only). Linux keeps 15 bytes. False
    where the C library has no ``pthread_setname_np``; nothing else changes."""
    try:
        import ctypes
        import ctypes.util

        libc = ctypes.CDLL(ctypes.util.find_library("c") or None)
        setname = libc.pthread_setname_np
        self_id = libc.pthread_self
    except (OSError, AttributeError):
        return False
    self_id.restype = ctypes.c_void_p
    setname.argtypes = (ctypes.c_void_p, ctypes.c_char_p)
    return setname(self_id(), name.encode("utf-8", "replace")[:15]) == 0


def configure_stream_socket(sock: socket.socket) -> None:
    """Non-blocking, TCP_NODELAY (no Nagle delay on small control messages) and keepalive that
    detects a vanished peer within about 10 s where the platform lets us tune it."""
    sock.setblocking(False)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    for name, value in (("TCP_KEEPIDLE", 5), ("TCP_KEEPINTVL", 1), ("TCP_KEEPCNT", 5)):
        opt = getattr(socket, name, None)
        if opt is not None:
            try:
                sock.setsockopt(socket.IPPROTO_TCP, opt, value)
            except OSError:  # pragma: no cover - platform dependent
                pass


class Connection:
    """One TCP connection: socket, stream decoder, bounded send queue and the bytes in flight.

    ``enqueue`` is called from any thread; everything else from the owning I/O thread only. The
    queue counts messages; when full the oldest queued message is dropped (never the one partly
    written, which would desynchronise the stream).
    """

    __slots__ = (
        "blocked_since",
        "closed",
        "unread_since",
        "unread_sent",
        "window_max",
        "decoder",
        "fileno",
        "limit",
        "lock",
        "out",
        "out_count",
        "partial_since",
        "peer",
        "queue",
        "sock",
        "want_write",
    )

    def __init__(
        self,
        sock: socket.socket,
        peer: Peer,
        *,
        send_queue: int,
        crc_check: bool,
        max_body_size: int,
    ) -> None:
        self.sock = sock
        self.fileno = sock.fileno()
        self.peer = peer
        self.decoder = StreamDecoder(crc_check=crc_check, max_body_size=max_body_size)
        self.queue: deque[bytes] = deque()
        self.limit = send_queue
        self.lock = threading.Lock()
        self.out: memoryview | None = None
        self.out_count = 0  # messages in ``out``; counted as sent once fully written
        self.want_write = False
        self.blocked_since = 0.0  # monotonic time the socket stopped taking our data
        self.partial_since = 0.0  # monotonic time an incomplete message began (0: none)
        self.window_max = 0  # the largest receive window the peer advertised
        self.unread_since = 0.0  # monotonic time the peer began to leave our data unread
        self.unread_sent = 0  # peer.sent then: only a peer we kept sending to is judged
        self.closed = False

    def unread_bytes(self) -> tuple[int, int] | None:
        """``(unread, waiting)``: about how many of our bytes the peer has received but its
        program has not read, and how many wait in our kernel because its window is closed.

        A client that never reads does not block our writes for a long time: the kernels
        buffer hundreds of kilobytes on both sides, minutes of a 10 Hz pose stream. Its
        advertised receive window shrinks as its buffer fills, though, from the first message
        on: the largest window it advertised minus the current one (``tcpi_snd_wnd``, Linux
        5.4 and later) tells it within seconds; a client with a tiny buffer closes its window
        instead, and our bytes wait unsent (``tcpi_notsent_bytes``). None where TCP_INFO
        lacks the fields.
        """
        try:
            info = self.sock.getsockopt(socket.IPPROTO_TCP, _TCP_INFO, _TCP_INFO_LEN)
        except (OSError, AttributeError):
            return None
        if len(info) < _SND_WND_OFFSET + 4:
            return None
        window = int.from_bytes(info[_SND_WND_OFFSET : _SND_WND_OFFSET + 4], sys.byteorder)
        waiting = int.from_bytes(info[_NOTSENT_OFFSET : _NOTSENT_OFFSET + 4], sys.byteorder)
        if window > self.window_max:
            self.window_max = window
        return self.window_max - window, waiting

    def enqueue(self, data: bytes) -> None:
        with self.lock:
            if len(self.queue) >= self.limit:
                self.queue.popleft()
                self.peer.dropped += 1
            self.queue.append(data)

    def flush(self) -> bool:
        """Write as much as the socket takes without blocking. Returns True when data remains
        (the caller then watches for writability). OSError propagates (connection is dead)."""
        sock = self.sock
        while True:
            out = self.out
            if out is None:
                with self.lock:
                    queue = self.queue
                    if not queue:
                        return False
                    first = queue.popleft()
                    count = 1
                    if queue and len(first) < IO_CHUNK:
                        # Gather small messages into one send() call.
                        parts = [first]
                        size = len(first)
                        while queue and size + len(queue[0]) <= IO_CHUNK:
                            nxt = queue.popleft()
                            parts.append(nxt)
                            size += len(nxt)
                        first = b"".join(parts)
                        count = len(parts)
                self.out_count = count
                out = memoryview(first)
            try:
                n = sock.send(out)
            except (BlockingIOError, InterruptedError):
                n = 0
            if n < len(out):
                self.out = out[n:]
                return True
            self.out = None
            self.peer.sent += self.out_count
            self.out_count = 0

    def discard_output(self) -> None:
        """Forget queued output (the connection is closing); it counts as dropped."""
        with self.lock:
            self.peer.dropped += len(self.queue) + (self.out_count if self.out is not None else 0)
            self.queue.clear()
        self.out = None
        self.out_count = 0


class CallbackGuard:
    """Runs user callbacks on the I/O thread: exceptions are logged and counted, never raised."""

    def __init__(self, owner: str) -> None:
        self.owner = owner
        self.errors = 0

    def __call__(self, callback: Callable[..., Any] | None, *args: Any) -> None:
        if callback is None:
            return
        try:
            callback(*args)
        except Exception:
            self.errors += 1
            log.exception(
                "%s: callback %r raised", self.owner, getattr(callback, "__name__", callback)
            )


def encode(msg: Message | bytes | bytearray | memoryview, version: int | None = None) -> bytes:
    """Bytes to send: a Message packed (in ``version`` when given), or pre-encoded bytes as is."""
    if isinstance(msg, Message):
        return msg.pack(version)
    if isinstance(msg, (bytes, bytearray, memoryview)):
        return bytes(msg)
    raise TypeError(f"can only send igtl Message or bytes, not {type(msg).__name__}")


class IdCounter:
    """Unique peer ids per transport (itertools.count is atomic under the GIL)."""

    def __init__(self) -> None:
        self._count = itertools.count(1)

    def __call__(self) -> int:
        return next(self._count)


def addr_text(address: Address) -> str:
    return f"{address[0]}:{address[1]}"


class IOThreadOwner:
    """Lifecycle shared by every transport: one daemon I/O thread, ``stop()`` safe twice or
    before ``start()``, context manager. Subclasses set up ``_waker``, call
    :meth:`_init_io_thread` in their constructor, start with :meth:`_launch`, and implement
    ``start``, ``_thread_main`` and ``_release`` (close what the I/O thread owned)."""

    name: str
    _waker: Waker

    def _init_io_thread(self) -> None:
        self._state_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._running = False
        self._stopped = False

    @property
    def thread(self) -> threading.Thread | None:
        """The I/O thread (e.g. to raise its scheduling priority), None before start()."""
        return self._thread

    def start(self) -> Any:  # pragma: no cover - overridden
        raise NotImplementedError

    def _named_main(self) -> None:
        name_native_thread(self.name.removeprefix("igtl-"))
        self._thread_main()

    def _thread_main(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def _release(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def _on_stopping(self) -> None:
        """Called under the state lock when stop() begins (e.g. to refuse further sends)."""

    def _launch(self) -> None:
        """Start the I/O thread; the caller holds ``_state_lock`` or passes ``locked=False``."""
        if self._thread is not None or self._stopped:
            raise RuntimeError(f"{self.name}: start() may be called once")
        self._running = True
        self._thread = threading.Thread(target=self._named_main, name=self.name, daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the I/O thread and close every socket. Safe to call twice, or before start."""
        with self._state_lock:
            if self._stopped:
                return
            self._stopped = True
            self._running = False
            self._on_stopping()
            thread = self._thread
        if thread is None:
            self._release()
            return
        self._waker.wake()
        if thread is not threading.current_thread():
            thread.join(timeout)
            if thread.is_alive():
                log.warning("%s: I/O thread did not stop within %.1f s", self.name, timeout)

    def __enter__(self) -> Any:
        if self._thread is None:
            self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
