"""Setting up CiA 402 nodes: the driver's parameters and its bus budget, what it knows of
each node, and each node's configuration over SDO (occ/drivers/cia402.py, whose module
docstring describes all of it).

Nothing here runs on the loop: parameters are read when the driver is built (``occd --check``
too), the nodes configured when it is. The EDS the emulator answers from ships with the driver
(``occ/drivers/eds/drive.eds``, package data): a node's ``eds`` names a file, or one of these.
"""

from __future__ import annotations

import logging
import math
import socket as _socket
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from importlib.resources import files
from pathlib import Path
from typing import Any

import can

from occ.drivers.cia402_protocol import (
    COB_RPDO,
    COB_SDO_RX,
    COB_TPDO,
    CW_DISABLE_VOLTAGE,
    CW_FAULT_RESET,
    MODE_CSP,
    MODE_CST,
    NMT_OPERATIONAL,
    NMT_STATES,
    STATUS_WORDS,
    cia402_state,
    emcy_meaning,
    frame_bits,
    master_sends,
    sdo_abort_meaning,
)
from occ.drivers.eds_lines import eds_refusal
from occ.errors import DriverError
from occ.joint import Joint

logger = logging.getLogger("occ.drivers.cia402")

#: a SocketCAN error frame's bus-off class, the mask of every class, and the socket option
#: that lets error frames through (linux/can/error.h, linux/can/raw.h)
CAN_ERR_BUSOFF = 0x40
CAN_ERR_MASK = 0x1FFFFFFF
CAN_RAW_ERR_FILTER = 2

#: the statusword mask and value of OPERATION ENABLED
OE_MASK, OE_VALUE = next((m, v) for m, v, name in STATUS_WORDS if name == "OPERATION ENABLED")

#: the EDS files shipped with the driver, and the one a node without ``eds`` uses
EDS_DIR = Path(str(files("occ.drivers") / "eds"))
DEFAULT_EDS = EDS_DIR / "drive.eds"

NODE_KEYS = {"node_id", "counts_per_unit", "eds", "rated_torque", "second_sensor"}
SECOND_KEYS = {"index", "subindex", "counts_per_unit", "tolerance", "latency_ms"}
SECOND_TOLERANCE = {"revolute": 0.01, "prismatic": 0.001}

RPDO_CSP = struct.Struct("<Hi")  # controlword, target position (counts)
RPDO_CST = struct.Struct("<Hh")  # controlword, target torque (per mille)
TPDO1 = struct.Struct("<Hih")  # statusword, position actual, torque actual
TPDO2 = struct.Struct("<i")  # velocity actual (counts/s)
TPDO2_SECOND = struct.Struct("<ii")  # velocity actual, second sensor (counts)
EMCY = struct.Struct("<HB")  # error code, error register
#: the objects' sizes in bits as mapped (index, subindex) -> bits
PDO_BITS = {0x6040: 16, 0x607A: 32, 0x6071: 16, 0x6041: 16, 0x6064: 32, 0x6077: 16, 0x606C: 32}


def resolve_eds(raw: Any) -> Path:
    """A node's ``eds``: a path (absolute, or relative to the working directory), or the
    name of an EDS shipped with the driver (``drive.eds``: the emulator's); none: that one."""
    if raw is None:
        return DEFAULT_EDS
    path = Path(str(raw))
    if path.is_absolute() or path.exists():
        return path
    shipped = EDS_DIR / path.name
    return shipped if shipped.exists() else path


@lru_cache(maxsize=16)
def load_od(path: str) -> Any:
    import canopen

    return canopen.import_od(path)


