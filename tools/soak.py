#!/usr/bin/env python3
"""Packet-loss soak of the slave's loss monitor: simulated time (exact) and real loopback.

The safety requirement under test (OCC, Arata et al. 2010; ``configs/slave.yaml``): the master
streams POSITION at 500 Hz; the slave tolerates up to 2 consecutive lost packets; motion stops
(holds) within 7 ms of the last good packet whenever the stream is 3 periods overdue; 3
consecutive losses, proven by the next packet's sequence number, or a master silent past the
grace (100 ms) latch the stop and alert the operators with a STATUS; late packets with
contiguous numbers only hold and resume (docs/ARCHITECTURE.md, "Safety").

``sim``
    The slave :class:`~occ.core.robot.Robot` (``configs/slave.yaml``) stepped tick by tick on a
    :class:`~occ.clock.SimClock` with its interfaces on in-process channels
    (:class:`occ_testkit.testing.SimRobot`, no sockets): the master's datagrams and the operator's
    COMMANDs come from peers on those channels, packed and decoded like real ones, and the
    operator reads the replies and alerts the robot sends it.
    The simulated master sends one POSITION every 2 ms (even ticks); a seeded
    :class:`loss_proxy.LossPattern` drops some. An independent oracle (this file, not the loss
    monitor) follows the drops and checks EXACTLY: a run of >= 3 consecutive losses that starts
    while the monitor is armed holds the robot at the tick 7 ms after the tick that took the last
    good packet and latches the stop at the tick of the packet that proves the gap (or at the
    grace); runs of 1-2 never hold nor stop it; every stop alerts the operators
    (STATUS STOPPED "packet loss ..."). After each stop the operator sends Run ``--pause-ms``
    later, so the soak continues. Runs that start while the robot is stopped, or after a Run
    before the first packet (the monitor is armed by the first packet), are *masked*: counted,
    not judged.

``real``
    ``occd`` slave and master processes on loopback, with temporary config copies (in the
    report folder): all ports moved to free ones, the master's POSITION ``remote`` pointed at a
    :class:`loss_proxy.LossProxy` (in this process) that forwards to the slave. An operator
    client (:class:`slicer_standin.SlicerStandIn`, COMMAND over TCP) records every STATUS and
    sends Run ``--pause-ms`` after each loss stop. At the end both daemons get SIGINT and write
    their statistics JSON. Stops are matched to the proxy's runs of drops by wall time (same
    machine, same clock): a loss stop must follow a run of >= 3 drops (or be a *silence* stop:
    the master itself fell silent for longer than the grace); a run of <= 2 drops must not stop
    the robot unless the stream was silent longer than the grace at the proxy anyway; every run
    of >= 3 drops that starts while the slave is RUNNING and armed must stop it exactly once.
    Latencies are estimated (stop STATUS time -
    arrival of the last good datagram at the proxy) and reported, never judged: wall-clock
    numbers depend on the machine's load.

    ``--runs N`` repeats the soak N times (``run-01/`` ... in the report folder, each a full
    report) and adds a summary judged against a bar (issue 26, "late is not lost, on a busy
    machine too"): no false latched stop (a stop not caused by a run of >= 3 drops, listed with
    the slave's own words) and every run of >= 3 drops stopped the slave with an alert within
    ``--stop-within-ms`` (default 20) of the last good packet. ``--hogs H`` runs H ordinary CPU
    hogs (busy pure-Python processes at normal priority, each ending by itself after the run's
    bound) beside each run: started before the daemons, killed after them; the load average
    before and after each run is in the summary.

Both modes write a report folder: ``report.json``, ``report.md``, ``runs.csv`` (every run of
drops and its outcome), plots (``drops_over_time.png``, ``run_lengths.png``,
``stop_latency.png``), and for ``real`` also the drop log, both stats JSON files and daemon logs.
Exit code 0 when every check passes, 1 otherwise, 2 on a usage error.

Examples::

    python tools/soak.py sim --sim-seconds 3600 --out /tmp/soak-sim
    python tools/soak.py sim --sim-seconds 30 --drop-runs 1:20 --drop-runs 2:20 --drop-runs 3:10
    python tools/soak.py real --duration 60 --out /tmp/soak-real
    python tools/soak.py real --drop-cycle 2,2,3 --hogs 2 --runs 20 --duration 30
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
if str(ROOT) not in sys.path:
    sys.path.insert(1, str(ROOT))

from loss_proxy import add_pattern_arguments  # noqa: E402
from soaklib.paper import run_paper_real_main  # noqa: E402
from soaklib.real import run_real  # noqa: E402
from soaklib.report import write_report  # noqa: E402
from soaklib.series import run_real_series, write_series_report  # noqa: E402
from soaklib.sim import run_sim  # noqa: E402


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="soak", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="mode", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--out", type=Path, default=None, help="report folder (default: a new temp dir)"
    )
    common.add_argument(
        "--config", default=str(ROOT / "configs" / "slave.yaml"), help="slave config"
    )
    common.add_argument(
        "--pause-ms",
        type=float,
        default=100.0,
        help="operator's pause between a stop and its Run (default 100)",
    )
    add_pattern_arguments(common)
    s = sub.add_parser("sim", parents=[common], help="the slave in simulated time (exact checks)")
    s.add_argument("--sim-seconds", type=float, default=60.0, help="simulated seconds (default 60)")
    s.add_argument(
        "--first-seq",
        type=int,
        default=0,
        help="sequence number before the first packet (e.g. 4294960000 tests the wrap)",
    )
    s.add_argument("--progress", action="store_true", help="progress on stderr every 30 s")
    r = sub.add_parser("real", parents=[common], help="occd slave + master through the loss proxy")
    r.add_argument("--duration", type=float, default=30.0, help="soak seconds (default 30)")
    r.add_argument("--master-config", default=str(ROOT / "configs" / "master.yaml"))
    r.add_argument("--delay-ms", type=float, default=0.0, help="proxy delay (ms)")
    r.add_argument("--jitter-ms", type=float, default=0.0, help="proxy jitter (ms)")
    r.add_argument(
        "--match-tolerance-ms",
        type=float,
        default=5.0,
        help="slack between the proxy's clock and the slave's silent interval when "
        "matching a stop to a run of drops (default 5 ms)",
    )
    r.add_argument(
        "--tolerate-other-stops",
        action="store_true",
        help="a stop not caused by packet loss (watchdog: an overloaded machine) is a "
        "warning, not a failure",
    )
    r.add_argument(
        "--relay-fifo",
        type=int,
        default=None,
        metavar="PRIO",
        help="run the loss proxy's thread SCHED_FIFO at PRIO where permitted (below the "
        "daemons' 59-61), so CPU hogs starve the daemons, not the relay (default: normal)",
    )
    r.add_argument(
        "--runs",
        type=int,
        default=None,
        metavar="N",
        help="repeat the soak N times (run-01/ ...) and judge the bar: no false latched stop, "
        "every run >= 3 stopped within --stop-within-ms",
    )
    r.add_argument(
        "--hogs",
        type=int,
        default=0,
        metavar="H",
        help="with --runs: H busy processes at normal priority beside each run (default 0)",
    )
    r.add_argument(
        "--stop-within-ms",
        type=float,
        default=20.0,
        help="with --runs: the bar, last good packet -> STOPPED alert (default 20 ms)",
    )
    import stability  # lazily: it imports this module for the report format

    pp = sub.add_parser(
        "paper",
        help="the OCC paper's stability protocol (simulated time, or "
        "--real: the daemons through the loss proxy)",
    )
    stability.add_arguments(pp)
    pr = pp.add_argument_group("against the daemons (--real)")
    pr.add_argument(
        "--real",
        action="store_true",
        help="occd slave + master (the two configs) through the loss proxy, both "
        "recording; the tracking error from the recordings",
    )
    pr.add_argument(
        "--duration", type=float, default=60.0, help="--real: seconds of the stream (default 60)"
    )
    pr.add_argument(
        "--record-rate-hz",
        type=float,
        default=500.0,
        help="--real: the slave's state rows per second in its recording (default 500)",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    command = " ".join(["tools/soak.py", *(argv if argv is not None else sys.argv[1:])])
    if args.mode == "paper":
        import stability

        if not args.real:
            return stability.execute(args, command, label="soak paper")
        return run_paper_real_main(args, command)
    out = args.out or Path(tempfile.mkdtemp(prefix=f"occ-soak-{args.mode}-"))
    out.mkdir(parents=True, exist_ok=True)
    if args.mode == "sim":
        # the simulated slave logs every safety stop: to a file, not the terminal
        logging.basicConfig(
            filename=str(out / "slave-sim.log"),
            level=logging.WARNING,
            format="%(levelname)s %(name)s: %(message)s",
        )
    if args.mode == "real" and (args.runs is not None or args.hogs):
        if args.runs is None or args.runs < 1 or args.hogs < 0:
            print("soak real: --hogs needs --runs N (N >= 1), H >= 0", file=sys.stderr)
            return 2
        try:
            rep = run_real_series(args, out, command)
        except SystemExit as err:
            if isinstance(err.code, str):
                print(err.code, file=sys.stderr)
                return 2
            raise
        rep.command = command
        write_series_report(rep, out)
        for c in rep.checks:
            print(f"[{c.label}] {c.name}: {c.detail}")
        print(f"soak real --runs {args.runs}: {'PASS' if rep.passed else 'FAIL'}; report in {out}")
        return 0 if rep.passed else 1
    try:
        rep = run_sim(args, out) if args.mode == "sim" else run_real(args, out)
    except SystemExit as err:
        if isinstance(err.code, str):
            print(err.code, file=sys.stderr)
            return 2
        raise
    rep.command = " ".join(["tools/soak.py", *(argv if argv is not None else sys.argv[1:])])
    write_report(rep, out)
    for c in rep.checks:
        print(f"[{c.label}] {c.name}: {c.detail}")
    print(f"soak {rep.mode}: {'PASS' if rep.passed else 'FAIL'}; report in {out}")
    return 0 if rep.passed else 1


if __name__ == "__main__":
    os.environ.setdefault("MPLBACKEND", "Agg")
    sys.exit(main())
