"""``soak.py paper --real``: the OCC paper's stability protocol against the daemons."""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

from loopback import stop_processes, wait_port
from loss_proxy import LossPattern, LossProxy
from soakreport import Report

from .common import MAX_TOLERATED, daemon_ends
from .daemons import set_master_remote, start_occd, stop_proc, write_configs
from .hogs import proc_cpu_s


def run_paper_real(args: argparse.Namespace, out: Path) -> tuple[Report, Any]:
    """The stability protocol with ``occd`` slave and master processes on loopback, the
    master's POSITION stream through a :class:`LossProxy` dropping 2 % of the packets in runs
    of exactly 2; both daemons record (``--record``) and the tracking error, inter-arrival and
    trajectories come from the two recordings (module docstring of tools/stability.py for the
    definitions; ``analyse_paper_recordings``)."""
    import stability
    from slicer_standin import SlicerStandIn

    rep = Report("paper-real")
    duration = float(args.duration)
    rate = 1000.0 / stability.PERIOD_MS
    packets = int(duration * rate)
    n_runs = int(round(args.loss * packets / 2.0))
    warmup = int(args.warmup * rate)
    try:
        pattern = LossPattern(
            seed=args.seed,
            drop_runs=[(2, n_runs)] if n_runs else [],
            expected=packets,
            warmup=warmup,
            tail=int(rate),
            min_gap=1,
        )
    except ValueError as err:
        raise SystemExit(f"soak paper --real: {err}") from None
    ports = write_configs(out, Path(args.slave_config), Path(args.master_config))
    slave_cfg = ports["_slave"]
    slave_cfg["recording"] = {
        **(slave_cfg.get("recording") or {}),
        "path": None,
        "rate_hz": float(args.record_rate_hz),
    }
    bound = duration + 30.0
    proxy = LossProxy(
        ("127.0.0.1", 0), ("127.0.0.1", ports["slave_udp"]), pattern, duration=bound, seed=args.seed
    )
    set_master_remote(ports, proxy.address[1])
    rec = {"slave": out / "slave.rec", "master": out / "master.rec"}
    procs: dict[str, subprocess.Popen[bytes]] = {}
    standin = None
    statuses: list[Any] = []
    cpu: dict[str, float | None] = {}
    codes: dict[str, int | None] = {}
    t_start = t_end = time.monotonic()
    try:
        procs["slave"] = start_occd(
            ports["slave_yaml"],
            out / "slave-stats.json",
            out / "slave.log",
            bound,
            extra=["--record", str(rec["slave"])],
        )
        if not wait_port(ports["slave_op"], 30.0, procs["slave"]):
            raise SystemExit(
                f"soak paper --real: the slave did not start (see {out / 'slave.log'})"
            )
        standin = SlicerStandIn("127.0.0.1", ports["slave_op"]).start()
        if not standin.connected.wait(10.0):
            raise SystemExit("soak paper --real: the operator client could not connect")
        proxy.start()
        procs["master"] = start_occd(
            ports["master_yaml"],
            out / "master-stats.json",
            out / "master.log",
            bound,
            extra=["--record", str(rec["master"])],
        )
        if not wait_port(ports["master_tcp"], 30.0, procs["master"]):
            raise SystemExit(
                f"soak paper --real: the master did not start (see {out / 'master.log'})"
            )
        t0 = time.monotonic()
        while proxy.counters.received == 0 and time.monotonic() - t0 < 10.0:
            time.sleep(0.01)
        t_start = time.monotonic()
        progress = (
            stability.Progress(duration, label="soak paper --real", unit="s")
            if args.progress
            else None
        )
        end = t_start + duration
        while time.monotonic() < end:
            time.sleep(0.05)
            for name, proc in procs.items():
                if proc.poll() is not None:
                    raise SystemExit(
                        f"soak paper --real: the {name} exited early with "
                        f"{proc.returncode} (see {out / (name + '.log')})"
                    )
            if progress is not None and progress.due():
                progress.show(time.monotonic() - t_start)
        t_end = time.monotonic()
        if standin is not None:
            with standin._lock:  # the alerts of the window (the shutdown's come after)
                statuses = list(standin.statuses)
        if progress is not None:
            progress.show(duration, final=True)
        for name, proc in procs.items():
            cpu[name] = proc_cpu_s(proc.pid)
    finally:
        # both at once (one SIGINT each: a second one ends a daemon without its statistics): a
        # slave left running without its master would latch a stop before its own SIGINT
        stop_processes(list(procs.values()))
        for name, proc in procs.items():
            codes[name] = stop_proc(proc)
        proxy.stop()
        if standin is not None:
            standin.stop()
    proxy.write_runs_csv(out / "proxy_runs.csv")
    stats: dict[str, Any] = {}
    for name in ("slave", "master"):
        try:
            stats[name] = json.loads((out / f"{name}-stats.json").read_text())
        except (OSError, ValueError):
            stats[name] = None
    params = (slave_cfg.get("controller") or {}).get("params") or {}
    traces = analyse_paper_real(
        rep,
        args,
        proxy,
        stats,
        statuses,
        rec,
        codes,
        cpu,
        t_end - t_start,
        float(params.get("scale", 0.1)),
    )
    return rep, traces