def bus_load(
    *,
    nodes: int,
    period: float,
    sync_every: int,
    bitrate: float,
    effort: bool = False,
    second_sensors: int = 0,
    node_heartbeat_ms: float = 10.0,
    master_heartbeat_ms: float = 12.5,
) -> tuple[float, str]:
    """The bus load (a fraction) of ``nodes`` CiA 402 nodes cycled as this driver does, and
    how it is made up (module docstring, "Bus budget")."""
    rpdo = frame_bits(RPDO_CST.size if effort else RPDO_CSP.size)
    tpdo1 = frame_bits(TPDO1.size)
    tpdo2 = frame_bits(TPDO2.size)
    tpdo2_second = frame_bits(TPDO2_SECOND.size)
    sync = frame_bits(0)
    per_cycle = nodes * (rpdo + tpdo1 + tpdo2) + second_sensors * (tpdo2_second - tpdo2) + sync
    cycle_s = period * sync_every
    bits_per_s = per_cycle / cycle_s
    heartbeat = frame_bits(1)
    if node_heartbeat_ms > 0:
        bits_per_s += nodes * heartbeat / (node_heartbeat_ms * 1e-3)
    if master_heartbeat_ms > 0:
        bits_per_s += heartbeat / (master_heartbeat_ms * 1e-3)
    load = bits_per_s / bitrate
    detail = (
        f"{nodes} node{'s' if nodes != 1 else ''} x (RPDO {rpdo} + TPDO1 {tpdo1} + TPDO2 "
        f"{tpdo2} bits) + SYNC {sync} bits every {cycle_s * 1e3:g} ms, plus heartbeats: "
        f"{bits_per_s / 1e3:.0f} kbit/s of {bitrate / 1e3:g} kbit/s (worst-case frames, "
        f"55 + 10 x bytes bits)"
    )
    return load, detail


