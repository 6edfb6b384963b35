"""OpenIGTLink over TCP: :class:`TCPServer` (many clients, one I/O thread) and :class:`TCPClient`.

Threading. Each transport owns one I/O thread running a ``selectors`` loop; it does every socket
call, decodes (``igtl.codec.StreamDecoder``) and runs the callbacks ``on_message(peer, msg)``,
``on_connect(peer)``, ``on_disconnect(peer, reason)`` and ``on_error(peer, exc)``. Callbacks must
be quick (enqueue and return); an exception in one is logged and counted (``callback_errors``),
never fatal to the thread. Without ``on_message``, messages go to a bounded inbox read with
``receive(timeout)``; when it is full the oldest entry is dropped (``receive_dropped``).

Sending never blocks the caller (the 1 kHz control loop): ``send`` packs the message in the
caller's thread (so a bad message raises ``ValueError`` there), appends it to each target's
bounded send queue and wakes the I/O thread, which writes without blocking and keeps partial
writes for later. A full queue drops that client's *oldest* queued message (``peer.dropped``);
other clients are unaffected. Messages still queued when a connection closes count as dropped.

Header-version negotiation (server, ``negotiate=True``), as PlusServer and 3D Slicer do: every
client is answered in the highest header version it has sent (``peer.header_version``, v1 until
it sends a v2 message). A v1 client therefore receives v1 messages without metadata or message
ID. A broadcast packs the message once per version in use, not once per client. With
``negotiate=False`` each message goes out in its own ``header_version``.

Garbage from a connection. Every ``DecodeError`` is counted (``peer.malformed``), passed to
``on_error(peer, err)`` and logged as a WARNING with the peer's address (rate-limited to 10 a
second per peer so a flood cannot flood the log). Then:

- ``err.recoverable`` (the 58-byte header was sound: bad CRC, bad extended header, metadata or
  content): the decoder skipped exactly that message and the connection carries on;
- otherwise (unknown header version, BODY_SIZE over ``max_body_size``): the stream cannot be
  re-framed, so the connection is closed (reason ``"protocol error: ..."``).

A connection that ends inside a message reports a ``TruncatedMessageError`` the same way. Other
clients are never affected.

Server admission. A connection from outside ``allowed_peers`` (IPs or CIDR networks) is sent a v1
STATUS with code ACCESS_DENIED (5) and error name ``"ACCESS_DENIED"``, then closed, logged with
its address and counted (``denied``). Past ``max_clients`` a connection is accepted and closed at
once, logged and counted (``rejected``); so is one from outside ``privileged_peers`` when only the
``reserved_slots`` (kept for operators) are left. ``max_buffered`` bounds the bytes of incomplete
messages over all clients together: the client whose read goes over it is closed
(``over_budget``), so many connections each just under the body limit cannot add up. Refusals
are logged within a per-host budget that survives reconnects (``HostLogLimits``).
``idle_timeout`` (seconds) closes clients that sent nothing for that long (reason ``"idle
timeout"``). A client that does not read what we send is closed after ``send_stall_timeout``:
when our writes block, or, long before that, when its advertised receive window shows
``unread_limit`` bytes left unread (``evicted_not_reading``).

Every socket gets TCP_NODELAY and SO_KEEPALIVE (with ~10 s dead-peer detection on Linux); the
listener gets SO_REUSEADDR so a restarted server can bind its port again at once.

The client reconnects after a failed connect or a disconnect, waiting ``backoff[0]`` seconds and
doubling up to ``backoff[1]`` (reset after a connection that lasted a second), until ``stop()``.
Each failed attempt is counted (``connect_failures``) and reported as
``on_error(None, TransportError)``. While disconnected ``send`` returns 0 and counts the
message as dropped: stale commands are never delivered late. ``stop()`` (either side) closes at
once; output still queued is discarded and counted as dropped.
"""

from __future__ import annotations

