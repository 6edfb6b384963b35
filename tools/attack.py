#!/usr/bin/env python3
"""Hostile input against running daemons: every case that was once a bug, replayed and measured.

Loopback only (127.0.0.1, free ports), every loop bounded in count and time. Two rigs of
``occd`` processes started from copies of ``configs/`` (tools/loopback.py):

``ready``
    The slave alone, READY (servos off, nothing to follow), with an operator client. The TCP
    cases run against its Slicer/operator port: its joints must not move at all.
``pair``
    Slave and master RUNNING, the master streaming POSITION at 500 Hz over UDP. The UDP cases run
    against the slave's stream port: the slave must follow its master and nobody else.

Each case measures, in one run of the daemon, a baseline window and then the attack window:
the loop's lateness p99 / p99.9 in each (from two ``GetStats Histogram="lateness"`` snapshots
subtracted, so the attack window holds only the attack's ticks), the daemon's RSS before and
after, whether it is alive and answers a GET_STATUS on a fresh connection afterwards, whether
anything moved, and the counter that proves the daemon saw and refused the attack. The verdict
(PASS/FAIL) is made of those deterministic checks only; timings are reported, not judged,
except the garbage flood, whose lateness bar (p99.9 within 2x of the baseline, issue 8) is
shown beside the verdict.

Cases (``--case NAME`` to run some; ``--list`` to list them):

- ``cmd-ff-name``: STRING ``CMD_`` + 16 bytes 0xff as device name (answered, not fatal);
- ``status-ff-name``: GET_STATUS with a 20-byte 0xff device name (answered);
- ``xml-entities``: a "billion laughs" ``CMD_`` STRING (refused before parsing);
- ``xml-oversize``: an XML command over 8 KiB (refused);
- ``body-200mib``: a header declaring a 200 MiB body (refused by the size limit, no memory);
- ``body-trickle``: a body just under the size limit, trickled in (taken, memory given back);
- ``slowloris``: clients sending 1 byte per 100 ms fill every free slot; fresh clients (Slicer-
  like and an operator) must get in and be answered once the message timeout frees the slots;
- ``no-read``: clients that never read fill every free slot; the same check after the
  send-stall timeout;
- ``udp-foreign``: a second local sender streams plausible POSITIONs with plausible message IDs
  while the master streams (refused as ``foreign``; the slave follows its master only);
- ``udp-far-ahead``: one datagram with a message ID far ahead, spoofed from the master's own
  address (raw socket; refused as implausible, no stop, no jump);
- ``udp-v1-silent``: the master frozen (SIGSTOP) while header-version-1 POSITIONs (no message ID)
  are spoofed from its address: the slave must hold and latch as for a dead master;
- ``udp-flood``: garbage datagrams at the sender's full rate from an allowed address while the
  master streams.

``--quick`` (CI, tests/tools/test_attack.py) shortens every window to about a second and lowers
the slave's ``message_timeout_s``/``send_stall_timeout_s`` (1.5 s / 1 s instead of 10 s / 5 s),
so the slot cases finish in seconds; the default run keeps the shipped configuration.

Examples::

    python tools/attack.py                  # every case, 5 s windows, table on stdout
    python tools/attack.py --quick          # every case, ~1 s windows (CI)
    python tools/attack.py --case udp-flood --attack-s 5 --json /tmp/attack.json

Exit code 0 when every case passed, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
if str(ROOT) not in sys.path:
    sys.path.insert(1, str(ROOT))

from loopback import pair_configs, wait_port, write_yaml  # noqa: E402
from slicer_standin import SlicerStandIn  # noqa: E402
from soaklib.daemons import start_occd, stop_proc  # noqa: E402

import igtl  # noqa: E402
from occ.core.stats import Histogram  # noqa: E402

#: the issue's bar for the garbage flood: lateness p99.9 under attack within 2x the baseline
FLOOD_BAR = 2.0
#: a joint that moves shows in the tip; the slave's tip under a steered sample moves by mm
TIP_TOLERANCE_MM = 0.5
HOLD_TOLERANCE_MM = 0.05


class AttackError(RuntimeError):
    """The harness itself could not do what it needed (a daemon did not start, ...)."""


# =============================================================================================
# settings and results
# =============================================================================================


@dataclass
class Settings:
    quick: bool
    baseline_s: float
    attack_s: float
    out: Path
    #: the slave's tcp-server timeouts as configured for the run (None: the shipped ones)
    message_timeout_s: float | None = None
    send_stall_timeout_s: float | None = None


@dataclass
class Row:
    case: str
    rig: str
    base_p99: float | None = None
    base_p999: float | None = None
    atk_p99: float | None = None
    atk_p999: float | None = None
    rss_before_mib: float | None = None
    rss_after_mib: float | None = None
    alive: bool = False
    answered: bool = False
    moved: str = "?"
    not_moved: bool = False
    counter: str = ""
    check: bool = False
    note: str = ""
    timing_bar: str = ""  # the flood's 2x bar, reported beside the verdict
    #: what went wrong beyond the deterministic checks (a stop, the timing bar): FAIL too
    problems: list[str] = field(default_factory=list)
    skipped: str = ""
    details: dict[str, Any] = field(default_factory=dict)

    @property
    def ratio(self) -> float | None:
        if self.base_p999 and self.atk_p999 is not None:
            return self.atk_p999 / self.base_p999
        return None

    @property
    def passed(self) -> bool:
        return bool(self.skipped) or (self.deterministic_ok and not self.problems)

    @property
    def deterministic_ok(self) -> bool:
        """The checks that do not depend on timing (what the CI test asserts)."""
        return self.alive and self.answered and self.not_moved and self.check

    @property
    def verdict(self) -> str:
        if self.skipped:
            return "SKIP"
        return "PASS" if self.passed else "FAIL"


# =============================================================================================
# raw OpenIGTLink bytes (what a hostile peer can send, not what our codec would build)
# =============================================================================================


def with_device_name(data: bytes, name: bytes) -> bytes:
    """``data`` (a packed message) with its 20-byte header device name replaced by ``name``.
    The header CRC field covers the body only, so the message stays valid."""
    return data[:14] + name.ljust(20, b"\0")[:20] + data[34:]


def header_only(type_name: str, body_size: int, version: int = 1) -> bytes:
    """A 58-byte header declaring ``body_size`` bytes that will never all come."""
    return struct.pack(">H12s20sQQQ", version, type_name.encode(), b"Attack", 0, body_size, 0)


def raw_message(type_name: str, body: bytes, device: str = "Blob") -> bytes:
    """A complete v1 message of an unregistered type: the daemon decodes it as RawMessage."""
    crc = igtl.wire.crc64(body)
    head = struct.pack(">H12s20sQQQ", 1, type_name.encode(), device.encode(), 0, len(body), crc)
    return head + body


def billion_laughs() -> str:
    ents = ['<!ENTITY lol "lol">'] + [
        f'<!ENTITY lol{i} "{("&lol%s;" % ("" if i == 1 else i - 1)) * 10}">' for i in range(1, 10)
    ]
    return f'<?xml version="1.0"?><!DOCTYPE lolz [{"".join(ents)}]><Command Name="&lol9;"/>'


def cmd_string(text: str, uid: str = "1") -> igtl.Message:
    return igtl.StringMessage(text, device_name=f"CMD_{uid}", header_version=2)


def get_status(device: str = "", version: int = 1) -> igtl.Message:
    cls = igtl.REGISTRY["GET_STATUS"]
    return cls(type_name="GET_STATUS", device_name=device, header_version=version)


def position(seq: int | None, pos_mm: tuple[float, float, float]) -> igtl.Message:
    """A POSITION as the master sends it (24-byte layout, run=1); v1 without ``seq``."""
    if seq is None:
        return igtl.PositionMessage(
            pos_mm,
            (0.0, 0.0, 0.0, 1.0),
            24,
            device_name="Master",
            timestamp=time.time(),
            header_version=1,
        )
    return igtl.PositionMessage(
        pos_mm,
        (0.0, 0.0, 0.0, 1.0),
        24,
        device_name="Master",
        timestamp=time.time(),
        header_version=2,
        message_id=seq,
        metadata={"run": "1", "clutch": "0"},
    )


class Spoofer:
    """UDP datagrams with any source address and port on loopback (a raw socket: root or
    CAP_NET_RAW). This is how a peer on the robot's computer can pose as the master."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_RAW)

    def send(self, payload: bytes, src: tuple[str, int], dst: tuple[str, int]) -> None:
        udp = struct.pack(">HHHH", src[1], dst[1], 8 + len(payload), 0)  # checksum 0: none
        ip = struct.pack(
            ">BBHHHBBH4s4s",
            0x45,
            0,
            20 + len(udp) + len(payload),
            0,
            0,
            64,
            socket.IPPROTO_UDP,
            0,
            socket.inet_aton(src[0]),
            socket.inet_aton(dst[0]),
        )  # the kernel fills the id and checksum
        self.sock.sendto(ip + udp + payload, (dst[0], 0))

    def close(self) -> None:
        self.sock.close()