class Node:
    """What the driver knows of one node (joint ``index``)."""

    __slots__ = (
        "index", "node_id", "joint", "cpu", "torque_scale", "eds", "od", "second",
        "statusword", "nmt", "hb_at", "tpdo_at", "emcy_pending", "last_emcy", "counts",
        "second_counts", "second_since", "tpdo1", "tpdo2", "emcys", "heartbeats",
        "target", "rpdo", "rpdo_msg", "cw", "owed_since", "sampled_at", "marks",
    )  # fmt: skip

    def __init__(self, index: int, joint: Joint, spec: Mapping[str, Any], effort: bool) -> None:
        self.index = index
        self.joint = joint.name
        self.node_id = int(spec["node_id"])
        self.cpu = float(spec["counts_per_unit"])
        rated = float(spec.get("rated_torque", 1.0))
        # per mille -> effort units, in the joint's sense (reversed with its counts)
        self.torque_scale = rated / 1000.0 * (1.0 if self.cpu > 0.0 else -1.0)
        self.eds = resolve_eds(spec.get("eds"))
        self.od: Any = None
        self.second: tuple[int, int, float, float, float] | None = None
        self.rpdo = bytearray((RPDO_CST if effort else RPDO_CSP).size)
        self.rpdo_msg = can.Message(
            arbitration_id=COB_RPDO[0] + self.node_id, is_extended_id=False, data=self.rpdo
        )
        self.cw = CW_DISABLE_VOLTAGE
        self.target = 0
        self.forget()
        self.hb_at = math.nan
        self.tpdo_at = math.nan
        #: the now of the first SYNC sent since this node's last TPDO 1 (NaN: none owed)
        self.owed_since = math.nan
        #: when the drive sampled its newest TPDO 1: the SYNC it answered (else its arrival)
        self.sampled_at = math.nan

    def forget(self) -> None:
        """What a new configuration starts without."""
        self.statusword: int | None = None
        self.nmt: int | None = None
        self.emcy_pending: tuple[int, int] | None = None
        self.last_emcy: tuple[int, int] | None = None
        self.counts: int | None = None
        self.second_counts: int | None = None
        self.second_since = math.nan
        self.tpdo1 = self.tpdo2 = self.emcys = self.heartbeats = 0
        #: its heartbeat and TPDO 1 counts when a wait off the loop thread began (mark)
        self.marks = (0, 0)

    @property
    def where(self) -> str:
        return f"node {self.node_id} (joint {self.joint})"

    def state(self) -> str:
        sw = self.statusword
        return "NO STATUSWORD YET" if sw is None else cia402_state(sw)

    # -- frames (the driver's read, on the loop thread) ---------------------------------------
    def take_tpdo1(self, data: bytes | bytearray, now: float) -> tuple[float, float] | None:
        """TPDO 1 (statusword, position, torque): (position, effort) in the joint's units, the
        reading stamped at the SYNC it answers; None for a frame too short."""
        if len(data) < TPDO1.size:
            return None
        sw, counts, torque = TPDO1.unpack_from(data)
        self.statusword = sw
        self.counts = counts
        self.tpdo_at = now
        owed = self.owed_since
        self.sampled_at = owed if owed == owed else now
        self.owed_since = math.nan
        self.tpdo1 += 1
        return counts / self.cpu, torque * self.torque_scale

    def take_tpdo2(self, data: bytes | bytearray) -> float | None:
        """TPDO 2 (velocity, and the second sensor when mapped): the velocity; None for a
        frame too short."""
        if self.second is not None and len(data) >= TPDO2_SECOND.size:
            vel, self.second_counts = TPDO2_SECOND.unpack_from(data)
        elif len(data) >= TPDO2.size:
            (vel,) = TPDO2.unpack_from(data)
        else:
            return None
        self.tpdo2 += 1
        return float(vel) / self.cpu

    def take_emcy(self, data: bytes | bytearray) -> bool:
        """An EMCY: kept (the first one not yet acted on, and the last); code 0 is the node's
        error reset. False for a frame too short."""
        if len(data) < EMCY.size:
            return False
        code, register = EMCY.unpack_from(data)
        self.emcys += 1
        if code != 0:
            self.last_emcy = (code, register)
            if self.emcy_pending is None:
                self.emcy_pending = (code, register)
        return True

    def take_heartbeat(self, data: bytes | bytearray, now: float) -> bool:
        """A heartbeat: the node's NMT state, and when it was heard (False: an empty frame)."""
        if not data:
            return False
        self.nmt = data[0] & 0x7F
        self.hb_at = now
        self.heartbeats += 1
        return True

    def mark(self) -> None:
        """An activation or a fault reset begins to wait off the loop thread: what it hears
        from here on is stamped with the last read's ``now`` (occ/drivers/cia402.py)."""
        self.marks = (self.heartbeats, self.tpdo1)

    def restamp(self, now: float) -> None:
        """The first read after that wait, at ``now``: a heartbeat heard while it waited was
        heard now, as far as its age goes, and a TPDO owed for one of its SYNCs is owed since
        now, if the node answered one then; a node not heard meanwhile keeps its ages."""
        beats, tpdos = self.marks
        if self.heartbeats != beats:
            self.hb_at = now
        if self.tpdo1 != tpdos and self.owed_since == self.owed_since:
            self.owed_since = now

    def second_check(self, first: float, now: float) -> str | None:
        """The second position sensor against the first (``first``, the joint's reading): the
        disagreement past the tolerance for longer than the latency, described; else None."""
        assert self.second is not None
        counts = self.second_counts
        if counts is None or first != first:
            return None
        _, _, cpu, tol, latency = self.second
        second = counts / cpu
        distance = abs(first - second)
        if distance <= tol:
            self.second_since = math.nan
            return None
        since = self.second_since
        if since != since:
            self.second_since = since = now
        if now - since <= latency:
            return None
        return (
            f"joint {self.joint}: second position sensor disagrees by {distance:.6g} "
            f"(first {first:.6g}, second {second:.6g}; tolerance {tol:g} for more than "
            f"latency_ms {latency * 1e3:g}, now {(now - since) * 1e3:.1f} ms)"
        )

    def fault(
        self, now: float, active: bool, t0: float, s: Settings, position: float
    ) -> str | None:
        """This node's first fault (occ/drivers/cia402.py, "Faults"), or None: an EMCY, the
        fault bit, OPERATION ENABLED left while ``active``, NMT OPERATIONAL left, its
        heartbeat or its TPDO overdue (``t0``: when the driver started listening), the second
        sensor against the first (``position``)."""
        sw = self.statusword
        if self.emcy_pending is not None:
            code, register = self.emcy_pending
            return f"EMCY {code:#06x} ({emcy_meaning(code)}), error register {register:#04x}"
        if sw is not None and sw & 0x08:
            return f"statusword {sw:#06x}: {cia402_state(sw)} (fault bit set)"
        if active and sw is not None and sw & OE_MASK != OE_VALUE:
            return f"statusword {sw:#06x}: left OPERATION ENABLED, now {cia402_state(sw)}"
        if self.nmt is not None and self.nmt != NMT_OPERATIONAL:
            return (
                f"left NMT OPERATIONAL: its heartbeat says "
                f"{NMT_STATES.get(self.nmt, hex(self.nmt))}"
            )
        seen = self.hb_at if self.hb_at == self.hb_at else t0
        if now - seen > s.node_hb_timeout:
            return (
                f"heartbeat consumer timeout: no heartbeat for {(now - seen) * 1e3:.1f} "
                f"ms (producer time {s.node_hb_ms} ms, timeout "
                f"{s.node_hb_timeout * 1e3:g} ms)"
            )
        if now - self.owed_since > s.feedback_timeout:  # NaN: nothing owed
            return (
                f"no TPDO for {(now - self.owed_since) * 1e3:.1f} ms since a SYNC asked "
                f"for one (feedback_timeout {s.feedback_timeout * 1e3:g} ms)"
            )
        if self.second is not None:
            return self.second_check(position, now)
        return None

    def controlword_by_sdo(self, cw: int) -> can.Message | None:
        """For a node out of NMT OPERATIONAL (it takes no PDO): the controlword as an
        expedited SDO download, to be sent and not waited for (the driver drops its answer);
        None for a node that takes PDOs."""
        if self.nmt is None or self.nmt == NMT_OPERATIONAL:
            return None
        request = struct.pack("<BHBH2x", 0x2B, 0x6040, 0, cw)
        return can.Message(
            arbitration_id=COB_SDO_RX + self.node_id, is_extended_id=False, data=request
        )

    def enabled(self) -> bool:
        return self.state() == "OPERATION ENABLED"

    def silent(self) -> bool:
        """No TPDO 1 since the wait off the loop thread began (:meth:`mark`): what its
        statusword says is older than the wait."""
        return self.tpdo1 == self.marks[1]

    def described(self) -> str:
        """Where the node is, for an Enable that did not get there; a node silent through it
        is told so, whatever its last statusword said."""
        sw = f"statusword {self.statusword or 0:#06x}"
        if self.silent():
            return f"{self.where}: no TPDO answered any SYNC of it (its last {sw}, {self.state()})"
        return f"{self.where} in {self.state()} ({sw})"

    def fault_reset_word(self, edge: bool) -> tuple[int, bool]:
        """The controlword of one step of a fault reset, and the next step's ``edge``: the
        reset is bit 7's rising edge (0x00, then 0x80) for a node in FAULT."""
        in_fault = self.statusword is not None and bool(self.statusword & 0x08)
        cw = CW_FAULT_RESET if in_fault and edge else CW_DISABLE_VOLTAGE
        return cw, in_fault and not edge

    def reset_refusal(self, answered: bool) -> str | None:
        """Why this node is not (yet) out of FAULT after a reset: no TPDO ``answered`` the
        reset's SYNC, or still the fault bit or an EMCY; None when it is out."""
        if not answered:
            return f"{self.where}: no TPDO answered the reset's SYNC"
        if not (self.statusword or 0) & 0x08 and self.emcy_pending is None:
            return None
        emcy = self.emcy_pending or self.last_emcy
        tail = f" (EMCY {emcy[0]:#06x}: {emcy_meaning(emcy[0])})" if emcy else ""
        return f"{self.where}: still {self.state()}{tail}"

    def stats(self) -> dict[str, Any]:
        """The node as GetStats shows it: its CiA 402 and NMT states, its last EMCY (code,
        meaning) and its frame counts."""
        emcy = self.last_emcy
        return {
            "node_id": self.node_id,
            "cia402": self.state(),
            "statusword": None if self.statusword is None else f"{self.statusword:#06x}",
            "nmt": None if self.nmt is None else NMT_STATES.get(self.nmt, hex(self.nmt)),
            "last_emcy": None
            if emcy is None
            else {
                "code": f"{emcy[0]:#06x}",
                "meaning": emcy_meaning(emcy[0]),
                "register": f"{emcy[1]:#04x}",
            },  # fmt: skip
            "tpdos": self.tpdo1 + self.tpdo2,
            "emcys": self.emcys,
            "heartbeats": self.heartbeats,
        }


