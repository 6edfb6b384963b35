#!/usr/bin/env python3
"""The OCC paper's packet-loss stability test (Arata et al., IJCARS 2010), in simulated time.

The protocol users repeat before trusting a network: the master streams its handle position to
the slave at 500 Hz while 2 % of the packets are lost, always in runs of exactly two
consecutive packets (about 10 lost packets, 5 double losses, a second); the master's simulated
hand moves X = 50 mm sine, Y = 50 mm cosine at 0.1 Hz, Z = 20 mm; motion scaling 10:1; 12
hours. The paper reports no instability, a mean tracking error of 0.094 mm (X) and 0.097 mm
(Y), the packet inter-arrival time jumping from 2 to 6 ms at each double loss (their Fig. 11)
and the input and output trajectories (Fig. 12).

Set-up (no sockets, no threads): the shipped ``configs/master.yaml`` and ``configs/slave.yaml``
as two :class:`occ_testkit.testing.SimRobot` on ONE :class:`~occ.clock.SimClock`, both ticked at
1 kHz (master first, then slave, at the same simulated instant). A peer on the master's
``slave`` interface receives the master controller's own POSITION stream (``teleop-master``
output, 500 Hz, sequence numbers, ``run``/``clutch`` metadata) and forwards each message to a
peer on the slave's ``master`` interface, through the wire codec, unless the loss injector drops
it. The injector is a seeded :class:`loss_proxy.LossPattern` with ``N`` scheduled runs of
exactly 2 drops, ``N = loss * packets / 2``, at least one delivered packet apart (so two runs
never merge into a run of 3, which the slave must and does stop on: tools/soak.py tests that).
"2 % of the packets" is read as the paper's "about 10 lost packets a second": 2 % of the
packets are *lost*, 1 % of them start a double loss (``--loss`` changes it).

Measured:

- stability: both robots stay RUNNING from start to end (no STOPPED, no FAULT), the slave's loss
  monitor never trips (a double loss is tolerated: ``max_consecutive: 2``), its holds and
  resumes are counted (a 6 ms gap is inside the 7 ms hold deadline, so none are expected), the
  slave re-indexes exactly once (at the start: a re-index later would mean it stopped
  following), and its joint velocities (measured positions, finite difference per 1 ms tick)
  stay within the configured limits;
- tracking error, per axis X/Y/Z in mm: the *ideal* slave tip
  ``slave_ref + scale * (master_handle - master_ref)`` minus the slave's *measured* tip (forward
  kinematics of its drives' measured joints), at every tick, where ``master_handle`` is the
  master's measured handle position at that tick (what its encoders read and what it streams)
  and ``master_ref``/``slave_ref`` are the references the slave took at its initial re-index (the
  base offset is part of both tips). Ticks of the first ``--settle`` seconds after the re-index
  are left out (the slave accelerating from rest onto a moving target). The error is thus the
  whole chain: the 2 ms sampling, the lost packets, the 1 ms loop, and the drives' response;
- packet inter-arrival at the slave's interface (the simulated instant each POSITION is handed
  to it): a histogram over the whole run, and a plot over a window (Fig. 11);
- trajectories over a window: master X/Y and slave X/Y (Fig. 12), and the tracking error.

Writes ``report.md`` and ``report.json`` (tools/soak.py's format), ``interarrival.png``,
``trajectories.png`` and ``tracking_error.png`` to ``--out``. Exit code 0 when every check
passes, 1 otherwise. Everything is simulated and seeded: the same arguments give the same
numbers on any machine; only ``wall_seconds`` and the speed ratio depend on the machine.

Examples::

    python tools/stability.py --minutes 10 --out /tmp/stability-10min
    python tools/stability.py                 # the paper's 12 hours (hours of wall time: see
                                              # docs/SOAK.md for the speed ratio)
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import signal
import sys
import tempfile
import time
import traceback
from array import array
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
if str(ROOT) not in sys.path:
    sys.path.insert(1, str(ROOT))

from loss_proxy import LossPattern  # noqa: E402
from soakreport import Report, histogram, write_report  # noqa: E402

#: the slave's loss tolerance (configs/slave.yaml safety.loss.max_consecutive) and the stream
PERIOD_MS = 2
DOUBLE_LOSS_GAP_MS = 3 * PERIOD_MS  # the packet after two lost ones arrives 6 ms after the last
#: the paper's result (mean tracking error, mm): reported next to ours
PAPER_MEAN_ERROR_MM = {"x": 0.094, "y": 0.097}
AXES = ("x", "y", "z")


@dataclass
class Traces:
    """What the plots need: a window of the run, sampled every tick (lists: a few MB at most)."""

    t_s: list[float] = field(default_factory=list)
    master_mm: list[tuple[float, float, float]] = field(default_factory=list)
    slave_mm: list[tuple[float, float, float]] = field(default_factory=list)
    ideal_mm: list[tuple[float, float, float]] = field(default_factory=list)
    #: (arrival time s, inter-arrival ms) of every packet handed to the slave in the window
    arrivals: list[tuple[float, int]] = field(default_factory=list)
    #: the same over the warm-up at the start (the stream without loss)
    arrivals_clean: list[tuple[float, int]] = field(default_factory=list)
    #: the motion scale (for the plot's title)
    scale: float = 0.1
    time_label: str = "simulated time (s)"
    #: bilateral teleoperation (a slave with a force source, e.g. configs/wall.yaml): the force
    #: on the instrument and on the hand (t s, N x 3 each; empty without forces)
    force_t: list[float] = field(default_factory=list)
    instrument_n: list[tuple[float, float, float]] = field(default_factory=list)
    hand_t: list[float] = field(default_factory=list)
    hand_n: list[tuple[float, float, float]] = field(default_factory=list)


class _Axis:
    """Running mean / RMS / max |x| of one axis's error and a histogram of |x| (0.1 um bins,
    for the p99): O(1) memory for 43 million ticks."""

    __slots__ = ("n", "total", "total_abs", "total_sq", "max_abs", "bins")

    #: histogram resolution (mm) and range: |e| above the range lands in the last bin
    BIN_MM = 1e-4
    NBINS = 20_000

    def __init__(self) -> None:
        self.n = 0
        self.total = 0.0
        self.total_abs = 0.0
        self.total_sq = 0.0
        self.max_abs = 0.0
        self.bins = [0] * (self.NBINS + 1)

    def add(self, v: float) -> None:
        a = abs(v)
        self.n += 1
        self.total += v
        self.total_abs += a
        self.total_sq += v * v
        if a > self.max_abs:
            self.max_abs = a
        i = int(a * 10_000.0)  # 1 / BIN_MM
        self.bins[i if i < 20_000 else 20_000] += 1

    def add_many(self, v: Any) -> None:
        """``add`` for every value of a float64 numpy array (a batch of ticks)."""
        import numpy as np

        if not len(v):
            return
        a = np.abs(v)
        self.n += len(v)
        self.total += float(v.sum())
        self.total_abs += float(a.sum())
        self.total_sq += float(np.dot(v, v))
        self.max_abs = max(self.max_abs, float(a.max()))
        idx = np.minimum((a * 10_000.0).astype(np.int64), self.NBINS)
        counts = np.bincount(idx, minlength=self.NBINS + 1)
        bins = self.bins
        for i in np.flatnonzero(counts).tolist():
            bins[i] += int(counts[i])

    def percentile(self, p: float) -> float:
        """Upper edge (mm) of the bin holding the p-th percentile of |e| (max |e| at most)."""
        if not self.n:
            return 0.0
        rank = math.ceil(p / 100.0 * self.n)
        seen = 0
        for i, c in enumerate(self.bins):
            seen += c
            if seen >= rank:
                return min((i + 1) * self.BIN_MM, self.max_abs)
        return self.max_abs

    def summary(self) -> dict[str, float | int]:
        n = max(self.n, 1)
        mean = round(self.total_abs / n, 5)
        p99 = round(self.percentile(99.0), 5)
        mx = round(self.max_abs, 5)
        return {
            "n": self.n,
            # the names: mean, p99 and max of |e| per axis
            "mean": mean,
            "p99": p99,
            "max": mx,
            "mean_abs_mm": mean,
            "p99_abs_mm": p99,
            "rms_mm": round(math.sqrt(self.total_sq / n), 5),
            "max_abs_mm": mx,
            "mean_signed_mm": round(self.total / n, 5),
        }


def _command(sim: Any, peer: Any, name: str) -> None:
    """One operator COMMAND, handled by the robot's next tick; a refusal ends the test."""
    cid = peer.send_command(name)
    sim.tick()
    reply = peer.reply_to(cid)
    if reply is None or reply.metadata.get("Status") != "SUCCESS":
        raise SystemExit(f"stability: {sim.config.robot.name} refused {name}: {reply}")


