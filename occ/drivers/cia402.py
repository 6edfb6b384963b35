"""CANopen CiA 402 servo drives (Maxon EPOS4, Elmo, ...) through the ``canopen`` library.

One driver owns one CAN bus (python-can) and one node per joint. Configuration happens off the
loop, over SDO; each tick only sends and reads process data (PDOs), SYNC and heartbeats, never
waiting for an answer. Only ``activate`` and ``reset`` (Enable, Reset) wait: for the nodes'
statuswords, over PDOs too, at most ``state_timeout_ms``. The driver says so
(``activation_waits = True``): the robot runs its ``activate`` on a thread of its own while the
loop goes on ticking, and touches the driver again only once it has ended (occ/core/powerup.py);
a Reset's ``reset`` likewise.

Configuration (``configure``, off the loop)
===========================================

Every node is sent NMT *enter pre-operational*, its device type (0x1000) is read (a node that
is no CiA 402 device is refused), then written over SDO (canopen's SDO client):

- all four RPDOs and TPDOs disabled while they are remapped (COB-ID bit 31);
- RPDO 1, synchronous (transmission type 1): controlword 0x6040 and target position 0x607A
  (CSP, ``command_interface: position``) or target torque 0x6071 (CST, ``effort``);
- TPDO 1, synchronous: statusword 0x6041, position actual 0x6064, torque actual 0x6077
  (8 bytes); TPDO 2, synchronous: velocity actual 0x606C and, when the joint has one, the
  second position sensor (``second_sensor``);
- modes of operation 0x6060 (8 CSP, 10 CST); interpolation time period 0x60C2 (the SYNC
  period: ``period`` x ``sync_every``); the node's heartbeat producer time 0x1017
  (``node_heartbeat_ms``) and its heartbeat consumer 0x1016 sub 1 (the master's node id,
  ``master_node_id``, and ``heartbeat_ms``: the drive stops itself, EMCY 0x8130, when the
  master's heartbeat is missing for that long: the device-side heartbeat of occ's driver
  contract);

then NMT *start*. An SDO abort or timeout fails the configuration naming the node, the joint,
the object (index:subindex and its name) and the abort code's meaning (CiA 301's table in
:mod:`occ.drivers.cia402_protocol`).

Activation, the cycle, stopping
===============================

``activate`` walks every node through the CiA 402 state machine together (controlword 0x06
shutdown, 0x07 switch on, 0x0F enable operation, each followed by a SYNC and judged by the
statusword of the TPDO it brings), holding each joint's measured position as its target. A node
that is not OPERATION ENABLED within ``state_timeout_ms`` (or is in FAULT) makes activate raise
naming it and its state, and every node is switched off again (controlword 0x00): Enable is
vetoed.

Off the loop thread: while activate waits, the loop neither reads nor writes the driver, so
activate sends the master's heartbeat itself (every quarter of ``heartbeat_ms`` of wall clock:
a node already enabled must not find its master silent) and, between its steps and every 10 ms
of a wait, looks at the base's ``activation_cancelled``: a cancel (Disable) or a safe stop
(EStop, Fault, the supervisor) asked from another thread switches every node off at once
(0x00) and ends it; the base then leaves the driver INACTIVE (cancel), or latches FAULT and
quick-stops every node (safe stop). The frames it took are stamped with the last read's
``now`` (the driver has no clock of its own): the first read after it counts the heartbeats'
and owed TPDOs' ages from its own ``now``.

Each tick the base checks the setpoints; every ``sync_every``-th tick ``write`` packs each node's
RPDO and sends the RPDOs and a SYNC (a synchronous RPDO takes effect at the SYNC, so the ticks
between would be overwritten unused); ``read`` takes every frame that arrived (the TPDOs the
previous SYNC brought, EMCYs, heartbeats) without waiting, and, while the driver is not
ACTIVE, sends the SYNC itself so positions stay readable. The master's heartbeat goes out
every quarter of ``heartbeat_ms`` (from reads and writes: a drive commanded is not orphaned).

``deactivate`` (Disable): disable voltage (controlword 0x00). A fault, and the supervisor's
safe stop (EStop): quick stop (0x02) on every node in the same call (in the RPDOs, with a
SYNC; to a node whose heartbeat says it left OPERATIONAL, where PDOs are not taken, also as an
expedited SDO download of 0x6040 that is sent and not waited for). ``reset``: the fault reset
(controlword bit 7, a rising edge), NMT start for a node that left OPERATIONAL; it succeeds only
when every node answers the reset's SYNC with a TPDO whose statusword is out of FAULT, and
raises naming the nodes that did not (a persisting cause). The heartbeat's and TPDO's ages are
not restarted by a reset: the first read after it judges a node that is still silent.

Faults (each raises from ``read``, which latches FAULT naming the driver, the node, the joint
and the cause, and quick-stops every node in that call)
=========================================================================================

- an EMCY frame with an error code other than 0 (its meaning from CiA 301/402's table, e.g.
  0x8611 following error, 0x7300 sensor, 0x2310 overcurrent, 0x3210 overvoltage, 0x4310
  temperature, 0x8130 heartbeat lost);
- a statusword with the fault bit (FAULT or FAULT REACTION ACTIVE), with or without an EMCY;
  while ACTIVE, a statusword that is not OPERATION ENABLED (the drive stopped on its own);
- a heartbeat consumer timeout: no heartbeat from a node for ``node_heartbeat_timeout_ms``;
- a node whose heartbeat says it left NMT OPERATIONAL;
- no TPDO from a node for ``feedback_timeout`` ms since a SYNC asked for one (a pause of the
  host, when no SYNC went out, is not the node's);
- a second position sensor that disagrees with the first by more than its ``tolerance`` for
  longer than its ``latency_ms``;
- a bus-off error frame (SocketCAN's error class 0x40; error frames are enabled on SocketCAN
  and counted in ``error_frames``).

The base class adds its own checks (following error, jump, frozen, limits).

Own frames: python-can's ``udp_multicast`` bus (4.6) hands a process the frames it sent itself,
so a master would receive its own RPDOs and SYNCs. The driver takes, by COB-ID, only what its
nodes send (EMCY, TPDO 1 and 2, SDO answers, heartbeats) and counts the frames only a master
sends as ``echoes`` (``cia402_protocol.master_sends``); canopen's listener is wrapped the same
way while it is in use (configure). python-can's own ``set_filters`` is not used: in software it
makes ``recv(timeout=0)`` return None at the first frame it drops, leaving the rest unread.

Bus budget
==========

Checked when the driver is built (``occd --check`` builds every driver): the bits per second
of the cycle's frames (per node an RPDO, TPDO 1 and TPDO 2 each SYNC; one SYNC) at the SYNC rate
(1 / (``period`` x ``sync_every``)), plus the heartbeats, over ``bitrate``. Each frame is counted
at its worst case with bit stuffing, ``55 + 10 x data bytes`` bits (135 for 8 bytes: Davis et
al., Real-Time Systems 35(3), 2007, eq. 2; :func:`~occ.drivers.cia402_protocol.frame_bits`).
Above ``bus_load_limit`` (0.7) the configuration is refused with the load, the figures and the
advice (fewer nodes per bus, or the ``sync_every`` that fits). Three CSP nodes at 1 Mbit/s
with a 1 kHz loop need 111 % with a SYNC every tick and 57 % with ``sync_every: 2``; eight
need 146 % even then.

A reading's age: a TPDO shows the drive at the SYNC it answers, and TPDOs come every
``sync_every`` ticks, or late in a burst. So that the base's jump check judges a step over the
time it really took, each joint's ``stamp`` is set back, when a new TPDO shows it, to the SYNC
of the reading it replaces (the base stamps every read, fresh or not).

Parameters
==========

=========================  ===============  ==============================================
key                        default          meaning
=========================  ===============  ==============================================
interface                  ``"socketcan"``  python-can interface (``virtual``,
                                            ``udp_multicast`` in tests)
channel                    ``"can0"``       python-can channel
bitrate                    1000000          bit/s (the bus budget's too)
bus_kwargs                 {}               extra keyword arguments for ``can.Bus``
nodes                      required         ``{joint: {node_id, counts_per_unit, eds,
                                            rated_torque, second_sensor}}``
sync_every                 1                a SYNC (and the RPDOs) every N-th tick
feedback_timeout           10.0             ms without a TPDO from a node: FAULT
node_heartbeat_ms          10               the nodes' heartbeat producer time (0x1017)
node_heartbeat_timeout_ms  30               ms without a node's heartbeat: FAULT
master_node_id             127              the master's node id (its heartbeat's COB-ID)
sdo_timeout_ms             300              an SDO answer's timeout at configure
state_timeout_ms           300              activate's and reset's bound on the state
                                            machine, ms
bus_load_limit             0.7              the bus load refused above
command_interface          ``"position"``   CSP; ``"effort"``: CST
period                     0.001            the loop period, s (make it robot.rate_hz's)
=========================  ===============  ==============================================

Per node: ``node_id`` (1-127), ``counts_per_unit`` (encoder counts per rad or m; negative for a
drive mounted reversed), ``eds`` (default configs/eds/drive.eds; a relative path is taken from
the working directory, else from the project's root), ``rated_torque`` (N m or N at 1000 per
mille of torque actual/target, default 1.0), ``second_sensor`` (optional: ``{index, subindex,
counts_per_unit, tolerance, latency_ms}``, a 32-bit object mapped into TPDO 2; tolerance in rad
or m, default 1 mm or 10 mrad by joint type, latency 5 ms).

Without hardware: ``interface: virtual`` with :class:`occ.drivers.cia402_sim.DriveEmulator` in
the same process, or ``udp_multicast`` with ``python -m occ.drivers.cia402_sim`` in another.
"""