def spoofer() -> Spoofer | None:
    try:
        return Spoofer()
    except PermissionError:
        return None


def ask_status(port: int, device: str, *, slicer: bool, timeout: float = 3.0) -> str | None:
    """One fresh connection: (Slicer's v2 greeting, then) GET_STATUS named ``device``; the
    state the daemon answers, or None (refused, closed, or no answer in ``timeout``)."""
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
            version = 1
            if slicer:
                s.sendall(igtl.StatusMessage(header_version=2, metadata={"dummy": "dummy"}).pack())
                version = 2
            s.sendall(get_status(device, version).pack())
            dec = igtl.StreamDecoder()
            end = time.monotonic() + timeout
            while time.monotonic() < end:
                s.settimeout(max(0.01, end - time.monotonic()))
                data = s.recv(65536)
                if not data:
                    return None
                dec.feed(data)
                for m in dec:
                    if m.message_type == "STATUS" and m.device_name == device:
                        return str(m.error_name)  # type: ignore[attr-defined]
    except OSError:
        return None
    return None


def ask_status_until(
    port: int, device: str, *, slicer: bool, within: float
) -> tuple[str | None, float]:
    """Retry :func:`ask_status` until answered or ``within`` seconds; (state, seconds taken)."""
    t0 = time.monotonic()
    end = t0 + within
    while True:
        st = ask_status(port, device, slicer=slicer, timeout=min(2.0, max(0.2, end - t0)))
        if st is not None or time.monotonic() >= end:
            return st, time.monotonic() - t0
        time.sleep(0.1)  # a refused attempt: try again (bounded by ``within``)


def send_all(
    port: int,
    messages: list[bytes],
    *,
    spread: float = 0.0,
    read_for: float = 1.0,
    want: Callable[[igtl.Message], bool] | None = None,
) -> tuple[int, bool]:
    """Send ``messages`` on one connection, paced evenly over ``spread`` seconds (so the attack
    window is the attack, not a burst and then quiet), and count the replies ``want`` accepts,
    reading for at most ``read_for`` s after the last one; returns (replies, closed by the
    server)."""
    got = 0
    dec = igtl.StreamDecoder(max_body_size=64 * 1024 * 1024)

    def take(s: socket.socket, until: float) -> bool:
        """Read what has arrived until ``until``; False when the server closed."""
        nonlocal got
        while True:
            s.settimeout(max(0.001, until - time.monotonic()))
            try:
                data = s.recv(65536)
            except TimeoutError:
                return True
            except OSError:
                return False
            if not data:
                return False
            dec.feed(data)
            for m in dec:
                if want is None or want(m):
                    got += 1
            if time.monotonic() >= until:
                return True

    with socket.create_connection(("127.0.0.1", port), timeout=5.0) as s:
        t0 = time.monotonic()
        for i, m in enumerate(messages):
            s.sendall(m)
            # pace: read replies meanwhile, until this message's slot in the spread is over
            if spread > 0 and not take(s, t0 + (i + 1) * spread / len(messages)):
                return got, True
        end = time.monotonic() + read_for
        while got < len(messages) and time.monotonic() < end:
            if not take(s, min(end, time.monotonic() + 0.05)):
                return got, True
    return got, False


# =============================================================================================
# the rigs
# =============================================================================================


