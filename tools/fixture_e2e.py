"""3D Slicer's virtual-fixture workflow on the shipped pair, end to end over real sockets.

What a user does (README, "Connect 3D Slicer", step 5), done as a script with the
SlicerOpenIGTLink wire behaviour of ``tools/slicer_standin.py``:

1. start ``occd configs/slave.yaml`` and ``occd configs/master.yaml`` (both ``--start
   running``: the master's simulated hand moves the OCC paper's motion, the slave follows at
   10:1 and sends its tip back to the master on the UDP link);
2. connect to the slave's 3D Slicer port (18944) and read the ``Tip`` TRANSFORM;
3. push a Markups point at exactly that position to the master (18945): POINT, the point's
   radius 20 mm, no attributes (the default kind, accessible);
4. watch the master's displayed force for ``--seconds`` of the motion (``GetStats``
   ``Format=json`` on 18945, and its ``peak_force_n``, the largest force of any tick);
5. move the sphere so that its surface is 20 mm from the tool (stiffness ``--stiffness`` N per
   mm of master motion): the force must pull toward it, ``k x depth / scale``, at most 10 N;
   then the same with the default stiffness (1 N/mm): 200 N asked, 10 N displayed.

It prints one JSON report (``--json``) and exits 0; the checks are the test's
(tests/occ/test_fixture_pair_e2e.py). The ports are read from the configs, so copies moved to
free ports work too; ``--lo-up`` brings up the loopback interface first (a fresh network
namespace, ``unshare -n``, where the shipped ports cannot collide with anything)::

    python tools/fixture_e2e.py --seconds 10
    unshare -n python tools/fixture_e2e.py --lo-up --seconds 10
"""

from __future__ import annotations

import argparse
import fcntl
import json
import math
import queue
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import yaml

import igtl
from igtl.messages.point import PointElement
from igtl.transport import TCPClient

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

from loopback import stop_processes, wait_port  # noqa: E402


def loopback_up() -> None:
    """``ip link set lo up`` without iproute2 (SIOCGIFFLAGS / SIOCSIFFLAGS)."""
    siocgifflags, siocsifflags, iff_up = 0x8913, 0x8914, 0x1
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        ifr = struct.pack("16sh", b"lo", 0)
        flags = struct.unpack("16sh", fcntl.ioctl(s, siocgifflags, ifr))[1]
        fcntl.ioctl(s, siocsifflags, struct.pack("16sh", b"lo", flags | iff_up))


