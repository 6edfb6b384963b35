#!/usr/bin/env python3
"""A lossy UDP forwarding proxy for OpenIGTLink datagrams (loopback soak testing).

Listens on one UDP port (127.0.0.1), forwards every datagram to another, and drops datagrams
by a configurable, seeded pattern. Put it between the master's POSITION stream and the slave::

    master --UDP--> proxy 127.0.0.1:LISTEN --(drops, delay)--> slave 127.0.0.1:TARGET

Drop patterns (combinable: a datagram is dropped if any of them says so):

``--loss P``
    independent (Bernoulli) loss with probability P per datagram.
``--burst PGB,PBG,LOSS_BAD``
    Gilbert-Elliott: a two-state Markov chain (good -> bad with probability PGB per datagram,
    bad -> good with PBG); a datagram is lost with probability LOSS_BAD in the bad state
    (``--loss-good`` in the good state, default 0). Mean burst length ~ 1/PBG.
``--drop-runs L:N`` (repeatable)
    N runs of exactly L consecutive datagrams, at random (seeded) places, spaced at least
    ``--min-gap`` datagrams apart so runs never merge, after ``--warmup`` datagrams and before
    ``--expected`` datagrams (default ``duration * rate_hz``) minus ``--tail``.
``--drop-cycle L1,L2,...``
    runs of these lengths in this order, repeated, every ``--min-gap`` datagrams (from the end
    of one run to the start of the next) between ``--warmup`` and ``--expected`` minus
    ``--tail``: ``2,2,3`` is the relay of the OCC test (drops of 2, 2, then 3 packets).
``--delay-ms D --jitter-ms J``
    every forwarded datagram waits D + uniform(-J, +J) ms (never below 0; with jitter,
    datagrams may be reordered, as on a real network).

Every drop is logged to ``--log`` (CSV): datagram index, IGTL sequence number (the v2 header's
message ID, big-endian uint32 at absolute offset 66..69; empty for v1 or short datagrams), the
cause, the wall time (Unix s) and the proxy's monotonic time of arrival, and the arrival time of
the last datagram before it that was *not* dropped. ``--runs-log`` writes one row per run of
consecutive drops (with the arrival time of the first good datagram after it, so the silence the
receiver saw can be computed). Everything is seeded (``--seed``): the same seed and the same
arrival sequence give the same drops.

Bounded: the proxy runs for ``--duration`` seconds (required as a script) or until ``stop()``.
Library use::

    pattern = LossPattern(seed=1, drop_runs=[(3, 2), (1, 20)], expected=4000, warmup=500)
    with LossProxy(("127.0.0.1", 0), ("127.0.0.1", 18946), pattern) as proxy:
        ... proxy.address ...   # point the master's ``remote`` here
    proxy.write_csv("drops.csv")

Plain sockets, one thread; only loopback addresses are accepted unless ``--allow-any``.
"""

from __future__ import annotations

import argparse
import csv
import heapq
import json
import os
import random
import select
import socket
import struct
import sys
import threading
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

__all__ = [
    "DropRecord",
    "LossPattern",
    "LossProxy",
    "RunRecord",
    "igtl_seq",
    "igtl_timestamp",
    "parse_drop_cycle",
    "parse_drop_runs",
    "main",
]

#: Linux's SO_TIMESTAMPNS (= SCM_TIMESTAMPNS; not exported by Python's socket module): the
#: kernel's arrival time of each datagram, a struct timespec in the ancillary data
_SO_TIMESTAMPNS = 35
_TIMESPEC = struct.Struct("@qq")
#: the header's timestamp: uint64 at offset 34 (32-bit seconds, 32-bit binary fraction)
_STAMP = struct.Struct(">II")

#: IGTL v2: 58-byte header, then ext header size (2), metadata header size (2), metadata size
#: (4), message ID (4): bytes 66..69 of the datagram.
SEQ_OFFSET = 66
_SEQ = struct.Struct(">I")