class EchoFilter(can.Listener):
    """canopen's listener, minus the frames only a master sends (its own, echoed)."""

    def __init__(self, inner: can.Listener, master_id: int) -> None:
        self.inner = inner
        self.master_id = master_id
        self.dropped = 0

    def on_message_received(self, msg: can.Message) -> None:
        if master_sends(msg.arbitration_id, self.master_id):
            self.dropped += 1
            return
        self.inner.on_message_received(msg)

    def stop(self) -> None:
        self.inner.stop()


@dataclass(frozen=True)
class Settings:
    """The driver's parameters, checked (module docstring of occ/drivers/cia402.py)."""

    bus_args: dict[str, Any]
    effort: bool
    sync_every: int
    feedback_timeout: float
    node_hb_ms: int
    node_hb_timeout: float
    master_id: int
    #: the drives' consumer time of the master's heartbeat (ms), and how often it is sent (s)
    consumer_ms: int
    master_hb_s: float
    sdo_timeout: float
    state_timeout: float


def read_settings(where: str, p: Mapping[str, Any], period: float, heartbeat_s: float,
                  effort: bool) -> Settings:  # fmt: skip
    """Every scalar parameter checked, each problem naming the driver and the parameter."""
    sync_every = int(p["sync_every"])
    if sync_every < 1:
        raise ValueError(f"{where}: sync_every must be an integer >= 1")
    cycle = period * sync_every
    feedback_timeout = float(p["feedback_timeout"]) * 1e-3
    if not feedback_timeout > cycle:
        raise ValueError(
            f"{where}: feedback_timeout {p['feedback_timeout']} ms must exceed the SYNC "
            f"period ({cycle * 1e3:g} ms: period x sync_every)"
        )
    node_hb_ms = int(p["node_heartbeat_ms"])
    node_hb_timeout = float(p["node_heartbeat_timeout_ms"]) * 1e-3
    if not 0 < node_hb_ms <= 0xFFFF or not node_hb_timeout > node_hb_ms * 1e-3:
        raise ValueError(
            f"{where}: node_heartbeat_ms must be 1-65535 and node_heartbeat_timeout_ms "
            f"above it, got {p['node_heartbeat_ms']} and {p['node_heartbeat_timeout_ms']}"
        )
    master_id = int(p["master_node_id"])
    if not 1 <= master_id <= 127:
        raise ValueError(f"{where}: master_node_id must be 1-127")
    hb_ms = round(heartbeat_s * 1e3)
    if hb_ms > 0xFFFF:
        raise ValueError(f"{where}: heartbeat_ms must be <= 65535, got {hb_ms}")
    sdo_timeout = float(p["sdo_timeout_ms"]) * 1e-3
    state_timeout = float(p["state_timeout_ms"]) * 1e-3
    if not (sdo_timeout > 0.0 and state_timeout > 0.0):
        raise ValueError(f"{where}: sdo_timeout_ms and state_timeout_ms must be > 0")
    bus_args = {
        "interface": p["interface"],
        "channel": p["channel"],
        "bitrate": int(p["bitrate"]),
        **dict(p["bus_kwargs"] or {}),
    }
    return Settings(
        bus_args, effort, sync_every, feedback_timeout, node_hb_ms, node_hb_timeout, master_id,
        hb_ms, heartbeat_s / 4.0, sdo_timeout, state_timeout,
    )  # fmt: skip


