"""The console's side of OpenIGTLink: one operator connection per daemon, and a poller.

Each :class:`DaemonLink` is an ordinary operator client (``igtl.transport.TCPClient``: its own
I/O thread, reconnecting with back-off when the daemon restarts). On connecting it asks
``GetState``; then the :class:`Console`'s poll thread asks ``GetStats`` (``Format="json"``,
``Histogram="lateness"``) ``poll_hz`` times a second, and never asks again while an answer is
outstanding (a slow or stuck daemon is not sent a queue of requests). Whatever the daemon sends
(its greeting, state changes, alerts, replies) lands in the link's
:class:`~occ_console.model.DaemonView` on the I/O thread; nothing here runs on the web server's
event loop, which reads snapshots and sends commands (``send`` never blocks).

Commands (Enable, Run, Stop, EStop, Reset, Disable) go as COMMAND with a fresh ``command_id``;
:meth:`DaemonLink.command` returns a ``concurrent.futures.Future`` completed by the daemon's
RTS_COMMAND (or failed with :class:`CommandTimeout` after ``timeout`` seconds, by the poll
thread). With a shared key (``--auth-key-file``, the daemon's ``auth_key_file``) every message
out is signed and every message in is checked; one without a valid tag is counted and ignored.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import Any

import igtl
from igtl.auth import sign, verify
from igtl.messages.base import Message
from igtl.transport import TCPClient

from .model import DaemonView

log = logging.getLogger("occ_console")

#: the operator commands the console sends (its buttons and POST endpoints)
COMMANDS = ("Enable", "Run", "Stop", "EStop", "Reset", "Disable")

#: the device name of every message the console sends (the daemon's log shows it)
DEVICE = "occ-console"


class CommandTimeout(Exception):
    """The daemon did not answer a command in time (or the link went down first)."""


def parse_endpoint(text: str) -> tuple[str, int]:
    """``HOST:PORT`` -> (host, port); ValueError with the reason otherwise."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"expected HOST:PORT, got {text!r}")
    return host, int(port)


