"""InterfaceManager: all network I/O of a daemon, and the queues that feed the control loop.

Each configured interface is one igtl transport (TCP server, TCP client or UDP endpoint) with its
own I/O thread, or an in-process channel (``inproc``: no thread, delivered on the sender's).
Those threads never touch robot state: they only put what arrives into queues whose meaning is
explicit (shared/DESIGN.md, "Queues"):

- :class:`StreamQueue` for pose streams (POSITION/TRANSFORM at up to 500 Hz): bounded, drained
  fully every tick, so the loop sees every sequence number (for the loss monitor) and uses the
  newest sample. When the loop falls behind, the oldest samples are dropped and counted.
- :class:`CommandQueue` for operator commands and other discrete requests (COMMAND, STRING
  ``CMD_*``, GET_*, VFIXTURE...): a bounded FIFO, never merged or silently dropped. A full queue
  answers the sender at once with an error reply; nothing is lost without the sender knowing.

Outgoing messages go through :meth:`InterfaceManager.send`, which only queues them on the
transport (never blocks the loop). A UDP interface without a ``remote`` (a slave's master
link) sends its outputs to its stream's owner, the master that streams to it: the return
channel (occ/haptics/returnlink.py); until a master is known they have nowhere to go and are not
built (``sends_to_owner``). Rate decimation of outputs is done by the robot's output
scheduler; a slow TCP client loses its own oldest data inside the transport.

Routing of an incoming message on interface *I*:

1. Operator requests (COMMAND, STRING whose device name starts with ``CMD_``, and every
   GET_/STT_/STP_ query), by the sender's role (:meth:`Interface.peer_role`): an ``operator``
   may ask anything; a ``viewer`` (3D Slicer) may query (GET_*, and the read-only commands
   ``GetState`` and ``GetStats``, the latter without sequence numbers); on a ``none``
   interface (a data link) nothing. A request the role does not allow is refused at once with
   an error reply (RTS_COMMAND / ``ACK_`` STRING / STATUS ACCESS_DENIED), logged (rate-limited)
   and counted; the others are parsed here (XML included) and enter the command queue.
2. A type listed in *I*'s ``inputs``: into that input's queue (``stream`` or ``command``).
3. STATUS (3D Slicer's greeting, PLUS keep-alives): counted as keep-alive, not an error.
4. Anything else: counted as ``unexpected`` and logged once per (interface, type).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from mypy_extensions import mypyc_attr

import igtl
from igtl.auth import ReplayGuard, load_key, sign, verify
from igtl.codec import unpack
from igtl.messages.base import Message, join_wire
from igtl.transport import InprocTransport, Peer, TCPClient, TCPServer, UDPEndpoint
from igtl.transport.common import AccessList, RateLimit
from occ.errors import CommandError
from occ.net.commands import READ_ONLY_COMMANDS, error_reply, parse_request
from occ.net.decoders import decode, pose_sample

log = logging.getLogger(__name__)

COMMAND_TYPES = frozenset({"COMMAND"})
#: commands a viewer may send: they read, never act (names compared in lower case)
ROLES = ("none", "viewer", "operator")
_TRANSPORT_REFUSALS = (
    "over_budget",
    "denied",
    "rejected",
    "idle_closed",
    "slow_message_closed",
    "evicted_not_reading",
)
QUERY_PREFIXES = ("GET_", "STT_", "STP_")


@dataclass(slots=True)
class Inbound:
    """One received message, as the loop sees it: the message as it came (for the recording
    and for replies) and, for an input a controller takes, its typed event (occ/events.py,
    decoded here once: the controllers only ever see that)."""

    interface: str
    peer: Peer
    msg: Message
    t_rx: float  # clock time at reception (the daemon clock, monotonic seconds)
    #: operator requests are parsed (XML included) on the interface thread, never by the loop
    request: Any = None
    #: the sender's role when it was received (``operator`` or ``viewer``)
    role: str = "operator"
    #: the decoded input (a pose sample, a point list...; None for an operator request)
    event: Any = None


#: what a stream queue holds: a received message with its event (a pose or a discrete input)
StreamItem = Inbound


def stream_item(interface: str, peer: Peer, msg: Message, t_rx: float) -> StreamItem:
    """A stream's message as the loop takes it, decoded once (on the interface thread): a
    pose as a typed sample (one object: the 500 Hz path), another input (fixture definitions,
    keyframes) as its event. The black box rebuilds its items with it (from their bytes)."""
    sample = pose_sample(interface, peer, msg, t_rx)
    event = sample if sample is not None else decode(interface, peer, msg, t_rx)
    return Inbound(interface, peer, msg, t_rx, event=event)


def rebuild_stream_item(interface: str, peer: Peer, wire: Any, t_rx: float) -> StreamItem:
    """A stream item kept as its message's wire bytes (``Message._wire``: bytes, or the
    decoder's pieces) rebuilt as :func:`stream_item` built it (the black box's writer)."""
    data = wire if isinstance(wire, bytes) else join_wire(wire)
    return stream_item(interface, peer, unpack(data, crc_check=False), t_rx)


class StreamQueue:
    """Bounded queue of stream inputs (typed pose samples, or the discrete inputs that share
    a stream: fixture definitions, keyframes), drained fully each tick; oldest dropped when full.

    A sample pushed out by a full queue was received in time by the daemon, which itself could
    not take it (its loop stalled): it is counted as a *local overflow* (``dropped``), never
    as network loss, and kept in a second bounded queue (:meth:`drain_overflow`) so that the
    loss monitor's sequence accounting still sees every number that arrived. Only when that
    one overflows too (``overflow_lost``: a loop stalled for thousands of samples) are
    numbers forgotten.

    ``pending`` and ``evicted`` are the two deques, public so that the loop can test them
    without a call each tick (``if q.pending``); only this class's methods change them.
    """

    __slots__ = ("pending", "evicted", "_lock", "depth", "received", "dropped", "overflow_lost")

    def __init__(self, depth: int = 10, overflow_depth: int = 4096) -> None:
        self.pending: deque[StreamItem] = deque()
        self.evicted: deque[StreamItem] = deque(maxlen=overflow_depth)
        self._lock = threading.Lock()
        self.depth = depth
        self.received = 0
        self.dropped = 0
        self.overflow_lost = 0

    def put(self, item: StreamItem) -> bool:
        with self._lock:
            dq = self.pending
            if len(dq) >= self.depth:
                ev = self.evicted
                if len(ev) == ev.maxlen:
                    self.overflow_lost += 1
                ev.append(dq.popleft())
                self.dropped += 1
            dq.append(item)
            self.received += 1
        return True

    def drain(self) -> list[StreamItem]:
        """Every queued sample, oldest first (the queue is left empty)."""
        with self._lock:
            out = list(self.pending)
            self.pending.clear()
        return out

    def drain_overflow(self) -> list[StreamItem]:
        """The samples pushed out since the last call (for accounting only), oldest first."""
        with self._lock:
            out = list(self.evicted)
            self.evicted.clear()
        return out

    def __len__(self) -> int:
        return len(self.pending)


class CommandQueue:
    """Bounded FIFO of discrete requests; ``put`` returns False when full (caller must answer).

    ``pending`` is the deque, tested by the loop without a call (``if q.pending``)."""

    __slots__ = ("pending", "_lock", "depth", "received", "refused")

    def __init__(self, depth: int = 64) -> None:
        self.pending: deque[Inbound] = deque()
        self._lock = threading.Lock()
        self.depth = depth
        self.received = 0
        self.refused = 0

    def put(self, item: Inbound) -> bool:
        with self._lock:
            if len(self.pending) >= self.depth:
                self.refused += 1
                return False
            self.pending.append(item)
            self.received += 1
            return True

    def drain(self, limit: int | None = None) -> list[Inbound]:
        out: list[Inbound] = []
        with self._lock:
            while self.pending and (limit is None or len(out) < limit):
                out.append(self.pending.popleft())
        return out

    def __len__(self) -> int:
        return len(self.pending)


def is_operator_request(msg: Message) -> bool:
    """COMMAND, a PLUS-style ``CMD_<id>`` STRING, or a GET_/STT_/STP_ query."""
    mtype = msg.message_type
    if mtype in COMMAND_TYPES or mtype.startswith(QUERY_PREFIXES):
        return True
    return mtype == "STRING" and msg.device_name.startswith("CMD_")


@dataclass
class InterfaceCounters:
    received: int = 0
    keepalive: int = 0
    unexpected: int = 0
    refused: int = 0
    foreign: int = 0  # stream samples from a sender that does not own the stream
    unauthenticated: int = 0  # messages without a valid HMAC on an interface with a key
    replayed: int = 0  # signed requests refused as replays (seen before, or too old)
    malformed: int = 0
    sent: int = 0
    send_dropped: int = 0
    no_destination: int = 0  # outputs of a return channel before any master streamed to it
    unexpected_types: set[str] = field(default_factory=set)


class Interface:
    """One configured network interface: a transport plus routing rules."""

    def __init__(
        self,
        cfg: Any,
        manager: InterfaceManager,
        *,
        clock_now: Callable[[], float],
        poll_streams: bool = False,
    ) -> None:
        self.cfg = cfg
        self.poll_streams = poll_streams
        self.name: str = cfg.name
        self.role: str = cfg.role
        #: operator addresses on an operator interface; None = every allowed peer
        self._operators = (
            AccessList([str(n) for n in cfg.operators]) if cfg.operators is not None else None
        )
        self.manager = manager
        self._now = clock_now
        self.counters = InterfaceCounters()
        self._log_limit = RateLimit(5)
        #: (host, port) the stream inputs must come from: configured, else the first sender
        self.configured_source: tuple[str, int] | None = (
            _split_remote(cfg.stream_source) if getattr(cfg, "stream_source", None) else None
        )
        self.stream_owner = self.configured_source
        #: a UDP link without ``remote``: its outputs go back to its stream's owner
        self.sends_to_owner: bool = cfg.transport == "udp" and not getattr(cfg, "remote", None)
        # type name -> queue for this interface's declared inputs
        self.streams: dict[str, StreamQueue] = {}
        self.command_inputs: set[str] = set()
        self.input_devices: dict[str, str | None] = {}
        for inp in cfg.inputs:
            self.input_devices[inp.type] = inp.device
            if inp.queue == "stream":
                self.streams[inp.type] = StreamQueue(inp.depth)
            else:
                self.command_inputs.add(inp.type)
        #: shared key: sent messages are signed, received ones must carry a valid tag
        self.auth_key: bytes | None = (
            load_key(cfg.auth_key_file.read_text(encoding="utf-8"))
            if getattr(cfg, "auth_key_file", None)
            else None
        )
        #: a signed request is taken once, within its window (judged on real time: the
        #: senders' clocks)
        self._replay = ReplayGuard(cfg.auth_max_age_s) if self.auth_key is not None else None
        self.transport = self._make_transport()

    def _make_transport(self) -> TCPServer | TCPClient | UDPEndpoint | InprocTransport:
        cfg = self.cfg
        allowed = [str(p) for p in cfg.allowed_peers] if cfg.allowed_peers else None
        common: dict[str, Any] = {"on_message": self._on_message, "on_error": self._on_error}
        # A server answers each client in the header version it has spoken (version 1 until it
        # sends a v2 message). A keyed interface signs in v2 metadata, which version 1 would
        # drop: it sends everything in v2 (a client that cannot read v2 cannot check tags).
        negotiate = self.auth_key is None
        if cfg.transport == "tcp-server":
            return TCPServer(
                cfg.host,
                cfg.port,
                negotiate=negotiate,
                allowed_peers=allowed,
                max_clients=cfg.max_clients,
                send_queue=cfg.send_queue,
                idle_timeout=cfg.idle_timeout_s,
                message_timeout=cfg.message_timeout_s,
                send_stall_timeout=cfg.send_stall_timeout_s,
                unread_limit=cfg.unread_limit_kib * 1024,
                max_buffered=1024
                * (
                    cfg.max_buffered_kib
                    if cfg.max_buffered_kib is not None
                    else max(8192, 2 * cfg.max_body_kib)
                ),
                max_body_size=cfg.max_body_kib * 1024,
                reserved_slots=cfg.operator_slots if cfg.operators is not None else 0,
                privileged_peers=(
                    [str(n) for n in cfg.operators] if cfg.operators is not None else None
                ),
                name=f"igtl-{self.name}",
                on_connect=self._on_connect,
                on_disconnect=self._on_disconnect,
                **common,
            )
        if cfg.transport == "tcp-client":
            host, port = _split_remote(cfg.remote)
            return TCPClient(
                host,
                port,
                send_queue=cfg.send_queue,
                max_body_size=cfg.max_body_kib * 1024,
                name=f"igtl-{self.name}",
                on_connect=self._on_connect,
                on_disconnect=self._on_disconnect,
                **common,
            )
        if cfg.transport == "udp":
            remote = _split_remote(cfg.remote) if cfg.remote else None
            return UDPEndpoint(
                cfg.host,
                cfg.port,
                remote=remote,
                allowed_peers=allowed,
                max_body_size=cfg.max_body_kib * 1024,
                # a stream the loop polls each tick needs no thread waking per datagram
                polled=self.poll_streams and bool(self.streams),
                # a pure sender (the master's stream) hears "nobody listens" from the kernel
                connect_remote=remote is not None and not cfg.inputs,
                name=f"igtl-{self.name}",
                **common,
            )
        if cfg.transport == "inproc":
            # a daemon's interface serves its peers as a tcp-server does: each answered in the
            # header version it speaks (peers announce theirs on joining the channel)
            return InprocTransport(
                cfg.channel,
                address=(cfg.host, cfg.port) if cfg.port else None,
                header_version=cfg.header_version,
                negotiate=negotiate,
                allowed_peers=allowed,
                max_peers=cfg.max_clients,
                max_body_size=cfg.max_body_kib * 1024,
                name=f"igtl-{self.name}",
                on_connect=self._on_connect,
                on_disconnect=self._on_disconnect,
                **common,
            )
        raise ValueError(f"unknown transport {cfg.transport!r}")

    # ------------------------------------------------------------------ I/O thread side
    def _on_connect(self, peer: Peer) -> None:
        log.info("%s: %s:%s connected", self.name, *peer.address[:2])
        self.manager._notify_connect(self, peer)

    def _on_disconnect(self, peer: Peer, reason: str) -> None:
        log.info("%s: %s:%s disconnected (%s)", self.name, *peer.address[:2], reason)

    def _on_error(self, peer: Peer | None, exc: BaseException) -> None:
        self.counters.malformed += 1
        addr = f"{peer.address[0]}:{peer.address[1]}" if peer is not None else "?"
        # The transport logs each one too; keep ours at debug to avoid double lines.
        log.debug("%s: malformed message from %s: %s", self.name, addr, exc)

    def _on_message(self, peer: Peer, msg: Message) -> None:
        """From the transport (its I/O thread): routed (:meth:`route`), a stream item into
        its queue for the loop."""
        item = self.route(peer, msg)
        if item is not None:
            self.streams[msg.message_type].put(item)

    def route(self, peer: Peer, msg: Message) -> StreamItem | None:
        """Every check and routing rule of the module docstring for one received message:
        refused, counted, queued as a request or answered here (None), or returned: a stream
        item (an accepted pose as a typed sample, or a discrete input of a stream queue) for
        the queue of its type, ``streams[msg.message_type]``. The loop that reads a socket
        itself hands the item straight to its tick; the I/O thread queues it."""
        c = self.counters
        c.received += 1
        if self.auth_key is not None:
            why = verify(msg, self.auth_key)
            if why:
                # not answered: a peer without the key learns nothing from this interface
                c.unauthenticated += 1
                if self._log_limit.allow():
                    log.warning(
                        "%s: refused %s from %s:%s: %s",
                        self.name,
                        msg.message_type,
                        *peer.address[:2],
                        why,
                    )
                return None
        mtype = msg.message_type
        t_rx = self._now()
        stream = self.streams.get(mtype)
        if stream is not None:
            want = self.input_devices.get(mtype)
            if want is None or want == msg.device_name:
                owner = self.stream_owner
                source = peer.address  # already (host, port): no tuple per datagram
                if owner is None:
                    # an ephemeral sender: the first one owns the stream until a Reset
                    self.stream_owner = owner = source
                    log.info("%s: stream owned by %s:%s", self.name, *source)
                    self._pin(source)
                if source != owner:
                    c.foreign += 1
                    if self._log_limit.allow():
                        log.warning(
                            "%s: refused %s from %s:%s: the stream belongs to %s:%s",
                            self.name,
                            mtype,
                            *source,
                            *owner,
                        )
                    return None
                # decoded here, once: a pose as a typed sample (one object: the 500 Hz
                # path), another input (fixture definitions, keyframes) as its event
                return stream_item(self.name, peer, msg, t_rx)
        if is_operator_request(msg) or mtype in self.command_inputs:
            self._command_input(peer, msg, t_rx)
            return None
        if mtype == "STATUS":
            c.keepalive += 1
            return None
        self._unexpected(peer, mtype)
        return None

    def _command_input(self, peer: Peer, msg: Message, t_rx: float) -> None:
        """An operator request or a discrete input routed to the command queue: judged (replay,
        the sender's role, the request's form), then queued, or refused with an answer."""
        c = self.counters
        mtype = msg.message_type
        item = Inbound(self.name, peer, msg, t_rx)
        request = is_operator_request(msg)
        replay = self._replay
        if replay is not None and (why := replay.check(msg, time.time())):
            c.replayed += 1  # answered: a sender with the key learns why (its clock?)
            self._refuse(item, f"{mtype} refused: {why}", igtl.StatusCode.ACCESS_DENIED)
            return
        # an operator request is judged by the sender's role even where its type is also
        # listed as an input (a viewer must not become an operator by the config's inputs)
        if request:
            role = self.peer_role(peer)
            if role == "none":
                self._refuse(
                    item,
                    f"interface {self.name} is a data link: it takes no requests",
                    igtl.StatusCode.ACCESS_DENIED,
                )
                return
            try:
                req = parse_request(msg)
            except CommandError as err:
                self._refuse(item, str(err), igtl.StatusCode.ILLEGAL_INSTRUCTION)
                return
            if (
                role == "viewer"
                and req.kind != "query"
                and req.name.strip().lower() not in READ_ONLY_COMMANDS
            ):
                self._refuse(
                    item,
                    f"{req.name}: a viewer may query but not command the robot; send "
                    "commands to an operator interface",
                    igtl.StatusCode.ACCESS_DENIED,
                )
                return
            item.request = req
            item.role = role
        else:  # a discrete input routed to the command queue (e.g. VFIXTURE): decoded
            item.event = decode(self.name, peer, msg, t_rx)
        if not self.manager.commands.put(item):
            self._refuse(item, "command queue full", igtl.StatusCode.BUSY)

    def _unexpected(self, peer: Peer, mtype: str) -> None:
        """A message this interface does not take: counted, its type logged once."""
        c = self.counters
        c.unexpected += 1
        if mtype not in c.unexpected_types:
            c.unexpected_types.add(mtype)
            log.info(
                "%s: ignoring unexpected %s from %s:%s (counted)",
                self.name,
                mtype,
                *peer.address[:2],
            )

    def peer_role(self, peer: Peer) -> str:
        """``operator``, ``viewer`` or ``none``: what this peer may ask on this interface."""
        role = self.role
        if role == "operator" and self._operators is not None:
            return "operator" if self._operators.allows(peer.address[0]) else "viewer"
        return role

    @property
    def answers(self) -> bool:
        """Whether clients of this interface are told the robot's state (viewers, operators)."""
        return self.role != "none"

    def _refuse(self, item: Inbound, reason: str, code: int) -> None:
        """Count, log (rate-limited: a flood must not flood the log) and answer the sender."""
        self.counters.refused += 1
        if self._log_limit.allow():
            log.warning(
                "%s: refused %s %r from %s:%s: %s",
                self.name,
                item.msg.message_type,
                item.msg.device_name,
                *item.peer.address[:2],
                reason,
            )
        self.manager.reply_error(item, reason, code=code)

    # ------------------------------------------------------------------ loop side
    def send(self, msg: Message, peer: Peer | None = None) -> int:
        """Queue ``msg`` for ``peer`` (None: every client of a server, a udp ``remote``, a
        tcp-client's server); returns how many peers it was queued for (0: dropped). Every
        transport has this ``send``, so nothing here depends on which one is configured."""
        if peer is None and self.sends_to_owner:
            owner = self.stream_owner
            if owner is None:
                self.counters.no_destination += 1
                return 0
            if self.auth_key is not None:
                msg = sign(msg, self.auth_key)
            n = self.transport.send(msg, owner)  # type: ignore[arg-type]
        else:
            if self.auth_key is not None:
                msg = sign(msg, self.auth_key)
            n = self.transport.send(msg, peer)
        if n:
            self.counters.sent += 1
        else:
            self.counters.send_dropped += 1
        return n

    def send_to_peer(self, msg: Message, peer: Peer) -> bool:
        """A reply to the sender of a request; like :meth:`send` but not counted as an output
        (replies never were)."""
        if self.auth_key is not None:
            msg = sign(msg, self.auth_key)
        return self.transport.send(msg, peer) > 0

    def release_stream(self) -> None:
        """Forget an ephemeral stream owner (operator Reset): the next sender owns it."""
        if self.stream_owner != self.configured_source:
            self._pin(self.configured_source)
        self.stream_owner = self.configured_source

    def _pin(self, source: tuple[str, int] | None) -> None:
        """A UDP stream's owner is the only sender its socket takes (the kernel drops the
        rest: a flood from elsewhere cannot fill the buffer the master's datagrams need)."""
        pin = getattr(self.transport, "pin_source", None)
        if pin is not None and self.streams and getattr(self.cfg, "kernel_filter", True):
            pin(source)

    def start(self) -> None:
        self.transport.start()
        if self.configured_source is not None:
            self._pin(self.configured_source)

    def stats(self) -> dict[str, Any]:
        c = self.counters
        t = self.transport.stats()
        streams = {
            k: {"received": q.received, "dropped": q.dropped} for k, q in self.streams.items()
        }
        return {
            "transport": self.cfg.transport,
            "role": self.role,
            "address": list(self.address) if self.address else None,
            "received": c.received,
            "sent": int(t.get("sent", c.sent)),
            "dropped": int(t.get("dropped", 0))
            + c.send_dropped
            + sum(q.dropped for q in self.streams.values()),
            "malformed": int(t.get("malformed", c.malformed)),
            "refused": c.refused,
            "foreign": c.foreign,
            "unauthenticated": c.unauthenticated,
            "replayed": c.replayed,
            "keepalive": c.keepalive,
            "unexpected": c.unexpected,
            **({"no_destination": c.no_destination} if self.sends_to_owner else {}),
            "streams": streams,
            "stream_owner": list(self.stream_owner) if self.stream_owner else None,
            # refusals by the transport, each under its reason
            **{k: int(t[k]) for k in _TRANSPORT_REFUSALS if k in t},
            **(
                {"refused_by_remote": int(t["refused_by_remote"])}
                if "refused_by_remote" in t
                else {}
            ),
            "peers": len(getattr(self.transport, "peers", []) or []),
        }

    @property
    def address(self) -> tuple[str, int] | None:
        return getattr(self.transport, "address", None)


