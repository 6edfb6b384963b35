"""``occ-ros2``: publish OCC daemons on ROS 2 (DDS), take commands from it.

Examples::

    occ-ros2 --connect 127.0.0.1:18944=/occ/slave --operator 127.0.0.1:18947=/occ/slave
    occ-ros2 --connect 127.0.0.1:18944=/occ/slave --domain-id 7 --duration 60 --stats /tmp/b.json
    occ-ros2 --master /occ/master=127.0.0.1:18946 --connect 127.0.0.1:18944=/occ/slave
    occ-ros2 --operator 127.0.0.1:18944=/occ/keyframe --ack-moves   # move_jp/move_cp run
    occ-ros2 --connect 127.0.0.1:18944=/occ/slave --servo /occ/slave=127.0.0.1:18948

Topics and types: occ_ros2/bridge.py, README "ROS 2". DDS runs on loopback only
by default (occ_ros2/cyclonedds-lo.xml); ``--dds-config env`` takes $CYCLONEDDS_URI instead.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading
from pathlib import Path
from types import FrameType

from .bridge import (
    DEFAULT_CONFIG,
    MAX_RATE_HZ,
    MOVE_JOINT_SPEED,
    MOVE_MIN_S,
    MOVE_TIP_SPEED,
    Bridge,
    parse_endpoint,
)
from .master import MasterStream, parse_master


def _endpoint(text: str) -> tuple[str, int, str]:
    try:
        return parse_endpoint(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from err


def _master(text: str) -> tuple[str, str, int]:
    try:
        return parse_master(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from err


def _domain_id(text: str) -> int:
    value = int(text)
    # 0..232: the ids whose RTPS ports (7400 + 250 * id + ...) fit below 65536
    if not 0 <= value <= 232:
        raise argparse.ArgumentTypeError(f"DDS domain id must be 0..232, got {value}")
    return value


def _rate(text: str) -> float:
    try:
        value = float(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"not a rate: {text!r}") from err
    if not 0.0 <= value <= MAX_RATE_HZ:
        raise argparse.ArgumentTypeError(f"rate must be 0 .. {MAX_RATE_HZ:g} Hz, got {text}")
    return value


def _speed(text: str) -> float:
    try:
        value = float(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"not a speed: {text!r}") from err
    if not 0.0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"a speed must be > 0, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="occ-ros2", description="Bridge OCC daemons (OpenIGTLink) to ROS 2 topics over DDS."
    )
    _add_endpoints(p)
    _add_publishing(p)
    _add_moves(p)
    p.add_argument("--duration", type=float, default=0.0, help="seconds to run (0: until Ctrl-C)")
    p.add_argument("--stats", type=Path, default=None, help="write statistics JSON here at exit")
    p.add_argument("--log-level", default="INFO")
    return p


def _add_endpoints(p: argparse.ArgumentParser) -> None:
    """The daemons the bridge talks to, and in which mode."""
    p.add_argument(
        "--connect",
        action="append",
        type=_endpoint,
        default=[],
        metavar="H:P=/NS",
        help="a daemon's viewer port and the namespace of its topics (repeatable)",
    )
    p.add_argument(
        "--operator",
        action="append",
        type=_endpoint,
        default=[],
        metavar="H:P=/NS",
        help="a daemon's operator port: commands from ROS 2 go there (repeatable)",
    )
    p.add_argument(
        "--master",
        action="append",
        type=_master,
        default=[],
        metavar="/NS=H:P",
        help="master mode: NS/servo_cp (PoseStamped) becomes the 500 Hz POSITION stream to a "
        "slave's UDP port (repeatable)",
    )
    p.add_argument(
        "--servo",
        action="append",
        type=_master,
        default=[],
        metavar="/NS=H:P",
        help="servo mode: the robot's own NS/servo_cp (PoseStamped in the world frame of its "
        "measured_cp) becomes the 500 Hz POSITION stream to its UDP port, taken as absolute "
        "targets (a slave config with `mapping: absolute`, configs/servo.yaml; repeatable)",
    )
    p.add_argument(
        "--auth-key-file",
        type=Path,
        default=None,
        help="master and servo modes: the slave's shared key file (its "
        "interfaces[].auth_key_file): every POSITION carries the HMAC tag the slave requires",
    )


def _add_publishing(p: argparse.ArgumentParser) -> None:
    """DDS, frames and the rate of what the bridge publishes."""
    p.add_argument(
        "--domain-id",
        type=_domain_id,
        default=None,
        help="DDS domain (default $ROS_DOMAIN_ID, else 0)",
    )
    p.add_argument(
        "--dds-config",
        default=str(DEFAULT_CONFIG),
        help="Cyclone DDS XML file (default: loopback only, discovery by multicast on lo and "
        "unicast to 127.0.0.1); 'env': "
        "$CYCLONEDDS_URI as Cyclone reads it",
    )
    p.add_argument("--world-frame", default="world", help="the world frame's name (frame_id)")
    p.add_argument(
        "--rate",
        type=_rate,
        default=0.0,
        metavar="HZ",
        help=f"publish each pose and joint topic at most this often (up to {MAX_RATE_HZ:g}; "
        "default 0: as the daemon's viewer output sends, its rate_hz)",
    )
    p.add_argument("--no-tf", action="store_true", help="do not publish /tf and /tf_static")


def _add_moves(p: argparse.ArgumentParser) -> None:
    """move_jp/move_cp: who acknowledges their plans and how long they take."""
    p.add_argument(
        "--ack-moves",
        action="store_true",
        help="acknowledge (KeyframeAck) the plans of move_jp/move_cp on the ROS 2 client's "
        "behalf: they run once the daemon has checked and previewed them. A safety decision "
        "for whoever starts the bridge with operator rights; without it a plan waits for an "
        "operator's KeyframeAck (README, ROS 2)",
    )
    p.add_argument(
        "--move-joint-speed",
        type=_speed,
        default=MOVE_JOINT_SPEED,
        metavar="PER_S",
        help=f"move_jp's time: the largest joint change over this (rad/s or m/s; default "
        f"{MOVE_JOINT_SPEED:g}), at least {MOVE_MIN_S:g} s",
    )
    p.add_argument(
        "--move-tip-speed",
        type=_speed,
        default=MOVE_TIP_SPEED,
        metavar="M_PER_S",
        help=f"move_cp's time: the tip's distance over this (m/s; default {MOVE_TIP_SPEED:g}), "
        f"at least {MOVE_MIN_S:g} s",
    )


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(name)s %(message)s")
    domain = args.domain_id
    if domain is None:
        domain = _domain_id(os.environ.get("ROS_DOMAIN_ID", "0") or "0")
    config = None if args.dds_config == "env" else Path(args.dds_config).read_text()
    if not (args.connect or args.operator or args.master or args.servo):
        print(
            "occ-ros2: nothing to bridge: give --connect, --operator, --master or --servo",
            file=sys.stderr,
        )
        return 2
    both = {ns for ns, _, _ in args.master} & {ns for ns, _, _ in args.servo}
    if both:
        twice = ", ".join(sorted(both))
        print(f"occ-ros2: {twice}: --master or --servo, not both", file=sys.stderr)
        return 2
    bridge = Bridge(
        args.connect,
        args.operator,
        domain_id=domain,
        config=config,
        world_frame=args.world_frame,
        rate_hz=args.rate,
        tf=not args.no_tf,
        ack_moves=args.ack_moves,
        move_joint_speed=args.move_joint_speed,
        move_tip_speed=args.move_tip_speed,
    )
    key = None
    if args.auth_key_file is not None:
        from igtl.auth import load_key

        try:
            key = load_key(args.auth_key_file.read_text(encoding="utf-8"))
        except (OSError, ValueError) as err:
            print(f"occ-ros2: --auth-key-file: {err}", file=sys.stderr)
            return 2
    masters = [
        MasterStream(bridge.participant, ns, (host, port), auth_key=key)
        for ns, host, port in args.master
    ]
    masters += [
        MasterStream(
            bridge.participant,
            ns,
            (host, port),
            auth_key=key,
            device="ServoCP",
            frames=("", args.world_frame),
        )  # fmt: skip
        for ns, host, port in args.servo
    ]
    servo = {ns for ns, _, _ in args.servo}
    done = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        done.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    bridge.start()
    for m in masters:
        m.start()
    names = [*bridge.robots, *(f"{m.ns} -> {m.remote[0]}:{m.remote[1]}" for m in masters)]
    logging.getLogger("occ_ros2").info("bridging %s on DDS domain %d", ", ".join(names), domain)
    try:
        done.wait(args.duration if args.duration > 0 else None)
    finally:
        for m in masters:
            m.stop()
        bridge.stop()
        stats = bridge.stats()
        for m in masters:
            stats[f"{'servo' if m.ns in servo else 'master'} {m.ns}"] = m.stats()
        if args.stats is not None:
            args.stats.write_text(json.dumps(stats, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