def _read_paper_recordings(rec: dict[str, Path]) -> dict[str, Any]:
    """What the paper's analysis needs from the two recordings, as numpy arrays: the master's
    outbound POSITION (its loop time, mm), the slave's inbound POSITION (loop time, run flag)
    and the slave's state rows (t, state code, tip mm)."""
    import numpy as np

    from occ.recording.record import STATE_DEVICE, iter_recording

    m_t, m_pos = [], []
    for msg in iter_recording(rec["master"]):
        meta = msg.metadata
        if msg.message_type == "POSITION" and meta.get("rec.dir") == "out":
            m_t.append(float(meta["rec.t"]))
            m_pos.append(tuple(msg.position))  # type: ignore[attr-defined]
    s_in_t, s_in_run, rows, columns = [], [], [], ""
    for msg in iter_recording(rec["slave"]):
        meta = msg.metadata
        if msg.message_type == "POSITION" and meta.get("rec.dir") == "in":
            s_in_t.append(float(meta["rec.t"]))
            s_in_run.append(meta.get("run", "1") == "1")
        elif msg.message_type == "NDARRAY" and msg.device_name == STATE_DEVICE:
            rows.append(np.asarray(msg.array, dtype=np.float64).ravel())  # type: ignore[attr-defined]
            columns = meta.get("columns", columns)
    cols = columns.split(",") if columns else []
    table = np.vstack(rows) if rows else np.zeros((0, max(len(cols), 1)))
    pick = (
        [cols.index(c) for c in ("t", "state", "tip.x_mm", "tip.y_mm", "tip.z_mm")] if rows else []
    )
    return {
        "m_t": np.asarray(m_t),
        "m_pos": np.asarray(m_pos, dtype=np.float64).reshape(-1, 3),
        "s_in_t": np.asarray(s_in_t),
        "s_in_run": np.asarray(s_in_run, dtype=bool),
        "rows": table[:, pick] if rows else np.zeros((0, 5)),
    }


def _paper_forces(traces: Any, rec: dict[str, Path]) -> dict[str, float]:
    """A slave that sends its contact force (configs/wall.yaml): the force panel's traces
    (occ/recording/plot.py reads both recordings: the slave's SlaveTip ``force_n``, the master's
    ``Force`` output) and their peaks and RMS difference in the report."""
    from occ.recording.plot import summarize_recording

    s = summarize_recording(rec["slave"], master=rec["master"])
    if not len(s.cf_t):
        return {}
    t0 = float(s.cf_t[0])
    traces.force_t = (s.cf_t - t0).tolist()
    traces.instrument_n = [tuple(v) for v in s.cf.tolist()]
    traces.hand_t = (s.hand_t - t0).tolist()
    traces.hand_n = [tuple(v) for v in s.hand.tolist()]
    return {k: round(v, 4) for k, v in s.force_stats().items()}


