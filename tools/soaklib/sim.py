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
    channels (:class:`occ.testing.SimRobot`): the master and an operator are peers on them."""

    def __init__(self, config: Path, *, first_seq: int = 0) -> None:
        from occ.testing import SimRobot

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
    from occ.safety import RobotState

    RUNNING, STOPPED = RobotState.RUNNING, RobotState.STOPPED
    rep = Report("sim")
    sim_s = float(args.sim_seconds)
    total_ticks = int(round(sim_s * 1000.0))
    pause = max(1, int(round(args.pause_ms)))
    packets = total_ticks // 2
    # scheduled runs must not fall into the stop-and-resume window of the previous one
    min_gap_default = int(math.ceil((pause + 100) / PERIOD_MS))
    try:
        pattern = pattern_from_args(args, sim_s, expected=packets, min_gap_default=min_gap_default)
    except ValueError as err:
        raise SystemExit(f"soak sim: {err}") from None
    if not (args.loss or args.burst or args.drop_runs or args.drop_cycle):
        # default: Gilbert-Elliott bursts (mean length 2) plus 0.5 % independent loss
        pattern = LossPattern(seed=args.seed, loss=0.005, burst=(0.002, 0.5, 1.0))
    slave = SimSlave(Path(args.config), first_seq=args.first_seq)
    robot = slave.robot
    for name in ("Enable", "Run"):
        r = slave.command(name)
        if r is None or r.metadata.get("Status") != "SUCCESS":
            raise SystemExit(f"soak sim: {name} refused: {r}")
    if robot.state is not RUNNING:
        raise SystemExit(f"soak sim: robot is {robot.state.value}, not RUNNING")
    t_origin = slave.k  # tick of the first packet
    w = 2.0 * math.pi * 0.1

    armed = False  # oracle: the monitor has seen a good packet since the last (re)start
    last_good: int | None = None
    open_run: dict[str, Any] | None = None  # the current run of drops
    expected_stop: int | None = None
    resume_at: int | None = None
    resume_cid: int | None = None
    stop_latencies: list[float] = []
    all_lengths: list[int] = []
    failures = rep.failures
    stops_ok = unexpected = missed = resumes = resume_failed = 0
    drops = 0
    t_wall0 = time.perf_counter()
    next_progress = t_wall0 + 30.0
    end_tick = slave.k + total_ticks
    status_seen = 0
    alert_ok = 0
    alert_bad: list[str] = []
    monitor = robot.streams.monitor
    assert monitor is not None
    grace_ticks = int(math.floor(monitor.grace_s * 1000.0 + 1e-9)) + 1  # elapsed > grace
    hold_latencies: list[float] = []
    unexpected_holds = 0
    was_holding = False

    def close_run(k: int) -> None:
        nonlocal open_run
        assert open_run is not None
        run = open_run
        open_run = None
        length = run["length"]
        all_lengths.append(length)
        if not run["evaluated"]:
            cat = "masked"
        elif run["stopped"]:
            cat = "stop" if length > MAX_TOLERATED else "bad-stop"
        else:
            cat = "no-stop" if length <= MAX_TOLERATED else "missed"
        rep.runs.append(
            RunOutcome(
                round((run["tick"] - t_origin) / 1000.0, 3),
                length,
                run["seq"],
                cat,
                run.get("latency"),
                hold_ms=run.get("hold"),
            )
        )

    while slave.k < end_tick:
        k = slave.k
        if time.perf_counter() > next_progress and args.progress:
            next_progress += 30.0
            print(
                f"soak sim: {(k - t_origin) / 1000.0:.0f}/{sim_s:.0f} simulated s, "
                f"{stops_ok} stops, {len(failures)} failures, "
                f"{time.perf_counter() - t_wall0:.0f} s",
                file=sys.stderr,
                flush=True,
            )
        pre = robot.state
        is_packet = k % 2 == 0
        drop = False
        seq = 0
        if is_packet:
            seq = slave.next_seq()
            drop = pattern.decide() is not None
            if not drop:
                t = (k - t_origin) * 0.001
                slave.deliver(seq, (50.0 * math.sin(w * t), 50.0 * math.cos(w * t), 20.0))
            else:
                drops += 1
        is_resume = resume_at == k
        if is_resume:
            resume_cid = slave.inject_command("Run")
        slave.tick()
        post = robot.state

        # ---- oracle: what should have happened at this tick
        closing = False
        if is_packet:
            if drop:
                if open_run is None:
                    open_run = {
                        "tick": k,
                        "seq": seq,
                        "length": 0,
                        "evaluated": armed and pre is RUNNING,
                        "last_good": last_good,
                        "stopped": False,
                        "hold": None,
                    }
                open_run["length"] += 1
            else:
                if open_run is not None:
                    closing = True
                    if (
                        open_run["evaluated"]
                        and not open_run["stopped"]
                        and open_run["length"] > MAX_TOLERATED
                    ):
                        expected_stop = k  # this packet proves the numbers missing
                if pre is RUNNING and not is_resume:
                    armed = True  # the first good packet after a (re)start arms the monitor
                    last_good = k
        if (
            open_run is not None
            and open_run["evaluated"]
            and not open_run["stopped"]
            and open_run["last_good"] is not None
            and k == open_run["last_good"] + grace_ticks
        ):
            expected_stop = k  # silent past the grace: a dead master
        # holds: exactly at +7 ms for a run of >= 3, never otherwise
        holding = monitor.holding and post is RUNNING
        if holding and not was_holding:
            if (
                open_run is not None
                and open_run["evaluated"]
                and open_run["hold"] is None
                and open_run["last_good"] is not None
            ):
                open_run["hold"] = k - open_run["last_good"]
                hold_latencies.append(float(open_run["hold"]))
            else:
                unexpected_holds += 1
                failures.append(
                    f"tick {k}: UNEXPECTED hold; open run "
                    f"{open_run['length'] if open_run else 0}, armed {armed}"
                )
        was_holding = holding
        if is_resume:
            resumes += 1
            r = slave.reply_to(resume_cid) if resume_cid is not None else None
            if r is None or r.metadata.get("Status") != "SUCCESS" or post is not RUNNING:
                resume_failed += 1
                failures.append(
                    f"tick {k}: operator Run failed: {r and r.metadata}, state {post.value}"
                )
            armed = False  # reset by entering RUNNING: armed again by the next packet
            resume_at = None
        if pre is RUNNING and post is STOPPED:
            reason = robot.state_machine.last_reason
            if expected_stop == k and open_run is not None:
                stops_ok += 1
                lat = float(k - open_run["last_good"])
                open_run["stopped"] = True
                open_run["latency"] = lat
                stop_latencies.append(lat)
                rep.stops.append(
                    {
                        "t_s": round((k - t_origin) / 1000.0, 3),
                        "latency_ms": lat,
                        "hold_ms": open_run["hold"],
                        "first_lost_seq": open_run["seq"],
                        "reason": reason,
                    }
                )
            else:
                unexpected += 1
                if open_run is not None:
                    open_run["stopped"] = True
                failures.append(
                    f"tick {k}: UNEXPECTED stop ({reason}); open run "
                    f"{open_run['length'] if open_run else 0}, armed {armed}, last good {last_good}"
                )
                rep.stops.append(
                    {
                        "t_s": round((k - t_origin) / 1000.0, 3),
                        "latency_ms": None,
                        "reason": reason,
                        "unexpected": True,
                    }
                )
            expected_stop = None
            armed = False
            was_holding = False
            resume_at = k + pause
        elif expected_stop == k:
            missed += 1
            failures.append(
                f"tick {k}: MISSED stop: run of {open_run and open_run['length']} losses "
                f"from seq {open_run and open_run['seq']}, robot {post.value}"
            )
            expected_stop = None
        if closing:
            close_run(k)
        if post is not RUNNING and post is not STOPPED:
            failures.append(
                f"tick {k}: robot left RUNNING/STOPPED: {post.value} "
                f"({robot.state_machine.last_reason}); soak aborted"
            )
            break
        # every STATUS to the operators: a STOPPED one must name the packet loss
        while status_seen < len(slave.statuses):
            tk, st = slave.statuses[status_seen]
            status_seen += 1
            if st.error_name == "STOPPED":
                if "packet loss" in st.status_message:
                    alert_ok += 1
                else:
                    alert_bad.append(f"tick {tk}: {st.status_message}")
        if len(failures) > 1000:
            failures.append("more than 1000 failures: soak aborted")
            break
    if open_run is not None:
        # the soak ended inside a run: judge it only if its outcome is already decided
        if open_run["evaluated"] and (open_run["stopped"] or open_run["length"] > MAX_TOLERATED):
            close_run(slave.k)
        else:
            all_lengths.append(open_run["length"])
    elapsed = time.perf_counter() - t_wall0
    counters = robot.streams.monitor.counters() if robot.streams.monitor is not None else {}
    slave.close()

    cats = Counter(r.category for r in rep.runs)
    evaluated = [r for r in rep.runs if r.category != "masked"]
    ev_short = [r for r in evaluated if r.length <= MAX_TOLERATED]
    ev_long = [r for r in evaluated if r.length > MAX_TOLERATED]
    n_stops = stops_ok + unexpected
    rep.numbers = {
        "sim_seconds": sim_s,
        "ticks": slave.k - t_origin,
        "packets": pattern.index,
        "dropped": drops,
        "drop_fraction": round(drops / pattern.index, 6) if pattern.index else 0.0,
        "pattern": pattern.describe(),
        "first_seq": args.first_seq,
        "last_seq": slave.seq,
        "pause_ms": pause,
        "runs_total": len(all_lengths),
        "runs_evaluated": len(evaluated),
        "runs_masked": cats.get("masked", 0),
        "runs_by_outcome": dict(sorted(cats.items())),
        "run_length_histogram_all": histogram(all_lengths),
        "run_length_histogram_evaluated": histogram([r.length for r in evaluated]),
        "stops": n_stops,
        "stops_expected": len(ev_long),
        "stops_unexpected": unexpected,
        "stops_missed": missed,
        "hold_latency_ms": summarize(hold_latencies),
        "holds_unexpected": unexpected_holds,
        "stop_latency_ms": summarize(stop_latencies),
        "stop_latency_histogram_ms": histogram([int(v) for v in stop_latencies]),
        "operator_runs": resumes,
        "operator_runs_failed": resume_failed,
        "status_alerts_stopped": alert_ok + len(alert_bad),
        "loss_monitor": counters,
        "wall_seconds": round(elapsed, 1),
        "speed_x_realtime": round((slave.k - t_origin) / 1000.0 / elapsed, 2) if elapsed else None,
    }
    rep.check(
        "stop iff run >= 3",
        unexpected == 0 and missed == 0 and cats.get("missed", 0) == 0 and stops_ok == len(ev_long),
        f"{len(ev_long)} evaluated runs >= 3 -> {stops_ok} latched stops at the expected tick "
        f"(the packet that proves the gap, or the grace); {unexpected} unexpected, {missed} missed",
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
        unexpected_holds == 0
        and len(held) == len(ev_long)
        and all(v == STOP_WITHIN_MS for v in hold_latencies),
        f"{len(hold_latencies)} holds, at {summarize(hold_latencies)} ms after the last good "
        f"packet (tick = 1 ms); {unexpected_holds} unexpected holds; latched stops at "
        f"{summarize(stop_latencies)} ms",
    )
    rep.check(
        "every stop alerts the operators",
        alert_ok == n_stops and not alert_bad,
        f"{alert_ok} STATUS STOPPED 'packet loss' alerts for {n_stops} stops"
        + (f"; other: {alert_bad[:3]}" if alert_bad else ""),
    )
    rep.check(
        "loss monitor trips == stops",
        counters.get("trips") == n_stops,
        f"loss monitor trips {counters.get('trips')}, observed stops {n_stops}",
    )
    rep.check(
        "operator Run resumes after every stop",
        resume_failed == 0 and resumes >= n_stops - 1,
        f"{resumes} Runs after {n_stops} stops, {resume_failed} failed",
    )
    rep.check(
        "enough evidence",
        len(ev_long) > 0 and len(ev_short) > 0,
        f"{len(ev_long)} runs >= 3 and {len(ev_short)} runs of 1-2 were judged",
        severity="warn",
    )
    return rep