# ---------------------------------------------------------------------------------------------
# The two sides. The master never hears from the slave (its hand is simulated, the stream only
# goes one way), so it can run ahead: each side has its own SimClock at the same instants, and
# the master side hands the slave side, per tick, the wire bytes of the POSITION packets the
# loss pattern let through, its state and its measured handle position. The slave side puts
# those bytes into the slave's interface at the simulated instant they were sent and ticks the
# slave. Both sides run the robots' own code (config, controllers, codec, loss monitor); only
# the process they run in differs (--jobs 1: one process, interleaved; 2: the master in a
# child process, which about halves the wall time on two free cores). The numbers are the same
# either way (tests/tools/test_stability.py).
# ---------------------------------------------------------------------------------------------

#: the header's type field of the master's stream (bytes 2-13, NUL-padded)
_POSITION_TYPE = b"POSITION".ljust(12, b"\0")
#: master ticks per hand-over (and per pipe message with --jobs 2)
BATCH_TICKS = 1000
#: the set-up: slave Enable, slave Run, master Enable, master Run (one tick of each robot per step)
SETUP_TICKS = 4


@dataclass
class _Batch:
    """Master ticks [k0, k0 + n): running flags, handle positions (m, 3 per tick) and the
    delivered packets (tick, wire bytes) in order."""

    k0: int
    n: int
    running: bytes
    handle: Any  # array('d')
    packets: list[tuple[int, bytes]]


@dataclass
class _MasterEnd:
    """What only the master side knows, at the end of its run."""

    packets_sent: int
    dropped: int
    delivered: int
    schedule: int
    gaps: Counter[int]
    closed_runs: Counter[int]
    arrivals: list[tuple[float, int]]
    arrivals_clean: list[tuple[float, int]]
    state: str
    reason: str