def analyse_paper_real(
    rep: Report,
    args: argparse.Namespace,
    proxy: LossProxy,
    stats: dict[str, Any],
    statuses: list[Any],
    rec: dict[str, Path],
    codes: dict[str, int | None],
    cpu: dict[str, float | None],
    window_s: float,
    scale: float,
) -> Any:
    import numpy as np
    import stability

    from occ.recording.record import STATE_CODES

    traces = stability.Traces(time_label="time since the stream started (s)")
    psum = proxy.summary()
    run_lengths = psum["run_length_histogram"]
    closed = sum(1 for r in proxy.runs if r.t_next_good is not None)
    expected_stops = sum(c for length, c in run_lengths.items() if int(length) > MAX_TOLERATED)
    slave_stats, master_stats = stats.get("slave") or {}, stats.get("master") or {}
    ctl = slave_stats.get("controller") or {}
    loss = slave_stats.get("loss") or {}
    # stops during the window, as the operator saw them (STATUS alerts)
    stops = [
        f"{s.error_name}: {s.status_message}"
        for s in statuses
        if s.error_name in ("STOPPED", "FAULT", "ESTOP")
    ]
    data = _read_paper_recordings(rec)
    forces = _paper_forces(traces, rec)
    m_t, m_pos, s_in_t, rows = data["m_t"], data["m_pos"], data["s_in_t"], data["rows"]
    # the window: from the first POSITION the slave took to the master's last one
    t_lo = float(s_in_t[0]) if len(s_in_t) else 0.0
    t_hi = float(m_t[-1]) if len(m_t) else 0.0
    # inter-arrival at the slave's loop (the tick that took each packet), 0.5 ms bins
    gaps_ms = np.diff(s_in_t[s_in_t <= t_hi]) * 1000.0 if len(s_in_t) > 1 else np.zeros(0)
    binned = np.round(gaps_ms * 2.0) / 2.0
    values, counts = np.unique(binned, return_counts=True)
    hist = {f"{v:g}": int(c) for v, c in zip(values.tolist(), counts.tolist(), strict=True)}
    long_gaps = int(np.count_nonzero(gaps_ms >= 5.0))
    arr_t = s_in_t[1 : len(gaps_ms) + 1] - t_lo
    sel = arr_t >= (arr_t[-1] - args.arrival_window if len(arr_t) else 0.0)
    traces.arrivals = list(zip(arr_t[sel].tolist(), gaps_ms[sel].tolist(), strict=True))
    sel0 = arr_t < args.warmup
    traces.arrivals_clean = list(zip(arr_t[sel0].tolist(), gaps_ms[sel0].tolist(), strict=True))
    # tracking error: the slave's measured tip against slave_ref + scale * (master - master_ref),
    # the master's handle interpolated at the slave's state rows, from the re-index + settle
    traces.scale = scale
    mref, sref = ctl.get("master_ref_mm"), ctl.get("slave_ref_mm")
    errs = {a: stability._Axis() for a in stability.AXES}
    compared = "not measured"
    run_in = s_in_t[data["s_in_run"]]
    if mref is not None and sref is not None and len(rows) and len(m_t) > 1 and len(run_in):
        t_reindex = float(run_in[0])
        t = rows[:, 0]
        ok = (
            (rows[:, 1] == STATE_CODES["RUNNING"])
            & (t >= t_reindex + args.settle)
            & (t >= m_t[0])
            & (t <= t_hi)
        )
        tr = rows[ok]
        hand = np.column_stack([np.interp(tr[:, 0], m_t, m_pos[:, c]) for c in range(3)])
        ideal = np.asarray(sref) + scale * (hand - np.asarray(mref))
        err = ideal - tr[:, 2:5]
        for c, a in enumerate(stability.AXES):
            errs[a].add_many(np.ascontiguousarray(err[:, c]))
        compared = (
            "ideal slave tip slave_ref + scale*(master handle - master_ref) minus the "
            "slave's measured tip, at every state row of the slave's recording "
            f"({args.record_rate_hz:g} Hz), the master's handle (its recorded POSITION "
            f"stream, 500 Hz) interpolated at the row's time, from the re-index + "
            f"{args.settle} s"
        )
        win = tr[:, 0] >= tr[-1, 0] - args.window if len(tr) else np.zeros(0, dtype=bool)
        traces.t_s = (tr[win, 0] - t_lo).tolist()
        traces.master_mm = [tuple(v) for v in hand[win].tolist()]
        traces.slave_mm = [tuple(v) for v in tr[win, 2:5].tolist()]
        traces.ideal_mm = [tuple(v) for v in ideal[win].tolist()]
    err_summary = {a: errs[a].summary() for a in stability.AXES}
    rep.numbers = {
        "wall_seconds": round(window_s, 1),
        "seed": args.seed,
        "loss_target": args.loss,
        "proxy": psum,
        "double_losses": run_lengths.get("2", 0),
        "double_losses_per_s": round(run_lengths.get("2", 0) / window_s, 3) if window_s else 0.0,
        "lost_packets_per_s": round(psum["dropped"] / window_s, 3) if window_s else 0.0,
        "expected_stops": expected_stops,
        "false_stops": max(0, len(stops) - expected_stops),
        "stops": stops[:20],
        "interarrival_histogram_ms": hist,
        "interarrival_gaps_ge_5ms": long_gaps,
        "double_losses_closed_by_a_packet": closed,
        "tracking_error_mm": err_summary,
        "tracking_error_paper_mean_mm": stability.PAPER_MEAN_ERROR_MM,
        "tracking_compared": compared,
        "scale": scale,
        "references_mm": {"master_ref": mref, "slave_ref": sref},
        "loss_monitor": loss,
        "slave_controller": {
            k: ctl.get(k)
            for k in ("samples", "reindexes", "ik_clamped", "ik_failures", "sample_to_write_us")
        },
        "cpu_seconds": {k: (round(v, 1) if v is not None else None) for k, v in cpu.items()},
        "cpu_percent": {
            k: (round(100.0 * v / window_s, 1) if v is not None and window_s else None)
            for k, v in cpu.items()
        },
        "exit_codes": codes,
        "loop_lateness_us": {k: (s or {}).get("lateness_us") for k, s in stats.items()},
        "recordings": {k: str(v) for k, v in rec.items()},
    }
    if forces:
        rep.numbers["forces"] = forces
    rep.check(
        "no stop, no fault",
        not stops,
        f"{len(stops)} STOPPED/FAULT alerts to the operator during {window_s:.0f} s"
        + (f": {stops[:3]}" if stops else ""),
    )
    rep.check(
        "the proxy lost packets in runs of exactly 2",
        set(run_lengths) <= {"2"} and run_lengths.get("2", 0) > 0,
        f"runs by length {run_lengths}, {psum['dropped']} of {psum['received']} packets "
        f"dropped ({100 * psum['drop_fraction']:.2f} %)",
    )
    rep.check(
        "slave follows without re-indexing",
        ctl.get("reindexes") == 1 and not ctl.get("ik_failures"),
        f"{ctl.get('reindexes')} re-index (the initial one), {ctl.get('ik_failures')} IK failures",
    )
    bound = args.max_mean_error_mm
    ex, ey = err_summary["x"], err_summary["y"]
    rep.check(
        f"mean tracking error X, Y <= {bound} mm",
        ex["n"] > 0 and ey["n"] > 0 and ex["mean"] <= bound and ey["mean"] <= bound,
        f"mean |e| X {ex['mean']} mm, Y {ey['mean']} mm (paper: 0.094, 0.097); p99 X "
        f"{ex['p99']}, Y {ey['p99']}; max X {ex['max']}, Y {ey['max']} mm ({ex['n']} rows)",
    )
    holds = loss.get("holds")
    rep.check(
        "no hold",
        holds is not None and holds <= 1,
        f"{holds} holds, {loss.get('resumes')} resumes (one hold is the master's shutdown at "
        "the end; others: a 6 ms gap plus > 1 ms of scheduling delay on this machine)",
        severity="warn",
    )
    rep.check(
        "every double loss seen as one long gap",
        long_gaps >= closed,
        f"{long_gaps} gaps >= 5 ms at the slave's loop for {closed} double losses closed by "
        f"a packet; histogram (0.5 ms bins) {hist}",
        severity="warn",
    )
    # the slave may end STOPPED (exit 4, occd --help) if it saw the master go before its SIGINT
    rep.check(
        "daemons ran and wrote statistics",
        codes.get("master") == 0
        and codes.get("slave") in (0, 4)
        and bool(slave_stats)
        and bool(master_stats),
        f"exit codes {codes}, "
        f"statistics {'present' if slave_stats and master_stats else 'missing'}; "
        f"{daemon_ends(stats)}",
    )
    return traces


def run_paper_real_main(args: argparse.Namespace, command: str) -> int:
    import stability

    out = args.out or Path(tempfile.mkdtemp(prefix="occ-soak-paper-real-"))
    out.mkdir(parents=True, exist_ok=True)
    done = stability.run_protocol(
        lambda: run_paper_real(args, out),
        out,
        command,
        "Stability test (OCC paper) against the daemons",
    )
    if isinstance(done, int):
        return done
    rep = done
    e = rep.numbers["tracking_error_mm"]
    print(
        f"soak paper --real: {rep.numbers['wall_seconds']:.0f} s; mean |e| X {e['x']['mean']} mm, "
        f"Y {e['y']['mean']} mm (paper: 0.094, 0.097); {'PASS' if rep.passed else 'FAIL'}; "
        f"report in {out}"
    )
    return 0 if rep.passed else 1
