"""The cell link: a member's heartbeats to its peers and theirs to it (issue 40).

No new wire protocol: a heartbeat is an OpenIGTLink NDARRAY over UDP, header version 2, one
datagram, as the master's stream is a POSITION over UDP. Its device name is ``CELL``, its header
message ID the member's sequence number (uint32, one more per heartbeat), its timestamp the
sender's wall clock. Its array (float64) holds the numbers: the member's measured joint
positions (the URDF's order), then its base pose in the patient frame (12 numbers: the rotation
by rows, then the translation in metres), then when its stop began (``stop_wall``, its wall
clock in s, 0 without a stop: the measured propagation). Its metadata (at most 8 entries, the
same from one heartbeat to the next until the state changes: packed once, igtl/wire.py's cache)
says what the others need to know:

==============  ==============================================================================
key             value
==============  ==============================================================================
``cell``        the cell's name (a heartbeat of another cell is refused)
``member``      the sender's name in the cell
``boot``        the sender's start (Unix ns): a restarted member is a newer boot
``state``       its robot state (``RUNNING``, ``FAULT``...)
``cause``       why it left RUNNING for a safety reason ('' when none stands)
``origin``      the member that stop comes from: itself, or a member whose stop it relays
``chain``       the hash of its kinematic chain (occ.kinematics.frame.chain_hash)
``leaving``     ``1`` in the heartbeat of a member that leaves the cell (an operator's command)
==============  ==============================================================================

With a key (``cell.auth_key_file``) every heartbeat carries the HMAC tag of igtl/auth.py and
one without a valid tag is refused and counted; a keyed heartbeat must also be fresh (its
timestamp within ``FRESH_S`` of this daemon's clock), so a recorded heartbeat of an earlier
boot cannot be passed off after this daemon restarts. Within a boot the sequence number refuses
a replay (the cell's judgement, occ/core/cell.py).

Sending is on the caller's thread (the loop, or the supervisor's when the loop hangs), never
blocking. Receiving, checking and decoding are the endpoint's own I/O thread's: it queues each
accepted heartbeat, and the loop takes them in arrival order (a check of an empty deque when
none came: no system call per tick; a heartbeat waits at most the interpreter's switch
interval, 0.5 ms in the shipped configs, for that thread).
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from igtl.auth import load_key, sign, verify
from igtl.messages.base import Message
from igtl.messages.ndarray import NDArrayMessage
from igtl.transport import Peer, UDPEndpoint
from igtl.transport.common import RateLimit

__all__ = ["Beat", "CellLink", "FRESH_S"]

log = logging.getLogger(__name__)

DEVICE = "CELL"
#: a keyed heartbeat's timestamp must be within this of the receiver's clock (s)
FRESH_S = 2.0


@dataclass(frozen=True, slots=True)
class Beat:
    """One heartbeat as received (or about to be sent)."""

    cell: str
    member: str
    boot: int
    seq: int
    state: str
    cause: str
    origin: str
    stop_wall: float
    chain: str
    q: tuple[float, ...]
    base: tuple[float, ...]
    leaving: bool = False
    #: the sender's wall clock when sent
    sent_wall: float = 0.0
    #: this daemon's clock when it arrived (0 for one being sent)
    t_rx: float = 0.0


def pack_beat(
    beat: Beat, key: bytes | None, *, seq: int | None = None, sent_wall: float | None = None
) -> Message:
    """The NDARRAY of one heartbeat (module docstring), signed with ``key``; ``seq`` and
    ``sent_wall`` instead of the beat's own when given."""
    meta = {
        "cell": beat.cell,
        "member": beat.member,
        "boot": str(beat.boot),
        "state": beat.state,
        "cause": beat.cause,
        "origin": beat.origin,
        "chain": beat.chain,
    }
    if beat.leaving:
        meta["leaving"] = "1"
    msg: Message = NDArrayMessage(
        device_name=DEVICE,
        header_version=2,
        timestamp=beat.sent_wall if sent_wall is None else sent_wall,
        message_id=(beat.seq if seq is None else seq) & 0xFFFFFFFF,
        metadata=meta,
        array=np.array((*beat.q, *beat.base, beat.stop_wall), dtype=np.float64),
    )
    return sign(msg, key) if key is not None else msg


class BeatError(ValueError):
    """A message on the cell link that is no heartbeat, or a malformed one."""


def unpack_beat(msg: Message, t_rx: float) -> Beat:
    """The heartbeat in ``msg``; BeatError saying what is wrong with it."""
    if not isinstance(msg, NDArrayMessage) or msg.device_name != DEVICE:
        raise BeatError(f"not a heartbeat: {msg.message_type} {msg.device_name!r}")
    if msg.header_version != 2:
        raise BeatError("header version 1: a heartbeat needs its metadata")
    m = msg.metadata
    numbers = np.asarray(msg.array, dtype=np.float64).ravel()
    if len(numbers) < 13 or not bool(np.isfinite(numbers).all()):
        raise BeatError("heartbeat without its base and stop time, or a number not finite")
    values = [float(v) for v in numbers]
    try:
        beat = Beat(
            cell=str(m["cell"]),
            member=str(m["member"]),
            boot=int(str(m["boot"])),
            seq=int(msg.message_id),
            state=str(m["state"]),
            cause=str(m.get("cause", "")),
            origin=str(m.get("origin", "")),
            stop_wall=values[-1],
            chain=str(m.get("chain", "")),
            q=tuple(values[:-13]),
            base=tuple(values[-13:-1]),
            leaving=str(m.get("leaving", "")) == "1",
            sent_wall=float(msg.timestamp),
            t_rx=t_rx,
        )
    except KeyError as err:
        raise BeatError(f"heartbeat without {err.args[0]!r}") from err
    except (TypeError, ValueError) as err:
        raise BeatError(f"heartbeat with a bad value: {err}") from err
    return beat