class _MasterSide:
    """The master SimRobot, its POSITION output tapped by the loss pattern."""

    def __init__(self, args: argparse.Namespace, total_ticks: int) -> None:
        from occ.clock import SimClock
        from occ.core.safety import RobotState
        from occ_testkit.testing import SimRobot

        self.running_state = RobotState.RUNNING
        packets = total_ticks // PERIOD_MS
        warmup = int(args.warmup * 1000.0 / PERIOD_MS)
        n_runs = int(round(args.loss * packets / 2.0))
        # min_gap=1: at least one delivered packet between two double losses (a run of 3 or 4
        # would be a different test, and the slave must stop on it)
        self.pattern = LossPattern(
            seed=args.seed,
            drop_runs=[(2, n_runs)] if n_runs else [],
            expected=packets,
            warmup=warmup,
            min_gap=1,
        )
        self.sim = sim = SimRobot(args.master_config, clock=SimClock())
        if sim.config.robot.rate_hz != 1000:
            sim.close()
            raise SystemExit("stability: both robots must tick at 1 kHz (one tick = 1 ms here)")
        self.total_ticks = total_ticks
        self.win_arr_start = max(0, total_ticks - int(round(args.arrival_window * 1000.0)))
        self.t0 = 0
        self.last_arrival: int | None = None
        self.gaps: Counter[int] = Counter()
        self.closed_runs: Counter[int] = Counter()  # runs of drops closed by a delivered packet
        self.pending = 0  # drops since the last delivered packet
        self.delivered = self.dropped = 0
        self.arrivals: list[tuple[float, int]] = []
        self.arrivals_clean: list[tuple[float, int]] = []
        self.warmup_ticks = warmup * PERIOD_MS
        self.out: list[tuple[int, bytes]] = []
        out_if = next(
            i.name for i in sim.config.interfaces if any(o.source == "teleop" for o in i.outputs)
        )
        sim.peer(out_if, address=("127.0.0.1", 40002), on_bytes=self._forward)
        ops = sim.robot.interfaces.operator_interfaces()[0].name
        self.op = sim.peer(ops, address=("127.0.0.1", 40001))

    def _forward(self, data: bytes) -> None:
        # called synchronously from the master's tick, at the simulated instant it sent the
        # packet: its wire bytes, as a proxy sees them (the slave decodes them, not this)
        if data[2:14] != _POSITION_TYPE:
            return
        if self.pattern.decide() is not None:
            self.dropped += 1
            self.pending += 1
            return
        k = self.sim.k  # the master's tick running now (its index moves on after the tick)
        self.out.append((k, data))
        self.delivered += 1
        if self.pending:
            self.closed_runs[self.pending] += 1  # the injector's own count, to check the gaps
            self.pending = 0
        prev = self.last_arrival
        if prev is not None and prev >= self.t0:
            gap = k - prev  # ms: one tick is 1 ms
            self.gaps[gap] += 1
            if k - self.t0 >= self.win_arr_start:
                self.arrivals.append(((k - self.t0) / 1000.0, gap))
            elif k - self.t0 < self.warmup_ticks:
                self.arrivals_clean.append(((k - self.t0) / 1000.0, gap))
        self.last_arrival = k

    def _take(self, k0: int, running: bytes, handle: Any) -> _Batch:
        out, self.out = self.out, []
        return _Batch(k0, self.sim.k - k0, running, handle, out)

    def setup(self) -> _Batch:
        """Ticks 0-3: two plain ticks (the slave enables and runs), then Enable and Run."""
        k0 = self.sim.k
        self.sim.tick()
        self.sim.tick()
        for name in ("Enable", "Run"):
            _command(self.sim, self.op, name)
        self.t0 = self.sim.k
        return self._take(k0, b"", array("d"))

    def batches(self) -> Iterator[_Batch]:
        """The test's ticks, BATCH_TICKS at a time, up to the end or the master's first tick
        out of RUNNING (its batch is the last)."""
        sim = self.sim
        data = sim.robot.data
        tip = data.frame.tip_position
        running = self.running_state
        end = self.t0 + self.total_ticks
        while sim.k < end:
            k0 = sim.k
            flags = bytearray()
            handle = array("d")
            stopped = False
            for _ in range(min(BATCH_TICKS, end - k0)):
                sim.tick()
                ok = data.state is running
                flags.append(ok)
                handle.extend(tip(data.q))
                if not ok:
                    stopped = True
                    break
            yield self._take(k0, bytes(flags), handle)
            if stopped:
                return

    def end(self) -> _MasterEnd:
        sm = self.sim.robot.state_machine
        return _MasterEnd(
            self.pattern.index,
            self.dropped,
            self.delivered,
            len(self.pattern.schedule),
            self.gaps,
            self.closed_runs,
            self.arrivals,
            self.arrivals_clean,
            self.sim.robot.data.state.value,
            sm.last_reason or "",
        )

    def close(self) -> None:
        self.sim.close()