def igtl_seq(datagram: bytes | bytearray | memoryview) -> int | None:
    """The message ID of an IGTL header-version-2 datagram, else None."""
    if len(datagram) < SEQ_OFFSET + 4:
        return None
    version = (datagram[0] << 8) | datagram[1]
    if version < 2:
        return None
    return int(_SEQ.unpack_from(datagram, SEQ_OFFSET)[0])


def parse_drop_runs(specs: Sequence[str]) -> list[tuple[int, int]]:
    """``["3:2", "1:20"]`` -> ``[(3, 2), (1, 20)]`` (run length, count)."""
    out: list[tuple[int, int]] = []
    for spec in specs:
        try:
            length_s, count_s = spec.split(":")
            length, count = int(length_s), int(count_s)
        except ValueError:
            raise ValueError(
                f"--drop-runs takes L:N (run length : number of runs), got {spec!r}"
            ) from None
        if length < 1 or count < 0:
            raise ValueError(f"--drop-runs {spec!r}: need L >= 1 and N >= 0")
        out.append((length, count))
    return out


def igtl_timestamp(datagram: bytes | bytearray | memoryview) -> float | None:
    """The header timestamp of an IGTL datagram (Unix seconds), None if short or zero."""
    if len(datagram) < 42:
        return None
    sec, frac = _STAMP.unpack_from(datagram, 34)
    return sec + frac / 4294967296.0 if sec else None


def parse_drop_cycle(spec: str | None) -> list[int]:
    """``"2,2,3"`` -> ``[2, 2, 3]`` (run lengths, in order); None or empty -> ``[]``."""
    if not spec:
        return []
    try:
        lengths = [int(v) for v in spec.split(",")]
    except ValueError:
        raise ValueError(
            f"--drop-cycle takes run lengths L1,L2,... (e.g. 2,2,3), got {spec!r}"
        ) from None
    if any(length < 1 for length in lengths):
        raise ValueError(f"--drop-cycle {spec!r}: every run length must be >= 1")
    return lengths


def parse_burst(spec: str) -> tuple[float, float, float]:
    try:
        parts = [float(v) for v in spec.split(",")]
    except ValueError:
        raise ValueError(f"--burst takes PGB,PBG[,LOSS_BAD], got {spec!r}") from None
    if len(parts) == 2:
        parts.append(1.0)
    if len(parts) != 3 or not all(0.0 <= p <= 1.0 for p in parts):
        raise ValueError(
            f"--burst takes three probabilities PGB,PBG,LOSS_BAD in [0, 1], got {spec!r}"
        )
    return parts[0], parts[1], parts[2]


