"""``soak.py sim``: the slave in simulated time, judged exactly by an oracle of its own."""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

from loss_proxy import LossPattern, pattern_from_args
from soakreport import Report, RunOutcome, histogram, summarize

from .common import MAX_TOLERATED, PERIOD_MS, STOP_WITHIN_MS


class SimSlave:
    """The slave Robot stepped tick by tick (1 kHz) on a SimClock, its interfaces on in-process
    channels (:class:`occ_testkit.testing.SimRobot`): the master and an operator are peers on
    them."""

    def __init__(self, config: Path, *, first_seq: int = 0) -> None:
        from occ_testkit.testing import SimRobot

        self.sim = SimRobot(config)
        self.robot = self.sim.robot
        self.clock = self.sim.clock
        cfg = self.sim.config
        ops = self.robot.interfaces.operator_interfaces()
        if not ops:
            self.sim.close()
            raise SystemExit(f"{config}: no operator (role: operator) interface")
        self.master = self.sim.peer(cfg.safety.loss.input, address=("127.0.0.1", 40000))
        self.operator = self.sim.peer(
            ops[0].name, address=("127.0.0.1", 40001), on_message=self._capture
        )
        self.seq = first_seq & 0xFFFFFFFF
        self.statuses: list[Any] = []  # (tick, STATUS) sent to the operator (alerts)
        self.replies: list[Any] = []  # RTS_COMMAND replies to the operator
        self.other_out = 0

    @property
    def k(self) -> int:
        return self.sim.k

    def _capture(self, msg: Any) -> None:
        t = msg.message_type
        if t == "STATUS":
            self.statuses.append((self.k, msg))
        elif t == "RTS_COMMAND":
            self.replies.append(msg)
        else:
            self.other_out += 1

    def next_seq(self) -> int:
        self.seq = (self.seq + 1) & 0xFFFFFFFF
        return self.seq

    def deliver(self, seq: int, pos_mm: tuple[float, float, float], *, run: bool = True) -> None:
        """One POSITION from the master, through the wire format (pack + CRC-checked decode)."""
        self.master.send_position(pos_mm, seq=seq, run=run, timestamp=self.clock.wall_time())

    def inject_command(self, name: str) -> int:
        """Queue an operator COMMAND; it is handled by the next tick."""
        return self.operator.send_command(name)

    def reply_to(self, command_id: int) -> Any | None:
        for r in reversed(self.replies[-8:]):
            if getattr(r, "command_id", None) == command_id:
                return r
        return None

    def tick(self) -> None:
        self.sim.tick()

    def command(self, name: str) -> Any:
        cid = self.inject_command(name)
        self.tick()
        return self.reply_to(cid)

    def close(self) -> None:
        self.sim.close()