class Operator(SlicerStandIn):
    """The harness's operator console (commands on the operator interface) with a Slicer of
    its own on the viewer interface that keeps the Tip over time."""

    def __init__(self, port: int, view_port: int | None = None) -> None:
        super().__init__("127.0.0.1", port)
        self.tips: list[tuple[float, tuple[float, ...]]] = []
        self.viewer = Operator(view_port) if view_port is not None else None
        if self.viewer is not None:
            self.viewer.tips = self.tips  # one list, filled by the viewer's connection
            self.viewer._lock = self._lock

    def start(self) -> Operator:
        super().start()
        if self.viewer is not None:
            self.viewer.start()
            self.viewer.connected.wait(10.0)
        return self

    def stop(self) -> Any:
        if self.viewer is not None:
            self.viewer.stop()
        return super().stop()

    def _on_message(self, peer: Any, msg: igtl.Message) -> None:
        super()._on_message(peer, msg)
        if msg.message_type == "TRANSFORM" and msg.device_name == "Tip":
            m = msg.matrix  # type: ignore[attr-defined]
            with self._lock:
                self.tips.append((time.monotonic(), tuple(float(v) for v in m.flatten())))

    def tips_since(self, t: float) -> list[tuple[float, ...]]:
        with self._lock:
            return [m for ts, m in self.tips if ts >= t]

    def command(self, name: str, text: str = "", timeout: float = 10.0) -> igtl.Message:
        cid = self.send_command(name, text)
        reply = self.wait_reply(cid, timeout)
        if reply is None:
            raise AttackError(f"no reply to {name} in {timeout:.0f} s")
        return reply


