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
``now`` (the driver has no clock of its own). The first read after it counts from its own
``now`` the ages of what was heard while it waited: the heartbeat of a node heard meanwhile,
and the TPDO owed for one of its SYNCs by a node that answered one of them. A node not heard
meanwhile keeps its ages (each node's counts are marked when the wait begins, after what came
before it is taken; a second wait before any read keeps the first one's marks).

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
raises naming the nodes that did not (a persisting cause). A reset waits as activate does, and
the first read after it likewise judges a node silent since before it on its real age.

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
drive mounted reversed), ``eds`` (a path, absolute or from the working directory, or the name
of an EDS shipped in occ/drivers/eds/: ``drive.eds``, the emulator's, is the default),
``rated_torque`` (N m or N at 1000 per mille of torque actual/target, default 1.0),
``second_sensor`` (optional: ``{index, subindex, counts_per_unit, tolerance, latency_ms}``, a
32-bit object mapped into TPDO 2; tolerance in rad or m, default 1 mm or 10 mrad by joint type,
latency 5 ms).

Without hardware: ``interface: virtual`` with :class:`occ.drivers.cia402_sim.DriveEmulator` in
the same process, or ``udp_multicast`` with ``python -m occ.drivers.cia402_sim`` in another.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Mapping, Sequence
from typing import Any

import can

from occ.drivers.base import CommandInterface, Driver, DriverState, LimitPolicy
from occ.drivers.can import round_saturated
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
    CW_QUICK_STOP,
    CW_SHUTDOWN,
    CW_SWITCH_ON,
    NMT_OPERATIONAL,
    STATUS_WORDS,
    master_sends,
)
from occ.drivers.cia402_setup import (
    CAN_ERR_BUSOFF,
    DEFAULT_EDS,
    RPDO_CSP,
    RPDO_CST,
    Node,
    bus_load,
    check_budget,
    close_network,
    enable_late,
    open_network,
    parse_nodes,
    read_settings,
)
from occ.errors import DriverError
from occ.joint import Joint

__all__ = ["CiA402Driver", "bus_load", "DEFAULT_EDS"]

logger = logging.getLogger(__name__)


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
_INT32 = (-(2**31), 2**31 - 1)
_INT16 = (-(2**15), 2**15 - 1)


#: OPERATION ENABLED's statusword mask and value (CiA 402's table), checked every read
#: the controlword that takes a node from each CiA 402 state towards OPERATION ENABLED
ENABLE_STEPS = {
    "SWITCH ON DISABLED": CW_SHUTDOWN,
    "READY TO SWITCH ON": CW_SWITCH_ON,
    "SWITCHED ON": CW_ENABLE_OPERATION,
    "OPERATION ENABLED": CW_ENABLE_OPERATION,
}
COUNTERS = (
    "sync_frames", "rpdo_frames", "tpdo_frames", "emcy_frames", "heartbeat_frames", "echoes",
    "ignored_frames", "quick_stops", "fault_resets", "error_frames",
)  # fmt: skip
_OE_MASK, _OE_VALUE = next((m, v) for m, v, name in STATUS_WORDS if name == "OPERATION ENABLED")