class Client:
    """A 3D Slicer-like OpenIGTLink client: greets in v2, keeps the last TRANSFORM of each
    device, and matches STRING/RTS_COMMAND replies."""

    def __init__(self, port: int, host: str = "127.0.0.1") -> None:
        self.last: dict[str, Any] = {}
        self.replies: queue.Queue[igtl.Message] = queue.Queue()
        self.statuses: list[str] = []
        self.connected = threading.Event()
        self._lock = threading.Lock()
        self._id = 0
        self.client = TCPClient(
            host,
            port,
            on_message=self._on_message,
            on_connect=self._on_connect,
            name=f"e2e-{port}",
        )

    def _on_connect(self, peer: Any) -> None:
        self.client.send(igtl.StatusMessage(header_version=2, metadata={"dummy": "dummy"}))
        self.connected.set()

    def _on_message(self, peer: Any, msg: igtl.Message) -> None:
        if msg.message_type == "TRANSFORM":
            with self._lock:
                self.last[msg.device_name] = (time.monotonic(), msg)
        elif msg.message_type == "STATUS":
            self.statuses.append(f"{msg.error_name}: {msg.status_message}")  # type: ignore[attr-defined]
        elif msg.message_type in ("STRING", "RTS_COMMAND"):
            self.replies.put(msg)

    def tip(self) -> tuple[float, tuple[float, float, float]] | None:
        with self._lock:
            got = self.last.get("Tip")
        if got is None:
            return None
        t, msg = got
        return t, tuple(float(v) for v in msg.translation)  # type: ignore[return-value]

    def _ask(self, name: str, text: str) -> int:
        """Send COMMAND ``name`` (replies to earlier ones dropped); its id."""
        self._id += 1
        while not self.replies.empty():
            self.replies.get_nowait()
        self.client.send(
            igtl.CommandMessage(
                command_id=self._id,
                command_name=name,
                command=text,
                device_name="command",
                header_version=2,
                metadata={"MRMLNodeName": "CommandNode"},
            )
        )
        return self._id

    def _reply(self, what: str, match: Any, timeout: float) -> igtl.Message:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            try:
                msg = self.replies.get(timeout=0.2)
            except queue.Empty:
                continue
            if match(msg):
                return msg
        raise TimeoutError(f"no {what} reply")

    def stats(self, timeout: float = 5.0) -> dict[str, Any]:
        """The daemon's GetStats as JSON (a COMMAND answered by a STRING ``STATS``)."""
        self._ask("GetStats", '<Command Name="GetStats" Format="json"/>')
        msg = self._reply(
            "GetStats", lambda m: m.message_type == "STRING" and m.device_name == "STATS", timeout
        )
        return json.loads(msg.string)  # type: ignore[attr-defined,no-any-return]

    def command(self, name: str, timeout: float = 10.0) -> dict[str, str]:
        """An operator COMMAND and its RTS_COMMAND reply's metadata (Status, Message)."""
        cid = self._ask(name, "")
        msg = self._reply(
            name,
            lambda m: m.message_type == "RTS_COMMAND" and getattr(m, "command_id", None) == cid,
            timeout,
        )
        return dict(msg.metadata)

    def send(self, msg: igtl.Message) -> None:
        self.client.send(msg)


def point_list(
    centre: tuple[float, float, float], radius: float, stiffness: float | None = None
) -> igtl.Message:
    """One Markups control point as SlicerOpenIGTLink sends a point list (POINT, v2,
    MRMLNodeName), its radius on the element; ``stiffness`` as a node attribute."""
    meta = {"MRMLNodeName": "Target"}
    if stiffness is not None:
        meta["stiffness"] = str(stiffness)
    el = PointElement(
        name="Target-1", group="Fiducial", rgba=(255, 0, 0, 255), position=centre, radius=radius
    )
    return igtl.PointMessage(points=(el,), device_name="Target", header_version=2, metadata=meta)


def ports(cfg: Path) -> dict[str, int]:
    raw = yaml.safe_load(cfg.read_text())
    return {i["name"]: int(i.get("port", 0)) for i in raw["interfaces"]}


def controller_stats(snap: dict[str, Any]) -> dict[str, Any]:
    ctrl = snap["controller"]
    return ctrl  # type: ignore[no-any-return]