# a plain Python class in the compiled build too (its methods still compiled): tests and tools
# replace its methods (reply) on an instance; the per-datagram path is Interface's, native
@mypyc_attr(native_class=False)
class InterfaceManager:
    """Owns every interface of a daemon (OCC's InterfaceManager: reusable on any robot)."""

    def __init__(
        self,
        interface_configs: Iterable[Any],
        *,
        clock_now: Callable[[], float],
        command_depth: int = 64,
        poll_streams: bool = False,
    ) -> None:
        self.commands = CommandQueue(command_depth)
        self.interfaces: dict[str, Interface] = {}
        self._connect_listeners: list[Callable[[Interface, Peer], None]] = []
        for cfg in interface_configs:
            self.interfaces[cfg.name] = Interface(
                cfg, self, clock_now=clock_now, poll_streams=poll_streams
            )

    def __getitem__(self, name: str) -> Interface:
        return self.interfaces[name]

    def start(self) -> None:
        for iface in self.interfaces.values():
            iface.start()
            log.info("interface %s: %s on %s", iface.name, iface.cfg.transport, iface.address)

    def stop(self) -> None:
        for iface in self.interfaces.values():
            try:
                iface.transport.stop()
            except Exception:  # noqa: BLE001 - stopping must reach every interface
                log.exception("interface %s: error while stopping", iface.name)

    def set_thread_priority(self, priority: int) -> str:
        """SCHED_FIFO ``priority`` for every interface's I/O thread; returns what applied."""
        import os

        done, failed = [], []
        for iface in self.interfaces.values():
            thread = iface.transport.thread
            tid = getattr(thread, "native_id", None)
            if tid is None:
                failed.append(f"{iface.name} (no thread)")
                continue
            try:
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
                done.append(iface.name)
            except (OSError, AttributeError) as err:
                failed.append(f"{iface.name} ({err.__class__.__name__})")
        text = f"SCHED_FIFO {priority} on {', '.join(done) or 'none'}"
        return text + (f"; refused for {', '.join(failed)}" if failed else "")

    def on_connect(self, listener: Callable[[Interface, Peer], None]) -> None:
        self._connect_listeners.append(listener)

    def _notify_connect(self, iface: Interface, peer: Peer) -> None:
        for listener in self._connect_listeners:
            try:
                listener(iface, peer)
            except Exception:  # noqa: BLE001 - a listener must not kill the I/O thread
                log.exception("connect listener failed")

    def operator_interfaces(self) -> list[Interface]:
        """The interfaces whose clients may command the robot (role ``operator``)."""
        return [i for i in self.interfaces.values() if i.role == "operator"]

    def broadcast_operators(self, msg: Message) -> None:
        """Send to every client of every viewer or operator interface (state changes, alerts:
        what the robot does is everyone's business; only operators may change it)."""
        for iface in self.interfaces.values():
            if iface.answers:
                iface.send(msg)

    def reply(self, item: Inbound, msg: Message) -> bool:
        return self.interfaces[item.interface].send_to_peer(msg, item.peer)

    def reply_error(
        self, item: Inbound, text: str, *, code: int = igtl.StatusCode.UNKNOWN_ERROR
    ) -> None:
        """Answer a request with an error in the form its sender expects."""
        self.reply(item, error_reply(item.msg, text, code=code))

    def stats(self) -> dict[str, Any]:
        return {name: iface.stats() for name, iface in self.interfaces.items()}


def _split_remote(remote: str) -> tuple[str, int]:
    host, _, port = remote.rpartition(":")
    return host.strip("[]"), int(port)