def _master_process(conn: Any, stop: Any, args: argparse.Namespace, total_ticks: int) -> None:
    """--jobs 2: the master side in a child process, its batches sent through ``conn``."""
    side = None
    # Ctrl-C reaches the whole process group: the parent decides (it sets ``stop``)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        side = _MasterSide(args, total_ticks)
        conn.send(("batch", side.setup()))
        for batch in side.batches():
            conn.send(("batch", batch))
            if stop.is_set():
                break
        conn.send(("end", side.end()))
    except SystemExit as err:
        conn.send(("error", str(err.code)))
    except BaseException:  # noqa: BLE001 - reported by the parent, which owns the exit code
        conn.send(("error", traceback.format_exc()))
    finally:
        if side is not None:
            side.close()
        conn.close()


class _MasterFeed:
    """The master side's batches, from this process (--jobs 1) or a child process (--jobs 2)."""

    def __init__(self, args: argparse.Namespace, total_ticks: int, jobs: int) -> None:
        self.side: _MasterSide | None = None
        self.proc: Any = None
        if jobs <= 1:
            self.side = _MasterSide(args, total_ticks)
            return
        import multiprocessing

        ctx = multiprocessing.get_context("fork")  # the parent's imports, no re-import
        self.conn, child = ctx.Pipe(duplex=False)
        self.stop = ctx.Event()
        self.proc = ctx.Process(
            target=_master_process, args=(child, self.stop, args, total_ticks), daemon=True
        )
        self.proc.start()
        child.close()
        self._end: _MasterEnd | None = None

    def _recv(self) -> tuple[str, Any]:
        try:
            kind, value = self.conn.recv()
        except EOFError:
            raise SystemExit(
                f"stability: the master process ended without a result (exit {self.proc.exitcode})"
            ) from None
        if kind == "error":
            raise SystemExit(f"stability: master process: {value}")
        return kind, value

    def setup(self) -> _Batch:
        if self.side is not None:
            return self.side.setup()
        kind, value = self._recv()
        assert kind == "batch"
        return value  # type: ignore[no-any-return]

    def batches(self) -> Iterator[_Batch]:
        if self.side is not None:
            yield from self.side.batches()
            return
        while True:
            kind, value = self._recv()
            if kind == "end":
                self._end = value
                return
            yield value

    def end(self, early: bool) -> _MasterEnd:
        """The master side's counters; ``early``: the slave side stopped before the end (the
        master process may have run a few batches further)."""
        if self.side is not None:
            return self.side.end()
        if self._end is None:
            if early:
                self.stop.set()
            while True:
                kind, value = self._recv()
                if kind == "end":
                    self._end = value
                    break
        return self._end

    def close(self) -> None:
        if self.side is not None:
            self.side.close()
        if self.proc is not None:
            self.stop.set()
            self.proc.join(10.0)
            if self.proc.is_alive():
                self.proc.kill()
                self.proc.join(5.0)
            self.conn.close()