# frame kinds in the receive table
_K_TPDO1, _K_TPDO2, _K_EMCY, _K_HB, _K_SDO = range(5)


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
        self._effort = self.command_interface == "effort"
        st = read_settings(where, p, self.period, self.heartbeat_s, self._effort)
        self._settings = st
        self._bus_args = st.bus_args
        self._sync_every = st.sync_every
        self._feedback_timeout = st.feedback_timeout
        self._node_hb_ms, self._node_hb_timeout = st.node_hb_ms, st.node_hb_timeout
        self._master_id = st.master_id
        self._consumer_ms, self._master_hb_s = st.consumer_ms, st.master_hb_s
        self._sdo_timeout, self._state_timeout = st.sdo_timeout, st.state_timeout
        self._nodes = parse_nodes(where, self.joints, p["nodes"], self._effort, self._master_id)
        # the bus budget (module docstring)
        self.bus_load = check_budget(
            where, st, self._nodes, self.period, float(p["bus_load_limit"])
        )
        n = len(self.joints)
        self._rx: dict[int, tuple[int, Node]] = {}
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
        self._restamp = False  # a wait off the loop thread marked (_mark), not yet read
        self._send_lock = threading.Lock()
        self._counters = dict.fromkeys(COUNTERS, 0)
        #: the identifier of a bus-off error frame not yet acted on (None: none)
        self._bus_off: int | None = None
        self.last_fault: str | None = None

    # ------------------------------------------------------------------ statistics
    def stats(self) -> dict[str, Any]:  # type: ignore[override]
        """Base counters, the frame counters, the bus load, and per joint its node: the
        CiA 402 state, the NMT state, the last EMCY (code, meaning) and its frame counts."""
        out: dict[str, Any] = dict(super().stats())
        out.update(self._counters)
        out["bus_load"] = round(self.bus_load, 3)
        out["nodes"] = {node.joint: node.stats() for node in self._nodes}
        if self.last_fault is not None:
            out["last_fault"] = self.last_fault
        return out

    def _default_noise(self) -> Sequence[float] | None:
        # one count: what a healthy encoder's reading toggles by at rest
        return [1.0 / abs(n.cpu) for n in self._nodes]

    # ------------------------------------------------------------------ configure
    def _configure(self) -> None:
        bus, network, echoes = open_network(self._where, self._settings, self._nodes, self.period)
        self._counters["echoes"] += echoes
        self._bus = bus
        self._network = network
        self._tick, self._restamp = 0, False  # counts start again: no marks stand
        self._t0 = math.nan
        self._master_hb_at = math.nan
        self._pos = [math.nan] * len(self.joints)
        for node in self._nodes:
            node.hb_at = node.tpdo_at = node.owed_since = node.sampled_at = math.nan
        # a first SYNC: every node's first TPDO is waiting for the first read (where it is)
        self._sync(rpdos=False)

    def _shutdown(self) -> None:
        bus, self._bus = self._bus, None
        network, self._network = self._network, None
        if bus is not None:
            close_network(network, bus)

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

    def _pack(self, node: Node, cw: int, target: int) -> None:
        node.cw = cw
        node.target = target
        (RPDO_CST if self._effort else RPDO_CSP).pack_into(node.rpdo, 0, cw, target)

    def _hold_target(self, node: Node) -> int:
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
        counters = self._counters
        if kind == _K_TPDO1:
            got = node.take_tpdo1(data, now)
            if got is None:
                counters["ignored_frames"] += 1
                return
            i = node.index
            self._pos[i], self._eff[i] = got
            counters["tpdo_frames"] += 1
        elif kind == _K_TPDO2:
            vel = node.take_tpdo2(data)
            if vel is None:
                counters["ignored_frames"] += 1
                return
            self._vel[node.index] = vel
            counters["tpdo_frames"] += 1
        elif kind == _K_EMCY:
            if not node.take_emcy(data):
                counters["ignored_frames"] += 1
                return
            counters["emcy_frames"] += 1
        elif kind == _K_HB and node.take_heartbeat(data, now):
            counters["heartbeat_frames"] += 1
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
            self._restamp = False  # after a wait off the loop thread (_mark)
            for node in nodes:
                node.restamp(now)
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
        t0, settings = self._t0, self._settings
        for node in self._nodes:
            cause = node.fault(now, active, t0, settings, self._pos[node.index])
            if cause is not None:
                return f"{self._where}: {node.where}: {cause}"
        return None

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
                    target = round_saturated(values[i] / node.torque_scale, *bounds)
                    node.cw, node.target = cw, target
                    pack(node.rpdo, 0, cw, target)
            else:
                pack, lo, hi = RPDO_CSP.pack_into, _INT32[0], _INT32[1]
                for i, node in enumerate(self._nodes):
                    c = values[i] * node.cpu  # round_saturated inline: every node, every SYNC
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
        self._waiting_hb_at = -math.inf
        self._mark()
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
                    raise DriverError(enable_late(self._where, self._nodes, self._state_timeout))
                for node, s in zip(self._nodes, states, strict=True):
                    self._pack(
                        node, ENABLE_STEPS.get(s, CW_DISABLE_VOLTAGE), self._hold_target(node)
                    )
                before = [n.tpdo1 for n in self._nodes]
                self._sync(rpdos=True)
                self._wait_tpdo(before, deadline)
        except DriverError as err:
            self._stop_all(CW_DISABLE_VOLTAGE)
            raise DriverError(f"{err}; every node switched off again") from err

    def _mark(self) -> None:
        """A wait off the loop thread begins: what came before taken, each node's counts marked
        (a second wait before any read keeps the first's); the first read restamps (_read)."""
        self._drain(self._now)
        if not self._restamp:
            self._restamp = True
            for node in self._nodes:
                node.mark()

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
            msg = node.controlword_by_sdo(cw)  # out of OPERATIONAL: no PDO taken
            if msg is not None:
                self._send(msg)
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
        self._mark()  # it may run off the loop thread, as activate
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
                cw, edge[i] = node.fault_reset_word(edge[i])
                self._pack(node, cw, self._hold_target(node))
            before = [n.tpdo1 for n in self._nodes]
            self._sync(rpdos=True)
            self._wait_tpdo(before, deadline)
            for i, (node, b) in enumerate(zip(self._nodes, before, strict=True)):
                answered[i] = answered[i] or node.tpdo1 > b
            words = [
                w for n, a in zip(self._nodes, answered, strict=True)
                if (w := n.reset_refusal(a)) is not None
            ]  # fmt: skip
            if not words:
                break
            if time.monotonic() > deadline:
                raise DriverError(
                    f"{self._where}: fault reset refused within "
                    f"{self._state_timeout * 1e3:g} ms: {'; '.join(words)}"
                )
