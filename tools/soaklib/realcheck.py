"""``soak.py real``: the outcome of a run, stops matched to the proxy's runs of drops."""

from __future__ import annotations

import argparse
import math
import re
from collections import Counter
from typing import Any

from loss_proxy import LossProxy
from soakreport import Report, RunOutcome, histogram, summarize

from .common import MAX_TOLERATED, STOP_WITHIN_MS, daemon_ends

_SEQ_RE = re.compile(r"(\d+) consecutive packets lost \(seq (\d+)-(\d+)(?: missing)?\)")
_DEADLINE_RE = re.compile(r"no packet for ([\d.]+) ms")


def parse_stop_reason(msg: str) -> dict[str, Any]:
    """What the slave says about a loss stop: its sequence evidence or its silence."""
    m = _SEQ_RE.search(msg)
    if m:
        return {
            "kind": "sequence",
            "lost": int(m.group(1)),
            "first": int(m.group(2)),
            "last": int(m.group(3)),
        }
    m = _DEADLINE_RE.search(msg)
    if m:
        return {"kind": "deadline", "silence_ms": float(m.group(1))}
    return {"kind": "other"}


GAP_CAUSES = {
    "relay read late": "the master sent on time and this soak's relay read it late",
    "master sent late": "the master stamped its samples on time and sent them late",
    "master silent": "the master stamped and sent nothing",
}


def gap_at_proxy(proxy: LossProxy, lo: float, hi: float) -> str | None:
    """The longest gap in the arrivals at the proxy that overlaps [lo, hi] (wall time), and who
    was late for it (:meth:`LossProxy._explain_gap`); None if there was none."""
    wall = proxy.mono_to_wall
    over = [
        (g, i)
        for i, (t0, g) in enumerate(proxy.gaps)
        if wall(t0) <= hi and wall(t0) + g >= lo  # type: ignore[operator]
    ]
    if not over:
        return None
    g, i = max(over)
    d = proxy.gap_detail[i] if i < len(proxy.gap_detail) else {}
    text = f"the stream arrived {g * 1e3:.1f} ms late at the proxy"
    if d:
        text += (
            f": {GAP_CAUSES[d['cause']]} (kernel arrival gap {d['kernel_gap_ms']} ms, the "
            f"next sample {d['age_ms']} ms old)"
        )
    return text