class Rig:
    """``occd`` processes on free loopback ports plus the operator client (the slave's)."""

    def __init__(self, name: str, settings: Settings, *, with_master: bool) -> None:
        self.name = name
        self.settings = settings
        self.with_master = with_master
        self.out = settings.out / name
        self.out.mkdir(parents=True, exist_ok=True)
        slave, master, self.ports = pair_configs()
        slave["stats"] = {"log_every_s": 3600.0}
        master["stats"] = {"log_every_s": 3600.0}
        # requests (names, XML, bodies) go to the operator interface, where they are parsed;
        # the slot cases fill the 3D Slicer (viewer) interface, whose lock-out they once caused
        tcp = [i for i in slave["interfaces"] if i["transport"] == "tcp-server"]
        self.tcp_iface = next(i for i in tcp if i.get("role") == "operator")
        self.view_iface = next(i for i in tcp if i.get("role") != "operator")
        self.udp_iface = next(i for i in slave["interfaces"] if i["transport"] == "udp")
        for itf in tcp:
            if settings.message_timeout_s is not None:
                itf["message_timeout_s"] = settings.message_timeout_s
            if settings.send_stall_timeout_s is not None:
                itf["send_stall_timeout_s"] = settings.send_stall_timeout_s
        self.robot_name = str(slave["robot"]["name"])  # the device name of its own STATUS
        self.max_clients = int(self.view_iface.get("max_clients", 8))
        self.message_timeout = float(self.view_iface.get("message_timeout_s", 10.0))
        self.send_stall_timeout = float(self.view_iface.get("send_stall_timeout_s", 5.0))
        write_yaml(self.out / "slave.yaml", slave)
        write_yaml(self.out / "master.yaml", master)
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.op: Operator | None = None

    @property
    def slave(self) -> subprocess.Popen[bytes]:
        return self.procs["slave"]

    def start(self, bound_s: float) -> Rig:
        start = "running" if self.with_master else "ready"
        self.procs["slave"] = start_occd(
            str(self.out / "slave.yaml"),
            self.out / "slave.json",
            self.out / "slave.log",
            bound_s,
            start,
        )
        if not wait_port(self.ports["slave_op"], 30.0, self.slave):
            raise AttackError(f"the slave did not start; see {self.out / 'slave.log'}")
        self.op = Operator(self.ports["slave_op"], self.ports["slave_tcp"]).start()
        if not self.op.connected.wait(10.0):
            raise AttackError("the operator client could not connect to the slave")
        if self.with_master:
            self.procs["master"] = start_occd(
                str(self.out / "master.yaml"),
                self.out / "master.json",
                self.out / "master.log",
                bound_s,
            )
            if not wait_port(self.ports["master_tcp"], 30.0, self.procs["master"]):
                raise AttackError(f"the master did not start; see {self.out / 'master.log'}")
            self.wait_following()
        return self

    def wait_following(self, timeout: float = 10.0) -> None:
        """Until the slave RUNS and takes its master's samples (its stream has an owner)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            s = self.stats(histogram=False)
            acc = (s.get("loss") or {}).get("accepted", 0)
            if s["state"] == "RUNNING" and acc > 50 and self.owner(s):
                return
            time.sleep(0.1)
        raise AttackError(f"the slave is not following its master after {timeout:.0f} s")

    def stop(self) -> dict[str, Any]:
        if self.op is not None:
            self.op.stop()
        final: dict[str, Any] = {}
        for name in ("master", "slave"):  # the master first: the slave then sees silence
            proc = self.procs.get(name)
            if proc is not None:
                final[f"{name}_exit"] = stop_proc(proc)
        try:
            s = json.loads((self.out / "slave.json").read_text())
            final["slave_final_state"] = s.get("final_state")
        except (OSError, ValueError):
            final["slave_final_state"] = None
        return final

    # ------------------------------------------------------------------ observations
    def stats(self, histogram: bool = True) -> dict[str, Any]:
        assert self.op is not None
        text = '<Command Name="GetStats" Histogram="lateness"/>' if histogram else ""
        end = time.monotonic() + 10.0
        while True:
            reply = self.op.command("GetStats", text)
            if reply.metadata.get("Status") == "SUCCESS":
                return json.loads(reply.metadata["Message"])
            # a queue full of the attacker's requests answers "busy": ask again, as an operator
            busy = any(w in reply.metadata.get("Message", "") for w in ("full", "busy"))
            if not busy or time.monotonic() > end:
                raise AttackError(f"GetStats refused: {reply.metadata}")
            time.sleep(0.05)

    def master_command(self, name: str) -> str:
        """An operator command to the master (its own TCP port); the reply's text."""
        with SlicerStandIn("127.0.0.1", self.ports["master_tcp"]) as c:
            if not c.connected.wait(5.0):
                raise AttackError("cannot reach the master's operator port")
            r = c.wait_reply(c.send_command(name), 10.0)
            return "no reply" if r is None else str(r.metadata.get("Message", ""))

    def udp_drops(self) -> int | None:
        """The kernel's drop count of the slave's stream socket (/proc/net/udp): datagrams
        that arrived while its receive buffer was full."""
        want = f"0100007F:{int(self.ports['slave_udp']):04X}"
        try:
            for line in Path("/proc/net/udp").read_text().splitlines()[1:]:
                f = line.split()
                if f[1] == want:
                    return int(f[-1])
        except (OSError, ValueError, IndexError):
            return None
        return None

    @staticmethod
    def udp_noports() -> int | None:
        """The kernel's count of datagrams that found no socket to take them (/proc/net/snmp
        Udp NoPorts): where a stream socket is pinned to its master (connected), the kernel
        drops every other sender's datagram and counts it here, machine-wide."""
        try:
            lines = [ln.split() for ln in Path("/proc/net/snmp").read_text().splitlines()]
            names, values = [ln for ln in lines if ln and ln[0] == "Udp:"][:2]
            return int(values[names.index("NoPorts")])
        except (OSError, ValueError, IndexError):
            return None

    def rss_mib(self) -> float | None:
        try:
            for line in Path(f"/proc/{self.slave.pid}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    return round(int(line.split()[1]) / 1024.0, 1)
        except OSError:
            return None
        return None

    def tip(self, after: float, timeout: float = 3.0) -> tuple[float, ...]:
        """The first Tip matrix the slave sends after monotonic time ``after``."""
        assert self.op is not None
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            tips = self.op.tips_since(after)
            if tips:
                return tips[0]
            time.sleep(0.02)
        raise AttackError("no Tip from the slave")

    def owner(self, s: dict[str, Any]) -> tuple[str, int] | None:
        own = s["interfaces"][self.udp_iface["name"]].get("stream_owner")
        return (own[0], int(own[1])) if own else None

    def tcp(self, s: dict[str, Any]) -> dict[str, Any]:
        return s["interfaces"][self.tcp_iface["name"]]

    def view(self, s: dict[str, Any]) -> dict[str, Any]:
        return s["interfaces"][self.view_iface["name"]]

    def udp(self, s: dict[str, Any]) -> dict[str, Any]:
        return s["interfaces"][self.udp_iface["name"]]

    @property
    def udp_addr(self) -> tuple[str, int]:
        return ("127.0.0.1", int(self.ports["slave_udp"]))

    @property
    def tcp_port(self) -> int:
        """The operator interface: requests are parsed there."""
        return int(self.ports["slave_op"])

    @property
    def view_port(self) -> int:
        """The 3D Slicer interface (a viewer)."""
        return int(self.ports["slave_tcp"])


def window(before: dict[str, Any], after: dict[str, Any]) -> tuple[float, float, int]:
    """Lateness p99, p99.9 (µs) and tick count of the ticks between two snapshots."""
    b = {int(k): v for k, v in before["lateness_buckets"].items()}
    a = {int(k): v for k, v in after["lateness_buckets"].items()}
    h = Histogram.from_buckets({i: n - b.get(i, 0) for i, n in a.items()})
    p99, p999 = h.percentiles((99.0, 99.9))
    return round(p99, 1), round(p999, 1), h.count


def delta(before: dict[str, Any], after: dict[str, Any], *path: str) -> int:
    def get(d: dict[str, Any]) -> int:
        for k in path:
            d = d.get(k, {}) if isinstance(d, dict) else {}
        return int(d) if isinstance(d, (int, float)) else 0

    return get(after) - get(before)


def max_shift_mm(tips: list[tuple[float, ...]], ref: tuple[float, ...], axis: int) -> float:
    """Largest move of the tip's translation (axis 0-2, or -1 for the norm) away from ``ref``."""
    worst = 0.0
    for m in tips:
        d = [m[3] - ref[3], m[7] - ref[7], m[11] - ref[11]]
        worst = max(worst, (sum(v * v for v in d) ** 0.5) if axis < 0 else abs(d[axis]))
    return worst


# =============================================================================================
# the cases: each attacks, then says what it saw (counter text, its own check, a note)
# =============================================================================================

Verdict = tuple[str, bool, str]
Attack = Callable[[Rig, Settings, dict[str, Any]], Callable[[dict[str, Any]], Verdict]]


def repeat_count(st: Settings, quick: int, full: int) -> int:
    return quick if st.quick else full


def case_cmd_ff_name(rig: Rig, st: Settings, before: dict[str, Any]) -> Callable[..., Verdict]:
    n = repeat_count(st, 50, 500)
    data = cmd_string('<Command Name="GetState"/>').pack()
    msg = with_device_name(data, b"CMD_" + b"\xff" * 16)
    got, closed = send_all(
        rig.tcp_port,
        [msg] * n,
        spread=st.attack_s,
        read_for=5.0,
        want=lambda m: m.message_type == "STRING" and m.device_name.startswith("ACK_"),
    )

    def judge(after: dict[str, Any]) -> Verdict:
        handled = delta(before, after, "commands", "handled")
        return (
            f"ACK {got}/{n}; commands handled +{handled}",
            got == n and not closed,
            "connection closed by the daemon" if closed else "",
        )

    return judge


def case_status_ff_name(rig: Rig, st: Settings, before: dict[str, Any]) -> Callable[..., Verdict]:
    n = repeat_count(st, 50, 500)
    msg = with_device_name(get_status().pack(), b"\xff" * 20)
    got, closed = send_all(
        rig.tcp_port,
        [msg] * n,
        spread=st.attack_s,
        read_for=5.0,
        want=lambda m: m.message_type == "STATUS" and m.device_name != rig.robot_name,
    )

    def judge(after: dict[str, Any]) -> Verdict:
        handled = delta(before, after, "commands", "handled")
        return (
            f"STATUS {got}/{n}; commands handled +{handled}",
            got == n and not closed,
            "connection closed by the daemon" if closed else "",
        )

    return judge


def _refused_xml(
    rig: Rig, st: Settings, before: dict[str, Any], text: str, expect: str
) -> Callable[..., Verdict]:
    n = repeat_count(st, 20, 200)
    msgs = [cmd_string(text, str(i)).pack() for i in range(n)]
    replies: list[str] = []

    def want(m: igtl.Message) -> bool:
        if m.message_type == "STRING" and m.device_name.startswith("ACK_"):
            replies.append(str(m.string))  # type: ignore[attr-defined]
            return True
        return False

    got, closed = send_all(rig.tcp_port, msgs, spread=st.attack_s, read_for=5.0, want=want)

    def judge(after: dict[str, Any]) -> Verdict:
        refused = delta(before, after, "interfaces", rig.tcp_iface["name"], "refused")
        failed = sum(1 for r in replies if 'Status="FAIL"' in r and expect in r)
        ok = got == n and failed == n and refused == n and not closed
        return (
            f"refused +{refused}; FAIL replies {failed}/{n}",
            ok,
            replies[0][:90] if replies else "no reply",
        )

    return judge


def case_xml_entities(rig: Rig, st: Settings, before: dict[str, Any]) -> Callable[..., Verdict]:
    return _refused_xml(rig, st, before, billion_laughs(), "DOCTYPE")


def case_xml_oversize(rig: Rig, st: Settings, before: dict[str, Any]) -> Callable[..., Verdict]:
    text = '<Command Name="GetState" Pad="' + "x" * 9000 + '"/>'
    return _refused_xml(rig, st, before, text, "too long")


def case_body_200mib(rig: Rig, st: Settings, before: dict[str, Any]) -> Callable[..., Verdict]:
    n = repeat_count(st, 5, 50)
    closed = 0
    t0 = time.monotonic()
    for i in range(n):
        pause = t0 + i * st.attack_s / n - time.monotonic()
        if pause > 0:
            time.sleep(pause)  # the connections spread over the attack window
        with socket.create_connection(("127.0.0.1", rig.tcp_port), timeout=5.0) as s:
            s.sendall(header_only("IMAGE", 200 * 1024 * 1024))
            s.sendall(b"\0" * 4096)  # the start of the body: it must not be buffered
            end = time.monotonic() + 5.0
            while time.monotonic() < end:
                try:
                    data = s.recv(65536)
                except (TimeoutError, OSError):
                    data = b""
                if not data:  # closed by the daemon (the STATUS greeting is read first)
                    closed += 1
                    break

    def judge(after: dict[str, Any]) -> Verdict:
        bad = delta(before, after, "interfaces", rig.tcp_iface["name"], "malformed")
        return (f"malformed +{bad}; closed {closed}/{n}", closed == n and bad >= n, "")

    return judge


def case_body_trickle(rig: Rig, st: Settings, before: dict[str, Any]) -> Callable[..., Verdict]:
    limit = int(rig.tcp_iface.get("max_body_kib", 1024)) * 1024
    body = random.Random(8).randbytes(limit - 1)
    data = raw_message("ATTACKBLOB", body)
    # spread over most of the message timeout (it must complete within it) or the window
    span = min(0.6 * rig.message_timeout, st.attack_s)
    chunks = 32
    step = len(data) // chunks + 1
    with socket.create_connection(("127.0.0.1", rig.tcp_port), timeout=5.0) as s:
        for i in range(chunks):
            s.sendall(data[i * step : (i + 1) * step])
            time.sleep(span / chunks)  # the trickle itself, not a synchronisation
        # the message is complete: the daemon counts it once it has decoded it
        end = time.monotonic() + 5.0
        taken = 0
        while time.monotonic() < end:
            s2 = rig.stats(histogram=False)
            taken = delta(before, s2, "interfaces", rig.tcp_iface["name"], "unexpected")
            if taken:
                break
            time.sleep(0.05)

    def judge(after: dict[str, Any]) -> Verdict:
        bad = delta(before, after, "interfaces", rig.tcp_iface["name"], "malformed")
        return (
            f"unexpected +{taken} (taken, {limit - 1} B body); malformed +{bad}",
            taken == 1 and bad == 0,
            f"trickled in {span:.1f} s",
        )

    return judge


def _fill_slots(
    rig: Rig, st: Settings, before: dict[str, Any], kind: str
) -> Callable[..., Verdict]:
    """Fill every free slot with hostile clients (plus two extra, which must be rejected), then
    ask for GET_STATUS on fresh connections until answered or the bound."""
    socks: list[socket.socket] = []
    stop = threading.Event()
    want = rig.max_clients - 1 + 2  # the operator holds one slot
    for _ in range(want):
        s = socket.socket()
        if kind == "no-read":
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 2048)
        s.settimeout(5.0)
        s.connect(("127.0.0.1", rig.view_port))
        socks.append(s)
    trickle: threading.Thread | None = None
    if kind == "slowloris":
        # a header declaring a 1000-byte body, sent 1 byte per 100 ms: never complete
        payload = header_only("STRING", 1000) + b"\0" * 1000

        def dribble() -> None:
            i = 0
            end = time.monotonic() + bound
            while not stop.is_set() and time.monotonic() < end and i < len(payload):
                for s in list(socks):
                    try:
                        s.send(payload[i : i + 1])
                    except OSError:
                        socks.remove(s)  # closed by the daemon: this one does not come back
                i += 1
                stop.wait(0.1)

        bound = rig.message_timeout + 15.0
        trickle = threading.Thread(target=dribble, daemon=True)
        trickle.start()
        within = rig.message_timeout + 10.0
    else:
        # ask for replies and never read them: the daemon's send buffer fills, then it stalls
        q = get_status("NoRead").pack() * 200
        for s in socks:
            try:
                s.setblocking(False)
                s.send(q)
            except OSError:
                pass
        within = rig.send_stall_timeout + (5.0 if st.quick else 20.0)
    t0 = time.monotonic()
    # the daemon has taken (or refused) them all once every slot is held
    end = t0 + 5.0
    while rig.view(rig.stats(histogram=False))["peers"] < rig.max_clients:
        if time.monotonic() > end:
            break
        time.sleep(0.05)
    slicer, t_slicer = ask_status_until(rig.view_port, "FreshSlicer", slicer=True, within=within)
    operator, t_op = ask_status_until(
        rig.tcp_port,
        "FreshOperator",
        slicer=False,
        within=max(1.0, within - (time.monotonic() - t0)),
    )
    stop.set()
    if trickle is not None:
        trickle.join(5.0)
    for s in socks:
        s.close()

    def judge(after: dict[str, Any]) -> Verdict:
        t = lambda k: delta(before, after, "interfaces", rig.view_iface["name"], k)  # noqa: E731
        freed = t("slow_message_closed") if kind == "slowloris" else t("evicted_not_reading")
        timeout = rig.message_timeout if kind == "slowloris" else rig.send_stall_timeout
        ok = slicer is not None and operator is not None and freed >= 1 and t("rejected") >= 1
        return (
            f"{'slow_message_closed' if kind == 'slowloris' else 'evicted_not_reading'} "
            f"+{freed}; rejected +{t('rejected')}",
            ok,
            f"{want} hostile clients; fresh Slicer answered after {t_slicer:.1f} s, operator "
            f"after {t_slicer + t_op:.1f} s (timeout {timeout:g} s)"
            if ok
            else f"fresh Slicer: {slicer}, operator: {operator} within {within:.0f} s",
        )

    return judge