class LossPattern:
    """Seeded per-datagram drop decisions: Bernoulli, Gilbert-Elliott and scheduled runs.

    :meth:`decide` is called once per datagram, in arrival order, and returns the cause of the
    drop (``"runs"``, ``"burst"``, ``"loss"``) or ``None`` to forward it. Pure logic (no clock),
    so the same object drives the real proxy and the simulated soak.
    """

    def __init__(
        self,
        *,
        seed: int = 0,
        loss: float = 0.0,
        burst: tuple[float, float, float] | None = None,
        loss_good: float = 0.0,
        drop_runs: Sequence[tuple[int, int]] = (),
        drop_cycle: Sequence[int] = (),
        expected: int = 0,
        warmup: int = 0,
        tail: int = 0,
        min_gap: int = 50,
    ) -> None:
        if not 0.0 <= loss <= 1.0:
            raise ValueError(f"loss must be in [0, 1], got {loss}")
        self.seed = seed
        self.loss = float(loss)
        self.burst = burst
        self.loss_good = float(loss_good)
        self.drop_runs_spec = list(drop_runs)
        self.drop_cycle = list(drop_cycle)
        # separate generators, so adding one pattern does not change the others' draws
        self._rng_loss = random.Random(f"{seed}/loss")
        self._rng_burst = random.Random(f"{seed}/burst")
        self._bad = False
        self.index = 0  # datagrams decided so far
        #: scheduled runs: sorted (first index, length)
        self.schedule: list[tuple[int, int]] = self._plan(
            drop_runs, expected=expected, warmup=warmup, tail=tail, min_gap=min_gap
        )
        if self.drop_cycle:
            if self.schedule:
                raise ValueError("--drop-cycle and --drop-runs cannot be combined")
            self.schedule = self._plan_cycle(
                self.drop_cycle, lo=warmup, hi=expected - tail, min_gap=min_gap
            )
        self._starts = {start: length for start, length in self.schedule}
        self._run_left = 0

    def _plan(
        self,
        drop_runs: Sequence[tuple[int, int]],
        *,
        expected: int,
        warmup: int,
        tail: int,
        min_gap: int,
    ) -> list[tuple[int, int]]:
        lengths = [length for length, count in drop_runs for _ in range(count)]
        if not lengths:
            return []
        rng = random.Random(f"{self.seed}/runs")
        rng.shuffle(lengths)
        lo, hi = warmup, expected - tail
        slack = (hi - lo) - sum(lengths) - (len(lengths) - 1) * min_gap
        if slack < 0:
            raise ValueError(
                f"{len(lengths)} drop runs ({sum(lengths)} datagrams, >= {min_gap} apart) "
                f"do not fit "
                f"in datagrams {lo}..{hi}: lengthen the duration or lower --min-gap"
            )
        offsets = sorted(rng.randint(0, slack) for _ in lengths)
        schedule = []
        pos = lo
        prev_off = 0
        for off, length in zip(offsets, lengths, strict=True):
            pos += off - prev_off
            prev_off = off
            schedule.append((pos, length))
            pos += length + min_gap
        return schedule

    @staticmethod
    def _plan_cycle(
        cycle: Sequence[int], *, lo: int, hi: int, min_gap: int
    ) -> list[tuple[int, int]]:
        """The cycle's runs in order, repeated, ``min_gap`` datagrams apart, in ``lo..hi``."""
        schedule: list[tuple[int, int]] = []
        pos = lo
        while True:
            length = cycle[len(schedule) % len(cycle)]
            if pos + length > hi:
                break
            schedule.append((pos, length))
            pos += length + max(1, min_gap)
        if not schedule:
            raise ValueError(
                f"--drop-cycle {','.join(map(str, cycle))}: no run fits in datagrams {lo}..{hi}"
            )
        return schedule

    def decide(self) -> str | None:
        i = self.index
        self.index += 1
        cause = None
        # scheduled runs
        start_len = self._starts.get(i)
        if start_len is not None:
            self._run_left = start_len
        if self._run_left > 0:
            self._run_left -= 1
            cause = "runs"
        # Gilbert-Elliott (always advanced, so its draws do not depend on the other patterns)
        if self.burst is not None:
            pgb, pbg, loss_bad = self.burst
            r = self._rng_burst
            if self._bad:
                if r.random() < pbg:
                    self._bad = False
            elif r.random() < pgb:
                self._bad = True
            p = loss_bad if self._bad else self.loss_good
            if r.random() < p and cause is None:
                cause = "burst"
        if self.loss > 0.0 and self._rng_loss.random() < self.loss and cause is None:
            cause = "loss"
        return cause

    def describe(self) -> dict[str, Any]:
        return {
            "seed": self.seed,
            "loss": self.loss,
            "burst": list(self.burst) if self.burst else None,
            "loss_good": self.loss_good,
            "drop_runs": [f"{length}:{count}" for length, count in self.drop_runs_spec],
            "drop_cycle": ",".join(map(str, self.drop_cycle)) or None,
            "scheduled_runs": len(self.schedule),
        }


@dataclass(slots=True)
class DropRecord:
    index: int
    seq: int | None
    cause: str
    t_wall: float
    t_mono: float
    t_prev_good: float | None  # monotonic arrival time of the last forwarded datagram before it