def check_budget(
    where: str, s: Settings, nodes: Sequence[Node], period: float, limit: float
) -> float:
    """The bus load of this driver's cycle (module docstring of occ/drivers/cia402.py, "Bus
    budget"); above ``limit`` a ValueError with the figure and what would fit."""
    seconds = sum(1 for n in nodes if n.second is not None)

    def load_at(every: int, count: int = len(nodes)) -> tuple[float, str]:
        return bus_load(
            nodes=count, period=period, sync_every=every, bitrate=s.bus_args["bitrate"],
            effort=s.effort, second_sensors=min(seconds, count), node_heartbeat_ms=s.node_hb_ms,
            master_heartbeat_ms=s.master_hb_s * 1e3,
        )  # fmt: skip

    load, detail = load_at(s.sync_every)
    if load > limit:
        fits = next((k for k in range(s.sync_every + 1, 11) if load_at(k)[0] <= limit), None)
        most = max(
            (k for k in range(1, len(nodes)) if load_at(s.sync_every, k)[0] <= limit),
            default=0,
        )
        advice = [
            f"at most {most} node{'s' if most > 1 else ''} per bus at this rate"
            if most
            else "a faster bus"
        ]
        if fits is not None:
            advice.append(f"sync_every: {fits} ({load_at(fits)[0]:.0%})")
        raise ValueError(
            f"{where}: bus load {load:.0%} exceeds bus_load_limit {limit:.0%}: "
            f"{detail}; use " + ", or ".join(advice)
        )
    return load


