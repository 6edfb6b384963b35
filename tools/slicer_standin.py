#!/usr/bin/env python3
"""A 3D Slicer stand-in: behaves on the wire like SlicerOpenIGTLink's client connector.

What it does, as Slicer does (shared/IGTL-PROTOCOL.md §6.1):

- connects as a TCP *client* (default 127.0.0.1:18944);
- on connect sends a header-version-2 STATUS with an empty device name and metadata
  ``dummy=dummy``, so the server starts answering in header version 2;
- attaches ``MRMLNodeName`` metadata to what it sends (VFIXTURE fixtures, Markups point lists
  as POINT, COMMANDs);
- receives TRANSFORMs (the robot's ``Tip`` and ``Base``) and STATUS messages.

It prints the tip as it arrives (``--print``), and at the end a JSON summary per device: count,
rate, interval mean / standard deviation / p99 / max (the stream's jitter), and the last
position. Used by the tests, the demo and the benchmarks.

Examples::

    python tools/slicer_standin.py --duration 10 --print
    python tools/slicer_standin.py --port 18945 --fixture 0,50,20,10 --hardness 0.5 --duration 1
    python tools/slicer_standin.py --command Enable --command Run --duration 2
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import threading
import time
from typing import Any

import igtl
from igtl.transport import TCPClient


class SlicerStandIn:
    """Connect, greet like Slicer, collect transforms. Thread-safe summary."""

    def __init__(self, host: str = "127.0.0.1", port: int = 18944, *, echo: bool = False) -> None:
        self.echo = echo
        self._lock = threading.Lock()
        self.arrivals: dict[str, list[float]] = {}
        self.last: dict[str, Any] = {}
        self.statuses: list[igtl.StatusMessage] = []
        self.replies: list[igtl.Message] = []
        self.connected = threading.Event()
        self._cmd_id = 0
        self.client = TCPClient(
            host,
            port,
            on_message=self._on_message,
            on_connect=self._on_connect,
            name="slicer-standin",
        )

    def start(self) -> SlicerStandIn:
        self.client.start()
        return self

    def stop(self) -> None:
        self.client.stop()

    def __enter__(self) -> SlicerStandIn:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _on_connect(self, peer: Any) -> None:
        # Slicer's greeting: tells PLUS-like servers that it speaks header version 2.
        self.client.send(igtl.StatusMessage(header_version=2, metadata={"dummy": "dummy"}))
        self.connected.set()

    def _on_message(self, peer: Any, msg: igtl.Message) -> None:
        now = time.perf_counter()
        with self._lock:
            if msg.message_type == "TRANSFORM":
                self.arrivals.setdefault(msg.device_name, []).append(now)
                self.last[msg.device_name] = msg
                if self.echo and msg.device_name == "Tip":
                    x, y, z = msg.translation  # type: ignore[attr-defined]
                    print(f"Tip {x:9.3f} {y:9.3f} {z:9.3f} mm", flush=True)
            elif msg.message_type == "STATUS":
                self.statuses.append(msg)  # type: ignore[arg-type]
                if self.echo:
                    print(f"STATUS {msg.error_name}: {msg.status_message}", flush=True)  # type: ignore[attr-defined]
            else:
                self.replies.append(msg)
                if self.echo:
                    print(
                        f"{msg.message_type} {msg.device_name}: {msg.content_summary()}", flush=True
                    )

    # --------------------------------------------------------------- sending, as Slicer does
    def send_command(self, name: str, text: str = "") -> int:
        """COMMAND as igtlioConnector::SendCommand: device "command", incrementing id."""
        self._cmd_id += 1
        cls = igtl.REGISTRY["COMMAND"]
        self.client.send(
            cls(
                command_id=self._cmd_id,
                command_name=name,
                command=text,
                device_name="command",
                header_version=2,
                metadata={"MRMLNodeName": "CommandNode"},
            )
        )
        return self._cmd_id

    def wait_reply(self, command_id: int, timeout: float = 5.0) -> igtl.Message | None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with self._lock:
                for r in self.replies:
                    if (
                        r.message_type == "RTS_COMMAND"
                        and getattr(r, "command_id", None) == command_id
                    ):
                        return r
            time.sleep(0.005)
        return None

    def send_fixtures(
        self,
        spheres: list[tuple[float, float, float, float]],
        hardness: float,
        kind: str = "accessible",
    ) -> None:
        cls = igtl.REGISTRY["VFIXTURE"]
        self.client.send(
            cls(
                spheres=tuple(spheres),
                hardness=hardness,
                device_name="Fixtures",
                header_version=2,
                metadata={"MRMLNodeName": "VirtualFixture", "kind": kind},
            )
        )

    def send_markups(self, points: list[tuple[float, float, float]], **kw: Any) -> None:
        self.client.send(markups_points(points, **kw))

    # --------------------------------------------------------------- results
    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        with self._lock:
            for dev, times in self.arrivals.items():
                d: dict[str, Any] = {"count": len(times)}
                if len(times) >= 2:
                    iv = [(b - a) * 1e3 for a, b in zip(times, times[1:], strict=False)]
                    span = times[-1] - times[0]
                    d["rate_hz"] = round((len(times) - 1) / span, 3) if span > 0 else None
                    d["interval_ms"] = {
                        "mean": round(statistics.fmean(iv), 3),
                        "std": round(statistics.pstdev(iv), 3),
                        "p99": round(sorted(iv)[min(len(iv) - 1, int(0.99 * len(iv)))], 3),
                        "max": round(max(iv), 3),
                        "min": round(min(iv), 3),
                    }
                m = self.last.get(dev)
                if m is not None:
                    d["last_mm"] = [round(v, 3) for v in m.translation]  # type: ignore[attr-defined]
                out[dev] = d
            out["_statuses"] = [f"{s.error_name}: {s.status_message}" for s in self.statuses][-10:]
        return out


def markups_points(
    points: list[tuple[float, float, float]],
    name: str = "F",
    *,
    kind: str | None = None,
    radius: float | None = None,
    stiffness: float | None = None,
    frame: str | None = None,
) -> igtl.Message:
    """A Markups point list as SlicerOpenIGTLink sends it: POINT, header v2, one element per
    control point (label ``NAME-i``, group ``Fiducial``, visible, radius 0, RAS mm) and
    ``MRMLNodeName``; the fixture metadata (``kind``, ``radius``, ``stiffness``, ``frame``) as
    a user adds it to the node's attributes (left out: the daemon's defaults)."""
    from igtl.messages.point import PointElement

    meta = {"MRMLNodeName": name}
    for key, value in (
        ("kind", kind),
        ("radius", radius),
        ("stiffness", stiffness),
        ("frame", frame),
    ):
        if value is not None:
            meta[key] = str(value)
    elements = tuple(
        PointElement(name=f"{name}-{i + 1}", group="Fiducial", rgba=(255, 0, 0, 255), position=p)
        for i, p in enumerate(points)
    )
    return igtl.PointMessage(points=elements, device_name=name, header_version=2, metadata=meta)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="3D Slicer stand-in (OpenIGTLinkIF client behaviour)")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=18944)
    p.add_argument("--duration", type=float, default=5.0, help="seconds to listen (default 5)")
    p.add_argument("--print", action="store_true", dest="echo", help="print every Tip and STATUS")
    p.add_argument("--command", action="append", default=[], help="send COMMAND NAME (repeatable)")
    p.add_argument(
        "--fixture",
        action="append",
        default=[],
        metavar="X,Y,Z,R",
        help="send a VFIXTURE sphere, patient frame (the frame of the slave's Tip), mm "
        "(repeatable)",
    )
    p.add_argument(
        "--hardness", type=float, default=1.0, help="fixture stiffness, N per mm of master motion"
    )
    p.add_argument(
        "--kind",
        default="accessible",
        choices=("accessible", "forbidden"),
        help="what the --fixture spheres are (the OCC paper: accessible)",
    )
    p.add_argument("--json", type=str, default=None, help="write the summary to this file")
    p.add_argument("--connect-timeout", type=float, default=5.0)
    args = p.parse_args(argv)
    s = SlicerStandIn(args.host, args.port, echo=args.echo).start()
    try:
        if not s.connected.wait(args.connect_timeout):
            print(f"slicer-standin: cannot connect to {args.host}:{args.port}", file=sys.stderr)
            return 1
        if args.fixture:
            try:
                spheres = [tuple(float(v) for v in f.split(",")) for f in args.fixture]
            except ValueError:
                p.error("--fixture takes X,Y,Z,R in mm")
            if any(len(sp) != 4 for sp in spheres):
                p.error("--fixture takes X,Y,Z,R in mm")
            s.send_fixtures(spheres, args.hardness, args.kind)  # type: ignore[arg-type]
        for name in args.command:
            cid = s.send_command(name)
            r = s.wait_reply(cid)
            status = r.metadata.get("Status") if r is not None else "no reply"
            print(f"command {name}: {status} {getattr(r, 'command', '') if r is not None else ''}")
        time.sleep(args.duration)
        summary = s.summary()
    finally:
        s.stop()
    text = json.dumps(summary, indent=2)
    print(text)
    if args.json:
        with open(args.json, "w") as fh:
            fh.write(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