@dataclass(slots=True)
class RunRecord:
    first_index: int
    length: int
    first_seq: int | None
    last_seq: int | None
    causes: str
    t_wall_first: float
    t_mono_first: float
    t_mono_last: float
    t_prev_good: float | None
    t_next_good: float | None = None  # None while the run is open (or never closed)
    t_wall_prev_good: float | None = None


@dataclass
class ProxyCounters:
    received: int = 0
    forwarded: int = 0
    dropped: int = 0
    send_errors: int = 0
    non_igtl_v2: int = 0
    max_queue: int = 0
    by_cause: dict[str, int] = field(default_factory=dict)
    #: the way back (the target's replies relayed to the sender: a slave's return channel)
    returned: int = 0
    return_dropped: int = 0


class LossProxy:
    """UDP forwarder with seeded drops and optional delay; one thread, bounded by ``duration``."""

    def __init__(
        self,
        listen: tuple[str, int],
        target: tuple[str, int],
        pattern: LossPattern | None = None,
        *,
        delay_ms: float = 0.0,
        jitter_ms: float = 0.0,
        duration: float | None = None,
        seed: int = 0,
        allow_any: bool = False,
        max_log: int = 1_000_000,
        gap_log_ms: float = 5.0,
        fifo_priority: int | None = None,
        return_pattern: LossPattern | None = None,
    ) -> None:
        if not allow_any:
            for host in (listen[0], target[0]):
                if not host.startswith("127."):
                    raise ValueError(f"{host}: loopback only (pass allow_any=True / --allow-any)")
        if delay_ms < 0 or jitter_ms < 0:
            raise ValueError("delay_ms and jitter_ms must be >= 0")
        self.target = target
        self.pattern = pattern if pattern is not None else LossPattern(seed=seed)
        #: the way back: datagrams the target sends to the proxy's sending socket go to the
        #: last sender, from the listening address (so the sender sees its peer's address),
        #: through this pattern's drops (None: all of them)
        self.return_pattern = return_pattern
        self._client: tuple[str, int] | None = None
        self.delay_s = delay_ms * 1e-3
        self.jitter_s = jitter_ms * 1e-3
        self.duration = duration
        self.max_log = max_log
        self._rng_delay = random.Random(f"{seed}/delay")
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        self.sock.bind(listen)
        self.sock.setblocking(False)
        self.address: tuple[str, int] = self.sock.getsockname()
        self.out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.out.setblocking(False)
        self.counters = ProxyCounters()
        #: (arrival of the datagram before the gap (monotonic), gap in s) for every inter-arrival
        #: gap longer than ``gap_log_ms``: stalls of the sender (or of the proxy) before any drop
        self.gaps: list[tuple[float, float]] = []
        #: why each of ``gaps`` happened (same order): the kernel's arrival gap (when the sender
        #: sent: loopback delivers inside ``sendto``), the age of the datagram after the gap
        #: (its header timestamp) and the verdict, "relay read late" (sent on time, this
        #: process read it late), "master sent late" (stamped on time, sent late) or "master
        #: silent" (nothing stamped: its loop did not run)
        self.gap_detail: list[dict[str, Any]] = []
        self._kernel_ts = False
        if sys.platform.startswith("linux"):
            try:
                self.sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
                self._kernel_ts = True
            except OSError:
                pass
        self._last_kernel: float | None = None
        #: SCHED_FIFO priority of the forwarding thread (where permitted); None: normal
        self.fifo_priority = fifo_priority
        self.scheduling = "normal"
        self.gap_log_s = gap_log_ms * 1e-3
        self._last_rx: float | None = None
        self.drops: list[DropRecord] = []
        self.runs: list[RunRecord] = []
        self._open_run: RunRecord | None = None
        self._last_good_mono: float | None = None
        self._last_good_wall: float | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self.t_start_mono: float | None = None
        self.t_start_wall: float | None = None

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> LossProxy:
        self._thread = threading.Thread(target=self.serve, name="loss-proxy", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        self.close()

    def close(self) -> None:
        for s in (self.sock, self.out):
            try:
                s.close()
            except OSError:
                pass

    def __enter__(self) -> LossProxy:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the serving thread to end (duration elapsed); True if it ended."""
        if self._thread is None:
            return True
        self._thread.join(timeout)
        return not self._thread.is_alive()

    # ------------------------------------------------------------------ the loop
    def serve(self) -> None:
        """Forward until ``duration`` elapses or :meth:`stop`; every wait is bounded."""
        mono = time.monotonic
        if self.fifo_priority is not None:
            try:  # Linux: pid 0 is the calling thread only
                os.sched_setscheduler(
                    threading.get_native_id(), os.SCHED_FIFO, os.sched_param(self.fifo_priority)
                )
                self.scheduling = f"SCHED_FIFO {self.fifo_priority}"
            except (OSError, AttributeError) as err:
                self.scheduling = f"normal (SCHED_FIFO refused: {err})"
        self.t_start_mono = mono()
        self.t_start_wall = time.time()
        end = self.t_start_mono + self.duration if self.duration is not None else float("inf")
        pending: list[tuple[float, int, bytes]] = []  # (due, n, datagram) for delayed sends
        n = 0
        sock = self.sock
        while not self._stop.is_set():
            now = mono()
            if now >= end:
                break
            timeout = min(0.05, end - now)
            if pending:
                timeout = max(0.0, min(timeout, pending[0][0] - now))
            try:
                ready, _, _ = select.select([sock, self.out], [], [], timeout)
            except (OSError, ValueError):
                break
            if self.out in ready:
                self._relay_back()
            if sock in ready:
                for _ in range(256):  # bounded batch per wake-up
                    kt: float | None = None
                    try:
                        if self._kernel_ts:
                            data, anc, _flags, addr = sock.recvmsg(65535, 64)
                            for level, kind, raw in anc:
                                if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS:
                                    sec, nsec = _TIMESPEC.unpack_from(raw)
                                    kt = sec + nsec * 1e-9
                        else:
                            data, addr = sock.recvfrom(65535)
                        self._client = addr
                    except BlockingIOError:
                        break
                    except OSError:
                        break
                    t = mono()
                    if self._on_datagram(data, t, kt):
                        due = t + self._delay()
                        if due <= t:
                            self._send(data)
                        else:
                            n += 1
                            heapq.heappush(pending, (due, n, data))
                            if len(pending) > self.counters.max_queue:
                                self.counters.max_queue = len(pending)
            now = mono()
            while pending and pending[0][0] <= now:
                self._send(heapq.heappop(pending)[2])
        for _, _, data in sorted(pending):  # flush what was in flight
            self._send(data)

    def _relay_back(self) -> None:
        """The target's replies (a slave's return channel) back to the sender, through the
        return pattern's drops; bounded batch per wake-up."""
        c = self.counters
        for _ in range(256):
            try:
                data = self.out.recv(65535)
            except (BlockingIOError, OSError):
                return
            client = self._client
            if client is None:
                continue  # nobody has sent yet: nobody to answer
            if self.return_pattern is not None and self.return_pattern.decide() is not None:
                c.return_dropped += 1
                continue
            try:
                self.sock.sendto(data, client)
                c.returned += 1
            except OSError:
                c.send_errors += 1

    def _delay(self) -> float:
        if self.jitter_s:
            return max(0.0, self.delay_s + self._rng_delay.uniform(-self.jitter_s, self.jitter_s))
        return self.delay_s

    def _send(self, data: bytes) -> None:
        try:
            self.out.sendto(data, self.target)
            self.counters.forwarded += 1
        except OSError:
            self.counters.send_errors += 1

    def _on_datagram(self, data: bytes, t: float, kernel_t: float | None = None) -> bool:
        """Decide one datagram; log it if dropped. Returns True to forward it. ``kernel_t``:
        the kernel's arrival time (Unix s) when known."""
        c = self.counters
        c.received += 1
        last_rx = self._last_rx
        self._last_rx = t
        if last_rx is not None and t - last_rx > self.gap_log_s and len(self.gaps) < self.max_log:
            self.gaps.append((last_rx, t - last_rx))
            self.gap_detail.append(self._explain_gap(t - last_rx, kernel_t, data))
        self._last_kernel = kernel_t
        seq = igtl_seq(data)
        if seq is None:
            c.non_igtl_v2 += 1
        index = self.pattern.index
        cause = self.pattern.decide()
        with self._lock:
            if cause is None:
                run = self._open_run
                if run is not None:
                    run.t_next_good = t
                    self._open_run = None
                self._last_good_mono = t
                self._last_good_wall = time.time()
                return True
            c.dropped += 1
            c.by_cause[cause] = c.by_cause.get(cause, 0) + 1
            wall = time.time()
            if len(self.drops) < self.max_log:
                self.drops.append(DropRecord(index, seq, cause, wall, t, self._last_good_mono))
            run = self._open_run
            if run is None:
                run = RunRecord(
                    index,
                    0,
                    seq,
                    seq,
                    cause,
                    wall,
                    t,
                    t,
                    self._last_good_mono,
                    t_wall_prev_good=self._last_good_wall,
                )
                self.runs.append(run)
                self._open_run = run
            run.length += 1
            run.last_seq = seq
            run.t_mono_last = t
            if cause not in run.causes.split("+"):
                run.causes += "+" + cause
        return False

    def _explain_gap(self, gap: float, kernel_t: float | None, data: bytes) -> dict[str, Any]:
        """Who was late for a gap in the arrivals this proxy read: itself, or the sender."""
        last_k = self._last_kernel
        k_gap = kernel_t - last_k if kernel_t is not None and last_k is not None else None
        stamp = igtl_timestamp(data)
        age = (kernel_t if kernel_t is not None else time.time()) - stamp if stamp else None
        if k_gap is not None and k_gap < 0.5 * gap:
            cause = "relay read late"
        elif age is not None and age > 0.5 * (k_gap if k_gap is not None else gap):
            cause = "master sent late"
        else:
            cause = "master silent"
        return {
            "gap_ms": round(gap * 1e3, 3),
            "kernel_gap_ms": None if k_gap is None else round(k_gap * 1e3, 3),
            "age_ms": None if age is None else round(age * 1e3, 3),
            "cause": cause,
        }

    # ------------------------------------------------------------------ results
    def mono_to_wall(self, t: float | None) -> float | None:
        if t is None or self.t_start_mono is None or self.t_start_wall is None:
            return None
        return self.t_start_wall + (t - self.t_start_mono)

    def summary(self) -> dict[str, Any]:
        with self._lock:
            hist: dict[int, int] = {}
            for r in self.runs:
                hist[r.length] = hist.get(r.length, 0) + 1
            c = self.counters
            return {
                "listen": list(self.address),
                "target": list(self.target),
                "received": c.received,
                "forwarded": c.forwarded,
                "dropped": c.dropped,
                "drop_fraction": round(c.dropped / c.received, 6) if c.received else 0.0,
                "by_cause": dict(c.by_cause),
                "send_errors": c.send_errors,
                "non_igtl_v2": c.non_igtl_v2,
                "max_delay_queue": c.max_queue,
                "runs": len(self.runs),
                "arrival_gaps_over_ms": {
                    "threshold_ms": self.gap_log_s * 1e3,
                    "count": len(self.gaps),
                    "max_ms": round(max((g for _, g in self.gaps), default=0.0) * 1e3, 3),
                    "by_cause": dict(Counter(d["cause"] for d in self.gap_detail)),
                },
                "run_length_histogram": {str(k): hist[k] for k in sorted(hist)},
                "pattern": self.pattern.describe(),
                "scheduling": self.scheduling,
                "delay_ms": self.delay_s * 1e3,
                "jitter_ms": self.jitter_s * 1e3,
            }

    def write_csv(self, path: str | Path) -> None:
        """The drop log: one row per dropped datagram."""
        with self._lock:
            rows = list(self.drops)
        with open(path, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["index", "seq", "cause", "t_wall", "t_mono", "t_prev_good_mono"])
            for d in rows:
                w.writerow(
                    [
                        d.index,
                        "" if d.seq is None else d.seq,
                        d.cause,
                        f"{d.t_wall:.6f}",
                        f"{d.t_mono:.6f}",
                        "" if d.t_prev_good is None else f"{d.t_prev_good:.6f}",
                    ]
                )

    def write_gaps_csv(self, path: str | Path) -> None:
        """One row per arrival gap longer than ``gap_log_ms``, with who was late for it."""
        with self._lock:
            rows = [
                {"t_wall": self.mono_to_wall(t0), **d}
                for (t0, _g), d in zip(self.gaps, self.gap_detail, strict=False)
            ]
        with open(path, "w", newline="") as fh:
            w = csv.DictWriter(fh, ["t_wall", "gap_ms", "kernel_gap_ms", "age_ms", "cause"])
            w.writeheader()
            for r in rows:
                w.writerow({k: ("" if v is None else v) for k, v in r.items()})

    def write_runs_csv(self, path: str | Path) -> None:
        """One row per run of consecutive drops."""
        with self._lock:
            rows = [asdict(r) for r in self.runs]
        fields = list(RunRecord.__dataclass_fields__)
        with open(path, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=fields)
            w.writeheader()
            for r in rows:
                w.writerow({k: ("" if v is None else v) for k, v in r.items()})