import errno
import logging
import selectors
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from .. import wire
from ..errors import DecodeError, TransportError, TruncatedMessageError
from ..messages.base import Message
from ..messages.status import StatusCode, StatusMessage
from .common import (
    IO_CHUNK,
    PEER_COUNTERS,
    AccessList,
    CallbackGuard,
    Connection,
    HostLogLimits,
    IdCounter,
    Inbox,
    IOThreadOwner,
    Peer,
    Waker,
    addr_text,
    configure_stream_socket,
    encode,
    should_log,
)

log = logging.getLogger("igtl.transport.tcp")

OnMessage = Callable[[Peer, Message], Any]
OnPeer = Callable[[Peer], Any]
OnDisconnect = Callable[[Peer, str], Any]
OnError = Callable[["Peer | None", BaseException], Any]
Sendable = Message | bytes | bytearray | memoryview

_LISTEN = object()
_WAKE = object()
_READ = selectors.EVENT_READ
_WRITE = selectors.EVENT_WRITE


def _transport_error(err: OSError) -> TransportError:
    exc = TransportError(str(err))
    exc.__cause__ = err
    return exc


def _connect_failure(where: str, err: OSError) -> TransportError:
    exc = TransportError(f"cannot connect to {where}: {err}")
    exc.__cause__ = err
    return exc