def case_slowloris(rig: Rig, st: Settings, before: dict[str, Any]) -> Callable[..., Verdict]:
    return _fill_slots(rig, st, before, "slowloris")


def case_no_read(rig: Rig, st: Settings, before: dict[str, Any]) -> Callable[..., Verdict]:
    return _fill_slots(rig, st, before, "no-read")


def _stream_for(seconds: float, rate_hz: float, send: Callable[[int], None]) -> int:
    """Call ``send(i)`` at ``rate_hz`` for ``seconds`` (bounded count); returns how many."""
    n = int(seconds * rate_hz)
    t0 = time.monotonic()
    for i in range(n):
        send(i)
        wait = t0 + (i + 1) / rate_hz - time.monotonic()
        if wait > 0:
            time.sleep(wait)  # pacing of the stream itself
    return n


def case_udp_foreign(rig: Rig, st: Settings, before: dict[str, Any]) -> Callable[..., Verdict]:
    seq0 = int(before["controller"].get("last_seq") or 0)
    t_start = time.monotonic()
    ref = rig.tip(t_start)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))

        def send(i: int) -> None:
            # what the master would send next, 30 mm higher: followed, it lifts the tip 3 mm
            seq = seq0 + int((time.monotonic() - t_start) * 500) + 1
            s.sendto(position(seq, (0.0, 50.0, 50.0)).pack(), rig.udp_addr)

        noports0 = rig.udp_noports()
        n = _stream_for(st.attack_s, 500.0, send)
        noports1 = rig.udp_noports()
        sender = s.getsockname()
    tips = rig.op.tips_since(t_start) if rig.op else []
    shift = max_shift_mm(tips, ref, 2)
    # the slave's socket is pinned to its master: the kernel drops the others (NoPorts)
    filtered = 0 if noports0 is None or noports1 is None else min(n, noports1 - noports0)

    def judge(after: dict[str, Any]) -> Verdict:
        foreign = delta(before, after, "interfaces", rig.udp_iface["name"], "foreign")
        owner = rig.owner(after)
        ok = foreign + filtered >= n and owner != tuple(sender) and after["state"] == "RUNNING"
        return (
            f"foreign +{foreign}, dropped by the kernel +{filtered} (of {n})",
            ok,
            f"owner {owner[1] if owner else None} (attacker {sender[1]}); tip z moved "
            f"{shift:.3f} mm over {len(tips)} Tips; state {after['state']}",
        )

    rig_shift[0] = shift
    return judge