def parse_nodes(
    where: str, joints: Sequence[Joint], spec: Any, effort: bool, master_id: int
) -> list[Node]:
    """The ``nodes`` parameter: one node per joint, each with its EDS loaded and checked."""
    names = [j.name for j in joints]
    if not isinstance(spec, Mapping):
        raise ValueError(
            f"{where}: params['nodes'] is required: {{joint: {{node_id, counts_per_unit, "
            f"eds}}}} for joints {names}"
        )
    missing = [j for j in names if j not in spec]
    unknown = sorted(set(map(str, spec)) - set(names))
    if missing or unknown:
        raise ValueError(f"{where}: nodes: missing joints {missing}, unknown {unknown}")
    nodes: list[Node] = []
    for i, joint in enumerate(joints):
        entry = spec[joint.name]
        if not isinstance(entry, Mapping):
            raise ValueError(f"{where}: nodes.{joint.name} must be a mapping, got {entry!r}")
        extra = sorted(set(map(str, entry)) - NODE_KEYS)
        if extra:
            raise ValueError(
                f"{where}: nodes.{joint.name}: unknown keys {extra}; known: {sorted(NODE_KEYS)}"
            )
        try:
            node = Node(i, joint, entry, effort)
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(
                f"{where}: nodes.{joint.name}: needs node_id and counts_per_unit ({err!r})"
            ) from err
        if not 1 <= node.node_id <= 127 or node.node_id == master_id:
            raise ValueError(
                f"{where}: nodes.{joint.name}: node_id {node.node_id} must be 1-127 and not "
                f"the master's ({master_id})"
            )
        if node.cpu == 0.0 or not math.isfinite(node.cpu):
            raise ValueError(f"{where}: nodes.{joint.name}: counts_per_unit must be != 0")
        if not node.eds.is_file():
            raise ValueError(f"{where}: nodes.{joint.name}: eds file {str(node.eds)!r} not found")
        try:
            node.od = load_od(str(node.eds))
        except Exception as err:  # noqa: BLE001 - a broken EDS, whatever the parser says
            # the file and line of what is wrong (occ/drivers/eds_lines.py), else its words
            raise ValueError(f"{where}: nodes.{joint.name}: {eds_refusal(node.eds, err)}") from err
        needed = [0x1000, 0x1016, 0x1017, 0x1400, 0x1600, 0x1800, 0x1801, 0x1A00, 0x1A01,
                  0x6040, 0x6041, 0x6060, 0x6064, 0x606C, 0x6077, 0x60C2,
                  0x6071 if effort else 0x607A]  # fmt: skip
        absent = [f"{k:#06x}" for k in needed if k not in node.od]
        if absent:
            raise ValueError(
                f"{where}: nodes.{joint.name}: eds {str(node.eds)!r} lacks objects {absent}"
            )
        second = entry.get("second_sensor")
        if second is not None:
            node.second = parse_second(where, joint, node, second)
        nodes.append(node)
    ids = [n.node_id for n in nodes]
    if len(set(ids)) != len(ids):
        raise ValueError(f"{where}: node_id values must be distinct, got {ids}")
    return nodes


