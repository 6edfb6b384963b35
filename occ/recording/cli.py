"""``occ-record``: export, replay or plot a recording (occ/recording/record.py is the format).

A module of its own so that the recording format imports neither its plots
(occ/recording/plot.py) nor its exports (occ/recording/export.py), which import it: no import
circle.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import igtl
from occ.recording.record import export_csv, replay


def main(argv: list[str] | None = None) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    try:
        if args.cmd == "plot":
            return _plot(args)
        if args.cmd == "export":
            return _export(args)
        return _replay(p, args)
    except (OSError, igtl.IGTLError) as err:
        print(f"occ-record: {err}", file=sys.stderr)
        return 1


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="occ-record", description="Export, replay or plot an occd recording."
    )
    sub = p.add_subparsers(dest="cmd", required=True)
    _add_export(sub)
    _add_replay(sub)
    _add_plot(sub)
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
        help="CSV: a directory; seq: OUT.seq.mha; mcap: OUT.mcap (one file) or OUT (a rosbag2 "
        "directory)",
    )
    e.add_argument(
        "--format",
        choices=["csv", "seq", "mcap"],
        default=None,
        help="default: from OUT (.mha/.mhd -> seq, .mcap -> mcap, else csv)",
    )
    e.add_argument(
        "--device",
        action="append",
        default=None,
        help="seq/mcap: only this TRANSFORM/POSITION stream (repeatable; default all)",
    )
    e.add_argument("--name", default=None, help="mcap: the robot's ROS name (default its own)")
    e.add_argument("--force", action="store_true", help="seq/mcap: replace an existing OUT")


def _add_replay(sub: Any) -> None:
    r = sub.add_parser("replay", help="send recorded messages to HOST:PORT with original timing")
    r.add_argument("file", type=Path)
    r.add_argument("target", help="HOST:PORT")
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
    from occ.recording.export import ExportError, export, guess_format  # rosbags lives there

    fmt = args.format or guess_format(args.out)
    if fmt == "csv":
        s, m = export_csv(args.file, args.out)
        print(f"wrote {s} and {m}")
        return 0
    try:
        summary = export(
            args.file,
            args.out,
            fmt,
            devices=set(args.device) if args.device else None,
            name=args.name,
            force=args.force,
        )
    except ExportError as err:
        print(f"occ-record: {err}", file=sys.stderr)
        return err.code
    print(f"wrote {args.out}: {summary}")
    return 0


def _replay(p: argparse.ArgumentParser, args: argparse.Namespace) -> int:
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