#: the last steering case's tip shift, read by the "moved" check of the pair rig
rig_shift = [0.0]


def case_udp_far_ahead(rig: Rig, st: Settings, before: dict[str, Any]) -> Callable[..., Verdict]:
    sp = spoofer()
    owner = rig.owner(before)
    if sp is None or owner is None:
        raise SkipCase("needs a raw socket (root or CAP_NET_RAW) to pose as the master")
    seq = int(before["controller"].get("last_seq") or 0) + 1_000_000
    t0 = time.monotonic()
    ref = rig.tip(t0)
    try:
        sp.send(position(seq, (0.0, 50.0, 50.0)).pack(), owner, rig.udp_addr)
    finally:
        sp.close()
    end = time.monotonic() + max(1.0, st.attack_s)
    implausible = 0
    while time.monotonic() < end:  # the daemon counts it when its loop drains it
        s2 = rig.stats(histogram=False)
        implausible = delta(before, s2, "loss", "implausible_seq")
        if implausible:
            break
        time.sleep(0.05)
    # three Tips after it (10 Hz): a jump would show
    end = time.monotonic() + 3.0
    while rig.op is not None and len(rig.op.tips_since(t0)) < 3 and time.monotonic() < end:
        time.sleep(0.02)
    rig_shift[0] = max_shift_mm(rig.op.tips_since(t0) if rig.op else [], ref, 2)

    def judge(after: dict[str, Any]) -> Verdict:
        trips = delta(before, after, "loss", "trips")
        lost = delta(before, after, "loss", "lost_total")
        # ``lost`` is reported, not judged: a stall of either loop on a busy machine can lose a
        # packet by itself; the far-ahead number must not count as loss (a stop would show it)
        ok = implausible == 1 and trips == 0 and after["state"] == "RUNNING"
        return (
            f"implausible_seq +{implausible}; trips +{trips}; lost +{lost}",
            ok,
            f"seq +1,000,000 spoofed from the master's {owner[0]}:{owner[1]}; state "
            f"{after['state']}",
        )

    return judge