from __future__ import annotations

import logging
import math
import socket as _socket
import struct
import threading
import time
from collections.abc import Mapping, Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

import can

from occ.drivers.base import CommandInterface, Driver, DriverState, LimitPolicy
from occ.drivers.cia402_protocol import (
    COB_EMCY,
    COB_HEARTBEAT,
    COB_NMT,
    COB_RPDO,
    COB_SDO_RX,
    COB_SDO_TX,
    COB_SYNC,
    COB_TPDO,
    CW_DISABLE_VOLTAGE,
    CW_ENABLE_OPERATION,
    CW_FAULT_RESET,
    CW_QUICK_STOP,
    CW_SHUTDOWN,
    CW_SWITCH_ON,
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
from occ.errors import DriverError
from occ.joint import Joint

__all__ = ["CiA402Driver", "bus_load", "DEFAULT_EDS"]

logger = logging.getLogger(__name__)

_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_EDS = _ROOT / "configs" / "eds" / "drive.eds"

_DEFAULTS: dict[str, Any] = {
    "interface": "socketcan",
    "channel": "can0",
    "bitrate": 1_000_000,
    "bus_kwargs": {},
    "nodes": None,
    "sync_every": 1,
    "feedback_timeout": 10.0,
    "node_heartbeat_ms": 10,
    "node_heartbeat_timeout_ms": 30.0,
    "master_node_id": 127,
    "sdo_timeout_ms": 300.0,
    "state_timeout_ms": 300.0,
    "bus_load_limit": 0.7,
    "command_interface": "position",
    "period": 0.001,
}
_NODE_KEYS = {"node_id", "counts_per_unit", "eds", "rated_torque", "second_sensor"}
_SECOND_KEYS = {"index", "subindex", "counts_per_unit", "tolerance", "latency_ms"}
_SECOND_TOLERANCE = {"revolute": 0.01, "prismatic": 0.001}

RPDO_CSP = struct.Struct("<Hi")  # controlword, target position (counts)
RPDO_CST = struct.Struct("<Hh")  # controlword, target torque (per mille)
TPDO1 = struct.Struct("<Hih")  # statusword, position actual, torque actual
TPDO2 = struct.Struct("<i")  # velocity actual (counts/s)
TPDO2_SECOND = struct.Struct("<ii")  # velocity actual, second sensor (counts)
EMCY = struct.Struct("<HB")  # error code, error register
#: the objects' sizes in bits as mapped (index, subindex) -> bits
_BITS = {0x6040: 16, 0x607A: 32, 0x6071: 16, 0x6041: 16, 0x6064: 32, 0x6077: 16, 0x606C: 32}
_INT32 = (-(2**31), 2**31 - 1)
_INT16 = (-(2**15), 2**15 - 1)

#: a SocketCAN error frame's bus-off class, the mask of every class, and the socket option
#: that lets error frames through (linux/can/error.h, linux/can/raw.h)
CAN_ERR_BUSOFF = 0x40
CAN_ERR_MASK = 0x1FFFFFFF
CAN_RAW_ERR_FILTER = 2

#: OPERATION ENABLED's statusword mask and value (CiA 402's table), checked every read
_OE_MASK, _OE_VALUE = next((m, v) for m, v, name in STATUS_WORDS if name == "OPERATION ENABLED")

# frame kinds in the receive table
_K_TPDO1, _K_TPDO2, _K_EMCY, _K_HB, _K_SDO = range(5)


def _saturate(value: float, bounds: tuple[int, int]) -> int:
    if value != value:
        raise ValueError("NaN cannot be sent")
    lo, hi = bounds
    if value >= hi:
        return hi
    if value <= lo:
        return lo
    return int(math.floor(value + 0.5))


def _resolve_eds(raw: Any) -> Path:
    if raw is None:
        return DEFAULT_EDS
    path = Path(str(raw))
    if path.is_absolute() or path.exists():
        return path
    beside = _ROOT / path
    return beside if beside.exists() else path


@lru_cache(maxsize=16)
def _load_od(path: str) -> Any:
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


class _Node:
    """What the driver knows of one node (joint ``index``)."""

    __slots__ = (
        "index", "node_id", "joint", "cpu", "torque_scale", "eds", "od", "second",
        "statusword", "nmt", "hb_at", "tpdo_at", "emcy_pending", "last_emcy", "counts",
        "second_counts", "second_since", "tpdo1", "tpdo2", "emcys", "heartbeats",
        "target", "rpdo", "rpdo_msg", "cw", "owed_since", "sampled_at",
    )  # fmt: skip

    def __init__(self, index: int, joint: Joint, spec: Mapping[str, Any], effort: bool) -> None:
        self.index = index
        self.joint = joint.name
        self.node_id = int(spec["node_id"])
        self.cpu = float(spec["counts_per_unit"])
        rated = float(spec.get("rated_torque", 1.0))
        # per mille -> effort units, in the joint's sense (reversed with its counts)
        self.torque_scale = rated / 1000.0 * (1.0 if self.cpu > 0.0 else -1.0)
        self.eds = _resolve_eds(spec.get("eds"))
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

    @property
    def where(self) -> str:
        return f"node {self.node_id} (joint {self.joint})"

    def state(self) -> str:
        sw = self.statusword
        return "NO STATUSWORD YET" if sw is None else cia402_state(sw)


class _EchoFilter(can.Listener):
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


class CiA402Driver(Driver):
    """CiA 402 drives over CANopen (module docstring)."""

    supported_interfaces = ("position", "effort")
    DEFAULT_PARAMS = _DEFAULTS
    #: the state machine's round trips: the robot powers it up off the loop thread
    activation_waits = True

    def __init__(
        self,
        name: str,
        joints: Sequence[Joint],
        params: Mapping[str, Any] | None = None,
        on_limit: LimitPolicy = "clamp",
        command_interface: CommandInterface | None = None,
    ) -> None:
        super().__init__(name, joints, params, on_limit, command_interface)
        p = self.params
        where = f"cia402 driver {name!r}"
        self._where = where
        self._bus_args: dict[str, Any] = {
            "interface": p["interface"],
            "channel": p["channel"],
            "bitrate": int(p["bitrate"]),
            **dict(p["bus_kwargs"] or {}),
        }
        self._effort = self.command_interface == "effort"
        self._sync_every = int(p["sync_every"])
        if self._sync_every < 1:
            raise ValueError(f"{where}: sync_every must be an integer >= 1")
        cycle = self.period * self._sync_every
        self._feedback_timeout = float(p["feedback_timeout"]) * 1e-3
        if not self._feedback_timeout > cycle:
            raise ValueError(
                f"{where}: feedback_timeout {p['feedback_timeout']} ms must exceed the SYNC "
                f"period ({cycle * 1e3:g} ms: period x sync_every)"
            )
        self._node_hb_ms = int(p["node_heartbeat_ms"])
        self._node_hb_timeout = float(p["node_heartbeat_timeout_ms"]) * 1e-3
        if (
            not 0 < self._node_hb_ms <= 0xFFFF
            or not self._node_hb_timeout > self._node_hb_ms * 1e-3
        ):
            raise ValueError(
                f"{where}: node_heartbeat_ms must be 1-65535 and node_heartbeat_timeout_ms "
                f"above it, got {p['node_heartbeat_ms']} and {p['node_heartbeat_timeout_ms']}"
            )
        self._master_id = int(p["master_node_id"])
        if not 1 <= self._master_id <= 127:
            raise ValueError(f"{where}: master_node_id must be 1-127")
        hb_ms = round(self.heartbeat_s * 1e3)
        if hb_ms > 0xFFFF:
            raise ValueError(f"{where}: heartbeat_ms must be <= 65535, got {hb_ms}")
        self._consumer_ms = hb_ms  # the drives' consumer time of the master's heartbeat
        self._master_hb_s = self.heartbeat_s / 4.0
        self._sdo_timeout = float(p["sdo_timeout_ms"]) * 1e-3
        self._state_timeout = float(p["state_timeout_ms"]) * 1e-3
        if not (self._sdo_timeout > 0.0 and self._state_timeout > 0.0):
            raise ValueError(f"{where}: sdo_timeout_ms and state_timeout_ms must be > 0")
        self._nodes = self._parse_nodes(p["nodes"])
        # the bus budget (module docstring)
        limit = float(p["bus_load_limit"])
        seconds = sum(1 for n in self._nodes if n.second is not None)
        hb_master_ms = self._master_hb_s * 1e3

        def load_at(every: int, nodes: int = len(self._nodes)) -> tuple[float, str]:
            return bus_load(
                nodes=nodes, period=self.period, sync_every=every,
                bitrate=self._bus_args["bitrate"], effort=self._effort,
                second_sensors=min(seconds, nodes), node_heartbeat_ms=self._node_hb_ms,
                master_heartbeat_ms=hb_master_ms,
            )  # fmt: skip

        self.bus_load, detail = load_at(self._sync_every)
        if self.bus_load > limit:
            fits = next(
                (k for k in range(self._sync_every + 1, 11) if load_at(k)[0] <= limit), None
            )
            most = max(
                (k for k in range(1, len(self._nodes)) if load_at(self._sync_every, k)[0] <= limit),
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
                f"{where}: bus load {self.bus_load:.0%} exceeds bus_load_limit {limit:.0%}: "
                f"{detail}; use " + ", or ".join(advice)
            )
        n = len(self.joints)
        self._rx: dict[int, tuple[int, _Node]] = {}
        for node in self._nodes:
            nid = node.node_id
            self._rx[COB_TPDO[0] + nid] = (_K_TPDO1, node)
            self._rx[COB_TPDO[1] + nid] = (_K_TPDO2, node)
            self._rx[COB_EMCY + nid] = (_K_EMCY, node)
            self._rx[COB_HEARTBEAT + nid] = (_K_HB, node)
            self._rx[COB_SDO_TX + nid] = (_K_SDO, node)
        #: the COB-IDs of the frames it sends itself (RPDO 1, SDO requests, SYNC, NMT, its
        #: heartbeat): what an echo usually is, told by one look-up
        self._own = frozenset(
            [COB_SYNC, COB_NMT, COB_HEARTBEAT + self._master_id]
            + [COB_RPDO[0] + n.node_id for n in self._nodes]
            + [COB_SDO_RX + n.node_id for n in self._nodes]
        )
        self._bus: can.BusABC | None = None
        self._network: Any = None
        self._pos = [math.nan] * n
        self._vel = [0.0] * n
        self._eff = [0.0] * n
        self._sync_msg = can.Message(arbitration_id=COB_SYNC, is_extended_id=False, data=b"")
        self._hb_msg = can.Message(
            arbitration_id=COB_HEARTBEAT + self._master_id,
            is_extended_id=False,
            data=bytes([NMT_OPERATIONAL]),
        )
        self._tick = 0
        self._now = math.nan
        self._t0 = math.nan
        self._master_hb_at = math.nan
        #: the master's heartbeat while activate waits (wall clock: the loop's is not read)
        self._waiting_hb_at = -math.inf
        #: the frames taken while activate waited are stamped with the last read's ``now``:
        #: the first read after it counts their ages from its own (see _read)
        self._restamp = False
        self._send_lock = threading.Lock()
        self._counters = {
            "sync_frames": 0,
            "rpdo_frames": 0,
            "tpdo_frames": 0,
            "emcy_frames": 0,
            "heartbeat_frames": 0,
            "echoes": 0,
            "ignored_frames": 0,
            "quick_stops": 0,
            "fault_resets": 0,
            "error_frames": 0,
        }
        #: the identifier of a bus-off error frame not yet acted on (None: none)
        self._bus_off: int | None = None
        self.last_fault: str | None = None

    # ------------------------------------------------------------------ parameters
    def _parse_nodes(self, spec: Any) -> list[_Node]:
        where = self._where
        if not isinstance(spec, Mapping):
            raise ValueError(
                f"{where}: params['nodes'] is required: {{joint: {{node_id, counts_per_unit, "
                f"eds}}}} for joints {self.joint_names}"
            )
        names = self.joint_names
        missing = [j for j in names if j not in spec]
        unknown = sorted(set(map(str, spec)) - set(names))
        if missing or unknown:
            raise ValueError(f"{where}: nodes: missing joints {missing}, unknown {unknown}")
        nodes: list[_Node] = []
        for i, joint in enumerate(self.joints):
            entry = spec[joint.name]
            if not isinstance(entry, Mapping):
                raise ValueError(f"{where}: nodes.{joint.name} must be a mapping, got {entry!r}")
            extra = sorted(set(map(str, entry)) - _NODE_KEYS)
            if extra:
                raise ValueError(
                    f"{where}: nodes.{joint.name}: unknown keys {extra}; "
                    f"known: {sorted(_NODE_KEYS)}"
                )
            try:
                node = _Node(i, joint, entry, self._effort)
            except (KeyError, TypeError, ValueError) as err:
                raise ValueError(
                    f"{where}: nodes.{joint.name}: needs node_id and counts_per_unit ({err!r})"
                ) from err
            if not 1 <= node.node_id <= 127 or node.node_id == self._master_id:
                raise ValueError(
                    f"{where}: nodes.{joint.name}: node_id {node.node_id} must be 1-127 and not "
                    f"the master's ({self._master_id})"
                )
            if node.cpu == 0.0 or not math.isfinite(node.cpu):
                raise ValueError(f"{where}: nodes.{joint.name}: counts_per_unit must be != 0")
            if not node.eds.is_file():
                raise ValueError(
                    f"{where}: nodes.{joint.name}: eds file {str(node.eds)!r} not found"
                )
            try:
                node.od = _load_od(str(node.eds))
            except Exception as err:  # noqa: BLE001 - a broken EDS, whatever the parser says
                raise ValueError(
                    f"{where}: nodes.{joint.name}: eds {str(node.eds)!r} does not load: {err}"
                ) from err
            needed = [0x1000, 0x1016, 0x1017, 0x1400, 0x1600, 0x1800, 0x1801, 0x1A00, 0x1A01,
                      0x6040, 0x6041, 0x6060, 0x6064, 0x606C, 0x6077, 0x60C2,
                      0x6071 if self._effort else 0x607A]  # fmt: skip
            absent = [f"{k:#06x}" for k in needed if k not in node.od]
            if absent:
                raise ValueError(
                    f"{where}: nodes.{joint.name}: eds {str(node.eds)!r} lacks objects {absent}"
                )
            second = entry.get("second_sensor")
            if second is not None:
                node.second = self._parse_second(joint, node, second)
            nodes.append(node)
        ids = [n.node_id for n in nodes]
        if len(set(ids)) != len(ids):
            raise ValueError(f"{where}: node_id values must be distinct, got {ids}")
        return nodes

    def _parse_second(
        self, joint: Joint, node: _Node, raw: Any
    ) -> tuple[int, int, float, float, float]:
        where = f"{self._where}: nodes.{joint.name}.second_sensor"
        if not isinstance(raw, Mapping) or "index" not in raw or "counts_per_unit" not in raw:
            raise ValueError(
                f"{where}: a mapping {{index, subindex, counts_per_unit, tolerance, "
                f"latency_ms}} is needed, got {raw!r}"
            )
        extra = sorted(set(map(str, raw)) - _SECOND_KEYS)
        if extra:
            raise ValueError(f"{where}: unknown keys {extra}; known: {sorted(_SECOND_KEYS)}")
        index, sub = int(raw["index"]), int(raw.get("subindex", 0))
        cpu = float(raw["counts_per_unit"])
        tol = float(raw.get("tolerance", _SECOND_TOLERANCE.get(joint.type, 0.01)))
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

    # ------------------------------------------------------------------ statistics
    def stats(self) -> dict[str, Any]:  # type: ignore[override]
        """Base counters, the frame counters, the bus load, and per joint its node: the
        CiA 402 state, the NMT state, the last EMCY (code, meaning) and its frame counts."""
        out: dict[str, Any] = dict(super().stats())
        out.update(self._counters)
        out["bus_load"] = round(self.bus_load, 3)
        nodes: dict[str, Any] = {}
        for node in self._nodes:
            emcy = node.last_emcy
            nodes[node.joint] = {
                "node_id": node.node_id,
                "cia402": node.state(),
                "statusword": None if node.statusword is None else f"{node.statusword:#06x}",
                "nmt": None if node.nmt is None else NMT_STATES.get(node.nmt, hex(node.nmt)),
                "last_emcy": None
                if emcy is None
                else {
                    "code": f"{emcy[0]:#06x}",
                    "meaning": emcy_meaning(emcy[0]),
                    "register": f"{emcy[1]:#04x}",
                },  # fmt: skip
                "tpdos": node.tpdo1 + node.tpdo2,
                "emcys": node.emcys,
                "heartbeats": node.heartbeats,
            }
        out["nodes"] = nodes
        if self.last_fault is not None:
            out["last_fault"] = self.last_fault
        return out

    def _default_noise(self) -> Sequence[float] | None:
        # one count: what a healthy encoder's reading toggles by at rest
        return [1.0 / abs(n.cpu) for n in self._nodes]

    # ------------------------------------------------------------------ configure
    def _configure(self) -> None:
        import canopen

        try:
            bus = can.Bus(**self._bus_args)
        except (can.CanError, OSError, ImportError, ValueError, TypeError) as err:
            raise DriverError(f"{self._where}: cannot open bus {self._bus_args}: {err}") from err
        sock = getattr(bus, "socket", None)
        if self._bus_args["interface"] == "socketcan" and sock is not None:
            try:  # error frames, every class (python-can leaves them off; as the can driver)
                sock.setsockopt(
                    _socket.SOL_CAN_RAW, CAN_RAW_ERR_FILTER, struct.pack("=I", CAN_ERR_MASK)
                )
            except (OSError, AttributeError) as err:
                logger.warning("%s: error frames not enabled: %s", self._where, err)
        network = canopen.Network(bus)
        network.NOTIFIER_CYCLE = 0.01  # its reader thread stops within 10 ms
        echo = _EchoFilter(network.listeners[0], self._master_id)
        network.listeners = [echo]  # type: ignore[list-item]  # any can.Listener will do
        try:
            network.connect()
            for node in self._nodes:
                node.forget()
                remote = canopen.RemoteNode(node.node_id, node.od)
                network.add_node(remote)
                remote.sdo.RESPONSE_TIMEOUT = self._sdo_timeout
                self._configure_node(node, remote)
            for node in self._nodes:
                network[node.node_id].nmt.send_command(0x01)  # NMT start
        except BaseException:
            self._close(network, bus)
            raise
        notifier, network.notifier = network.notifier, None
        if notifier is not None:
            notifier.stop(1.0)  # from here on the loop reads the bus itself (read)
        self._counters["echoes"] += echo.dropped
        self._bus = bus
        self._network = network
        self._tick = 0
        self._t0 = math.nan
        self._master_hb_at = math.nan
        self._pos = [math.nan] * len(self.joints)
        for node in self._nodes:
            node.hb_at = node.tpdo_at = node.owed_since = node.sampled_at = math.nan
        # a first SYNC: every node's first TPDO is waiting for the first read (where it is)
        self._sync(rpdos=False)

    def _configure_node(self, node: _Node, remote: Any) -> None:
        import canopen

        nid = node.node_id
        remote.nmt.send_command(0x80)  # enter pre-operational: PDOs stop, SDO answers
        try:
            device = int.from_bytes(remote.sdo.upload(0x1000, 0), "little")
        except canopen.SdoAbortedError as err:
            raise self._sdo_error(node, 0x1000, 0, "device type", "read", err) from err
        except (canopen.SdoCommunicationError, can.CanError) as err:
            raise self._sdo_error(node, 0x1000, 0, "device type", "read", err) from err
        if device & 0xFFFF != 402:
            raise DriverError(
                f"{self._where}: {node.where}: device type {device:#010x} is not a CiA 402 "
                f"drive (profile {device & 0xFFFF}, not 402)"
            )
        mode = MODE_CST if self._effort else MODE_CSP
        target = 0x6071 if self._effort else 0x607A

        def entry(index: int, sub: int = 0, bits: int | None = None) -> int:
            return (index << 16) | (sub << 8) | (bits if bits is not None else _BITS[index])

        tpdo2 = [entry(0x606C)]
        if node.second is not None:
            tpdo2.append(entry(node.second[0], node.second[1], 32))
        period_value, period_index = _interpolation_period(self.period * self._sync_every)
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
            (0x1017, 0, self._node_hb_ms),
            (0x1016, 1, (self._master_id << 16) | self._consumer_ms),
        ]
        for index, sub, value in writes:
            var = node.od.get_variable(index, sub)
            name = var.name if var is not None else "?"
            try:
                if var is None:
                    raise DriverError(
                        f"{self._where}: {node.where}: the EDS {str(node.eds)!r} has no object "
                        f"{index:#06x}:{sub:02x}"
                    )
                remote.sdo.download(index, sub, var.encode_raw(value))
            except canopen.SdoAbortedError as err:
                raise self._sdo_error(node, index, sub, name, f"write {value:#x}", err) from err
            except (canopen.SdoCommunicationError, can.CanError) as err:
                raise self._sdo_error(node, index, sub, name, f"write {value:#x}", err) from err

    def _sdo_error(
        self, node: _Node, index: int, sub: int, name: str, what: str, err: Exception
    ) -> DriverError:
        code = getattr(err, "code", None)
        if code is not None:
            cause = f"aborted by the node with {code:#010x}: {sdo_abort_meaning(code)}"
        elif isinstance(err, can.CanError):
            cause = f"not sent: {err}"
        else:
            cause = f"no answer within {self._sdo_timeout * 1e3:.0f} ms (SDO timeout: {err})"
        return DriverError(
            f"{self._where}: {node.where}: configure: SDO {what} to {index:04X}:{sub:02X} "
            f"({name}) {cause}"
        )

    @staticmethod
    def _close(network: Any, bus: can.BusABC) -> None:
        notifier = getattr(network, "notifier", None)
        if notifier is not None:
            network.notifier = None
            try:
                notifier.stop(1.0)
            except Exception:  # noqa: BLE001 - closing anyway
                logger.exception("cia402: notifier did not stop")
        bus.shutdown()

    def _shutdown(self) -> None:
        bus, self._bus = self._bus, None
        network, self._network = self._network, None
        if bus is not None:
            self._close(network, bus)

    # ------------------------------------------------------------------ frames
    def _send(self, msg: can.Message) -> None:
        bus = self._bus
        if bus is None:
            return
        try:
            with self._send_lock:
                bus.send(msg, timeout=0.0005)
        except can.CanError as err:
            raise DriverError(
                f"{self._where}: send of {msg.arbitration_id:#05x} failed: {err}"
            ) from err

    def _pack(self, node: _Node, cw: int, target: int) -> None:
        node.cw = cw
        node.target = target
        (RPDO_CST if self._effort else RPDO_CSP).pack_into(node.rpdo, 0, cw, target)

    def _hold_target(self, node: _Node) -> int:
        """What an RPDO commands while not servoing: the measured position (CSP) or 0 (CST)."""
        if self._effort:
            return 0
        return node.counts if node.counts is not None else node.target

    def _sync(self, rpdos: bool) -> None:
        """Every node's RPDO (``rpdos``) and a SYNC, under one hold of the send lock."""
        bus = self._bus
        if bus is None:
            return
        counters = self._counters
        msg = self._sync_msg
        self._owe(self._now)
        try:
            with self._send_lock:
                if rpdos:
                    for node in self._nodes:
                        msg = node.rpdo_msg
                        bus.send(msg, timeout=0.0005)
                    counters["rpdo_frames"] += len(self._nodes)
                    msg = self._sync_msg
                bus.send(msg, timeout=0.0005)
        except can.CanError as err:
            raise DriverError(
                f"{self._where}: send of {msg.arbitration_id:#05x} failed: {err}"
            ) from err
        counters["sync_frames"] += 1

    def _owe(self, now: float) -> None:
        """A SYNC goes out at ``now``: every node owes a TPDO from then on."""
        for node in self._nodes:
            if node.owed_since != node.owed_since:
                node.owed_since = now

    def _take(self, msg: can.Message, now: float) -> None:
        """One received frame (module docstring): its node's state updated."""
        if msg.is_error_frame:
            self._counters["error_frames"] += 1
            if msg.arbitration_id & CAN_ERR_BUSOFF and self._bus_off is None:
                self._bus_off = msg.arbitration_id
            return
        if msg.is_remote_frame or msg.is_extended_id:
            self._counters["ignored_frames"] += 1
            return
        cob = msg.arbitration_id
        found = self._rx.get(cob)
        if found is None:
            if cob in self._own:  # its own frame, echoed (udp_multicast): the usual case
                self._counters["echoes"] += 1
                return
            key = "echoes" if master_sends(cob, self._master_id) else "ignored_frames"
            self._counters[key] += 1
            return
        kind, node = found
        data = msg.data
        if kind == _K_TPDO1:
            if len(data) < TPDO1.size:
                self._counters["ignored_frames"] += 1
                return
            sw, counts, torque = TPDO1.unpack_from(data)
            node.statusword = sw
            node.counts = counts
            i = node.index
            self._pos[i] = counts / node.cpu
            self._eff[i] = torque * node.torque_scale
            node.tpdo_at = now
            owed = node.owed_since
            node.sampled_at = owed if owed == owed else now
            node.owed_since = math.nan
            node.tpdo1 += 1
            self._counters["tpdo_frames"] += 1
        elif kind == _K_TPDO2:
            if node.second is not None and len(data) >= TPDO2_SECOND.size:
                vel, node.second_counts = TPDO2_SECOND.unpack_from(data)
            elif len(data) >= TPDO2.size:
                (vel,) = TPDO2.unpack_from(data)
            else:
                self._counters["ignored_frames"] += 1
                return
            self._vel[node.index] = vel / node.cpu
            node.tpdo2 += 1
            self._counters["tpdo_frames"] += 1
        elif kind == _K_EMCY:
            if len(data) < EMCY.size:
                self._counters["ignored_frames"] += 1
                return
            code, register = EMCY.unpack_from(data)
            node.emcys += 1
            self._counters["emcy_frames"] += 1
            if code != 0:  # 0: the node's error reset
                node.last_emcy = (code, register)
                if node.emcy_pending is None:
                    node.emcy_pending = (code, register)
        elif kind == _K_HB:
            if data:
                node.nmt = data[0] & 0x7F
                node.hb_at = now
                node.heartbeats += 1
                self._counters["heartbeat_frames"] += 1
        # _K_SDO: a late SDO answer from configure: nothing to do

    def _drain(self, now: float, limit: int = 0) -> int:
        bus = self._bus
        if bus is None:
            return 0
        taken = 0
        most = limit or 64 * len(self._nodes)
        while taken < most:
            try:
                msg = bus.recv(timeout=0.0)
            except can.CanError as err:
                raise DriverError(f"{self._where}: receive failed: {err}") from err
            if msg is None:
                break
            self._take(msg, now)
            taken += 1
        return taken

    def _wait_tpdo(self, before: list[int], deadline: float) -> None:
        """Take frames until every node's TPDO 1 count passed ``before`` or ``deadline``."""
        bus = self._bus
        if bus is None:
            return
        stamp = self._now
        while True:
            if all(n.tpdo1 > b for n, b in zip(self._nodes, before, strict=True)):
                return
            left = deadline - time.monotonic()
            if left <= 0.0 or self.activation_cancelled:
                return
            self._waiting_heartbeat()
            try:
                msg = bus.recv(timeout=min(left, 0.01))
            except can.CanError as err:
                raise DriverError(f"{self._where}: receive failed: {err}") from err
            if msg is not None:
                self._take(msg, stamp)

    # ------------------------------------------------------------------ the cycle
    def _read(self, now: float) -> tuple[Sequence[float], Sequence[float], Sequence[float]]:
        if self._t0 != self._t0:
            self._t0 = now
        self._now = now
        nodes = self._nodes
        if self._restamp:
            # heard while activate waited on another thread, stamped then with the last
            # read's now: heard now, as far as the ages go (the loop's time moved on)
            self._restamp = False
            for node in nodes:
                if node.hb_at == node.hb_at:
                    node.hb_at = now
                if node.owed_since == node.owed_since:
                    node.owed_since = now
        shown = [n.sampled_at for n in nodes]
        fresh = [n.tpdo1 for n in nodes]
        self._drain(now)
        joints = self.joints
        for i, node in enumerate(nodes):
            if node.tpdo1 != fresh[i] and shown[i] == shown[i]:
                # a new reading: the one it replaces was sampled then, not at the last read
                joints[i].stamp = shown[i]
        state = self.state
        if state is not DriverState.FAULT:
            why = self._judge(now, state is DriverState.ACTIVE)
            if why is not None:
                self.last_fault = why
                raise DriverError(why)
        if state is not DriverState.ACTIVE:
            self._tick += 1
            if self._tick % self._sync_every == 0:
                self._sync(rpdos=False)
        self._heartbeat(now)
        return self._pos, self._vel, self._eff

    def _waiting_heartbeat(self) -> None:
        """The master's heartbeat while activate or reset waits (the loop neither reads nor
        writes meanwhile): a node already enabled must not find its master silent."""
        if self._master_hb_s > 0.0:
            t = time.monotonic()
            if t - self._waiting_hb_at >= self._master_hb_s:
                self._waiting_hb_at = t
                self._send(self._hb_msg)

    def _heartbeat(self, now: float) -> None:
        """The master's heartbeat, every quarter of ``heartbeat_ms`` of reads and writes."""
        if self._master_hb_s > 0.0:
            last = self._master_hb_at
            if last != last or now - last >= self._master_hb_s:
                self._master_hb_at = now
                self._send(self._hb_msg)

    def _judge(self, now: float, active: bool) -> str | None:
        """The first fault among the nodes (module docstring, "Faults"), or None."""
        if self._bus_off is not None:
            return (
                f"{self._where}: bus-off on {self._bus_args['channel']}: the CAN controller "
                f"left the bus (error frame {self._bus_off:#x})"
            )
        t0 = self._t0
        for node in self._nodes:
            cause: str | None = None
            sw = node.statusword
            if node.emcy_pending is not None:
                code, register = node.emcy_pending
                cause = f"EMCY {code:#06x} ({emcy_meaning(code)}), error register {register:#04x}"
            elif sw is not None and sw & 0x08:
                cause = f"statusword {sw:#06x}: {cia402_state(sw)} (fault bit set)"
            elif active and sw is not None and sw & _OE_MASK != _OE_VALUE:
                cause = f"statusword {sw:#06x}: left OPERATION ENABLED, now {cia402_state(sw)}"
            elif node.nmt is not None and node.nmt != NMT_OPERATIONAL:
                cause = (
                    f"left NMT OPERATIONAL: its heartbeat says "
                    f"{NMT_STATES.get(node.nmt, hex(node.nmt))}"
                )
            else:
                seen = node.hb_at if node.hb_at == node.hb_at else t0
                if now - seen > self._node_hb_timeout:
                    cause = (
                        f"heartbeat consumer timeout: no heartbeat for {(now - seen) * 1e3:.1f} "
                        f"ms (producer time {self._node_hb_ms} ms, timeout "
                        f"{self._node_hb_timeout * 1e3:g} ms)"
                    )
                elif now - node.owed_since > self._feedback_timeout:  # NaN: nothing owed
                    cause = (
                        f"no TPDO for {(now - node.owed_since) * 1e3:.1f} ms since a SYNC asked "
                        f"for one (feedback_timeout {self._feedback_timeout * 1e3:g} ms)"
                    )
            if cause is None and node.second is not None:
                cause = self._second_check(node, now)
            if cause is not None:
                return f"{self._where}: {node.where}: {cause}"
        return None

    def _second_check(self, node: _Node, now: float) -> str | None:
        assert node.second is not None
        first = self._pos[node.index]
        counts = node.second_counts
        if counts is None or first != first:
            return None
        _, _, cpu, tol, latency = node.second
        second = counts / cpu
        distance = abs(first - second)
        if distance <= tol:
            node.second_since = math.nan
            return None
        since = node.second_since
        if since != since:
            node.second_since = since = now
        if now - since <= latency:
            return None
        return (
            f"joint {node.joint}: second position sensor disagrees by {distance:.6g} "
            f"(first {first:.6g}, second {second:.6g}; tolerance {tol:g} for more than "
            f"latency_ms {latency * 1e3:g}, now {(now - since) * 1e3:.1f} ms)"
        )

    def _write(self, values: Sequence[float], now: float) -> None:
        self._now = now
        self._tick += 1
        if self._tick % self._sync_every == 0:
            # packed only when sent: a synchronous RPDO takes effect at the SYNC, so the ticks
            # between would be overwritten unused (the base checked every one of them)
            cw = CW_ENABLE_OPERATION
            if self._effort:
                pack, bounds = RPDO_CST.pack_into, _INT16
                for i, node in enumerate(self._nodes):
                    target = _saturate(values[i] / node.torque_scale, bounds)
                    node.cw, node.target = cw, target
                    pack(node.rpdo, 0, cw, target)
            else:
                pack, lo, hi = RPDO_CSP.pack_into, _INT32[0], _INT32[1]
                for i, node in enumerate(self._nodes):
                    c = values[i] * node.cpu  # _saturate inline: every node, every SYNC
                    if c != c:
                        raise ValueError("NaN cannot be sent")
                    target = hi if c >= hi else lo if c <= lo else int(math.floor(c + 0.5))
                    node.cw, node.target = cw, target
                    pack(node.rpdo, 0, cw, target)
            self._sync(rpdos=True)
        self._heartbeat(now)

    # ------------------------------------------------------------------ state machine
    def _activate(self) -> None:
        unknown = [n.where for n in self._nodes if n.counts is None]
        if unknown:
            raise DriverError(f"{self._where}: {', '.join(unknown)}: no position reported yet")
        deadline = time.monotonic() + self._state_timeout
        steps = {
            "SWITCH ON DISABLED": CW_SHUTDOWN,
            "READY TO SWITCH ON": CW_SWITCH_ON,
            "SWITCHED ON": CW_ENABLE_OPERATION,
            "OPERATION ENABLED": CW_ENABLE_OPERATION,
        }
        self._waiting_hb_at = -math.inf
        self._restamp = True  # what it takes is stamped with the last read's now
        try:
            while True:
                if self.activation_cancelled:
                    # a safe stop or a cancel while powering up: off now (the base then
                    # latches FAULT and quick-stops, or leaves it INACTIVE)
                    self._stop_all(CW_DISABLE_VOLTAGE)
                    return
                self._waiting_heartbeat()
                self._drain(self._now)  # TPDOs of earlier SYNCs: judged before this step
                why = self._judge(self._now, active=False)
                if why is not None:
                    raise DriverError(f"{why}; not enabled")
                states = [n.state() for n in self._nodes]
                if all(s == "OPERATION ENABLED" for s in states):
                    break
                if time.monotonic() > deadline:
                    late = [
                        f"{n.where} in {s} (statusword {n.statusword or 0:#06x})"
                        for n, s in zip(self._nodes, states, strict=True)
                        if s != "OPERATION ENABLED"
                    ]
                    raise DriverError(
                        f"{self._where}: not OPERATION ENABLED within "
                        f"{self._state_timeout * 1e3:g} ms: {'; '.join(late)}"
                    )
                for node, s in zip(self._nodes, states, strict=True):
                    self._pack(node, steps.get(s, CW_DISABLE_VOLTAGE), self._hold_target(node))
                before = [n.tpdo1 for n in self._nodes]
                self._sync(rpdos=True)
                self._wait_tpdo(before, deadline)
        except DriverError as err:
            self._stop_all(CW_DISABLE_VOLTAGE)
            raise DriverError(f"{err}; every node switched off again") from err

    def _stop_all(self, cw: int) -> None:
        """``cw`` (quick stop or disable voltage) to every node at once, with a SYNC."""
        bus = self._bus
        if bus is None:
            return
        fmt = RPDO_CST if self._effort else RPDO_CSP
        for node in self._nodes:
            data = bytearray(fmt.size)
            fmt.pack_into(data, 0, cw, self._hold_target(node))
            node.cw = cw
            self._send(can.Message(arbitration_id=node.rpdo_msg.arbitration_id,
                                   is_extended_id=False, data=data))  # fmt: skip
        self._counters["rpdo_frames"] += len(self._nodes)
        self._owe(self._now)
        self._send(can.Message(arbitration_id=COB_SYNC, is_extended_id=False, data=b""))
        self._counters["sync_frames"] += 1
        for node in self._nodes:
            if node.nmt is not None and node.nmt != NMT_OPERATIONAL:
                # a node out of OPERATIONAL takes no PDO: the controlword as an expedited SDO
                # download, sent and not waited for (its answer is dropped by _take)
                request = struct.pack("<BHBH2x", 0x2B, 0x6040, 0, cw)
                self._send(can.Message(arbitration_id=COB_SDO_RX + node.node_id,
                                       is_extended_id=False, data=request))  # fmt: skip
        if cw == CW_QUICK_STOP:
            self._counters["quick_stops"] += 1

    def _deactivate(self) -> None:
        # a fault (the base calls this once FAULT is latched): quick stop; Disable: voltage off
        self._stop_all(CW_QUICK_STOP if self.state is DriverState.FAULT else CW_DISABLE_VOLTAGE)

    def _safe_stop(self) -> None:
        self._stop_all(CW_QUICK_STOP)

    def _reset(self) -> None:
        if self._bus is None:
            return  # never configured: the base configures it again
        self._restamp = True  # it may run off the loop thread: see _activate
        self._drain(self._now)  # what came before the reset was acted on
        self._bus_off = None
        for node in self._nodes:
            node.emcy_pending = None
            node.second_since = math.nan
        self._counters["fault_resets"] += 1
        network = self._network
        deadline = time.monotonic() + self._state_timeout
        edge = [False] * len(self._nodes)
        answered = [False] * len(self._nodes)
        while True:
            for i, node in enumerate(self._nodes):
                if node.nmt is not None and node.nmt != NMT_OPERATIONAL and network is not None:
                    network[node.node_id].nmt.send_command(0x01)
                    node.nmt = None  # judged again from its next heartbeat
                in_fault = node.statusword is not None and node.statusword & 0x08
                # the fault reset is bit 7's rising edge: 0x00, then 0x80
                cw = CW_FAULT_RESET if in_fault and edge[i] else CW_DISABLE_VOLTAGE
                edge[i] = bool(in_fault) and not edge[i]
                self._pack(node, cw, self._hold_target(node))
            before = [n.tpdo1 for n in self._nodes]
            self._sync(rpdos=True)
            self._wait_tpdo(before, deadline)
            for i, (node, b) in enumerate(zip(self._nodes, before, strict=True)):
                answered[i] = answered[i] or node.tpdo1 > b
            bad = [
                n for n, a in zip(self._nodes, answered, strict=True)
                if not a or (n.statusword or 0) & 0x08 or n.emcy_pending is not None
            ]  # fmt: skip
            if not bad:
                break
            if time.monotonic() > deadline:
                words = []
                for node, a in zip(self._nodes, answered, strict=True):
                    if node not in bad:
                        continue
                    if not a:
                        words.append(f"{node.where}: no TPDO answered the reset's SYNC")
                        continue
                    emcy = node.emcy_pending or node.last_emcy
                    tail = f" (EMCY {emcy[0]:#06x}: {emcy_meaning(emcy[0])})" if emcy else ""
                    words.append(f"{node.where}: still {node.state()}{tail}")
                raise DriverError(
                    f"{self._where}: fault reset refused within "
                    f"{self._state_timeout * 1e3:g} ms: {'; '.join(words)}"
                )
        self.last_fault = None


def _interpolation_period(seconds: float) -> tuple[int, int]:
    """0x60C2's (value, index): ``seconds = value x 10^index``, value 1-255."""
    for index in (-3, -4, -5, -6):
        value = seconds / 10.0**index
        if abs(value - round(value)) < 1e-6 and 1 <= round(value) <= 255:
            return round(value), index
    raise ValueError(f"interpolation period {seconds} s cannot be written to 0x60C2")