def _on_sigterm_interrupt() -> Any:
    """SIGTERM raises KeyboardInterrupt (like Ctrl-C) until the returned function is called."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    def handler(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, handler)
    return lambda: signal.signal(signal.SIGTERM, old)


class Progress:
    """A progress bar on stderr: redrawn in place on a terminal (every 0.5 s), one line every
    ``every`` seconds otherwise (a log file, CI)."""

    def __init__(
        self,
        total_s: float,
        label: str = "stability",
        every: float = 30.0,
        unit: str = "simulated s",
    ) -> None:
        self.total = max(total_s, 1e-9)
        self.label = label
        self.unit = unit
        self.tty = sys.stderr.isatty()
        self.every = 0.5 if self.tty else every
        self.t0 = time.perf_counter()
        self.next = self.t0 + self.every

    def due(self) -> bool:
        return time.perf_counter() >= self.next

    def show(self, done_s: float, final: bool = False) -> None:
        now = time.perf_counter()
        self.next = now + self.every
        el = max(now - self.t0, 1e-9)
        frac = min(done_s / self.total, 1.0)
        speed = done_s / el
        eta = (self.total - done_s) / speed if speed > 0 else float("inf")
        width = 30
        bar = "#" * int(frac * width) + "-" * (width - int(frac * width))
        text = (
            f"{self.label}: [{bar}] {100 * frac:5.1f}% "
            f"{done_s:,.0f}/{self.total:,.0f} {self.unit}, "
            f"{speed:.1f}x real time, {el / 60:.1f} min"
            + ("" if final else f", ~{eta / 60:.1f} min left")
        )
        if self.tty:
            print("\r" + text, end="\n" if final else "", file=sys.stderr, flush=True)
        else:
            print(text, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> tuple[Report, Traces]:
    import numpy as np

    from occ.clock import SimClock
    from occ.core.safety import RobotState
    from occ_testkit.testing import SimRobot

    running = RobotState.RUNNING
    rep = Report("stability")
    seconds = args.minutes * 60.0 if args.minutes is not None else args.hours * 3600.0
    total_ticks = int(round(seconds * 1000.0))
    jobs = int(getattr(args, "jobs", 1) or 1)

    clock = SimClock()
    slave = SimRobot(args.slave_config, clock=clock)
    feed: _MasterFeed | None = None
    try:
        if slave.config.robot.rate_hz != 1000:
            raise SystemExit("stability: both robots must tick at 1 kHz (one tick = 1 ms here)")
        feed = _MasterFeed(args, total_ticks, jobs)
        slave_ctl = slave.robot.controller.controllers[0]
        slave_frame = slave.robot.data.frame
        scale = float(slave_ctl.scale)
        vmax = [j.limits.velocity for j in slave.config.robot.joints]
        # the slave's master interface: where the (surviving) POSITION packets arrive
        to_slave = slave.peer(slave.config.safety.loss.input, address=("127.0.0.1", 40000))
        ops_s = slave.robot.interfaces.operator_interfaces()[0].name
        op_slave = slave.peer(ops_s, address=("127.0.0.1", 40003))
        win_start_tick = max(0, total_ticks - int(round(args.window * 1000.0)))
        traces = Traces(scale=scale)
        period = slave.period
        send = to_slave.send
        set_clock = clock.set

        def deliver(batch: _Batch, k: int, i: int) -> int:
            """Hand the slave the packets the master sent at tick k (from index i on)."""
            pk = batch.packets
            while i < len(pk) and pk[i][0] == k:
                set_clock(k * period)  # the instant the master sent it (SimRobot.tick's now)
                send(pk[i][1])
                i += 1
            return i

        # the slave runs first (it holds until the master's run=1 packets come), then the
        # master: the slave re-indexes on the first packet of a RUNNING master
        setup = feed.setup()
        if setup.n != SETUP_TICKS or setup.k0 != 0:
            raise SystemExit(f"stability: unexpected master set-up ({setup.k0}, {setup.n})")
        i = 0
        for k, name in enumerate(("Enable", "Run")):
            _command(slave, op_slave, name)  # slave tick k, then the master's tick k
            i = deliver(setup, k, i)
        for k in (2, 3):  # the master's Enable and Run ticks, then the slave's
            i = deliver(setup, k, i)
            slave.tick()
        t0 = slave.k
        errs = {a: _Axis() for a in AXES}
        qd_max = [0.0] * len(vmax)
        left_running: list[str] = []
        settle_ticks = int(round(args.settle * 1000.0))
        s_data = slave.robot.data
        q_prev = list(s_data.q)
        reindex_tick: int | None = None
        progress = Progress(seconds) if args.progress else None
        t_wall0 = time.perf_counter()
        cpu0 = time.process_time()
        stopped_early = False
        tip_s = slave_frame.tip_position
        seg_refs: tuple[Any, Any] | None = None  # (master_ref, slave_ref) of the segment
        seg_idx: list[int] = []  # the batch's ticks compared (indices into the batch)
        seg_tip = array("d")  # the slave's measured tip at those ticks
        seg_batch: _Batch | None = None

        def flush() -> None:
            """Tracking error of the ticks collected so far (numpy, per batch)."""
            if not seg_idx:
                return
            assert seg_refs is not None and seg_batch is not None
            mref, sref = (np.asarray(r, dtype=np.float64)[:3] for r in seg_refs)
            hand = np.frombuffer(seg_batch.handle, dtype=np.float64).reshape(-1, 3)[seg_idx]
            tip = np.frombuffer(seg_tip, dtype=np.float64).reshape(-1, 3).copy()
            ideal = sref + scale * (hand - mref)
            err = (ideal - tip) * 1000.0
            for c, a in enumerate(AXES):
                errs[a].add_many(np.ascontiguousarray(err[:, c]))
            first = seg_batch.k0 - t0
            inwin = [n for n, j in enumerate(seg_idx) if first + j >= win_start_tick]
            for n in inwin:
                traces.t_s.append((first + seg_idx[n]) / 1000.0)
                traces.master_mm.append(tuple((hand[n] * 1000.0).tolist()))  # type: ignore[arg-type]
                traces.slave_mm.append(tuple((tip[n] * 1000.0).tolist()))  # type: ignore[arg-type]
                traces.ideal_mm.append(tuple((ideal[n] * 1000.0).tolist()))  # type: ignore[arg-type]
            seg_idx.clear()
            del seg_tip[:]

        # SIGINT (Ctrl-C) or SIGTERM end the run early with a report of what was simulated
        interrupted = False
        restore = _on_sigterm_interrupt()
        try:
            for batch in feed.batches():
                flags, k0 = batch.running, batch.k0
                seg_batch = batch
                qs = array("d", q_prev)  # the slave's measured joints, tick by tick, from the last
                pi = 0
                for j in range(batch.n):
                    km = k0 + j  # the master's tick and the slave's (lockstep)
                    pi = deliver(batch, km, pi)
                    slave.tick()
                    if not flags[j] or s_data.state is not running:
                        k = km - t0
                        why = slave.robot.state_machine.last_reason
                        m_state = "RUNNING" if flags[j] else "not RUNNING"
                        if not flags[j]:
                            m_end = feed.end(early=False)
                            m_state = m_end.state
                            why = why or m_end.reason
                        left_running.append(
                            f"t={k / 1000.0:.3f} s: master {m_state}, "
                            f"slave {s_data.state.value} ({why})"
                        )
                        stopped_early = True
                        break
                    q = s_data.q
                    qs.extend(q)
                    mref = slave_ctl.master_ref
                    if mref is None:
                        continue  # not following yet (no packet of a RUNNING master so far)
                    if reindex_tick is None:
                        reindex_tick = km - t0
                    if km - t0 - reindex_tick < settle_ticks:
                        continue
                    if seg_refs is None or mref is not seg_refs[0]:
                        flush()  # a new re-index (a failed check): the refs change from here
                        seg_refs = (mref, slave_ctl.slave_ref)
                    seg_idx.append(j)
                    seg_tip.extend(tip_s(q))
                flush()
                # joint velocities: measured positions, finite difference per 1 ms tick
                qa = np.frombuffer(qs, dtype=np.float64).reshape(-1, len(vmax)).copy()
                if len(qa) > 1:
                    qd = np.abs(np.diff(qa, axis=0)).max(axis=0) * 1000.0
                    qd_max = [max(a, float(b)) for a, b in zip(qd_max, qd, strict=True)]
                q_prev = qa[-1].tolist()
                if stopped_early:
                    break
                if progress is not None and progress.due():
                    progress.show((slave.k - t0) / 1000.0)
        except KeyboardInterrupt:
            interrupted = stopped_early = True
        finally:
            restore()
        elapsed = time.perf_counter() - t_wall0
        cpu_s = time.process_time() - cpu0
        sim_s = (slave.k - t0) / 1000.0
        if progress is not None:
            progress.show(sim_s, final=True)
        m = feed.end(early=stopped_early)
        counters = slave.robot.streams.monitor.counters() if slave.robot.streams.monitor else {}
        ctl_stats = slave_ctl.stats()
    finally:
        slave.close()
        if feed is not None:
            feed.close()
    # the child's CPU time (--jobs 2), counted once it has exited
    cpu_children = 0.0
    if jobs > 1:
        t = os.times()
        cpu_children = t.children_user + t.children_system
    traces.arrivals = m.arrivals
    traces.arrivals_clean = m.arrivals_clean
    gaps, closed_runs, dropped, delivered = m.gaps, m.closed_runs, m.dropped, m.delivered

    double_gaps = gaps.get(DOUBLE_LOSS_GAP_MS, 0)
    other_gaps = {g: c for g, c in gaps.items() if g not in (PERIOD_MS, DOUBLE_LOSS_GAP_MS)}
    speed = sim_s / elapsed if elapsed > 0 else None
    err_summary = {a: errs[a].summary() for a in AXES}
    rep.numbers = {
        "simulated_seconds": sim_s,
        "seed": args.seed,
        "loss_target": args.loss,
        "packets_sent": m.packets_sent,
        "packets_dropped": dropped,
        "packets_delivered": delivered,
        "drop_fraction": round(dropped / m.packets_sent, 6) if m.packets_sent else 0.0,
        "double_losses_scheduled": m.schedule,
        "double_losses_per_s": round(double_gaps / sim_s, 3) if sim_s else 0.0,
        "lost_packets_per_s": round(dropped / sim_s, 3) if sim_s else 0.0,
        "interarrival_histogram_ms": histogram(list(gaps.elements()))
        if sum(gaps.values()) < 100_000
        else {str(g): gaps[g] for g in sorted(gaps)},
        # the protocol schedules no run of 3: no stop is expected, any stop is a false one
        "expected_stops": 0,
        "false_stops": len(left_running),
        "tracking_error_mm": err_summary,
        "tracking_error_paper_mean_mm": PAPER_MEAN_ERROR_MM,
        "tracking_compared": "ideal slave tip slave_ref + scale*(master measured handle - "
        "master_ref) minus slave measured tip (FK of measured joints), every 1 ms tick, after "
        f"the initial re-index + {args.settle} s settle",
        "scale": scale,
        "slave_joint_velocity_max": [round(v, 5) for v in qd_max],
        "slave_joint_velocity_limit": vmax,
        "loss_monitor": counters,
        "slave_controller": {
            k: ctl_stats.get(k) for k in ("samples", "reindexes", "ik_clamped", "ik_failures")
        },
        "wall_seconds": round(elapsed, 1),
        "cpu_seconds": round(cpu_s + cpu_children, 2),
        # per process with --jobs 2 (the slower side sets the wall time): the slave's process
        # (slave ticks, its decoding, the tracking error) and the master's child process
        "cpu_seconds_slave_process": round(cpu_s, 2),
        "cpu_seconds_master_process": round(cpu_children, 2) if jobs > 1 else None,
        "jobs": jobs,
        "interrupted": interrupted,
        "speed_x_realtime": round(speed, 2) if speed else None,
        "wall_hours_for_12h": round(12.0 / speed, 2) if speed else None,
    }
    if interrupted:
        rep.check(
            "ran the whole duration",
            False,
            f"interrupted after {sim_s:.0f} of {seconds:.0f} simulated s (SIGINT/SIGTERM); the "
            "numbers are those of the part that ran",
        )
    rep.check(
        "no stop, no fault",
        not left_running,
        f"master and slave RUNNING for all {sim_s:.0f} simulated s"
        if not left_running
        else left_running[0],
    )
    rep.check(
        "double losses never latch",
        counters.get("trips") == 0 and counters.get("max_run") == 2,
        f"loss monitor: {counters.get('trips')} trips, longest run "
        f"{counters.get('max_run')}, {counters.get('lost_total')} lost",
    )
    rep.check(
        "no hold",
        counters.get("holds") == 0 and counters.get("resumes") == 0,
        f"{counters.get('holds')} holds, {counters.get('resumes')} resumes (a 6 ms gap is "
        "inside the 7 ms hold deadline)",
    )
    rep.check(
        "slave follows without re-indexing",
        ctl_stats.get("reindexes") == 1 and ctl_stats.get("ik_failures") == 0,
        f"{ctl_stats.get('reindexes')} re-index (the initial one), "
        f"{ctl_stats.get('ik_failures')} IK failures, {ctl_stats.get('ik_clamped')} clamped",
    )
    rep.check(
        "joint velocities bounded",
        all(v <= lim for v, lim in zip(qd_max, vmax, strict=True)),
        f"max |qd| {[round(v, 4) for v in qd_max]} <= limits {vmax}",
    )
    rep.check(
        "every double loss seen as one 6 ms gap",
        set(closed_runs) <= {2} and double_gaps == closed_runs[2] and not other_gaps,
        f"{double_gaps} gaps of 6 ms for {closed_runs[2]} double losses closed by a packet "
        f"(runs by length: {dict(closed_runs)}); other gaps: {other_gaps or 'none'}",
    )
    bound = args.max_mean_error_mm
    rep.check(
        f"mean tracking error X, Y <= {bound} mm",
        all(err_summary[a]["n"] > 0 and err_summary[a]["mean_abs_mm"] <= bound for a in ("x", "y")),
        f"mean |e| X {err_summary['x']['mean_abs_mm']} mm, "
        f"Y {err_summary['y']['mean_abs_mm']} mm (paper: 0.094, 0.097); "
        f"max X {err_summary['x']['max_abs_mm']}, "
        f"Y {err_summary['y']['max_abs_mm']} mm",
    )
    return rep, traces


def plot(rep: Report, out: Path, traces: Traces) -> list[str]:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("stability: matplotlib missing, no plots (pip install matplotlib)", file=sys.stderr)
        return []
    files: list[str] = []
    # Fig. 11: inter-arrival over time without loss (the warm-up) and with it (the last
    # seconds), and the whole run's histogram
    fig, (ax0, ax1, ax2) = plt.subplots(
        1, 3, figsize=(13, 3.6), gridspec_kw={"width_ratios": [2, 3, 1.3]}, sharey=False
    )
    for ax, data, title, color in (
        (ax0, traces.arrivals_clean, "without loss (warm-up)", "tab:green"),
        (ax1, traces.arrivals, "with 2 % double losses (end of the run)", "tab:blue"),
    ):
        if data:
            ts, gs = zip(*data, strict=True)
            ax.step(ts, gs, where="post", color=color, linewidth=0.8)
            ax.plot(ts, gs, ".", markersize=3, color=color)
        ax.set_ylim(0, 8)
        ax.set_xlabel(traces.time_label)
        ax.set_title(title, fontsize=10)
    ax0.set_ylabel("POSITION inter-arrival at the slave (ms)")
    hist = rep.numbers.get("interarrival_histogram_ms", {})
    ax2.bar([float(g) for g in hist], list(hist.values()), width=0.4, color="tab:blue")
    ax2.set_yscale("log")
    ax2.set_xlabel("inter-arrival (ms)")
    ax2.set_ylabel("packets (whole run)")
    ax2.set_title("histogram", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "interarrival.png", dpi=90)
    plt.close(fig)
    files.append("interarrival.png")
    if traces.t_s:
        # Fig. 12: master (input) and slave (output), each on its own scale (10:1)
        fig, axes = plt.subplots(2, 1, figsize=(11, 6), sharex=True)
        for ax, i, a in zip(axes, (0, 1), ("X", "Y"), strict=True):
            ax.plot(
                traces.t_s,
                [m[i] for m in traces.master_mm],
                color="tab:blue",
                label=f"master {a} (mm)",
            )
            ax.set_ylabel(f"master {a} (mm)", color="tab:blue")
            tw = ax.twinx()
            tw.plot(
                traces.t_s,
                [s[i] for s in traces.slave_mm],
                color="tab:red",
                linestyle="--",
                label=f"slave {a} (mm)",
            )
            tw.set_ylabel(f"slave tip {a} (mm)", color="tab:red")
        axes[0].set_title(
            f"input (master handle) and output (slave tip) trajectories, scale {traces.scale:g}"
        )
        axes[-1].set_xlabel(traces.time_label)
        fig.tight_layout()
        fig.savefig(out / "trajectories.png", dpi=90)
        plt.close(fig)
        files.append("trajectories.png")
        fig, ax = plt.subplots(figsize=(11, 4))
        for i, (a, c) in enumerate(zip(("X", "Y"), ("tab:blue", "tab:orange"), strict=True)):
            ax.plot(
                traces.t_s,
                [(d[i] - s[i]) for d, s in zip(traces.ideal_mm, traces.slave_mm, strict=True)],
                color=c,
                linewidth=0.8,
                label=f"{a}: ideal - slave tip",
            )
        ax.set_xlabel(traces.time_label)
        ax.set_ylabel("tracking error (mm)")
        ax.set_title("tracking error over the window")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / "tracking_error.png", dpi=90)
        plt.close(fig)
        files.append("tracking_error.png")
    if traces.force_t:
        files.append(plot_forces(traces, out, plt))
    return files


def plot_forces(traces: Traces, out: Path, plt: Any) -> str:
    """The force panel: the force on the instrument (the slave's) and on the hand (the
    master's displayed force), magnitude and x, over the run."""
    fig, axes = plt.subplots(2, 1, figsize=(11, 5), sharex=True)
    for ax, what in zip(axes, ("magnitude", "x"), strict=True):
        for t, f, label, style in (
            (traces.force_t, traces.instrument_n, "at the instrument", {"color": "0.6", "lw": 2}),
            (traces.hand_t, traces.hand_n, "on the hand", {"color": "tab:red", "lw": 0.8}),
        ):
            if not t:
                continue
            ys = [math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2) if what == "magnitude" else v[0]
                  for v in f]  # fmt: skip
            ax.plot(t, ys, label=label, **style)
        ax.set_ylabel(f"force {what} (N)")
        ax.grid(True, alpha=0.3)
    axes[0].set_title("bilateral teleoperation: the slave's contact force and the hand's")
    axes[0].legend(fontsize=8)
    axes[-1].set_xlabel(traces.time_label)
    fig.tight_layout()
    fig.savefig(out / "forces.png", dpi=90)
    plt.close(fig)
    return "forces.png"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="stability", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    return p


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The protocol's options (here and in ``tools/soak.py paper``)."""
    d = p.add_mutually_exclusive_group()
    d.add_argument("--hours", type=float, default=12.0, help="simulated hours (default 12)")
    d.add_argument("--minutes", type=float, default=None, help="simulated minutes instead")
    p.add_argument("--seed", type=int, default=1, help="loss pattern seed (default 1)")
    p.add_argument(
        "--loss",
        type=float,
        default=0.02,
        help="fraction of packets lost, all in runs of exactly 2 (default 0.02)",
    )
    p.add_argument(
        "--warmup",
        type=float,
        default=1.0,
        help="seconds of stream without loss at the start (default 1)",
    )
    p.add_argument(
        "--settle",
        type=float,
        default=1.0,
        help="seconds after the re-index left out of the tracking error (default 1)",
    )
    p.add_argument(
        "--window",
        type=float,
        default=20.0,
        help="seconds at the end of the run plotted as trajectories (default 20)",
    )
    p.add_argument(
        "--arrival-window",
        type=float,
        default=2.0,
        help="seconds at the end of the run plotted as inter-arrival (default 2)",
    )
    p.add_argument(
        "--max-mean-error-mm",
        type=float,
        default=0.1,
        help="bound on the mean |tracking error| in X and Y (default 0.1 mm)",
    )
    p.add_argument("--master-config", default=str(ROOT / "configs" / "master.yaml"))
    p.add_argument("--slave-config", default=str(ROOT / "configs" / "slave.yaml"))
    p.add_argument("--out", type=Path, default=None, help="report folder (default: a temp dir)")
    p.add_argument(
        "--progress",
        action="store_true",
        help="a progress bar on stderr (in place on a terminal, a line every 30 s otherwise)",
    )
    p.add_argument(
        "--jobs",
        type=int,
        choices=(1, 2),
        default=2,
        help="processes: 2 runs the master in a child process (about twice as fast on two free "
        "cores; the same numbers), 1 keeps both robots in this one (default 2)",
    )