def case_udp_v1_silent(rig: Rig, st: Settings, before: dict[str, Any]) -> Callable[..., Verdict]:
    sp = spoofer()
    owner = rig.owner(before)
    if sp is None or owner is None:
        raise SkipCase("needs a raw socket (root or CAP_NET_RAW) to pose as the master")
    master = rig.procs["master"]
    freeze_s = max(0.5, st.attack_s)
    os.kill(master.pid, signal.SIGSTOP)
    t0 = time.monotonic()
    try:
        n = _stream_for(
            freeze_s,
            500.0,
            lambda i: sp.send(position(None, (0.0, 50.0, 50.0)).pack(), owner, rig.udp_addr),
        )
    finally:
        os.kill(master.pid, signal.SIGCONT)
        sp.close()
    # the Tips while it should hold: from 50 ms after the freeze (the hold starts at 7 ms and
    # the drive settles) to the end of the freeze
    held = [m for ts, m in (rig.op.tips if rig.op else []) if t0 + 0.05 <= ts <= t0 + freeze_s]
    shift = max_shift_mm(held, held[0], -1) if held else 0.0
    rig_shift[0] = shift if shift > HOLD_TOLERANCE_MM else 0.0
    s_mid = rig.stats(histogram=False)
    state, alert = s_mid["state"], s_mid.get("last_alert", "")
    # the operator answers the stop, as after any loss stop, so the next cases find it running
    # the frozen master's drive stopped itself (heartbeat): it is in FAULT, as after any freeze
    # longer than its heartbeat; its operator resets it, then the slave's answers the stop
    for cmd in ("Reset", "Enable", "Run"):
        rig.master_command(cmd)
    if state == "STOPPED":
        assert rig.op is not None
        rig.op.command("Run")
    rig.wait_following()

    def judge(after: dict[str, Any]) -> Verdict:
        trips = delta(before, after, "loss", "trips")
        unseq = delta(before, after, "loss", "unsequenced")
        ok = (
            state == "STOPPED"
            and "no packet for" in alert
            and trips == 1
            and unseq >= 1
            and shift <= HOLD_TOLERANCE_MM
        )
        return (
            f"unsequenced +{unseq}/{n}; trips +{trips}",
            ok,
            f"master frozen {freeze_s:.1f} s: slave {state} ({alert[:70]}); tip moved "
            f"{shift:.3f} mm while holding; Run -> following again",
        )

    return judge


