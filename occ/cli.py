"""``occd``: run one robot daemon from a YAML configuration.

Exit codes:
  0  stopped cleanly (duration elapsed, SIGINT or SIGTERM)
  1  runtime error (a port already in use, a driver that cannot start, ...)
  2  usage error or invalid configuration (every problem is listed as FILE:LINE path: message)
  3  the robot ended latched in FAULT or ESTOP
  4  the robot ended STOPPED by a safety stop (packet loss, a dead master, the watchdog); the
     cause is in the log, the STATUS alerts and ``last_alert`` of the --stats file

This is the only place that configures logging and installs signal handlers. Log records are
handed to a background thread (QueueHandler), so the control loop never waits on log I/O.
"""

from __future__ import annotations

import argparse
import atexit
import json
import logging
import logging.handlers
import queue
import signal
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

from occ import _native
from occ.core.loader import load_config
from occ.errors import ConfigError, OCCError

if TYPE_CHECKING:
    from occ.core.robot import Robot

EXIT_OK, EXIT_RUNTIME, EXIT_USAGE, EXIT_FAULT, EXIT_STOPPED = 0, 1, 2, 3, 4

log = logging.getLogger("occd")


def setup_logging(level: str) -> logging.handlers.QueueListener:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(
        logging.Formatter(
            "%(asctime)s.%(msecs)03d %(levelname)-7s %(name)s: %(message)s", "%H:%M:%S"
        )
    )
    q: queue.SimpleQueue[logging.LogRecord] = queue.SimpleQueue()
    listener = logging.handlers.QueueListener(q, handler, respect_handler_level=False)
    root = logging.getLogger()
    root.handlers[:] = [logging.handlers.QueueHandler(q)]
    root.setLevel(getattr(logging, level.upper()))
    listener.start()
    atexit.register(listener.stop)
    return listener


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="occd",
        description="Open-Core-Control robot daemon: runs the robot described by CONFIG.",
        epilog=__doc__.split("\n\n")[1] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("config", type=Path, help="the daemon's YAML configuration")
    p.add_argument("--check", action="store_true", help="validate CONFIG and exit (0 valid, 2 not)")
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="S",
        help="stop after S seconds (default: until SIGINT/SIGTERM)",
    )
    p.add_argument(
        "--stats",
        type=Path,
        default=None,
        metavar="FILE",
        help="write the timing statistics as JSON to FILE at exit",
    )
    p.add_argument(
        "--record",
        type=Path,
        default=None,
        metavar="FILE",
        help="record every message in and out plus the loop state to FILE "
        "(overrides recording.path)",
    )
    p.add_argument(
        "--log-level",
        default="INFO",
        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        help="log level (default INFO)",
    )
    p.add_argument(
        "--start",
        choices=["ready", "enabled", "running"],
        default="ready",
        help="state to reach at start-up without an operator (default: ready, "
        "servos off; operators send Enable and Run)",
    )
    p.add_argument(
        "--status-line",
        action="store_true",
        help="print a live one-line status to stderr every second",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        config = load_config(args.config)
    except ConfigError as err:
        for line in err.errors:
            print(line, file=sys.stderr)
        return EXIT_USAGE
    if args.check:
        print(f"{args.config}: valid ({config.robot.name}, {len(config.interfaces)} interfaces)")
        return EXIT_OK
    setup_logging(args.log_level)
    return run(config, args)


def run(config: Any, args: argparse.Namespace) -> int:
    from occ.core.robot import build_robot
    from occ.core.safety import RobotState

    recorder = _recorder(config, args)
    try:
        robot = build_robot(config, recorder=recorder)
    except (OCCError, OSError, ImportError, ValueError) as err:  # ValueError: plugin params
        log.error("cannot build the robot: %s", err)
        return EXIT_RUNTIME

    def on_signal(signum: int, _frame: Any) -> None:
        log.info("signal %s: stopping", signal.Signals(signum).name)
        robot.stop_loop()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)

    stop_reporter = threading.Event()
    code = EXIT_OK
    try:
        robot.configure()
        robot.activate()
        if recorder is not None:
            recorder.start()
        # in the loop's first tick: power comes on where the loop goes on commanding it
        robot.start_in(*{"enabled": ("enable",), "running": ("enable", "run")}.get(args.start, ()))
        threading.Thread(
            target=_report,
            args=(robot, config.stats.log_every_s, args.status_line, stop_reporter),
            name="occd-reporter",
            daemon=True,
        ).start()
        log.info(
            "%s running at %d Hz (%s); hot path %s",
            config.robot.name,
            config.robot.rate_hz,
            ", ".join(f"{n}={i.address}" for n, i in robot.interfaces.interfaces.items()),
            _native.describe(),
        )
        robot.run(duration=args.duration)
        log.info("%s", robot.loop.realtime_report or "loop ended")
    except OSError as err:
        log.error("runtime error: %s", err)
        code = EXIT_RUNTIME
    except OCCError as err:
        log.error("runtime error: %s", err)
        code = EXIT_RUNTIME
    finally:
        stop_reporter.set()
        final_state = _shut_down(robot, recorder, args)
    if code == EXIT_OK and final_state in (RobotState.FAULT, RobotState.ESTOP):
        code = EXIT_FAULT
    elif code == EXIT_OK and final_state is RobotState.STOPPED and robot.last_alert:
        code = EXIT_STOPPED
    return code


def _recorder(config: Any, args: argparse.Namespace) -> Any:
    """The recorder of ``--record`` or the configured ``recording.path``; None when neither."""
    from occ.recording.record import Recorder, writer_priority

    rec_path = args.record or config.recording.path
    if not rec_path:
        return None
    return Recorder(
        rec_path,
        rate_hz=config.recording.rate_hz,
        include_messages=config.recording.include_messages,
        fifo_priority=writer_priority(config),
    )


def _report(robot: Robot, every: float, show_status: bool, stop: threading.Event) -> None:
    """The reporter thread: the status line each second, the statistics every ``every`` s."""
    last = 0.0
    while not stop.wait(1.0):
        last += 1.0
        if show_status:
            print("\r" + status_line(robot), end="", file=sys.stderr, flush=True)
        if every and last >= every:
            last = 0.0
            log.info("%s", robot.stats.format_line())


def _shut_down(robot: Robot, recorder: Any, args: argparse.Namespace) -> Any:
    """Shut the robot and its recorder down, log and write the statistics; the robot's state
    before the shutdown."""
    if args.status_line:
        print(file=sys.stderr)
    final_state = robot.state
    robot.shutdown()
    if recorder is not None:
        recorder.close()
    snap = robot.snapshot()
    snap["final_state"] = final_state.value  # before the shutdown
    log.info("%s", robot.stats.format_line())
    if args.stats is not None:
        args.stats.parent.mkdir(parents=True, exist_ok=True)
        args.stats.write_text(json.dumps(snap, indent=2, default=str) + "\n")
        log.info("statistics written to %s", args.stats)
    return final_state


def status_line(robot: Robot) -> str:
    s = robot.stats
    late = s.lateness.summary()
    parts = [
        f"{robot.name} {robot.state.value:8s}",
        f"ticks {s.ticks}",
        f"late p99 {late['p99']:.0f}us max {late['max']:.0f}us",
    ]
    if robot.streams.monitor is not None:
        c = robot.streams.monitor.counters()
        parts.append(
            f"rx {c.get('received', 0)} lost {c.get('lost_total', 0)} run {c.get('max_run', 0)}"
        )
    for name, iface in robot.interfaces.interfaces.items():
        st = iface.counters
        parts.append(f"{name} in {st.received} out {st.sent}")
    return " | ".join(parts)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