def run_sim(args: argparse.Namespace, out: Path) -> Report:
    rep = Report("sim")
    sim_s = float(args.sim_seconds)
    total_ticks = int(round(sim_s * 1000.0))
    pause = max(1, int(round(args.pause_ms)))
    pattern = _sim_pattern(args, sim_s, total_ticks // 2, pause)
    slave = _started_slave(Path(args.config), args.first_seq)
    oracle = _Oracle(rep, slave, pause)
    t_wall0 = time.perf_counter()
    oracle.run(slave.k + total_ticks, pattern, progress=args.progress, sim_s=sim_s)
    oracle.finish()
    elapsed = time.perf_counter() - t_wall0
    monitor = slave.robot.streams.monitor
    counters = monitor.counters() if monitor is not None else {}
    slave.close()
    _sim_numbers(rep, oracle, pattern, args, sim_s, pause, counters, elapsed)
    _sim_checks(rep, oracle, counters)
    return rep


def _sim_pattern(args: argparse.Namespace, sim_s: float, packets: int, pause: int) -> LossPattern:
    """The drops: from the options, or by default Gilbert-Elliott bursts (mean length 2) plus
    0.5 % independent loss."""
    # scheduled runs must not fall into the stop-and-resume window of the previous one
    min_gap_default = int(math.ceil((pause + 100) / PERIOD_MS))
    try:
        pattern = pattern_from_args(args, sim_s, expected=packets, min_gap_default=min_gap_default)
    except ValueError as err:
        raise SystemExit(f"soak sim: {err}") from None
    if not (args.loss or args.burst or args.drop_runs or args.drop_cycle):
        pattern = LossPattern(seed=args.seed, loss=0.005, burst=(0.002, 0.5, 1.0))
    return pattern


def _started_slave(config: Path, first_seq: int) -> SimSlave:
    """The simulated slave, enabled and RUNNING by its operator's commands."""
    from occ.core.safety import RobotState

    slave = SimSlave(config, first_seq=first_seq)
    for name in ("Enable", "Run"):
        r = slave.command(name)
        if r is None or r.metadata.get("Status") != "SUCCESS":
            raise SystemExit(f"soak sim: {name} refused: {r}")
    if slave.robot.state is not RobotState.RUNNING:
        raise SystemExit(f"soak sim: robot is {slave.robot.state.value}, not RUNNING")
    return slave


class _Oracle:
    """What the loss monitor must do, followed independently tick by tick: the drops it sees,
    when it must hold and latch a stop, the operator's Run after each stop, and the alerts."""

    def __init__(self, rep: Report, slave: SimSlave, pause: int) -> None:
        from occ.core.safety import RobotState

        self.RUNNING, self.STOPPED = RobotState.RUNNING, RobotState.STOPPED
        self.rep, self.slave, self.robot, self.pause = rep, slave, slave.robot, pause
        self.t_origin = slave.k  # tick of the first packet
        self.w = 2.0 * math.pi * 0.1
        self.armed = False  # the monitor has seen a good packet since the last (re)start
        self.last_good: int | None = None
        self.open_run: dict[str, Any] | None = None  # the current run of drops
        self.expected_stop: int | None = None
        self.resume_at: int | None = None
        self.resume_cid: int | None = None
        self.stop_latencies: list[float] = []
        self.all_lengths: list[int] = []
        self.failures = rep.failures
        self.stops_ok = self.unexpected = self.missed = self.resumes = self.resume_failed = 0
        self.drops = 0
        self.status_seen = 0
        self.alert_ok = 0
        self.alert_bad: list[str] = []
        monitor = self.robot.streams.monitor
        assert monitor is not None
        self.monitor = monitor
        self.grace_ticks = int(math.floor(monitor.grace_s * 1000.0 + 1e-9)) + 1  # elapsed > grace
        self.hold_latencies: list[float] = []
        self.unexpected_holds = 0
        self.was_holding = False

    def close_run(self, k: int) -> None:
        assert self.open_run is not None
        run = self.open_run
        self.open_run = None
        length = run["length"]
        self.all_lengths.append(length)
        if not run["evaluated"]:
            cat = "masked"
        elif run["stopped"]:
            cat = "stop" if length > MAX_TOLERATED else "bad-stop"
        else:
            cat = "no-stop" if length <= MAX_TOLERATED else "missed"
        self.rep.runs.append(
            RunOutcome(
                round((run["tick"] - self.t_origin) / 1000.0, 3),
                length,
                run["seq"],
                cat,
                run.get("latency"),
                hold_ms=run.get("hold"),
            )
        )

    def run(self, end_tick: int, pattern: LossPattern, *, progress: bool, sim_s: float) -> None:
        """Tick the slave to ``end_tick`` (or an abort), judging every tick."""
        t_wall0 = time.perf_counter()
        next_progress = t_wall0 + 30.0
        slave = self.slave
        while slave.k < end_tick:
            k = slave.k
            if time.perf_counter() > next_progress and progress:
                next_progress += 30.0
                print(
                    f"soak sim: {(k - self.t_origin) / 1000.0:.0f}/{sim_s:.0f} simulated s, "
                    f"{self.stops_ok} stops, {len(self.failures)} failures, "
                    f"{time.perf_counter() - t_wall0:.0f} s",
                    file=sys.stderr,
                    flush=True,
                )
            if not self.step(k, pattern):
                break

    def step(self, k: int, pattern: LossPattern) -> bool:
        """One tick: the master's packet (or its drop), the operator's Run when due, the tick,
        then what should have happened at it; False when the soak must stop."""
        slave, robot = self.slave, self.robot
        pre = robot.state
        is_packet = k % 2 == 0
        drop = False
        seq = 0
        if is_packet:
            seq = slave.next_seq()
            drop = pattern.decide() is not None
            if not drop:
                t = (k - self.t_origin) * 0.001
                w = self.w
                slave.deliver(seq, (50.0 * math.sin(w * t), 50.0 * math.cos(w * t), 20.0))
            else:
                self.drops += 1
        is_resume = self.resume_at == k
        if is_resume:
            self.resume_cid = slave.inject_command("Run")
        slave.tick()
        post = robot.state
        closing = is_packet and self._account_packet(k, drop, seq, pre, is_resume)
        self._check_grace(k)
        self._check_hold(k, post)
        if is_resume:
            self._check_resume(k, post)
        if pre is self.RUNNING and post is self.STOPPED:
            self._on_stop(k)
        elif self.expected_stop == k:
            self.missed += 1
            run = self.open_run
            self.failures.append(
                f"tick {k}: MISSED stop: run of {run and run['length']} losses "
                f"from seq {run and run['seq']}, robot {post.value}"
            )
            self.expected_stop = None
        if closing:
            self.close_run(k)
        if post is not self.RUNNING and post is not self.STOPPED:
            self.failures.append(
                f"tick {k}: robot left RUNNING/STOPPED: {post.value} "
                f"({robot.state_machine.last_reason}); soak aborted"
            )
            return False
        self._read_alerts()
        if len(self.failures) > 1000:
            self.failures.append("more than 1000 failures: soak aborted")
            return False
        return True

    def _account_packet(self, k: int, drop: bool, seq: int, pre: Any, is_resume: bool) -> bool:
        """A packet tick: a drop opens or lengthens the run of drops; a good packet ends it (and
        proves a run of >= 3 missing) and arms the monitor. True when a run ends here."""
        if drop:
            if self.open_run is None:
                self.open_run = {
                    "tick": k,
                    "seq": seq,
                    "length": 0,
                    "evaluated": self.armed and pre is self.RUNNING,
                    "last_good": self.last_good,
                    "stopped": False,
                    "hold": None,
                }
            self.open_run["length"] += 1
            return False
        closing = False
        run = self.open_run
        if run is not None:
            closing = True
            if run["evaluated"] and not run["stopped"] and run["length"] > MAX_TOLERATED:
                self.expected_stop = k  # this packet proves the numbers missing
        if pre is self.RUNNING and not is_resume:
            self.armed = True  # the first good packet after a (re)start arms the monitor
            self.last_good = k
        return closing

    def _check_grace(self, k: int) -> None:
        run = self.open_run
        if (
            run is not None
            and run["evaluated"]
            and not run["stopped"]
            and run["last_good"] is not None
            and k == run["last_good"] + self.grace_ticks
        ):
            self.expected_stop = k  # silent past the grace: a dead master

    def _check_hold(self, k: int, post: Any) -> None:
        """Holds: exactly at +7 ms for a run of >= 3, never otherwise."""
        holding = self.monitor.holding and post is self.RUNNING
        if holding and not self.was_holding:
            run = self.open_run
            if (
                run is not None
                and run["evaluated"]
                and run["hold"] is None
                and run["last_good"] is not None
            ):
                run["hold"] = k - run["last_good"]
                self.hold_latencies.append(float(run["hold"]))
            else:
                self.unexpected_holds += 1
                self.failures.append(
                    f"tick {k}: UNEXPECTED hold; open run "
                    f"{run['length'] if run else 0}, armed {self.armed}"
                )
        self.was_holding = holding

    def _check_resume(self, k: int, post: Any) -> None:
        self.resumes += 1
        cid = self.resume_cid
        r = self.slave.reply_to(cid) if cid is not None else None
        if r is None or r.metadata.get("Status") != "SUCCESS" or post is not self.RUNNING:
            self.resume_failed += 1
            self.failures.append(
                f"tick {k}: operator Run failed: {r and r.metadata}, state {post.value}"
            )
        self.armed = False  # reset by entering RUNNING: armed again by the next packet
        self.resume_at = None

    def _on_stop(self, k: int) -> None:
        """RUNNING -> STOPPED at tick ``k``: expected here, or a failure."""
        reason = self.robot.state_machine.last_reason
        run = self.open_run
        t_s = round((k - self.t_origin) / 1000.0, 3)
        if self.expected_stop == k and run is not None:
            self.stops_ok += 1
            lat = float(k - run["last_good"])
            run["stopped"] = True
            run["latency"] = lat
            self.stop_latencies.append(lat)
            self.rep.stops.append(
                {
                    "t_s": t_s,
                    "latency_ms": lat,
                    "hold_ms": run["hold"],
                    "first_lost_seq": run["seq"],
                    "reason": reason,
                }
            )
        else:
            self.unexpected += 1
            if run is not None:
                run["stopped"] = True
            self.failures.append(
                f"tick {k}: UNEXPECTED stop ({reason}); open run "
                f"{run['length'] if run else 0}, armed {self.armed}, last good {self.last_good}"
            )
            self.rep.stops.append(
                {"t_s": t_s, "latency_ms": None, "reason": reason, "unexpected": True}
            )
        self.expected_stop = None
        self.armed = False
        self.was_holding = False
        self.resume_at = k + self.pause

    def _read_alerts(self) -> None:
        """Every STATUS to the operators: a STOPPED one must name the packet loss."""
        statuses = self.slave.statuses
        while self.status_seen < len(statuses):
            tk, st = statuses[self.status_seen]
            self.status_seen += 1
            if st.error_name == "STOPPED":
                if "packet loss" in st.status_message:
                    self.alert_ok += 1
                else:
                    self.alert_bad.append(f"tick {tk}: {st.status_message}")

    def finish(self) -> None:
        """The soak ended inside a run: judge it only if its outcome is already decided."""
        run = self.open_run
        if run is not None:
            if run["evaluated"] and (run["stopped"] or run["length"] > MAX_TOLERATED):
                self.close_run(self.slave.k)
            else:
                self.all_lengths.append(run["length"])


def _sim_numbers(
    rep: Report,
    o: _Oracle,
    pattern: LossPattern,
    args: argparse.Namespace,
    sim_s: float,
    pause: int,
    counters: dict[str, Any],
    elapsed: float,
) -> None:
    cats = Counter(r.category for r in rep.runs)
    evaluated = [r for r in rep.runs if r.category != "masked"]
    ev_long = [r for r in evaluated if r.length > MAX_TOLERATED]
    ticks = o.slave.k - o.t_origin
    rep.numbers = {
        "sim_seconds": sim_s,
        "ticks": ticks,
        "packets": pattern.index,
        "dropped": o.drops,
        "drop_fraction": round(o.drops / pattern.index, 6) if pattern.index else 0.0,
        "pattern": pattern.describe(),
        "first_seq": args.first_seq,
        "last_seq": o.slave.seq,
        "pause_ms": pause,
        "runs_total": len(o.all_lengths),
        "runs_evaluated": len(evaluated),
        "runs_masked": cats.get("masked", 0),
        "runs_by_outcome": dict(sorted(cats.items())),
        "run_length_histogram_all": histogram(o.all_lengths),
        "run_length_histogram_evaluated": histogram([r.length for r in evaluated]),
        "stops": o.stops_ok + o.unexpected,
        "stops_expected": len(ev_long),
        "stops_unexpected": o.unexpected,
        "stops_missed": o.missed,
        "hold_latency_ms": summarize(o.hold_latencies),
        "holds_unexpected": o.unexpected_holds,
        "stop_latency_ms": summarize(o.stop_latencies),
        "stop_latency_histogram_ms": histogram([int(v) for v in o.stop_latencies]),
        "operator_runs": o.resumes,
        "operator_runs_failed": o.resume_failed,
        "status_alerts_stopped": o.alert_ok + len(o.alert_bad),
        "loss_monitor": counters,
        "wall_seconds": round(elapsed, 1),
        "speed_x_realtime": round(ticks / 1000.0 / elapsed, 2) if elapsed else None,
    }


def _sim_checks(rep: Report, o: _Oracle, counters: dict[str, Any]) -> None:
    cats = Counter(r.category for r in rep.runs)
    evaluated = [r for r in rep.runs if r.category != "masked"]
    ev_short = [r for r in evaluated if r.length <= MAX_TOLERATED]
    ev_long = [r for r in evaluated if r.length > MAX_TOLERATED]
    n_stops = o.stops_ok + o.unexpected
    rep.check(
        "stop iff run >= 3",
        o.unexpected == 0
        and o.missed == 0
        and cats.get("missed", 0) == 0
        and o.stops_ok == len(ev_long),
        f"{len(ev_long)} evaluated runs >= 3 -> {o.stops_ok} latched stops at the expected tick "
        f"(the packet that proves the gap, or the grace); {o.unexpected} unexpected, "
        f"{o.missed} missed",
    )
    rep.check(
        "runs of 1-2 never stop",
        cats.get("bad-stop", 0) == 0 and all(r.category == "no-stop" for r in ev_short),
        f"{len(ev_short)} evaluated runs of 1-2 losses, "
        f"{cats.get('bad-stop', 0)} followed by a stop",
    )
    held = [r for r in ev_long if r.hold_ms is not None]
    rep.check(
        "every run >= 3 holds motion at exactly +7 ms",
        o.unexpected_holds == 0
        and len(held) == len(ev_long)
        and all(v == STOP_WITHIN_MS for v in o.hold_latencies),
        f"{len(o.hold_latencies)} holds, at {summarize(o.hold_latencies)} ms after the last good "
        f"packet (tick = 1 ms); {o.unexpected_holds} unexpected holds; latched stops at "
        f"{summarize(o.stop_latencies)} ms",
    )
    rep.check(
        "every stop alerts the operators",
        o.alert_ok == n_stops and not o.alert_bad,
        f"{o.alert_ok} STATUS STOPPED 'packet loss' alerts for {n_stops} stops"
        + (f"; other: {o.alert_bad[:3]}" if o.alert_bad else ""),
    )
    rep.check(
        "loss monitor trips == stops",
        counters.get("trips") == n_stops,
        f"loss monitor trips {counters.get('trips')}, observed stops {n_stops}",
    )
    rep.check(
        "operator Run resumes after every stop",
        o.resume_failed == 0 and o.resumes >= n_stops - 1,
        f"{o.resumes} Runs after {n_stops} stops, {o.resume_failed} failed",
    )
    rep.check(
        "enough evidence",
        len(ev_long) > 0 and len(ev_short) > 0,
        f"{len(ev_long)} runs >= 3 and {len(ev_short)} runs of 1-2 were judged",
        severity="warn",
    )