def case_udp_flood(rig: Rig, st: Settings, before: dict[str, Any]) -> Callable[..., Verdict]:
    rng = random.Random(88)
    junk: list[bytes] = []
    for i in range(256):
        if i % 2:
            # a real-looking POSITION header whose body does not match its CRC
            good = position(i, (0.0, 0.0, 0.0)).pack()
            junk.append(good[:-4] + rng.randbytes(4))
        else:
            junk.append(rng.randbytes(rng.randint(1, 1400)))
    limit = int(st.attack_s * 400_000)  # a bound on the count whatever this machine's speed
    t0 = time.monotonic()
    ref = rig.tip(t0)
    drops0 = rig.udp_drops()
    noports0 = rig.udp_noports()
    sent = 0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        end = t0 + st.attack_s
        while sent < limit and time.monotonic() < end:
            for j in range(256):
                try:
                    s.sendto(junk[j], rig.udp_addr)
                except OSError:  # ENOBUFS and the like: the flood goes on
                    pass
            sent += 256
    elapsed = time.monotonic() - t0
    drops1 = rig.udp_drops()
    noports1 = rig.udp_noports()
    kernel = None if drops0 is None or drops1 is None else drops1 - drops0
    filtered = None if noports0 is None or noports1 is None else noports1 - noports0
    rig_shift[0] = 0.0  # the master moves the slave: only its own path is allowed (below)

    def judge(after: dict[str, Any]) -> Verdict:
        bad = delta(before, after, "interfaces", rig.udp_iface["name"], "malformed")
        trips = delta(before, after, "loss", "trips")
        holds = delta(before, after, "loss", "holds")
        owner_kept = rig.owner(after) == rig.owner(before)
        # read and refused as malformed, or (socket pinned to the master) never let in
        ok = (bad >= 1 or (filtered or 0) >= sent // 2) and owner_kept
        tips = rig.op.tips_since(t0) if rig.op else []
        if after["state"] != "RUNNING" or trips:
            flood_problems.append(
                f"the slave latched {after['state']}: {after.get('last_alert', '')[:80]}"
            )
        return (
            f"malformed +{bad} of {sent} sent ({sent / elapsed:,.0f}/s), not let in +{filtered}, "
            f"buffer drops +{kernel}; holds +{holds}; trips +{trips}",
            ok,
            f"state {after['state']}; owner kept {owner_kept}; tip z moved "
            f"{max_shift_mm(tips, ref, 2):.3f} mm",
        )

    return judge


#: what the flood did wrong beyond its deterministic checks (read by run_case)
flood_problems: list[str] = []


class SkipCase(Exception):
    """The case cannot run here (e.g. no raw socket); reported as SKIP with the reason."""


CASES: dict[str, tuple[str, Attack]] = {
    "cmd-ff-name": ("ready", case_cmd_ff_name),
    "status-ff-name": ("ready", case_status_ff_name),
    "xml-entities": ("ready", case_xml_entities),
    "xml-oversize": ("ready", case_xml_oversize),
    "body-200mib": ("ready", case_body_200mib),
    "body-trickle": ("ready", case_body_trickle),
    "slowloris": ("ready", case_slowloris),
    "no-read": ("ready", case_no_read),
    "udp-foreign": ("pair", case_udp_foreign),
    "udp-far-ahead": ("pair", case_udp_far_ahead),
    "udp-v1-silent": ("pair", case_udp_v1_silent),
    "udp-flood": ("pair", case_udp_flood),
}


# =============================================================================================
# running a case: baseline window, attack window, then the checks
# =============================================================================================


def run_case(name: str, rig: Rig, st: Settings) -> Row:
    row = Row(name, rig.name)
    _, attack = CASES[name]
    s0 = rig.stats()
    # one event (e.g. a VM pause tripping the supervisor) must not spill into the next cases:
    # bring the rig back to its starting state first, as its operator would
    if rig.name == "ready" and s0["state"] != "READY":
        assert rig.op is not None
        rig.op.command("Reset")
        s0 = rig.stats()
    elif rig.name == "pair" and s0["state"] != "RUNNING":
        assert rig.op is not None
        rig.op.command("Run")
        rig.wait_following()
        s0 = rig.stats()
    row.rss_before_mib = rig.rss_mib()
    t_ref = time.monotonic()
    ref = rig.tip(t_ref) if rig.name == "ready" else None
    time.sleep(st.baseline_s)  # the baseline window: the daemon left alone
    s1 = rig.stats()
    row.base_p99, row.base_p999, n_base = window(s0, s1)
    rig_shift[0] = 0.0
    try:
        judge = attack(rig, st, s1)
    except SkipCase as why:
        row.skipped = str(why)
        row.note = str(why)
        return row
    s2 = rig.stats()
    row.atk_p99, row.atk_p999, n_atk = window(s1, s2)
    row.rss_after_mib = rig.rss_mib()
    row.counter, row.check, row.note = judge(s2)
    row.alive = rig.slave.poll() is None
    row.answered = ask_status(rig.tcp_port, "AfterAttack", slicer=False, timeout=5.0) is not None
    if ref is not None:
        # READY: nothing may move at all; the Tip is the forward kinematics of the joints read
        now = rig.tip(time.monotonic())
        row.not_moved = now == ref
        row.moved = "unchanged" if row.not_moved else "MOVED"
        if s2["state"] != "READY":
            row.problems.append(f"state READY -> {s2['state']}: {s2.get('last_alert', '')}")
    else:
        row.not_moved = rig_shift[0] <= TIP_TOLERANCE_MM
        row.moved = (
            f"follows master only ({rig_shift[0]:.2f} mm)"
            if row.not_moved
            else f"STEERED ({rig_shift[0]:.2f} mm)"
        )
    if name == "udp-flood":
        row.problems += flood_problems
        flood_problems.clear()
        if row.ratio is not None:
            met = row.ratio <= FLOOD_BAR
            row.timing_bar = f"{'met' if met else 'NOT met'} (bar {FLOOD_BAR:g}x)"
            if not met:
                row.problems.append(
                    f"lateness p99.9 {row.ratio:.1f}x the baseline (bar {FLOOD_BAR:g}x)"
                )
    row.details = {"ticks_baseline": n_base, "ticks_attack": n_atk, "state_after": s2["state"]}
    return row


def run(names: list[str], st: Settings) -> tuple[list[Row], dict[str, Any]]:
    rows: list[Row] = []
    finals: dict[str, Any] = {}
    for rig_name in ("ready", "pair"):
        todo = [n for n in names if CASES[n][0] == rig_name]
        if not todo:
            continue
        # a hard bound for the daemons themselves: they stop even if this process dies
        bound = 60.0 + len(todo) * (st.baseline_s + st.attack_s + 45.0)
        rig = Rig(rig_name, st, with_master=(rig_name == "pair"))
        try:
            rig.start(bound)
            for n in todo:
                print(f"[attack] {n} ...", file=sys.stderr, flush=True)
                rows.append(run_case(n, rig, st))
                print(
                    f"[attack] {n}: {rows[-1].verdict} {rows[-1].counter}",
                    file=sys.stderr,
                    flush=True,
                )
                if rig.slave.poll() is not None:
                    break  # the daemon is dead: the other cases of this rig cannot run
        finally:
            finals[rig_name] = rig.stop()
    return rows, finals


# =============================================================================================
# output
# =============================================================================================


def fmt(v: float | None, unit: str = "") -> str:
    return "-" if v is None else f"{v:,.0f}{unit}" if v >= 100 else f"{v:.1f}{unit}"


def table(rows: list[Row]) -> str:
    head = (
        "| case | rig | lateness p99 / p99.9 µs, baseline | attack | p99.9 ratio | "
        "RSS MiB before / after | alive, answered | moved | counter | verdict |"
    )
    lines = [head, "|" + "---|" * 10]
    for r in rows:
        ratio = "-" if r.ratio is None else f"{r.ratio:.2f}x"
        if r.timing_bar:
            ratio += f" {r.timing_bar}"
        lines.append(
            f"| {r.case} | {r.rig} | {fmt(r.base_p99)} / {fmt(r.base_p999)} | "
            f"{fmt(r.atk_p99)} / {fmt(r.atk_p999)} | {ratio} | "
            f"{fmt(r.rss_before_mib)} / {fmt(r.rss_after_mib)} | "
            f"{'yes' if r.alive else 'NO'}, {'yes' if r.answered else 'NO'} | {r.moved} | "
            f"{r.counter} | **{r.verdict}** |"
        )
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--quick", action="store_true", help="~1 s windows and short slave timeouts (CI)"
    )
    p.add_argument(
        "--case",
        action="append",
        choices=list(CASES),
        default=None,
        help="run this case (repeatable; default: all)",
    )
    p.add_argument("--list", action="store_true", help="list the cases and exit")
    p.add_argument(
        "--baseline-s", type=float, default=None, help="baseline window (default 5, quick 1)"
    )
    p.add_argument(
        "--attack-s", type=float, default=None, help="attack window (default 5, quick 1)"
    )
    p.add_argument("--out", type=Path, default=None, help="folder for configs, logs, stats")
    p.add_argument("--json", type=Path, default=None, help="write the rows as JSON here")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.list:
        for name, (rig, _) in CASES.items():
            print(f"{name:16s} {rig}")
        return 0
    out = args.out or Path(tempfile.mkdtemp(prefix="occ-attack-"))
    out.mkdir(parents=True, exist_ok=True)
    dflt = 1.0 if args.quick else 5.0
    st = Settings(
        quick=args.quick,
        baseline_s=args.baseline_s if args.baseline_s is not None else dflt,
        attack_s=args.attack_s if args.attack_s is not None else dflt,
        out=out,
        message_timeout_s=1.5 if args.quick else None,
        send_stall_timeout_s=1.0 if args.quick else None,
    )
    names = args.case or list(CASES)
    rows, finals = run(names, st)
    print(table(rows))
    for r in rows:
        if r.note or r.problems:
            print(f"- {r.case}: {'; '.join([r.note, *r.problems]).strip('; ')}")
    print(f"daemons: {json.dumps(finals)}; files in {out}")
    if args.json is not None:
        args.json.write_text(
            json.dumps(
                {
                    "settings": {k: str(v) for k, v in asdict(st).items()},
                    "rows": [dict(asdict(r), verdict=r.verdict, ratio=r.ratio) for r in rows],
                    "daemons": finals,
                },
                indent=2,
            )
        )
    return 0 if all(r.passed for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