def parse_second(
    driver: str, joint: Joint, node: Node, raw: Any
) -> tuple[int, int, float, float, float]:
    """A joint's ``second_sensor``: (index, subindex, counts per unit, tolerance, latency s)."""
    where = f"{driver}: nodes.{joint.name}.second_sensor"
    if not isinstance(raw, Mapping) or "index" not in raw or "counts_per_unit" not in raw:
        raise ValueError(
            f"{where}: a mapping {{index, subindex, counts_per_unit, tolerance, "
            f"latency_ms}} is needed, got {raw!r}"
        )
    extra = sorted(set(map(str, raw)) - SECOND_KEYS)
    if extra:
        raise ValueError(f"{where}: unknown keys {extra}; known: {sorted(SECOND_KEYS)}")
    index, sub = int(raw["index"]), int(raw.get("subindex", 0))
    cpu = float(raw["counts_per_unit"])
    tol = float(raw.get("tolerance", SECOND_TOLERANCE.get(joint.type, 0.01)))
    latency = float(raw.get("latency_ms", 5.0)) * 1e-3
    if cpu == 0.0 or not math.isfinite(cpu) or not tol > 0.0 or not latency >= 0.0:
        raise ValueError(
            f"{where}: counts_per_unit != 0, tolerance > 0 and latency_ms >= 0 are needed"
        )
    var = node.od.get_variable(index, sub)
    if var is None or not var.pdo_mappable or var.data_type not in (0x4, 0x7):
        raise ValueError(
            f"{where}: object {index:#06x}:{sub:02x} is not a mappable 32-bit object of "
            f"{str(node.eds)!r}"
        )
    return index, sub, cpu, tol, latency


def open_network(
    where: str, s: Settings, nodes: Sequence[Node], period: float
) -> tuple[can.BusABC, Any, int]:
    """The bus opened (error frames on, on SocketCAN), canopen's network on it with own frames
    dropped, every node configured over SDO and started (NMT start), canopen's reader thread
    stopped (the driver reads the bus itself from then on): (bus, network, own frames dropped).
    Everything is closed again when a node fails."""
    import canopen

    try:
        bus = can.Bus(**s.bus_args)
    except (can.CanError, OSError, ImportError, ValueError, TypeError) as err:
        raise DriverError(f"{where}: cannot open bus {s.bus_args}: {err}") from err
    sock = getattr(bus, "socket", None)
    if s.bus_args["interface"] == "socketcan" and sock is not None:
        try:  # error frames, every class (python-can leaves them off; as the can driver)
            sock.setsockopt(
                _socket.SOL_CAN_RAW, CAN_RAW_ERR_FILTER, struct.pack("=I", CAN_ERR_MASK)
            )
        except (OSError, AttributeError) as err:
            logger.warning("%s: error frames not enabled: %s", where, err)
    network = canopen.Network(bus)
    network.NOTIFIER_CYCLE = 0.01  # its reader thread stops within 10 ms
    echo = EchoFilter(network.listeners[0], s.master_id)
    network.listeners = [echo]  # type: ignore[list-item]  # any can.Listener will do
    try:
        network.connect()
        for node in nodes:
            node.forget()
            remote = canopen.RemoteNode(node.node_id, node.od)
            network.add_node(remote)
            remote.sdo.RESPONSE_TIMEOUT = s.sdo_timeout
            configure_node(where, node, remote, s, period)
        for node in nodes:
            network[node.node_id].nmt.send_command(0x01)  # NMT start
    except BaseException:
        close_network(network, bus)
        raise
    notifier, network.notifier = network.notifier, None
    if notifier is not None:
        notifier.stop(1.0)  # from here on the loop reads the bus itself (read)
    return bus, network, echo.dropped