class _StreamTransport(IOThreadOwner):
    """What the server and the client share: one selector loop serving Connections."""

    def __init__(
        self,
        *,
        name: str,
        on_message: OnMessage | None,
        on_connect: OnPeer | None,
        on_disconnect: OnDisconnect | None,
        on_error: OnError | None,
        send_queue: int,
        receive_queue: int,
        max_body_size: int,
        crc_check: bool,
    ) -> None:
        if send_queue < 1:
            raise ValueError(f"send_queue must be >= 1, got {send_queue}")
        self.name = name
        self.on_message = on_message
        self.on_connect = on_connect
        self.on_disconnect = on_disconnect
        self.on_error = on_error
        self._send_queue = send_queue
        self._max_body = max_body_size
        self._crc_check = crc_check
        self._inbox = Inbox(receive_queue)
        self._guard = CallbackGuard(name)
        self._next_id = IdCounter()
        self._log_limits = HostLogLimits()
        self._waker = Waker()
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._waker.r, _READ, _WAKE)
        self._dirty: deque[Connection] = deque()
        self._rxbuf = bytearray(IO_CHUNK)
        self._rxview = memoryview(self._rxbuf)
        #: bytes of incomplete messages over all connections (None: each one's body limit only)
        self.max_buffered: int | None = None
        self._over_budget = 0
        self._cond = threading.Condition()
        self._init_io_thread()
        self._closed_totals = dict.fromkeys(PEER_COUNTERS, 0)

    # ------------------------------------------------------------------ public, any thread
    def receive(self, timeout: float | None = None) -> tuple[Peer, Message] | None:
        """Next (peer, message) from the inbox, or None after ``timeout`` seconds (None: wait)."""
        if self.on_message is not None:
            raise RuntimeError("on_message is set, so messages never reach receive()")
        return self._inbox.get(timeout)

    def _launch(self) -> None:
        with self._state_lock:
            super()._launch()

    def _thread_main(self) -> None:
        try:
            self._run()
        except Exception:  # pragma: no cover - a bug; keep the cause visible
            log.exception("%s: I/O thread failed", self.name)
        finally:
            self._shutdown()
            self._release()

    def _run(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def _shutdown(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def _release(self) -> None:
        try:
            self._sel.close()
        finally:
            self._waker.close()

    # ------------------------------------------------------------------ I/O thread
    def _handle(self, key: selectors.SelectorKey, mask: int) -> None:
        conn: Connection = key.data
        if conn.closed:
            return
        try:
            if mask & _READ:
                self._read(conn)
            if mask & _WRITE and not conn.closed:
                self._flush(conn)
        except Exception as err:  # a bug must cost one connection, not the thread
            log.exception("%s: unexpected error on %s", self.name, addr_text(conn.peer.address))
            self._close(conn, f"internal error: {err!r}")

    def _service_wake(self) -> None:
        self._waker.drain()
        dirty = self._dirty
        while dirty:
            conn = dirty.popleft()
            if not conn.closed and not conn.want_write:
                self._flush(conn)

    def _read(self, conn: Connection) -> None:
        peer = conn.peer
        try:
            n = conn.sock.recv_into(self._rxbuf)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as err:
            self._close(conn, f"receive failed: {err}", _transport_error(err))
            return
        if n == 0:
            if conn.decoder.buffered:
                try:
                    conn.decoder.close()
                except TruncatedMessageError as err:
                    self._malformed(conn, err)
            self._close(conn, "closed by peer")
            return
        now = peer.last_received = time.monotonic()
        decoder = conn.decoder
        if not decoder.buffered:
            conn.partial_since = now  # a message starts: it must complete in time
        decoder.feed(self._rxview[:n])
        on_message = self.on_message
        while True:
            try:
                msg = decoder.next_message()
            except DecodeError as err:
                self._malformed(conn, err)
                if not err.recoverable:
                    self._close(conn, f"protocol error: {err}")
                    return
                continue
            if msg is None:
                if self.max_buffered and decoder.buffered:
                    self._check_budget(conn)
                return
            peer.received += 1
            if msg.header_version > peer.header_version:
                peer.note_version(msg.header_version)
            if on_message is not None:
                self._guard(on_message, peer, msg)
            else:
                self._inbox.put((peer, msg))
            if conn.closed:  # a callback disconnected it
                return

    def _open_connections(self) -> list[Connection]:  # pragma: no cover - overridden
        return []

    def _check_budget(self, conn: Connection) -> None:
        """Bytes of messages begun but not complete, over every client, stay within
        ``max_buffered``: the connection whose read went over it is closed (counted)."""
        budget = self.max_buffered
        total = sum(c.decoder.buffered for c in self._open_connections())
        if budget is not None and total > budget:
            self._over_budget += 1
            self._close(
                conn,
                f"{total} bytes buffered over all clients, budget {budget}",
            )

    def _malformed(self, conn: Connection, err: DecodeError) -> None:
        peer = conn.peer
        peer.malformed += 1
        if should_log(peer):
            log.warning(
                "%s: malformed data from %s (%s): %s",
                self.name,
                addr_text(peer.address),
                "message skipped" if err.recoverable else "stream desynchronised, closing",
                err,
            )
        self._guard(self.on_error, peer, err)

    def _flush(self, conn: Connection) -> None:
        try:
            pending = conn.flush()
        except OSError as err:
            self._close(conn, f"send failed: {err}", _transport_error(err))
            return
        if pending != conn.want_write:
            if pending:
                conn.blocked_since = time.monotonic()
            conn.want_write = pending
            self._sel.modify(conn.sock, _READ | _WRITE if pending else _READ, conn)

    def _close(self, conn: Connection, reason: str, error: BaseException | None = None) -> None:
        if conn.closed:
            return
        conn.closed = True
        try:
            self._sel.unregister(conn.sock)
        except (KeyError, ValueError):
            pass
        try:
            conn.sock.close()
        except OSError:
            pass
        peer = conn.peer
        conn.discard_output()
        self._forget(conn)
        totals = self._closed_totals
        for name in PEER_COUNTERS:
            totals[name] += getattr(peer, name)
        log.info("%s: %s disconnected (%s)", self.name, addr_text(peer.address), reason)
        if error is not None:
            self._guard(self.on_error, peer, error)
        self._guard(self.on_disconnect, peer, reason)
        with self._cond:
            self._cond.notify_all()

    def _forget(self, conn: Connection) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def _new_connection(self, sock: socket.socket, address: Any) -> Connection:
        peer = Peer(self._next_id(), address, self._log_limits.get(str(address[0])))
        conn = Connection(
            sock,
            peer,
            send_queue=self._send_queue,
            crc_check=self._crc_check,
            max_body_size=self._max_body,
        )
        self._sel.register(sock, _READ, conn)
        return conn

    def _totals(self, peers: list[Peer]) -> dict[str, int]:
        totals = dict(self._closed_totals)
        for peer in peers:
            for name in PEER_COUNTERS:
                totals[name] += getattr(peer, name)
        return totals


class TCPServer(_StreamTransport):
    """An OpenIGTLink TCP server: many clients, one I/O thread (see the module docstring)."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 18944,
        *,
        on_message: OnMessage | None = None,
        on_connect: OnPeer | None = None,
        on_disconnect: OnDisconnect | None = None,
        on_error: OnError | None = None,
        allowed_peers: list[str] | None = None,
        max_clients: int = 16,
        send_queue: int = 256,
        receive_queue: int = 1024,
        max_body_size: int = wire.DEFAULT_MAX_BODY_SIZE,
        crc_check: bool = True,
        idle_timeout: float | None = None,
        message_timeout: float | None = 10.0,
        send_stall_timeout: float | None = 5.0,
        negotiate: bool = True,
        reserved_slots: int = 0,
        privileged_peers: list[str] | None = None,
        unread_limit: int = 16 * 1024,
        max_buffered: int | None = None,
        name: str = "igtl-tcp-server",
    ) -> None:
        self._check_limits(
            message_timeout=message_timeout,
            send_stall_timeout=send_stall_timeout,
            max_clients=max_clients,
            idle_timeout=idle_timeout,
            reserved_slots=reserved_slots,
            privileged_peers=privileged_peers,
        )
        self._access = AccessList(allowed_peers)
        #: the last ``reserved_slots`` client slots are kept for these hosts (operators), so
        #: viewers or a flood of connections from elsewhere cannot lock them out
        self.reserved_slots = reserved_slots
        self._privileged = AccessList(privileged_peers) if privileged_peers is not None else None
        super().__init__(
            name=name,
            on_message=on_message,
            on_connect=on_connect,
            on_disconnect=on_disconnect,
            on_error=on_error,
            send_queue=send_queue,
            receive_queue=receive_queue,
            max_body_size=max_body_size,
            crc_check=crc_check,
        )
        self.host = host
        self.port = port
        self.max_clients = max_clients
        self.idle_timeout = idle_timeout
        #: a message begun must be complete within this time (a slowloris sender is closed)
        self.message_timeout = message_timeout
        #: a client whose socket takes none of our data for this long is closed (it does not
        #: read; it would hold a slot and its queue forever)
        self.send_stall_timeout = send_stall_timeout
        #: a client that leaves this many of our bytes unread for ``send_stall_timeout`` is
        #: closed too (its kernel buffers would hide a blocked write for minutes); 0 = off
        self.unread_limit = unread_limit
        if max_buffered is not None and max_buffered < 1:
            raise ValueError(f"max_buffered must be positive or None, got {max_buffered}")
        self.max_buffered = max_buffered
        self.negotiate = negotiate
        self.address: tuple[str, int] = (host, port)
        self._init_server_state()

    @staticmethod
    def _check_limits(
        *,
        message_timeout: float | None,
        send_stall_timeout: float | None,
        max_clients: int,
        idle_timeout: float | None,
        reserved_slots: int,
        privileged_peers: list[str] | None,
    ) -> None:
        """ValueError for a timeout that is not positive, fewer than one client slot, or
        reserved slots that leave none for others or that nobody may take."""
        for what, value in (
            ("message_timeout", message_timeout),
            ("send_stall_timeout", send_stall_timeout),
        ):
            if value is not None and value <= 0:
                raise ValueError(f"{what} must be positive or None, got {value}")
        if max_clients < 1:
            raise ValueError(f"max_clients must be >= 1, got {max_clients}")
        if idle_timeout is not None and idle_timeout <= 0:
            raise ValueError(f"idle_timeout must be positive or None, got {idle_timeout}")
        if not 0 <= reserved_slots < max_clients:
            raise ValueError(
                f"reserved_slots must be >= 0 and < max_clients ({max_clients}), "
                f"got {reserved_slots}"
            )
        if reserved_slots and privileged_peers is None:
            raise ValueError("reserved_slots needs privileged_peers (who may take them)")

    def _init_server_state(self) -> None:
        """The listener (opened by :meth:`start`), the connection table, the close queue, the
        counters and the ACCESS_DENIED farewell."""
        self._listener: socket.socket | None = None
        # Published copy-on-write by the I/O thread; senders read it without a lock.
        self._conns: dict[int, Connection] = {}
        self._to_close: deque[tuple[int, str]] = deque()
        self._connections = 0
        self._rejected = 0
        self._denied = 0
        self._accept_errors = 0
        self._idle_closed = 0
        self._slow_closed = 0
        self._evicted = 0
        self._denied_bytes = StatusMessage(
            code=StatusCode.ACCESS_DENIED,
            error_name="ACCESS_DENIED",
            status_message="connection not allowed",
        ).pack()

    # ------------------------------------------------------------------ public, any thread
    def start(self) -> TCPServer:
        """Bind and listen (errors such as a port in use raise here), then start the I/O thread."""
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        try:
            # create_server sets SO_REUSEADDR (POSIX): a restarted server rebinds at once.
            listener = socket.create_server(
                (self.host, self.port), family=family, backlog=max(16, self.max_clients)
            )
        except OSError:
            self.stop()  # release the selector and wake-up sockets
            raise
        listener.setblocking(False)
        self._listener = listener
        self.address = listener.getsockname()[:2]
        self._sel.register(listener, _READ, _LISTEN)
        try:
            self._launch()
        except BaseException:
            self._sel.unregister(listener)
            listener.close()
            raise
        log.info("%s: listening on %s", self.name, addr_text(self.address))
        return self

    @property
    def peers(self) -> list[Peer]:
        """The connected clients (a snapshot)."""
        return [c.peer for c in self._conns.values()]

    def send(self, msg: Sendable, peer: Peer | int | None = None) -> int:
        """Queue ``msg`` for one peer (Peer or id) or all (None); returns how many peers it was
        queued for. Never blocks. Bytes are sent as they are (no negotiation)."""
        if not isinstance(msg, (Message, bytes, bytearray, memoryview)):
            raise TypeError(f"can only send igtl Message or bytes, not {type(msg).__name__}")
        conns = self._conns
        targets: Any
        if peer is None:
            targets = conns.values()
        else:
            conn = conns.get(peer if isinstance(peer, int) else peer.id)
            if conn is None:
                return 0
            targets = (conn,)
        negotiate = self.negotiate and isinstance(msg, Message)
        packed: dict[int | None, bytes] = {}
        count = 0
        for conn in targets:
            version = conn.peer.header_version if negotiate else None
            data = packed.get(version)
            if data is None:
                data = packed[version] = encode(msg, version)
            conn.enqueue(data)
            self._dirty.append(conn)
            count += 1
        if count:
            self._waker.wake()
        return count

    def disconnect(self, peer: Peer | int, reason: str = "closed by server") -> None:
        """Ask the I/O thread to close one client (asynchronous, any thread)."""
        self._to_close.append((peer if isinstance(peer, int) else peer.id, reason))
        self._waker.wake()

    def wait_for_peers(self, n: int = 1, timeout: float = 5.0) -> bool:
        """Wait until at least ``n`` clients are connected."""
        with self._cond:
            return self._cond.wait_for(lambda: len(self._conns) >= n, timeout)

    def stats(self) -> dict[str, Any]:
        """Counters: totals over all connections so far, plus one dict per connected client."""
        peers = self.peers
        out: dict[str, Any] = self._totals(peers)
        out.update(
            rejected=self._rejected,
            denied=self._denied,
            idle_closed=self._idle_closed,
            slow_message_closed=self._slow_closed,
            evicted_not_reading=self._evicted,
            over_budget=self._over_budget,
            connections=self._connections,
            clients=len(peers),
            accept_errors=self._accept_errors,
            receive_dropped=self._inbox.dropped,
            callback_errors=self._guard.errors,
            peers=[p.as_dict() for p in peers],
        )
        return out

    # ------------------------------------------------------------------ I/O thread
    def _run(self) -> None:
        select = self._sel.select
        limits = [
            t for t in (self.idle_timeout, self.message_timeout, self.send_stall_timeout) if t
        ]
        check_every = min([t / 4 for t in limits] + [0.25]) if limits else 1.0
        next_check = time.monotonic() + check_every
        while self._running:
            for key, mask in select(max(0.0, next_check - time.monotonic())):
                data = key.data
                if data is _WAKE:
                    self._service_wake()
                    while self._to_close:
                        pid, reason = self._to_close.popleft()
                        conn = self._conns.get(pid)
                        if conn is not None:
                            self._close(conn, reason)
                elif data is _LISTEN:
                    self._accept()
                else:
                    self._handle(key, mask)
            now = time.monotonic()
            if now >= next_check:
                next_check = now + check_every
                if limits:
                    self._enforce_timeouts(now)

    def _enforce_timeouts(self, now: float) -> None:
        """Free the slots of clients that hold them without being clients: silent ones (idle
        timeout), ones that trickle a message byte by byte (message timeout), ones that do
        not read what we send (send-stall timeout). Each is counted under its own name."""
        idle, slow, stall = self.idle_timeout, self.message_timeout, self.send_stall_timeout
        for conn in list(self._conns.values()):
            if idle and now - conn.peer.last_received > idle:
                self._idle_closed += 1
                self._close(conn, "idle timeout")
            elif slow and conn.decoder.buffered and now - conn.partial_since > slow:
                self._slow_closed += 1
                self._close(conn, f"message not completed within {slow:g} s")
            elif stall and conn.want_write and now - conn.blocked_since > stall:
                self._evicted += 1
                self._close(conn, f"not reading: nothing sent for {stall:g} s")
            elif stall and self.unread_limit:
                backlog = conn.unread_bytes()
                if backlog is None or (backlog[0] < self.unread_limit and not backlog[1]):
                    conn.unread_since = 0.0
                elif not conn.unread_since:
                    conn.unread_since = now
                    conn.unread_sent = conn.peer.sent
                elif now - conn.unread_since > stall and conn.peer.sent > conn.unread_sent + 1:
                    # ... and we went on sending to it: a client that read a big answer and
                    # then only listens advertises its reopened window with its next ACK, so
                    # its shrunken window alone is stale, not proof (the staff console was
                    # closed every 10-40 s after an 18 KB GetStats answer)
                    self._evicted += 1
                    self._close(
                        conn,
                        f"not reading: about {backlog[0]} bytes left unread, {backlog[1]} "
                        f"waiting for its window, for {stall:g} s",
                    )

    def _accept(self) -> None:
        assert self._listener is not None
        while True:
            try:
                sock, address = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as err:
                # e.g. EMFILE: out of descriptors. Count and retry on the next readiness.
                self._accept_errors += 1
                log.error("%s: accept failed: %s", self.name, err)
                return
            self._connections += 1
            where = addr_text(address)
            # refusals are counted always, logged within the host's budget (a peer that
            # reconnects in a loop must not fill the disk)
            if not self._access.allows(address[0]):
                self._denied += 1
                if self._log_limits.get(str(address[0])).allow():
                    log.warning(
                        "%s: connection from %s denied (not in allowed_peers)", self.name, where
                    )
                self._refuse(sock, self._denied_bytes)
                continue
            full = self._full_for(address[0])
            if full:
                self._rejected += 1
                if self._log_limits.get(str(address[0])).allow():
                    log.warning("%s: connection from %s rejected (%s)", self.name, where, full)
                self._refuse(sock, b"")
                continue
            try:
                configure_stream_socket(sock)
                conn = self._new_connection(sock, address)
            except OSError as err:
                log.warning("%s: could not set up connection from %s: %s", self.name, where, err)
                sock.close()
                continue
            conns = dict(self._conns)
            conns[conn.peer.id] = conn
            self._conns = conns
            log.info("%s: %s connected (peer %d)", self.name, where, conn.peer.id)
            self._guard(self.on_connect, conn.peer)
            with self._cond:
                self._cond.notify_all()

    def _open_connections(self) -> list[Connection]:
        return list(self._conns.values())

    def _full_for(self, host: str) -> str:
        """Why a new client from ``host`` cannot have a slot now ('' if it can)."""
        n = len(self._conns)
        if n >= self.max_clients:
            return f"max_clients={self.max_clients} reached"
        if (
            self.reserved_slots
            and n >= self.max_clients - self.reserved_slots
            and self._privileged is not None
            and not self._privileged.allows(host)
        ):
            return f"the last {self.reserved_slots} of {self.max_clients} slots are reserved"
        return ""

    @staticmethod
    def _refuse(sock: socket.socket, farewell: bytes) -> None:
        """Send a short farewell (fits the empty socket buffer), end our side, close. Unread input
        is drained first: closing with unread data would reset the connection and could destroy
        the farewell before the client reads it."""
        try:
            sock.setblocking(False)
            if farewell:
                sock.send(farewell)
            sock.shutdown(socket.SHUT_WR)
            for _ in range(16):
                if not sock.recv(65536):
                    break
        except OSError:
            pass
        finally:
            sock.close()

    def _forget(self, conn: Connection) -> None:
        conns = dict(self._conns)
        conns.pop(conn.peer.id, None)
        self._conns = conns

    def _shutdown(self) -> None:
        for conn in list(self._conns.values()):
            self._close(conn, "server stopped")
        if self._listener is not None:
            try:
                self._sel.unregister(self._listener)
            except (KeyError, ValueError):
                pass
            self._listener.close()
        log.info("%s: stopped", self.name)


class TCPClient(_StreamTransport):
    """An OpenIGTLink TCP client that keeps reconnecting until stopped (module docstring)."""

    def __init__(
        self,
        host: str,
        port: int,
        *,
        on_message: OnMessage | None = None,
        on_connect: OnPeer | None = None,
        on_disconnect: OnDisconnect | None = None,
        on_error: OnError | None = None,
        reconnect: bool = True,
        backoff: tuple[float, float] = (0.05, 2.0),
        connect_timeout: float = 2.0,
        send_queue: int = 256,
        receive_queue: int = 1024,
        max_body_size: int = wire.DEFAULT_MAX_BODY_SIZE,
        crc_check: bool = True,
        name: str = "igtl-tcp-client",
    ) -> None:
        if not 0 < backoff[0] <= backoff[1]:
            raise ValueError(f"backoff must be (first, cap) with 0 < first <= cap, got {backoff}")
        if connect_timeout <= 0:
            raise ValueError(f"connect_timeout must be positive, got {connect_timeout}")
        super().__init__(
            name=name,
            on_message=on_message,
            on_connect=on_connect,
            on_disconnect=on_disconnect,
            on_error=on_error,
            send_queue=send_queue,
            receive_queue=receive_queue,
            max_body_size=max_body_size,
            crc_check=crc_check,
        )
        self.host = host
        self.port = port
        self.reconnect = reconnect
        self.backoff = backoff
        self.connect_timeout = connect_timeout
        self._conn: Connection | None = None
        self._peer: Peer | None = None
        self._drop_lock = threading.Lock()
        self._gave_up = False
        self._dropped_offline = 0
        self._connects = 0
        self._connect_failures = 0
        self._connect_error: TransportError | None = None

    # ------------------------------------------------------------------ public, any thread
    def start(self) -> TCPClient:
        self._launch()
        return self

    @property
    def connected(self) -> bool:
        conn = self._conn
        return conn is not None and not conn.closed

    @property
    def peer(self) -> Peer | None:
        """The server as a Peer: the current connection's, else the last one's (None before)."""
        return self._peer

    def wait_connected(self, timeout: float = 5.0) -> bool:
        """True once connected; False after ``timeout``, or at once when a client without
        ``reconnect`` has given up (or was stopped)."""
        with self._cond:
            return (
                self._cond.wait_for(
                    lambda: self.connected or self._gave_up or self._stopped, timeout
                )
                and self.connected
            )

    def send(self, msg: Sendable, peer: Peer | int | None = None) -> int:
        """Queue ``msg`` (in its own header version) for the server; returns 1, or 0 (counted
        as dropped) when not connected. ``peer`` is for the signature every transport shares:
        None or the server's Peer (or id); another peer, e.g. that of an earlier connection,
        gets 0 (a stale reply must not reach a new connection). Never blocks."""
        data = encode(msg)
        conn = self._conn
        if conn is None or conn.closed:
            with self._drop_lock:
                self._dropped_offline += 1
            return 0
        if peer is not None and (peer if isinstance(peer, int) else peer.id) != conn.peer.id:
            with self._drop_lock:
                self._dropped_offline += 1
            return 0
        conn.enqueue(data)
        self._dirty.append(conn)
        self._waker.wake()
        return 1

    def stats(self) -> dict[str, Any]:
        peer = self._peer
        conn = self._conn
        live = [peer] if peer is not None and conn is not None and not conn.closed else []
        out: dict[str, Any] = self._totals(live)
        out["dropped"] += self._dropped_offline
        out.update(
            connected=bool(live),
            connects=self._connects,
            connect_failures=self._connect_failures,
            receive_dropped=self._inbox.dropped,
            callback_errors=self._guard.errors,
            peer=peer.as_dict() if peer is not None else None,
        )
        return out

    # ------------------------------------------------------------------ I/O thread
    def _run(self) -> None:
        first, cap = self.backoff
        delay = first
        while self._running:
            sock, address = self._connect()
            if sock is not None:
                started = time.monotonic()
                self._serve(sock, address)
                if time.monotonic() - started >= 1.0:
                    delay = first
            elif self._running:
                self._connect_failures += 1
                if self._connect_error is not None:
                    self._guard(self.on_error, None, self._connect_error)
            if not (self._running and self.reconnect):
                break
            self._pause(delay)
            delay = min(delay * 2, cap)
        # wake wait_connected() callers: this client will not connect any more
        self._gave_up = True
        with self._cond:
            self._cond.notify_all()

    def _pause(self, seconds: float) -> None:
        """Wait, but return at once when stop() wakes us."""
        deadline = time.monotonic() + seconds
        while self._running:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return
            for key, _mask in self._sel.select(remaining):
                if key.data is _WAKE:
                    self._service_wake()

    def _connect(self) -> tuple[socket.socket | None, Any]:
        where = f"{self.host}:{self.port}"
        self._connect_error = None
        try:
            family, kind, proto, _, address = socket.getaddrinfo(
                self.host, self.port, type=socket.SOCK_STREAM
            )[0]
            sock = socket.socket(family, kind, proto)
        except OSError as err:
            log.info("%s: cannot connect to %s: %s", self.name, where, err)
            self._connect_error = _connect_failure(where, err)
            return None, None
        try:
            sock.setblocking(False)
            code = sock.connect_ex(address)
            if code not in (0, errno.EINPROGRESS, errno.EWOULDBLOCK, errno.EALREADY):
                raise OSError(code, errno.errorcode.get(code, str(code)))
            if code:
                self._sel.register(sock, _WRITE, None)
                try:
                    deadline = time.monotonic() + self.connect_timeout
                    ready = False
                    while self._running and not ready:
                        remaining = deadline - time.monotonic()
                        if remaining <= 0:
                            raise TimeoutError(f"no answer within {self.connect_timeout} s")
                        for key, _mask in self._sel.select(remaining):
                            if key.data is _WAKE:
                                self._service_wake()
                            else:
                                ready = True
                    if not ready:  # stopping
                        sock.close()
                        return None, None
                finally:
                    self._sel.unregister(sock)
                code = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
                if code:
                    raise OSError(code, errno.errorcode.get(code, str(code)))
            configure_stream_socket(sock)
            return sock, address
        except OSError as err:
            log.info("%s: cannot connect to %s: %s", self.name, where, err)
            self._connect_error = _connect_failure(where, err)
            sock.close()
            return None, None

    def _serve(self, sock: socket.socket, address: Any) -> None:
        conn = self._new_connection(sock, address)
        self._peer = conn.peer
        self._conn = conn
        self._connects += 1
        log.info("%s: connected to %s", self.name, addr_text(address))
        self._guard(self.on_connect, conn.peer)
        with self._cond:
            self._cond.notify_all()
        select = self._sel.select
        while self._running and not conn.closed:
            for key, mask in select(1.0):
                if key.data is _WAKE:
                    self._service_wake()
                else:
                    self._handle(key, mask)
        if not conn.closed:
            self._close(conn, "client stopped")

    def _forget(self, conn: Connection) -> None:
        pass  # ``connected`` reads conn.closed

    def _shutdown(self) -> None:
        conn = self._conn
        if conn is not None and not conn.closed:
            self._close(conn, "client stopped")