def run(
    slave_cfg: Path, master_cfg: Path, seconds: float, stiffness: float, out_dir: Path
) -> dict[str, Any]:
    sp, mp = ports(slave_cfg), ports(master_cfg)
    slicer_port, master_port = sp["slicer"], mp["operator"]
    report: dict[str, Any] = {"ports": {"slicer": slicer_port, "master": master_port}}
    procs: list[subprocess.Popen[bytes]] = []

    def start(cfg: Path, name: str) -> subprocess.Popen[bytes]:
        log = (out_dir / f"{name}.log").open("wb")
        return subprocess.Popen(
            [
                sys.executable,
                "-m",
                "occ.cli",
                str(cfg),
                "--start",
                "running",
                "--log-level",
                "WARNING",
            ],
            cwd=ROOT,
            stdout=log,
            stderr=subprocess.STDOUT,
        )

    slicer = Client(slicer_port)
    master = Client(master_port)
    try:
        procs.append(start(slave_cfg, "slave"))
        assert wait_port(slicer_port, 30.0, procs[0]), "the slave did not listen"
        procs.append(start(master_cfg, "master"))
        assert wait_port(master_port, 30.0, procs[1]), "the master did not listen"
        slicer.client.start()
        master.client.start()
        assert slicer.connected.wait(10.0) and master.connected.wait(10.0)
        # the pair is up when the master has a fresh tip from a slave that follows it
        end = time.monotonic() + 20.0
        ms: dict[str, Any] = {}
        while time.monotonic() < end:
            ms = controller_stats(master.stats())
            tip = ms.get("slave_tip") or {}
            if tip.get("status") == "fresh" and tip.get("following") and ms["fixture_gain"] == 1:
                break
            time.sleep(0.1)
        report["ready"] = ms.get("slave_tip")
        # 2-3: the Tip as Slicer shows it, and a point list there (radius 20 mm)
        got = None
        end = time.monotonic() + 5.0
        while got is None and time.monotonic() < end:
            got = slicer.tip()
            time.sleep(0.05)
        assert got is not None, "no Tip from the slave"
        t_tip, tip_mm = got
        master.send(point_list(tip_mm, 20.0))
        report["point"] = {"centre_mm": tip_mm, "radius_mm": 20.0}
        # 4: the motion for `seconds`, watched: the displayed force, and the tool against
        # the Tip Slicer shows at the same moment
        samples = []
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            st = controller_stats(master.stats())
            now_tip = slicer.tip()
            samples.append(
                {
                    "t": round(time.monotonic() - t0, 3),
                    "force_n": st["force_n"],
                    "tool_mm": st["tool_mm"],
                    "slicer_tip_mm": None if now_tip is None else now_tip[1],
                    "tip_status": (st.get("slave_tip") or {}).get("status"),
                    "fixtures": st["fixtures"],
                }
            )
            time.sleep(0.1)
        st = controller_stats(master.stats())
        report["inside"] = {
            "samples": samples,
            "peak_force_n": st["peak_force_n"],
            "fixture_kinds": st["fixture_kinds"],
            "travel_mm": max(math.dist(s["tool_mm"], tip_mm) for s in samples if s["tool_mm"]),
        }
        # 5: the sphere 20 mm away (surface to tool), pulling with `stiffness`, then with
        # the default stiffness (1 N/mm: clamped)
        for label, k in (("outside", stiffness), ("outside_default", None)):
            tool = controller_stats(master.stats())["tool_mm"]
            centre = (tool[0] + 40.0, tool[1], tool[2])
            master.send(point_list(centre, 20.0, k))
            time.sleep(0.5)
            rows = []
            for _ in range(15):
                st = controller_stats(master.stats())
                rows.append(
                    {"tool_mm": st["tool_mm"], "force_n": st["force_n"], "gain": st["fixture_gain"]}
                )
                time.sleep(0.1)
            report[label] = {
                "centre_mm": centre,
                "radius_mm": 20.0,
                "stiffness": k,
                "scale": st["fixture_map"]["scale"],
                "rows": rows,
                "max_force_n": st["max_force_n"] if "max_force_n" in st else 10.0,
            }
        report["slave_tip"] = controller_stats(master.stats())["slave_tip"]
        report["master_statuses"] = master.statuses[-10:]
    finally:
        slicer.client.stop()
        master.client.stop()
        stop_processes(procs)
        report["exit_codes"] = [p.returncode for p in procs]
    return report


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--slave", type=Path, default=ROOT / "configs" / "slave.yaml")
    p.add_argument("--master", type=Path, default=ROOT / "configs" / "master.yaml")
    p.add_argument("--seconds", type=float, default=10.0, help="the motion watched (10: a lap)")
    p.add_argument(
        "--stiffness",
        type=float,
        default=0.02,
        help="N per mm of master motion for the sphere 20 mm away",
    )
    p.add_argument("--lo-up", action="store_true", help="bring the loopback interface up first")
    p.add_argument("--out-dir", type=Path, default=Path("."), help="the daemons' logs")
    p.add_argument("--json", type=Path, default=None, help="write the report here")
    args = p.parse_args(argv)
    if args.lo_up:
        loopback_up()
    args.out_dir.mkdir(parents=True, exist_ok=True)
    report = run(args.slave, args.master, args.seconds, args.stiffness, args.out_dir)
    text = json.dumps(report, indent=1)
    if args.json is not None:
        args.json.write_text(text)
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