def analyse_real(
    rep: Report,
    proxy: LossProxy,
    statuses: list[Any],
    runs_sent: list[dict[str, Any]],
    stats: dict[str, Any],
    codes: dict[str, int | None],
    t_start: float,
    t_end: float,
    deadline_ms: float,
    args: argparse.Namespace,
) -> None:
    """Match the slave's stops (STATUS, wall time) to the proxy's runs of drops.

    The slave says why it stopped: "N consecutive packets lost (seq a-b)" (a late packet showed
    the gap) or "no packet for X ms" (its deadline; X is loop time since the tick that took the
    last good packet). A deadline stop at wall time T covers the slave's silent interval
    [T - X, T]; it is attributed to the proxy's run of drops that overlaps that interval (with
    ``--match-tolerance-ms`` for the delivery from the proxy to the slave's loop).
    """
    wall = proxy.mono_to_wall
    tol = args.match_tolerance_ms * 1e-3
    timeline = sorted((float(st.timestamp), st.error_name, st.status_message) for st in statuses)
    stops = [
        (t, msg)
        for t, state, msg in timeline
        if state == "STOPPED" and "->" in msg and t_start <= t <= t_end
    ]

    def state_at(t: float) -> tuple[str, float]:
        state, since = "UNKNOWN", -math.inf
        for tt, s, _msg in timeline:
            if tt > t:
                break
            if s in ("RUNNING", "STOPPED", "ENABLED", "READY", "FAULT", "ESTOP") and s != state:
                state, since = s, tt
        return state, since

    runs = [r for r in proxy.runs if t_start <= r.t_wall_first <= t_end - 0.05]
    dropped_seqs = {d.seq for d in proxy.drops if d.seq is not None}
    run_of_seq = {}
    for i, r in enumerate(runs):
        if r.first_seq is not None and r.last_seq is not None:
            for s in range(r.first_seq, r.first_seq + r.length):
                run_of_seq[s & 0xFFFFFFFF] = i
    attributed: dict[int, list[float]] = {}
    stop_rows: list[dict[str, Any]] = []
    fails: list[str] = []  # stops that contradict the requirement
    late_short: list[
        str
    ] = []  # a run of 1-2 plus late delivery: the slave's deadline, legitimately
    deadline_only: list[str] = []
    other_stops: list[str] = []
    latencies: list[float] = []
    for t_stop, msg in stops:
        rel = round(t_stop - t_start, 4)
        row: dict[str, Any] = {"t_s": rel, "reason": msg}
        stop_rows.append(row)
        if "packet loss" not in msg:
            row["kind"] = "other"
            other_stops.append(f"{rel:.3f} s: {msg}")
            continue
        why = parse_stop_reason(msg)
        row.update(why)
        idx: int | None = None
        if why["kind"] == "sequence":
            seqs = [(why["first"] + j) & 0xFFFFFFFF for j in range(why["lost"])]
            by_proxy = sum(1 for s in seqs if s in dropped_seqs)
            if why["lost"] <= MAX_TOLERATED or by_proxy < why["lost"]:
                row["kind"] = "sequence stop not explained by the proxy (FAIL)"
                fails.append(
                    f"{rel:.3f} s: slave lost {why['lost']} (seq {why['first']}-{why['last']}), "
                    f"proxy dropped {by_proxy} of them: {msg}"
                )
                continue
            idx = run_of_seq.get(seqs[0])
        else:
            silence = why.get("silence_ms")
            if silence is None or silence < deadline_ms:
                row["kind"] = f"silence stop shorter than the {deadline_ms:g} ms grace (FAIL)"
                fails.append(
                    f"{rel:.3f} s: stopped after only {silence} ms without a packet: {msg}"
                )
                continue
            lo = t_stop - silence * 1e-3 - tol
            over = [
                i
                for i, r in enumerate(runs)
                if wall(r.t_mono_first) <= t_stop and wall(r.t_mono_last) >= lo
            ]  # type: ignore[operator]
            idx = max(over, key=lambda i: runs[i].length) if over else None
        if idx is None:
            lo = t_stop - (why.get("silence_ms") or 0.0) * 1e-3 - tol
            where = gap_at_proxy(proxy, lo, t_stop) or "no gap at the proxy: late inside the slave"
            row["kind"] = "deadline (no drop)"
            row["diagnosis"] = where
            deadline_only.append(f"{rel:.3f} s: {msg}; {where}")
            continue
        run = runs[idx]
        attributed.setdefault(idx, []).append(t_stop)
        prev_good = wall(run.t_prev_good)
        s_proxy = (
            (run.t_next_good - run.t_prev_good) * 1e3
            if run.t_next_good is not None and run.t_prev_good is not None
            else None
        )
        row.update(
            run_length=run.length,
            run_first_seq=run.first_seq,
            silence_at_proxy_ms=None if s_proxy is None else round(s_proxy, 3),
        )
        if prev_good is not None:
            row["latency_est_ms"] = round((t_stop - prev_good) * 1e3, 3)
        if run.length > MAX_TOLERATED:
            row["kind"] = "run>=3"
            slow = gap_at_proxy(proxy, prev_good, t_stop) if prev_good is not None else None
            if slow is not None:
                row["diagnosis"] = slow
            if prev_good is not None:
                latencies.append((t_stop - prev_good) * 1e3)
        else:
            row["kind"] = "run<=2 + late delivery"
            lo = t_stop - (why.get("silence_ms") or 0.0) * 1e-3 - tol
            row["diagnosis"] = gap_at_proxy(proxy, lo, t_stop) or "no gap at the proxy"
            late_short.append(
                f"{rel:.3f} s: run of {run.length} (seq {run.first_seq}), proxy silence "
                f"{s_proxy if s_proxy is None else round(s_proxy, 2)} ms, slave silence "
                f"{why.get('silence_ms')} ms"
            )
    rep.stops = stop_rows

    missed: list[str] = []
    double: list[str] = []
    for i, r in enumerate(runs):
        prev_good = wall(r.t_prev_good)
        state, since = state_at(prev_good if prev_good is not None else r.t_wall_first)
        # armed: RUNNING, and a packet got through after the (re)start (10 ms margin)
        evaluable = state == "RUNNING" and prev_good is not None and prev_good - since >= 0.010
        hits = attributed.get(i, [])
        if len(hits) > 1:
            double.append(f"run at {r.t_wall_first - t_start:.3f} s: {len(hits)} stops")
        if r.length > MAX_TOLERATED:
            if hits:
                cat = "stop"
            elif evaluable:
                cat = "missed"
                missed.append(
                    f"run of {r.length} from seq {r.first_seq} at {r.t_wall_first - t_start:.3f} s"
                )
            else:
                cat = "masked"
        elif hits:
            cat = "deadline-stop"
        else:
            cat = "no-stop" if evaluable else "masked"
        lat = round((hits[0] - prev_good) * 1e3, 3) if hits and prev_good is not None else None
        rep.runs.append(
            RunOutcome(round(r.t_wall_first - t_start, 4), r.length, r.first_seq, cat, lat)
        )

    cats = Counter(r.category for r in rep.runs)
    loss_stops = [s for s in stop_rows if s.get("kind") != "other"]
    judged_long = sum(1 for r in rep.runs if r.length > MAX_TOLERATED and r.category != "masked")
    short = [r for r in rep.runs if r.length <= MAX_TOLERATED]
    slave_stats = stats.get("slave") or {}
    master_stats = stats.get("master") or {}
    run_ok = [r for r in runs_sent if r["status"] == "SUCCESS"]
    rep.numbers.update(
        {
            "duration_s": round(t_end - t_start, 3),
            "proxy": proxy.summary(),
            "runs_in_window": len(runs),
            "runs_by_outcome": dict(sorted(cats.items())),
            "run_length_histogram": histogram([r.length for r in runs]),
            "stops": len(stops),
            "stops_by_kind": dict(Counter(s["kind"] for s in stop_rows)),
            "runs_ge3_judged": judged_long,
            "stop_latency_est_ms": summarize(latencies),
            "stop_latency_est_within_8ms": sum(1 for v in latencies if v <= STOP_WITHIN_MS + 1.0),
            "operator_runs": len(runs_sent),
            "operator_runs_ok": len(run_ok),
            "status_messages": len(statuses),
            "slave_loss_monitor": slave_stats.get("loss"),
            "slave_state_at_exit": slave_stats.get("state"),
            "slave_lateness_us": slave_stats.get("lateness_us"),
            "slave_watchdog": slave_stats.get("watchdog"),
            "slave_sample_to_write_us": (slave_stats.get("controller") or {}).get(
                "sample_to_write_us"
            ),
            "slave_master_iface": (slave_stats.get("interfaces") or {}).get("master"),
            "master_ticks": master_stats.get("ticks"),
            "master_lateness_us": master_stats.get("lateness_us"),
            "master_seq": (master_stats.get("controller") or {}).get("seq"),
            "exit_codes": codes,
            "grace_ms": deadline_ms,
            "match_tolerance_ms": args.match_tolerance_ms,
        }
    )
    rep.check(
        "every loss stop follows a run >= 3 (or a deadline)",
        not fails,
        f"{len(loss_stops)} loss stops: {sum(1 for s in stop_rows if s.get('kind') == 'run>=3')} "
        f"after runs >= 3, {len(late_short)} after a run of 1-2 plus > {deadline_ms} ms of silence "
        f"at the slave, {len(deadline_only)} deadline stops without drops, "
        f"{len(fails)} contradicting "
        f"the requirement" + (f": {fails[:3]}" if fails else ""),
    )
    rep.check(
        "runs of 1-2 drops caused no stop by themselves",
        not fails,
        f"{len(short)} runs of 1-2: {cats.get('no-stop', 0)} no stop, "
        f"{cats.get('deadline-stop', 0)} "
        f"stopped by the deadline because the next packet reached the slave late (slave silence "
        f"> {deadline_ms} ms)",
    )
    rep.check(
        "every run >= 3 (slave RUNNING) stopped the robot exactly once",
        not missed and not double,
        f"{judged_long} runs >= 3 judged, {cats.get('stop', 0)} stopped, {len(missed)} missed; "
        f"{sum(1 for r in rep.runs if r.length > MAX_TOLERATED and r.category == 'masked')} masked "
        f"(slave already stopped)"
        + (f": {missed[:3]}" if missed else "")
        + (f"; {double[:3]}" if double else ""),
    )
    rep.check(
        "operator Run resumed after every stop",
        len(run_ok) == len(runs_sent) and len(runs_sent) >= len(stops) - 1,
        f"{len(run_ok)}/{len(runs_sent)} Runs succeeded for {len(stops)} stops",
    )
    rep.check(
        "no stop other than packet loss",
        not other_stops,
        f"{len(other_stops)} other stops" + (f": {other_stops[:3]}" if other_stops else ""),
        severity="warn" if args.tolerate_other_stops else "fail",
    )
    rep.check(
        "daemons ran and wrote statistics",
        # the slave ends STOPPED (exit 4) when the master goes first at the end of a soak
        bool(slave_stats)
        and bool(master_stats)
        and codes.get("master") == 0
        and codes.get("slave") in (0, 4),
        f"exit codes {codes}, stats: slave {'ok' if slave_stats else 'missing'}, "
        f"master {'ok' if master_stats else 'missing'}; {daemon_ends(stats)}",
    )
    rep.check(
        "no deadline stop without drops",
        not deadline_only,
        f"{len(deadline_only)} (timing, not loss: the stream paused > {deadline_ms} ms)"
        + (f": {deadline_only[:3]}" if deadline_only else ""),
        severity="warn",
    )
    rep.check(
        "no run of 1-2 stopped the robot (even with late delivery)",
        not late_short,
        f"{len(late_short)}" + (f": {late_short[:3]}" if late_short else ""),
        severity="warn",
    )
    trips = (slave_stats.get("loss") or {}).get("trips")
    rep.check(
        "slave loss-monitor trips match the loss stops",
        trips is not None and len(loss_stops) <= trips <= len(loss_stops) + 1,
        f"trips {trips} (one more is the end-of-soak master shutdown), "
        f"loss stops {len(loss_stops)}",
        severity="warn",
    )
    rep.check(
        "enough evidence",
        judged_long > 0 and cats.get("no-stop", 0) > 0,
        f"{judged_long} runs >= 3 and {cats.get('no-stop', 0)} runs of 1-2 judged",
        severity="warn",
    )
