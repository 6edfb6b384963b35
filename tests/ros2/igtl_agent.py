"""An OpenIGTLink operator for the bridge's namespace tests: what a person at 3D Slicer's
console (or a script) does to the daemon while a ROS 2 node uses the bridge.

Run as a subprocess inside the test's network namespace (the daemon's port exists only
there)::

    python igtl_agent.py PORT

It connects to 127.0.0.1:PORT as 3D Slicer does (tools/fixture_e2e.py's client: a v2 STATUS
first) and answers JSON lines on stdin with one JSON line each on stdout:

- ``{"op": "command", "name": "KeyframeAck", "args": {"Plan": "3"}}``: a COMMAND (the
  arguments as XML attributes), answered with the daemon's reply ``{"status", "message"}``;
- ``{"op": "point", "centre": [x, y, z], "radius": 20.0}``: a Markups point list (POINT), as
  SlicerOpenIGTLink pushes one (a virtual fixture on a master);
- ``{"op": "stats"}``: the daemon's ``GetStats`` (its ``controller`` section);
- ``{"op": "exit"}``.
"""

from __future__ import annotations

import json
import queue
import sys
import time
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))

from fixture_e2e import Client, point_list  # noqa: E402

import igtl  # noqa: E402


def command(client: Client, cid: int, name: str, args: dict[str, str], timeout: float) -> dict:
    attrs = "".join(f" {k}={quoteattr(str(v))}" for k, v in args.items())
    client.send(
        igtl.CommandMessage(
            command_id=cid,
            command_name=name,
            command=f"<Command Name={quoteattr(name)}{attrs}/>",
            device_name="operator",
            header_version=2,
        )
    )
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            msg = client.replies.get(timeout=0.1)
        except queue.Empty:
            continue
        if msg.message_type == "RTS_COMMAND" and int(getattr(msg, "command_id", -1)) == cid:
            return {"status": msg.metadata.get("Status"), "message": msg.metadata.get("Message")}
    return {"status": None, "message": f"no reply to {name} within {timeout} s"}


def main() -> int:
    port = int(sys.argv[1])
    client = Client(port)
    client.client.start()
    if not client.connected.wait(10.0):
        sys.stdout.write(json.dumps({"ready": False, "error": f"no connection to {port}"}) + "\n")
        return 1

    def answer(obj: dict[str, Any]) -> None:
        sys.stdout.write(json.dumps(obj) + "\n")
        sys.stdout.flush()

    answer({"ready": True})
    cid = 1000
    for line in sys.stdin:
        try:
            req = json.loads(line)
        except ValueError:
            answer({"error": f"not JSON: {line!r}"})
            continue
        op = req.get("op")
        if op == "command":
            cid += 1
            args = {str(k): str(v) for k, v in req.get("args", {}).items()}
            answer(command(client, cid, str(req["name"]), args, float(req.get("timeout", 10.0))))
        elif op == "point":
            centre = tuple(float(v) for v in req["centre"])
            client.send(point_list(centre, float(req["radius"]), req.get("stiffness")))  # type: ignore[arg-type]
            answer({"sent": True})
        elif op == "stats":
            answer(client.stats()["controller"])
        elif op == "exit":
            answer({"bye": True})
            break
        else:
            answer({"error": f"unknown op {op!r}"})
    client.client.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
