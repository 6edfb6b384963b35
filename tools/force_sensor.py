#!/usr/bin/env python3
"""A force sensor on the network: OpenIGTLink SENSOR readings at a fixed rate, as a separate
process (the German Heart Center's strain gauges on the instrument, or a 6-axis F/T sensor's
driver that speaks OpenIGTLink).

Each reading is a SENSOR message, device ``--device`` (``ForceSensor``), unit N, three values
(fx, fy, fz; six with ``--torque``), header version 2, the message ID a sequence number, the
header timestamp the time of the reading, sent over UDP to ``--to HOST:PORT`` (the slave's
sensor interface; a slave with ``force: {sources: [sensor], sensor_interface: ...}`` takes it).

Profiles (N, in the sensor's frame):

``constant``  ``--force FX,FY,FZ`` all the time;
``press``     from 0 up to ``--force`` and back, a raised cosine over ``--period`` seconds
              (an instrument pressing on tissue and releasing it), repeated;
``sine``      ``--force`` times sin(2 pi t / period).

The run is bounded (``--seconds``, default 10); it prints one JSON line with what it sent.

    python tools/force_sensor.py --to 127.0.0.1:18949 --profile press --force 0,0,3 --seconds 20
"""

from __future__ import annotations

import argparse
import json
import math
import socket
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import igtl  # noqa: E402
from igtl.messages.sensor import NEWTON  # noqa: E402


def reading(profile: str, force: tuple[float, ...], period: float, t: float) -> list[float]:
    """The force at time ``t`` (s) of the profile."""
    if profile == "constant":
        k = 1.0
    elif profile == "press":
        k = 0.5 - 0.5 * math.cos(2.0 * math.pi * t / period)
    elif profile == "sine":
        k = math.sin(2.0 * math.pi * t / period)
    else:
        raise ValueError(f"unknown profile {profile!r}")
    return [k * f for f in force]


def run(args: argparse.Namespace) -> dict[str, object]:
    host, _, port = args.to.rpartition(":")
    force = tuple(float(v) for v in args.force.split(","))
    if len(force) != 3:
        raise SystemExit("--force: three numbers, fx,fy,fz")
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    period = 1.0 / args.rate
    t0 = time.monotonic()
    deadline = t0
    seq = 0
    peak = 0.0
    while True:
        now = time.monotonic()
        t = now - t0
        if t >= args.seconds:
            break
        values = reading(args.profile, force, args.period, t)
        if args.torque:
            values += [0.0, 0.0, 0.0]
        seq += 1
        msg = igtl.SensorMessage(
            tuple(values), NEWTON, device_name=args.device, header_version=2,
            message_id=seq, timestamp=time.time(),
        )  # fmt: skip
        sock.sendto(msg.pack(), (host, int(port)))
        peak = max(peak, math.sqrt(sum(v * v for v in values[:3])))
        deadline += period
        delay = deadline - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        elif delay < -period:
            deadline = time.monotonic()  # behind: no burst
    sock.close()
    return {"sent": seq, "seconds": round(time.monotonic() - t0, 3), "peak_n": round(peak, 4)}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--to", required=True, metavar="HOST:PORT", help="the slave's sensor port")
    p.add_argument("--device", default="ForceSensor")
    p.add_argument("--profile", choices=("constant", "press", "sine"), default="press")
    p.add_argument("--force", default="0,0,2", help="fx,fy,fz in N (the profile's amplitude)")
    p.add_argument("--period", type=float, default=4.0, help="s, of press and sine")
    p.add_argument("--rate", type=float, default=500.0, help="readings per second")
    p.add_argument("--torque", action="store_true", help="send six values (torque zero)")
    p.add_argument("--seconds", type=float, default=10.0, help="bounded run (s)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not 0.0 < args.seconds <= 3600.0 or not 0.0 < args.rate <= 5000.0:
        raise SystemExit("--seconds must be in (0, 3600], --rate in (0, 5000]")
    print(json.dumps(run(args)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