def configure_node(where: str, node: Node, remote: Any, s: Settings, period: float) -> None:
    """One node configured over SDO (module docstring of occ/drivers/cia402.py): every
    abort or timeout a DriverError naming the node, the object and the abort's meaning."""
    import canopen

    nid = node.node_id
    remote.nmt.send_command(0x80)  # enter pre-operational: PDOs stop, SDO answers
    try:
        device = int.from_bytes(remote.sdo.upload(0x1000, 0), "little")
    except canopen.SdoAbortedError as err:
        raise sdo_error(where, s.sdo_timeout, node, 0x1000, 0, "device type", "read", err) from err
    except (canopen.SdoCommunicationError, can.CanError) as err:
        raise sdo_error(where, s.sdo_timeout, node, 0x1000, 0, "device type", "read", err) from err
    if device & 0xFFFF != 402:
        raise DriverError(
            f"{where}: {node.where}: device type {device:#010x} is not a CiA 402 "
            f"drive (profile {device & 0xFFFF}, not 402)"
        )
    mode = MODE_CST if s.effort else MODE_CSP
    target = 0x6071 if s.effort else 0x607A

    def entry(index: int, sub: int = 0, bits: int | None = None) -> int:
        return (index << 16) | (sub << 8) | (bits if bits is not None else PDO_BITS[index])

    tpdo2 = [entry(0x606C)]
    if node.second is not None:
        tpdo2.append(entry(node.second[0], node.second[1], 32))
    period_value, period_index = interpolation_period(period * s.sync_every)
    writes: list[tuple[int, int, int]] = []
    for k in range(4):  # every PDO off while remapped
        writes.append((0x1400 + k, 1, 0x80000000 | (COB_RPDO[k] + nid)))
        writes.append((0x1800 + k, 1, 0x80000000 | (COB_TPDO[k] + nid)))
    for mapping, entries in (
        (0x1600, [entry(0x6040), entry(target)]),
        (0x1A00, [entry(0x6041), entry(0x6064), entry(0x6077)]),
        (0x1A01, tpdo2),
    ):
        writes.append((mapping, 0, 0))
        writes.extend((mapping, s, e) for s, e in enumerate(entries, 1))
        writes.append((mapping, 0, len(entries)))
    writes += [
        (0x1400, 2, 1),  # synchronous
        (0x1400, 1, COB_RPDO[0] + nid),
        (0x1800, 2, 1),
        (0x1800, 1, COB_TPDO[0] + nid),
        (0x1801, 2, 1),
        (0x1801, 1, COB_TPDO[1] + nid),
        (0x6060, 0, mode),
        (0x60C2, 1, period_value),
        (0x60C2, 2, period_index),
        (0x1017, 0, s.node_hb_ms),
        (0x1016, 1, (s.master_id << 16) | s.consumer_ms),
    ]
    for index, sub, value in writes:
        var = node.od.get_variable(index, sub)
        name = var.name if var is not None else "?"
        try:
            if var is None:
                raise DriverError(
                    f"{where}: {node.where}: the EDS {str(node.eds)!r} has no object "
                    f"{index:#06x}:{sub:02x}"
                )
            remote.sdo.download(index, sub, var.encode_raw(value))
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError, can.CanError) as err:
            what = f"write {value:#x}"
            raise sdo_error(where, s.sdo_timeout, node, index, sub, name, what, err) from err


def sdo_error(
    where: str,
    timeout: float,
    node: Node,
    index: int,
    sub: int,
    name: str,
    what: str,
    err: Exception,
) -> DriverError:
    """The configure failure of one SDO transfer, with the abort code's meaning."""
    code = getattr(err, "code", None)
    if code is not None:
        cause = f"aborted by the node with {code:#010x}: {sdo_abort_meaning(code)}"
    elif isinstance(err, can.CanError):
        cause = f"not sent: {err}"
    else:
        cause = f"no answer within {timeout * 1e3:.0f} ms (SDO timeout: {err})"
    return DriverError(
        f"{where}: {node.where}: configure: SDO {what} to {index:04X}:{sub:02X} ({name}) {cause}"
    )


def close_network(network: Any, bus: can.BusABC) -> None:
    """canopen's notifier stopped (if it still runs) and the bus shut down."""
    notifier = getattr(network, "notifier", None)
    if notifier is not None:
        network.notifier = None
        try:
            notifier.stop(1.0)
        except Exception:  # noqa: BLE001 - closing anyway
            logger.exception("cia402: notifier did not stop")
    bus.shutdown()


def interpolation_period(seconds: float) -> tuple[int, int]:
    """0x60C2's (value, index): ``seconds = value x 10^index``, value 1-255."""
    for index in (-3, -4, -5, -6):
        value = seconds / 10.0**index
        if abs(value - round(value)) < 1e-6 and 1 <= round(value) <= 255:
            return round(value), index
    raise ValueError(f"interpolation period {seconds} s cannot be written to 0x60C2")


def enable_late(where: str, nodes: Sequence[Node], timeout: float) -> str:
    """Why an Enable did not get every node to OPERATION ENABLED within ``timeout``: the nodes
    that answered none of its SYNCs first (the Enable waited on them, so the others may not
    have got their next step, and a silent node's old statusword may still say OPERATION
    ENABLED), then every other node short of it."""
    silent = [n.described() for n in nodes if n.silent()]
    short = [n.described() for n in nodes if not n.silent() and not n.enabled()]
    return (
        f"{where}: not OPERATION ENABLED within {timeout * 1e3:g} ms: {'; '.join(silent + short)}"
    )