class DaemonLink:
    """One daemon's operator connection and its view (module docstring)."""

    def __init__(
        self,
        view: DaemonView,
        *,
        auth_key: bytes | None = None,
        on_change: Callable[[], None] = lambda: None,
        stats_timeout: float = 5.0,
    ) -> None:
        self.view = view
        self.auth_key = auth_key
        self.on_change = on_change
        self.stats_timeout = stats_timeout
        self._lock = threading.Lock()
        self._next_id = 0
        # command id -> (name, future, deadline)
        self._pending: dict[int, tuple[str, Future[dict[str, Any]], float]] = {}
        self._stats_asked = 0.0  # monotonic time of the outstanding GetStats (0: none)
        self.stats_asked = 0
        self.stats_timeouts = 0
        self.client = TCPClient(
            view.host,
            view.port,
            on_message=self._on_message,
            on_connect=self._on_connect,
            on_disconnect=self._on_disconnect,
            on_error=self._on_error,
            backoff=(0.2, 2.0),
            name=f"occ-console-igtl-{view.id}",
        )

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> DaemonLink:
        self.client.start()
        return self

    def stop(self) -> None:
        self.client.stop()
        self._fail_pending("the console is stopping")

    # ------------------------------------------------------------------ sending (any thread)
    def _send(self, msg: Message) -> bool:
        if self.auth_key is not None:
            msg = sign(msg, self.auth_key)
        return self.client.send(msg) == 1

    def _command_message(self, name: str, xml: str = "") -> tuple[int, Message]:
        with self._lock:
            self._next_id = (self._next_id + 1) & 0xFFFFFFFF
            cid = self._next_id
        msg = igtl.CommandMessage(
            command_id=cid,
            command_name=name,
            command=xml,
            device_name=DEVICE,
            header_version=2,
            message_id=cid,
            timestamp=time.time(),
        )
        return cid, msg

    def command(self, name: str, timeout: float = 3.0) -> Future[dict[str, Any]]:
        """Send operator command ``name``; the future gets ``{"command", "ok", "message"}``
        from the daemon's reply, or CommandTimeout."""
        fut: Future[dict[str, Any]] = Future()
        cid, msg = self._command_message(name)
        with self._lock:
            self._pending[cid] = (name, fut, time.monotonic() + timeout)
        if not self._send(msg):
            with self._lock:
                self._pending.pop(cid, None)
            fut.set_exception(CommandTimeout(f"{self.view.address} is not connected"))
        return fut

    def expire(self, mono: float) -> None:
        """Fail the commands that were not answered in time; forget a GetStats that was not
        answered within ``stats_timeout`` (the next poll asks again)."""
        with self._lock:
            expired = [(cid, p) for cid, p in self._pending.items() if p[2] <= mono]
            for cid, _ in expired:
                del self._pending[cid]
            if self._stats_asked and mono - self._stats_asked > self.stats_timeout:
                self.stats_timeouts += 1
                self._stats_asked = 0.0
        for _, (name, fut, _) in expired:
            if not fut.done():
                fut.set_exception(CommandTimeout(f"{name}: no answer from {self.view.address}"))

    def poll(self, mono: float) -> None:
        """On the poll thread: ask for statistics unless an answer is outstanding."""
        self.expire(mono)
        with self._lock:
            asked = self._stats_asked
        if asked or not self.client.connected:
            return
        _, msg = self._command_message(
            "GetStats", '<Command Name="GetStats" Format="json" Histogram="lateness"/>'
        )
        with self._lock:
            self._stats_asked = mono
        if self._send(msg):
            self.stats_asked += 1
        else:
            with self._lock:
                self._stats_asked = 0.0

    def _fail_pending(self, why: str) -> None:
        with self._lock:
            pending = list(self._pending.values())
            self._pending.clear()
            self._stats_asked = 0.0
        for name, fut, _ in pending:
            if not fut.done():
                fut.set_exception(CommandTimeout(f"{name}: {why}"))

    # ------------------------------------------------------------------ the I/O thread
    def _on_connect(self, peer: Any) -> None:
        with self.view.lock:
            self.view.on_connect(time.time())
        _, msg = self._command_message("GetState")
        self._send(msg)
        self.on_change()

    def _on_disconnect(self, peer: Any, reason: str) -> None:
        with self.view.lock:
            self.view.on_disconnect(time.time(), reason)
        self._fail_pending(f"connection to {self.view.address} lost ({reason})")
        self.on_change()

    def _on_error(self, peer: Any, exc: BaseException) -> None:
        with self.view.lock:
            self.view.on_link_error(str(exc))

    def _on_message(self, peer: Any, msg: Message) -> None:
        if self.auth_key is not None and verify(msg, self.auth_key):
            with self.view.lock:
                self.view.unauthenticated += 1
            return
        t = msg.timestamp if msg.timestamp > 0.0 else time.time()
        mtype = msg.message_type
        view = self.view
        if mtype == "STATUS":
            with view.lock:
                view.on_status(
                    t,
                    msg.device_name,
                    int(getattr(msg, "code", 0)),
                    str(getattr(msg, "error_name", "")),
                    str(getattr(msg, "status_message", "")),
                )
        elif mtype == "STRING" and msg.device_name == "STATS":
            with self._lock:
                self._stats_asked = 0.0
            text = str(getattr(msg, "string", ""))
            # a keep-alive (an empty STATUS, which the daemon's interface thread only counts)
            # after every answer: the daemon judges whether a client reads by the receive
            # window it last advertised, and the ACK of an answer advertises a window short
            # by that answer (read a moment later). Without a newer segment from us that
            # stale window stood until the next poll, and answers over the daemon's
            # unread_limit_kib (16 KiB; the lateness buckets make them 15-30 KiB) looked like
            # a client that does not read: closed after send_stall_timeout_s (5 s)
            self._send(igtl.StatusMessage(device_name=DEVICE, header_version=2))
            try:
                stats = json.loads(text)
                if not isinstance(stats, dict):
                    raise ValueError("not a JSON object")
            except ValueError as err:
                with view.lock:
                    view.bad_stats += 1
                log.warning("%s: unreadable GetStats answer: %s", view.address, err)
                return
            with view.lock:
                view.on_stats(time.time(), time.monotonic(), stats)
        elif mtype == "RTS_COMMAND":
            self._on_reply(t, msg)
        else:
            return
        self.on_change()

    def _on_reply(self, t: float, msg: Message) -> None:
        cid = int(getattr(msg, "command_id", 0))
        ok = msg.metadata.get("Status") == "SUCCESS"
        text = str(msg.metadata.get("Message", ""))
        name = str(getattr(msg, "command_name", ""))
        with self._lock:
            pending = self._pending.pop(cid, None)
            if name == "GetStats":  # refused (busy): ask again at the next poll
                self._stats_asked = 0.0
        view = self.view
        with view.lock:
            if name == "GetState" and ok:
                view.on_state_reply(t, text)
            elif pending is not None:
                view.on_reply(t, pending[0], ok, text)
        if pending is not None and not pending[1].done():
            pending[1].set_result({"command": pending[0], "ok": ok, "message": text})