def read_drop_csv(path: str | Path) -> list[dict[str, Any]]:
    """Read a drop log written by :meth:`LossProxy.write_csv`."""
    out = []
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            out.append(
                {
                    "index": int(row["index"]),
                    "seq": int(row["seq"]) if row["seq"] else None,
                    "cause": row["cause"],
                    "t_wall": float(row["t_wall"]),
                    "t_mono": float(row["t_mono"]),
                    "t_prev_good_mono": float(row["t_prev_good_mono"])
                    if row["t_prev_good_mono"]
                    else None,
                }
            )
    return out


def _hostport(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not host:
        host = "127.0.0.1"
    try:
        return host, int(port)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected [HOST:]PORT, got {text!r}") from None


def add_pattern_arguments(p: argparse.ArgumentParser) -> None:
    """The drop-pattern options, shared with tools/soak.py."""
    g = p.add_argument_group("drop pattern (combinable)")
    g.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    g.add_argument(
        "--loss", type=float, default=0.0, metavar="P", help="independent loss probability"
    )
    g.add_argument(
        "--burst",
        type=parse_burst,
        default=None,
        metavar="PGB,PBG,LOSS_BAD",
        help="Gilbert-Elliott: good->bad, bad->good probabilities, loss in bad state",
    )
    g.add_argument(
        "--loss-good",
        type=float,
        default=0.0,
        metavar="P",
        help="Gilbert-Elliott loss probability in the good state (default 0)",
    )
    g.add_argument(
        "--drop-runs",
        action="append",
        default=[],
        metavar="L:N",
        help="N runs of exactly L consecutive datagrams at random places (repeatable)",
    )
    g.add_argument(
        "--drop-cycle",
        default=None,
        metavar="L1,L2,...",
        help="runs of these lengths in order, repeated, --min-gap datagrams apart "
        "(2,2,3: the relay of the OCC test)",
    )
    g.add_argument(
        "--min-gap",
        type=int,
        default=None,
        metavar="N",
        help="datagrams between scheduled runs, at least (default: 1 s of stream)",
    )
    g.add_argument(
        "--warmup",
        type=float,
        default=1.0,
        metavar="S",
        help="no scheduled run in the first S seconds of the stream (default 1)",
    )
    g.add_argument(
        "--tail",
        type=float,
        default=1.0,
        metavar="S",
        help="no scheduled run in the last S seconds (default 1)",
    )
    g.add_argument(
        "--rate-hz",
        type=float,
        default=500.0,
        help="the stream's datagram rate, to place runs in time (default 500)",
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="loss_proxy",
        description="Lossy UDP forwarding proxy for OpenIGTLink datagrams (seeded drop patterns).",
        epilog="Example: loss_proxy.py --listen 18956 --target 18946 --duration 30 "
        "--drop-runs 3:5 --drop-runs 1:50 --log drops.csv",
    )
    p.add_argument(
        "--listen",
        type=_hostport,
        required=True,
        metavar="[HOST:]PORT",
        help="where the sender sends (default host 127.0.0.1; port 0 = any free)",
    )
    p.add_argument(
        "--target",
        type=_hostport,
        required=True,
        metavar="[HOST:]PORT",
        help="where datagrams are forwarded to",
    )
    p.add_argument("--duration", type=float, required=True, metavar="S", help="run for S seconds")
    p.add_argument("--delay-ms", type=float, default=0.0, help="delay per forwarded datagram (ms)")
    p.add_argument(
        "--jitter-ms", type=float, default=0.0, help="uniform +- jitter on the delay (ms)"
    )
    p.add_argument("--log", type=Path, default=None, help="drop log CSV")
    p.add_argument("--runs-log", type=Path, default=None, help="runs-of-drops CSV")
    p.add_argument("--summary", type=Path, default=None, help="write the JSON summary here too")
    p.add_argument(
        "--expected",
        type=int,
        default=None,
        metavar="N",
        help="datagrams expected in total, to place --drop-runs (default duration*rate)",
    )
    p.add_argument("--allow-any", action="store_true", help="allow non-loopback addresses")
    add_pattern_arguments(p)
    args = p.parse_args(argv)
    try:
        pattern = pattern_from_args(args, args.duration, expected=args.expected)
        proxy = LossProxy(
            args.listen,
            args.target,
            pattern,
            delay_ms=args.delay_ms,
            jitter_ms=args.jitter_ms,
            duration=args.duration,
            seed=args.seed,
            allow_any=args.allow_any,
        )
    except (ValueError, OSError) as err:
        print(f"loss_proxy: {err}", file=sys.stderr)
        return 2
    print(
        f"loss_proxy: {proxy.address[0]}:{proxy.address[1]} -> {args.target[0]}:{args.target[1]} "
        f"for {args.duration} s, {len(pattern.schedule)} scheduled runs",
        file=sys.stderr,
        flush=True,
    )
    try:
        proxy.serve()
    except KeyboardInterrupt:
        pass
    finally:
        proxy.close()
    if args.log:
        proxy.write_csv(args.log)
    if args.runs_log:
        proxy.write_runs_csv(args.runs_log)
    text = json.dumps(proxy.summary(), indent=2)
    if args.summary:
        args.summary.write_text(text + "\n")
    print(text)
    return 0


def pattern_from_args(
    args: argparse.Namespace,
    duration: float,
    *,
    expected: int | None = None,
    min_gap_default: int | None = None,
) -> LossPattern:
    runs = parse_drop_runs(args.drop_runs)
    rate = args.rate_hz
    total = expected if expected is not None else int(duration * rate)
    min_gap = (
        args.min_gap
        if args.min_gap is not None
        else (min_gap_default if min_gap_default is not None else int(rate))
    )
    return LossPattern(
        seed=args.seed,
        loss=args.loss,
        burst=args.burst,
        loss_good=args.loss_good,
        drop_runs=runs,
        drop_cycle=parse_drop_cycle(args.drop_cycle),
        expected=total,
        warmup=int(args.warmup * rate),
        tail=int(args.tail * rate),
        min_gap=min_gap,
    )


if __name__ == "__main__":
    sys.exit(main())