def run_protocol(
    produce: Callable[[], tuple[Report, Traces]], out: Path, command: str, title: str
) -> Report | int:
    """Run one form of the protocol (``produce``), write its report folder with the paper's
    figures and print its checks; the report, or exit code 2 for a set-up error (a
    ``SystemExit`` with a message, printed to stderr). Shared by the simulated and the real
    form (``tools/soak.py paper --real``)."""
    try:
        rep, traces = produce()
    except SystemExit as err:
        if isinstance(err.code, str):
            print(err.code, file=sys.stderr)
            return 2
        raise
    rep.command = command
    write_report(rep, out, title=title, plotter=lambda r, o: plot(r, o, traces))
    for c in rep.checks:
        print(f"[{c.label}] {c.name}: {c.detail}")
    return rep


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    command = " ".join(["tools/stability.py", *(argv if argv is not None else sys.argv[1:])])
    return execute(args, command)


def execute(args: argparse.Namespace, command: str, label: str = "stability") -> int:
    """Run the protocol with parsed ``args``, write the report folder, print the checks; the
    exit code (0 pass, 1 fail, 2 set-up error). ``tools/soak.py paper`` calls this too."""
    out = args.out or Path(tempfile.mkdtemp(prefix="occ-stability-"))
    out.mkdir(parents=True, exist_ok=True)
    # the simulated robots log every state change: to a file, not the terminal
    logging.basicConfig(
        filename=str(out / "sim.log"),
        level=logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    done = run_protocol(
        lambda: run(args), out, command, "Stability test (OCC paper, simulated time)"
    )
    if isinstance(done, int):
        return done
    rep = done
    n = rep.numbers
    e = n["tracking_error_mm"]
    print(
        f"{label}: {n['simulated_seconds']:.0f} simulated s at {n['speed_x_realtime']}x real "
        f"time ({n['wall_seconds']} s wall, {n['cpu_seconds']} s CPU); mean |e| X "
        f"{e['x']['mean']} mm, Y {e['y']['mean']} mm (paper: 0.094, 0.097); "
        f"{'PASS' if rep.passed else 'FAIL'}; report in {out}"
    )
    return 0 if rep.passed else 1


if __name__ == "__main__":
    os.environ.setdefault("MPLBACKEND", "Agg")
    sys.exit(main())