class Console:
    """The daemons the console watches, and the thread that polls them."""

    def __init__(
        self,
        endpoints: Sequence[tuple[str, int]],
        *,
        poll_hz: float = 2.0,
        window_s: float = 10.0,
        auth_key: bytes | None = None,
    ) -> None:
        if not 0.1 <= poll_hz <= 10.0:
            raise ValueError(f"poll_hz must be 0.1..10 (a modest rate), got {poll_hz}")
        self.poll_hz = poll_hz
        self._listeners: list[Callable[[], None]] = []
        self.links = [
            DaemonLink(
                DaemonView(str(i), host, port, window_s=window_s),
                auth_key=auth_key,
                on_change=self._changed,
            )
            for i, (host, port) in enumerate(endpoints)
        ]
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def link(self, ident: str) -> DaemonLink | None:
        for link in self.links:
            if link.view.id == ident:
                return link
        return None

    def add_listener(self, fn: Callable[[], None]) -> None:
        """``fn()`` after every change (on an I/O thread: it must only hand over)."""
        self._listeners.append(fn)

    def remove_listener(self, fn: Callable[[], None]) -> None:
        if fn in self._listeners:
            self._listeners.remove(fn)

    def _changed(self) -> None:
        for fn in list(self._listeners):
            try:
                fn()
            except Exception:  # noqa: BLE001 - a listener must not end an I/O thread
                log.exception("console listener failed")

    def snapshot(self) -> list[dict[str, Any]]:
        out = []
        now = time.time()
        for link in self.links:
            with link.view.lock:
                snap = link.view.snapshot(now)
            snap["link"]["stats_asked"] = link.stats_asked
            snap["link"]["stats_timeouts"] = link.stats_timeouts
            out.append(snap)
        return out

    def start(self) -> Console:
        for link in self.links:
            link.start()
        self._thread = threading.Thread(target=self._poll, name="occ-console-poll", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        for link in self.links:
            link.stop()

    def _poll(self) -> None:
        period = 1.0 / self.poll_hz
        next_t = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            due = now >= next_t
            if due:
                # behind (a suspended laptop): the next poll a period from now, no burst
                next_t = next_t + period if next_t + period > now else now + period
            for link in self.links:
                try:
                    link.poll(now) if due else link.expire(now)
                except Exception:  # noqa: BLE001 - one link's trouble must not stop the rest
                    log.exception("%s: poll failed", link.view.address)
            # short waits: an unanswered command fails within 0.1 s of its timeout
            self._stop.wait(min(0.1, max(0.0, next_t - time.monotonic())))