@dataclass
class LinkCounters:
    sent: int = 0
    send_failed: int = 0
    received: int = 0
    #: not a heartbeat, malformed, of another cell, or from an unknown member / address
    refused: int = 0
    unauthenticated: int = 0
    stale: int = 0


class CellLink:
    """The UDP endpoint of one member: ``send`` a heartbeat to every peer, ``take`` the
    heartbeats received since the last call (each from a known member at its address,
    authenticated when keyed)."""

    def __init__(
        self,
        cell: str,
        me: str,
        bind: tuple[str, int],
        peers: dict[str, tuple[str, int]],
        *,
        key_text: str | None = None,
        now: Callable[[], float],
        wall: Callable[[], float] = time.time,
        polled: bool = False,
    ) -> None:
        """``polled``: :meth:`take` reads the socket itself first (simulated time: a heartbeat
        sent before a tick is taken in that tick, whatever the I/O thread is doing)."""
        self.cell, self.me = cell, me
        self.peers = dict(peers)
        self._by_address = {addr: name for name, addr in peers.items()}
        self.key = load_key(key_text) if key_text is not None else None
        self._now, self._wall = now, wall
        self.counters = LinkCounters()
        self._inbox: deque[Beat] = deque(maxlen=1024)
        self._seq = itertools.count(1)  # next() is atomic: the loop and the supervisor send
        self._send_lock = threading.Lock()
        self._log_limit = RateLimit(5)
        self.polled = polled
        self.endpoint = UDPEndpoint(
            bind[0],
            bind[1],
            allowed_peers=sorted({h for h, _ in peers.values()}),
            polled=polled,
            on_message=self._receive,
            on_error=self._on_error,
            name=f"cell-{me}",
        )

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self.endpoint.start()

    def stop(self) -> None:
        self.endpoint.stop()

    # ------------------------------------------------------------------ sending
    def send(self, beat: Beat) -> int:
        """``beat`` to every peer, its ``seq`` and ``sent_wall`` given here (:meth:`Beat` fields
        left 0 by the caller), packed once; never blocks. The number of peers it went to."""
        with self._send_lock:  # one sequence order on the wire, whichever thread sends
            data = pack_beat(beat, self.key, seq=next(self._seq), sent_wall=self._wall()).pack()
            ok = 0
            for addr in self.peers.values():
                try:
                    sent = self.endpoint.send(data, addr)
                except (OSError, ValueError):
                    sent = 0
                ok += sent
                if sent:
                    self.counters.sent += 1
                else:
                    self.counters.send_failed += 1
            return ok

    # ------------------------------------------------------------------ receiving
    def take(self) -> list[Beat]:
        """The heartbeats received since the last call, in arrival order (the loop's)."""
        if self.polled:
            self.endpoint.poll(32, self._receive)
        inbox = self._inbox
        if not inbox:
            return []
        out = []
        while inbox:
            out.append(inbox.popleft())
        return out

    def _receive(self, peer: Peer, msg: Message) -> None:
        c = self.counters
        c.received += 1
        name = self._by_address.get(peer.address[:2])
        if name is None:
            self._refuse(f"from {peer.address[0]}:{peer.address[1]}, no member's address")
            return
        if self.key is not None:
            why = verify(msg, self.key)
            if why:
                c.unauthenticated += 1
                self._refuse(f"from {name}: {why}", count=False)
                return
            age = self._wall() - float(msg.timestamp)
            if not abs(age) <= FRESH_S:
                c.stale += 1
                self._refuse(f"from {name}: sent {age:.1f} s ago (clocks apart?)", count=False)
                return
        try:
            beat = unpack_beat(msg, self._now())
        except BeatError as err:
            self._refuse(f"from {name}: {err}")
            return
        if beat.cell != self.cell or beat.member != name:
            self._refuse(f"from {name}'s address: member {beat.member!r} of cell {beat.cell!r}")
            return
        self._inbox.append(beat)

    def _refuse(self, why: str, count: bool = True) -> None:
        if count:
            self.counters.refused += 1
        if self._log_limit.allow():
            log.warning("cell link: refused a heartbeat %s", why)

    def _on_error(self, peer: Peer | None, exc: BaseException) -> None:
        self.counters.refused += 1

    def stats(self) -> dict[str, int]:
        c = self.counters
        return {
            "sent": c.sent,
            "send_failed": c.send_failed,
            "received": c.received,
            "refused": c.refused,
            "unauthenticated": c.unauthenticated,
            "stale": c.stale,
        }
