"""``occ-record``: export, replay or plot a recording (occ/recording/record.py is the format),
or tell why a black box dump was written (``why``, occ/recording/why.py).

A module of its own so that the recording format imports neither its plots
(occ/recording/plot.py) nor its exports (occ/recording/export.py), which import it: no import
circle.

Exit status of ``occ-record export``:

- 0: the recording was read to its end and exported whole;
- 1: nothing was exported (nothing to export, an existing output, a file that cannot be read
  or written); nothing was written;
- 2: the command was wrong (an output name whose form the exporter cannot write, a format that
  does not fit the name, a missing optional dependency); nothing was read or written;
- 4 (``replay --deterministic``): the replay DIVERGED from the recorded run (the first
  difference printed: tick, field, recorded, replayed); 0 when it was exact, 1 when the
  dump cannot be replayed (none there, no checkpoint, inputs overwritten);
- 3: SALVAGED: the recording is damaged (cut mid-message, a bad header, damaged messages);
  what could be read was exported, and the message on stderr says where the damage is (its
  byte offset, the last message read, its time).

Exit status of ``occ-record why DIR``: 0 when the stop was explained (what the dump did not
hold is said in the output); 1 when DIR is not a black box dump (the message says why); 2 for
a wrong command.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import igtl
from occ.recording.record import ReadReport, replay

#: the exit status of an export of a damaged recording, made up to the damage
SALVAGED = 3


def main(argv: list[str] | None = None) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    try:
        if args.cmd == "plot":
            return _plot(args)
        if args.cmd == "export":
            return _export(args)
        if args.cmd == "why":
            return _why(args)
        return _replay(p, args)
    except (OSError, igtl.IGTLError) as err:
        print(f"occ-record: {err}", file=sys.stderr)
        return 1


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="occ-record",
        description="Export, replay or plot an occd recording; tell why a black box dump was "
        "written.",
        epilog="export exits 0 when complete, 3 when a damaged recording was salvaged up to "
        "the damage, 1 when nothing was exported, 2 for a wrong command (an output name it "
        "cannot write); why exits 0 when it explained the dump, 1 when DIR is not a dump, 2 "
        "for a wrong command",
    )
    sub = p.add_subparsers(dest="cmd", required=True)
    _add_export(sub)
    _add_replay(sub)
    _add_plot(sub)
    _add_why(sub)
    return p


def _add_export(sub: Any) -> None:
    e = sub.add_parser(
        "export",
        help="write CSV (state.csv, messages.csv), a sequence metafile for 3D Slicer and PLUS "
        "(--format seq) or a ROS 2 bag (--format mcap)",
    )
    e.add_argument("file", type=Path)
    e.add_argument(
        "out",
        type=Path,
        help="CSV: a directory (a name without a file suffix); seq: OUT.seq.mha (.mha, .mhd); "
        "mcap: OUT.mcap (one file) or OUT (a rosbag2 directory); other names are refused",
    )
    e.add_argument(
        "--format",
        choices=["csv", "seq", "mcap"],
        default=None,
        help="default: from OUT (.mha/.mhd -> seq, .mcap -> mcap, a directory -> csv)",
    )
    e.add_argument(
        "--device",
        action="append",
        default=None,
        help="seq/mcap: only this TRANSFORM/POSITION stream (repeatable; default all)",
    )
    e.add_argument("--name", default=None, help="mcap: the robot's ROS name (default its own)")
    e.add_argument(
        "--force",
        action="store_true",
        help="replace an existing OUT (CSV: its state.csv and messages.csv), once the new one "
        "is whole",
    )


def _add_replay(sub: Any) -> None:
    r = sub.add_parser(
        "replay",
        help="send recorded messages to HOST:PORT with original timing; or, with "
        "--deterministic DIR, run a black box dump's ticks again and compare every output",
    )
    r.add_argument("file", type=Path)
    r.add_argument("target", nargs="?", default=None, help="HOST:PORT")
    r.add_argument(
        "--deterministic",
        action="store_true",
        help="FILE is a black box dump: rebuild the robot from its config in simulated time, "
        "feed every input at its recorded tick, compare every output bit for bit (exit 0 "
        "exact, 4 diverged: the first difference printed)",
    )
    r.add_argument(
        "--config",
        type=Path,
        default=None,
        help="with --deterministic: this daemon config instead of the dump's (what if)",
    )
    r.add_argument("--json", action="store_true", help="with --deterministic: JSON output")
    r.add_argument("--udp", action="store_true")
    r.add_argument("--speed", type=float, default=1.0)
    r.add_argument("--direction", choices=["in", "out"], default="in")
    r.add_argument("--interface", default=None)
    r.add_argument("--type", action="append", dest="types", default=None)


def _add_plot(sub: Any) -> None:
    g = sub.add_parser(
        "plot",
        help="a PNG: trajectories, tracking error, state timeline with causes, loop timing",
    )
    g.add_argument("file", type=Path)
    g.add_argument("-o", "--out", type=Path, default=None, help="PNG path (default FILE.png)")
    g.add_argument(
        "--scale",
        type=float,
        default=0.1,
        help="motion scale master -> slave for the tracking error (default 0.1, the shipped "
        "slave's)",
    )
    g.add_argument(
        "--master",
        type=Path,
        default=None,
        help="the master's recording: its own POSITION stream as the reference (every packet)",
    )


def _add_why(sub: Any) -> None:
    w = sub.add_parser(
        "why",
        help="the chain that led to a black box dump: the numbers a loss stop judged lost, "
        "the samples a late stream brought, a drive fault's reading and rule, a collision's "
        "link and clearance, who asked an EStop or a dump; the transitions before it",
    )
    w.add_argument("dir", type=Path, help="a black box dump (black_box.dir/<robot>-<time>-<cause>)")
    w.add_argument("--json", action="store_true", help="JSON for machines instead of text")
    w.add_argument(
        "--last",
        type=_seconds,
        default=5.0,
        metavar="S",
        help="the state transitions and holds of the last S seconds before the trigger (default 5)",
    )


def _seconds(text: str) -> float:
    try:
        s = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number of seconds: {text!r}") from None
    if not s >= 0.0 or s == float("inf"):
        raise argparse.ArgumentTypeError(f"must be 0 or more seconds, got {text!r}")
    return s


def _why(args: argparse.Namespace) -> int:
    from occ.recording.why import NotADump, explain, load_dump, to_json
    from occ.recording.whytext import render

    try:
        dump = load_dump(args.dir)
    except NotADump as err:
        print(f"occ-record why: {err}", file=sys.stderr)
        return 1
    x = explain(dump, args.last)
    sys.stdout.write(to_json(x) + "\n" if args.json else render(x))
    return 0


def _plot(args: argparse.Namespace) -> int:
    from occ.recording.plot import PlotError, plot_recording

    try:
        png = plot_recording(args.file, args.out, scale=args.scale, master=args.master)
    except PlotError as err:
        print(f"occ-record: {err}", file=sys.stderr)
        return err.code
    print(f"wrote {png}")
    return 0


def _export(args: argparse.Namespace) -> int:
    from occ.recording.export import ExportError, export  # rosbags lives there

    report = ReadReport()
    try:
        summary = export(
            args.file,
            args.out,
            args.format,
            devices=set(args.device) if args.device else None,
            name=args.name,
            force=args.force,
            report=report,
        )
    except ExportError as err:
        print(f"occ-record: {err}", file=sys.stderr)
        if report.path and not report.complete:
            print(f"occ-record: {report.describe()}", file=sys.stderr)
        return err.code
    print(f"wrote {args.out}: {summary}")
    if not report.complete:
        print(f"occ-record: SALVAGED: {report.describe()}", file=sys.stderr)
        return SALVAGED
    return 0


def _replay(p: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    if args.deterministic:
        if args.target is not None:
            p.error("replay --deterministic takes a dump directory, not a target")
        from occ.core.replay import main_deterministic  # the robot: only when asked

        return main_deterministic(args.file, args.config, as_json=args.json)
    if args.config is not None or args.json:
        p.error("--config and --json go with --deterministic")
    if args.target is None:
        p.error("replay needs HOST:PORT (or --deterministic DIR)")
    host, _, port = args.target.rpartition(":")
    if not host or not port.isdigit():
        p.error(f"target must be HOST:PORT, got {args.target!r}")
    n = replay(
        args.file,
        (host, int(port)),
        udp=args.udp,
        speed=args.speed,
        direction=args.direction,
        interface=args.interface,
        types=set(args.types) if args.types else None,
    )
    print(f"replayed {n} messages")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
