"""A CiA 402 servo drive emulator: CANopen slave nodes on a python-can bus.

One :class:`DriveEmulator` plays one or more drives (node ids) on one bus. Each node's object
dictionary comes from an EDS (``canopen.import_od``; by default occ/drivers/eds/drive.eds,
shipped as package data) and it answers as a CiA 301/402 slave would:

- **NMT**: boot-up message, then PRE-OPERATIONAL; start, stop, enter pre-operational, reset
  node and reset communication (both back to PRE-OPERATIONAL). A heartbeat on every state
  change, and every producer time (0x1017) after that.
- **SDO server**: expedited and segmented upload and download (block transfer is answered with
  an abort), with the CiA 301 abort codes for a missing object or sub-index, a read-only object,
  a length that does not match, an object that cannot be mapped or a mapping too long.
- **PDOs** as configured over SDO (0x1400-0x1403/0x1600-0x1603, 0x1800-0x1803/0x1A00-0x1A03):
  a synchronous RPDO (transmission type 0-240) is applied at the next SYNC, an asynchronous
  one (254, 255) on arrival; a synchronous TPDO is sent every N-th SYNC (type N, 1-240).
- **Heartbeat consumer** (0x1016 sub 1: the master's node id and time): the master's
  heartbeat missing for that long while OPERATION ENABLED is a fault, EMCY 0x8130.
- **CiA 402**: the device control state machine driven by the controlword (0x6040), shown in
  the statusword (0x6041); quick stop option 2 (stop, then SWITCH ON DISABLED); fault reset on
  the rising edge of bit 7, refused while the cause persists.
- **Dynamics** at each SYNC, over the interpolation period (0x60C2): in CSP (mode 8) a
  first-order servo following the target position (``bandwidth_hz``); in CST (mode 10) the
  target torque into a damped mass. Position actual (0x6064, counts), velocity actual
  (0x606C, counts/s), torque actual (0x6077, per mille), following error actual (0x60F4),
  the following error window (0x6065) and time out (0x6066): outside it, EMCY 0x8611. A second
  encoder (0x2100) reads the position times ``second_ratio``, plus an injected offset.
- **Faults to inject** (methods of :class:`DriveEmulator`, or lines on standard input when run
  as a process): an EMCY with a code (the node goes to FAULT), the statusword's fault bit
  alone (no EMCY), heartbeat stopped, TPDOs muted or paused, a stalled motor (the following
  error grows: EMCY 0x8611), an NMT state change on the node's own, an enable the node refuses,
  an SDO abort on a chosen object, a second encoder that disagrees. ``persist=True`` keeps the
  cause until :meth:`DriveEmulator.clear`: a fault reset is refused meanwhile.

Why raw python-can frames and not canopen's ``LocalNode``: the emulator must step its dynamics
on each SYNC and send its TPDOs in the same step, answer an SDO with a chosen abort, delay or
drop any frame, and (in tests) do all of it on the caller's thread at a point the test chooses
(:meth:`DriveEmulator.settle`), so that a test is deterministic. ``LocalNode`` answers from the
notifier's thread, produces no TPDO on SYNC by itself and offers no place for these faults;
what the emulator takes from canopen is the EDS parser and the data types of its objects.

Time: by default the wall clock (``time.monotonic``), for a separate process. A test passes
``clock`` (its simulated time): then the heartbeats are produced and the heartbeat consumer
judged only while frames are handled, under the emulator's lock, so nothing happens between
two calls of the test that the test did not cause. The dynamics always step by the
interpolation period, once per SYNC.

Run as a process (udp_multicast: every process on the host that opens the group is on the bus)::

    python -m occ.drivers.cia402_sim --interface udp_multicast --channel 239.74.163.2 \\
        --nodes 1,2,3 --eds occ/drivers/eds/drive.eds

and type fault commands on its standard input, one a line (``help`` lists them)::

    emcy 2 0x2310          fault bit 3   heartbeat 2 off   tpdo 1 off   pause 1 50
    stall 3                nmt 2 pre     refuse 1          abort 2 0x6060 0 0x06090030
    second 1 500           clear 2       status

and ``timing`` (``timing reset``) for the master's cycle as the drives receive it: the time
from the cycle's first and last RPDO to its SYNC and from the SYNC to the TPDOs answering it
(:class:`CycleTimes`), one JSON line.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import struct
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import can

from occ.drivers.cia402_protocol import (
    COB_EMCY,
    COB_HEARTBEAT,
    COB_NMT,
    COB_RPDO,
    COB_SDO_RX,
    COB_SDO_TX,
    COB_SYNC,
    CW_FAULT_RESET,
    MODE_CSP,
    MODE_CST,
    NMT_BOOT,
    NMT_ENTER_PRE_OPERATIONAL,
    NMT_OPERATIONAL,
    NMT_PRE_OPERATIONAL,
    NMT_RESET_COMMUNICATION,
    NMT_RESET_NODE,
    NMT_START,
    NMT_STATES,
    NMT_STOP,
    NMT_STOPPED,
    SW_FOLLOWING_ERROR,
    SW_FOLLOWS_TARGET,
    SW_QUICK_STOP,
    SW_REMOTE,
    SW_TARGET_REACHED,
    SW_VOLTAGE_ENABLED,
    emcy_meaning,
)
from occ.drivers.cia402_setup import DEFAULT_EDS

__all__ = ["DriveEmulator", "EmulatedNode", "DEFAULT_EDS", "main"]

logger = logging.getLogger(__name__)


# CiA 402 states, as statusword state bits
NOT_READY = 0x0000
SWITCH_ON_DISABLED = 0x0040
READY_TO_SWITCH_ON = 0x0021
SWITCHED_ON = 0x0023
OPERATION_ENABLED = 0x0027
QUICK_STOP_ACTIVE = 0x0007
FAULT = 0x0008
STATE_NAMES = {
    NOT_READY: "NOT READY TO SWITCH ON",
    SWITCH_ON_DISABLED: "SWITCH ON DISABLED",
    READY_TO_SWITCH_ON: "READY TO SWITCH ON",
    SWITCHED_ON: "SWITCHED ON",
    OPERATION_ENABLED: "OPERATION ENABLED",
    QUICK_STOP_ACTIVE: "QUICK STOP ACTIVE",
    FAULT: "FAULT",
}

#: struct codes of the CANopen basic data types (CiA 301 data type indices)
_STRUCT = {
    0x1: "?",
    0x2: "b",
    0x3: "h",
    0x4: "i",
    0x5: "B",
    0x6: "H",
    0x7: "I",
    0x15: "q",
    0x1B: "Q",
}
_ABORT_NO_OBJECT = 0x06020000
_ABORT_NO_SUB = 0x06090011
_ABORT_READ_ONLY = 0x06010002
_ABORT_WRITE_ONLY = 0x06010001
_ABORT_LENGTH = 0x06070010
_ABORT_NOT_MAPPABLE = 0x06040041
_ABORT_PDO_LENGTH = 0x06040042
_ABORT_COMMAND = 0x05040001
_ABORT_TOGGLE = 0x05030000
_ABORT_STATE = 0x08000022


class _Abort(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(f"{code:#010x}")
        self.code = code


class EmulatedNode:
    """One emulated CiA 402 drive (its object dictionary, NMT and device state, dynamics)."""

    def __init__(
        self,
        node_id: int,
        eds: str | Path,
        send: Callable[[int, bytes], None],
        *,
        bandwidth_hz: float = 40.0,
        second_ratio: float = 1.0,
        torque_per_count: float = 0.05,
        accel_per_permille: float = 2000.0,
        damping: float = 20.0,
    ) -> None:
        import canopen  # the EDS parser (the emulator's only use of canopen)

        if not 1 <= node_id <= 127:
            raise ValueError(f"node id {node_id} outside 1-127")
        self.node_id = node_id
        self._send = send
        self.od = canopen.import_od(str(eds), node_id=node_id)
        #: (index, subindex) -> the canopen variable describing it
        self.vars: dict[tuple[int, int], Any] = {}
        for obj in self.od.values():
            subs = list(obj.values()) if hasattr(obj, "subindices") else [obj]
            for var in subs:
                self.vars[(var.index, var.subindex)] = var
        self.values: dict[tuple[int, int], Any] = {}
        self.bandwidth_hz = bandwidth_hz
        self.second_ratio = second_ratio
        self.torque_per_count = torque_per_count
        self.accel_per_permille = accel_per_permille
        self.damping = damping
        # fault injection
        self.persist = False  # the injected cause stays until clear(): fault reset refused
        self.heartbeat_on = True
        self.tpdo_on = True
        self.tpdo_paused_until = -math.inf
        self.stalled = False
        self.refuse_enable = False
        self.second_offset = 0.0
        self.sdo_aborts: dict[tuple[int, int], int] = {}
        # counters
        self.syncs = 0
        self.rpdos = 0
        self.tpdos = 0
        self.emcys = 0
        self.sdo_requests = 0
        self.quick_stops = 0
        self.fault_resets_refused = 0
        self.controlwords: list[int] = []  # every controlword applied, in order (tests)
        self._reset_od()
        self.nmt = NMT_BOOT
        self.state = NOT_READY

    # ------------------------------------------------------------ object dictionary
    def _reset_od(self) -> None:
        for key, var in self.vars.items():
            default = var.default if var.default is not None else 0
            self.values[key] = default
        self.position = 0.0  # counts (float: the dynamics' state)
        self.velocity = 0.0  # counts/s
        self.torque = 0.0  # per mille
        self.fe_since = math.nan
        self.cw_prev = 0
        self.pending_rpdo: dict[int, bytes] = {}
        self._sdo_down: tuple[int, int, bytearray, int] | None = None  # index, sub, data, toggle
        self._sdo_up: tuple[bytes, int, int] | None = None  # data, offset, toggle
        self._pdo_cache: dict[int, list[tuple[int, int, str]]] = {}
        self.hb_next = math.nan
        self.master_seen = math.nan

    def get(self, index: int, subindex: int = 0) -> Any:
        return self.values[(index, subindex)]

    def set(self, index: int, subindex: int, value: Any) -> None:
        self.values[(index, subindex)] = value

    def _var(self, index: int, subindex: int) -> Any:
        var = self.vars.get((index, subindex))
        if var is None:
            if not any(k[0] == index for k in self.vars):
                raise _Abort(_ABORT_NO_OBJECT)
            raise _Abort(_ABORT_NO_SUB)
        return var

    def _encode(self, var: Any, value: Any) -> bytes:
        return bytes(var.encode_raw(value))

    def sdo_read(self, index: int, subindex: int) -> bytes:
        if (index, subindex) in self.sdo_aborts:
            raise _Abort(self.sdo_aborts[(index, subindex)])
        var = self._var(index, subindex)
        if var.access_type == "wo":
            raise _Abort(_ABORT_WRITE_ONLY)
        return self._encode(var, self.values[(index, subindex)])

    def sdo_write(self, index: int, subindex: int, data: bytes, now: float) -> None:
        if (index, subindex) in self.sdo_aborts:
            raise _Abort(self.sdo_aborts[(index, subindex)])
        var = self._var(index, subindex)
        if var.access_type in ("ro", "const"):
            raise _Abort(_ABORT_READ_ONLY)
        code = _STRUCT.get(var.data_type)
        if code is not None and len(data) != struct.calcsize(code):
            raise _Abort(_ABORT_LENGTH)
        value = var.decode_raw(data)
        self._write_object(index, subindex, value, now)

    def _write_object(self, index: int, subindex: int, value: Any, now: float) -> None:
        if 0x1600 <= index <= 0x1603 or 0x1A00 <= index <= 0x1A03:
            if subindex > 0 and value:
                mapped = self.vars.get(((value >> 16) & 0xFFFF, (value >> 8) & 0xFF))
                if mapped is None or not mapped.pdo_mappable:
                    raise _Abort(_ABORT_NOT_MAPPABLE)
            if subindex == 0:
                bits = sum(self.get(index, s) & 0xFF for s in range(1, value + 1))
                if bits > 64:
                    raise _Abort(_ABORT_PDO_LENGTH)
            self._pdo_cache.clear()
        elif 0x1400 <= index <= 0x1403 or 0x1800 <= index <= 0x1803:
            self._pdo_cache.clear()
        self.values[(index, subindex)] = value
        if index == 0x6040:
            self._controlword(int(value))
        elif index == 0x1017:
            self.hb_next = now  # restart the producer
        elif index == 0x6060:
            self.values[(0x6061, 0)] = value

    def _mapping(self, mapping_index: int) -> list[tuple[int, int, str]]:
        """The objects a PDO maps: (index, subindex, struct code), cached until changed."""
        cached = self._pdo_cache.get(mapping_index)
        if cached is None:
            cached = []
            for s in range(1, int(self.get(mapping_index, 0)) + 1):
                entry = int(self.get(mapping_index, s))
                index, sub = (entry >> 16) & 0xFFFF, (entry >> 8) & 0xFF
                var = self.vars[(index, sub)]
                cached.append((index, sub, _STRUCT[var.data_type]))
            self._pdo_cache[mapping_index] = cached
        return cached

    # ------------------------------------------------------------ NMT and heartbeat
    def boot(self, now: float) -> None:
        self.nmt = NMT_BOOT
        self._send(COB_HEARTBEAT + self.node_id, bytes([NMT_BOOT]))
        self.nmt = NMT_PRE_OPERATIONAL
        self.state = SWITCH_ON_DISABLED  # NOT READY -> SWITCH ON DISABLED once initialised
        self.hb_next = now

    def set_nmt(self, state: int, now: float) -> None:
        if state != self.nmt:
            self.nmt = state
            self._heartbeat(now)

    def nmt_command(self, command: int, now: float) -> None:
        if command == NMT_START:
            self.set_nmt(NMT_OPERATIONAL, now)
        elif command == NMT_STOP:
            self.set_nmt(NMT_STOPPED, now)
        elif command == NMT_ENTER_PRE_OPERATIONAL:
            self.set_nmt(NMT_PRE_OPERATIONAL, now)
        elif command in (NMT_RESET_NODE, NMT_RESET_COMMUNICATION):
            if command == NMT_RESET_NODE:
                position = self.position
                self._reset_od()
                self.position = position
                self.state = NOT_READY
            self.boot(now)

    def _heartbeat(self, now: float) -> None:
        period_ms = int(self.get(0x1017, 0))
        if period_ms > 0:
            self.hb_next = now + period_ms * 1e-3
        if self.heartbeat_on:
            self._send(COB_HEARTBEAT + self.node_id, bytes([self.nmt]))

    def timers(self, now: float) -> None:
        """The heartbeat producer and consumer at ``now``."""
        period_ms = int(self.get(0x1017, 0))
        if period_ms > 0 and not now < self.hb_next:
            self._heartbeat(now)
        consumer = int(self.get(0x1016, 1))
        time_ms = consumer & 0xFFFF
        seen = self.master_seen
        if time_ms and seen == seen and now - seen > time_ms * 1e-3:
            self.master_seen = math.nan  # judged once per heartbeat lost
            if self.state == OPERATION_ENABLED:
                self.fault(0x8130, now)

    def master_heartbeat(self, master_id: int, now: float) -> None:
        consumer = int(self.get(0x1016, 1))
        if (consumer >> 16) & 0x7F == master_id:
            self.master_seen = now

    # ------------------------------------------------------------ CiA 402 device control
    def statusword(self) -> int:
        state = self.state
        sw = state | SW_REMOTE
        if state in (READY_TO_SWITCH_ON, SWITCHED_ON, OPERATION_ENABLED):
            sw |= SW_QUICK_STOP | SW_VOLTAGE_ENABLED
        elif state == QUICK_STOP_ACTIVE:
            sw |= SW_VOLTAGE_ENABLED
        if state == OPERATION_ENABLED:
            mode = int(self.get(0x6060, 0))
            if mode == MODE_CSP:
                sw |= SW_FOLLOWS_TARGET
                if abs(self.get(0x607A, 0) - self.position) < 1.0:
                    sw |= SW_TARGET_REACHED
                if self.fe_since == self.fe_since:
                    sw |= SW_FOLLOWING_ERROR
        return sw

    def _controlword(self, cw: int) -> None:
        prev, self.cw_prev = self.cw_prev, cw
        self.controlwords.append(cw)
        state = self.state
        if state == FAULT:
            if cw & CW_FAULT_RESET and not prev & CW_FAULT_RESET:
                if self.persist:
                    self.fault_resets_refused += 1
                    self.emcy(int(self.get(0x603F, 0)))  # still there: said again
                else:
                    self.state = SWITCH_ON_DISABLED
                    self.set(0x603F, 0, 0)
                    self.set(0x1001, 0, 0)
                    self.emcy(0x0000)  # error reset
            return
        if state == NOT_READY:
            return
        if cw & 0x82 == 0x00:  # disable voltage
            self.state = SWITCH_ON_DISABLED
        elif cw & 0x86 == 0x02:  # quick stop
            if state == OPERATION_ENABLED:
                self.quick_stops += 1
                self.state = QUICK_STOP_ACTIVE
            elif state != QUICK_STOP_ACTIVE:
                self.state = SWITCH_ON_DISABLED
        elif cw & 0x87 == 0x06:  # shutdown
            if state in (SWITCH_ON_DISABLED, SWITCHED_ON, OPERATION_ENABLED):
                self.state = READY_TO_SWITCH_ON
        elif cw & 0x8F == 0x07:  # switch on / disable operation
            if state in (READY_TO_SWITCH_ON, OPERATION_ENABLED):
                self.state = SWITCHED_ON
        elif cw & 0x8F == 0x0F:  # enable operation (from READY: switch on, then enable)
            if state in (SWITCHED_ON, READY_TO_SWITCH_ON):
                if self.refuse_enable:
                    self.state = SWITCHED_ON
                else:
                    self.state = OPERATION_ENABLED
                    self.values[(0x607A, 0)] = round(self.position)  # no jump at enable
                    self.fe_since = math.nan

    def fault(self, code: int, now: float, *, send_emcy: bool = True) -> None:
        """Enter FAULT with error code ``code`` (0x603F), announced by an EMCY unless not."""
        self.state = FAULT
        self.velocity = 0.0
        self.set(0x603F, 0, code)
        self.set(0x1001, 0, 0x01 | (0x02 if code & 0xF000 == 0x2000 else 0))
        if send_emcy:
            self.emcy(code)

    def emcy(self, code: int) -> None:
        self.emcys += 1
        data = struct.pack("<HB5x", code, int(self.get(0x1001, 0)))
        self._send(COB_EMCY + self.node_id, data)

    # ------------------------------------------------------------ PDOs and the cycle
    def rpdo(self, k: int, data: bytes, now: float) -> None:
        if self.nmt != NMT_OPERATIONAL:
            return
        self.rpdos += 1
        if int(self.get(0x1400 + k, 2)) <= 240:
            self.pending_rpdo[k] = data
        else:
            self._apply_rpdo(k, data, now)

    def _apply_rpdo(self, k: int, data: bytes, now: float) -> None:
        mapping = self._mapping(0x1600 + k)
        fmt = "<" + "".join(code for _, _, code in mapping)
        if len(data) < struct.calcsize(fmt):
            self.emcy(0x8210)
            return
        for (index, sub, _), value in zip(mapping, struct.unpack_from(fmt, data), strict=True):
            if index == 0x6040:
                continue  # applied last: the targets it enables are in place first
            self._write_object(index, sub, value, now)
        for (index, sub, _), value in zip(mapping, struct.unpack_from(fmt, data), strict=True):
            if index == 0x6040:
                self._write_object(index, sub, value, now)

    def sync(self, now: float) -> None:
        if self.nmt != NMT_OPERATIONAL:
            return
        self.syncs += 1
        pending, self.pending_rpdo = self.pending_rpdo, {}
        for k in sorted(pending):
            self._apply_rpdo(k, pending[k], now)
        self.step(self.interpolation_period(), now)
        if not self.tpdo_on or now < self.tpdo_paused_until:
            return
        for k in range(4):
            cob = int(self.get(0x1800 + k, 1))
            kind = int(self.get(0x1800 + k, 2))
            if cob & 0x80000000 or not 1 <= kind <= 240 or self.syncs % kind:
                continue
            mapping = self._mapping(0x1A00 + k)
            fmt = "<" + "".join(code for _, _, code in mapping)
            values = [self.values[(i, s)] for i, s, _ in mapping]
            self.tpdos += 1
            self._send(cob & 0x7FF, struct.pack(fmt, *values))

    def interpolation_period(self) -> float:
        return float(self.get(0x60C2, 1)) * 10.0 ** int(self.get(0x60C2, 2))

    def step(self, dt: float, now: float) -> None:
        """The motor over ``dt`` s in the present state and mode."""
        mode = int(self.get(0x6060, 0))
        before = self.position
        if self.state == OPERATION_ENABLED and not self.stalled:
            if mode == MODE_CSP:
                target = float(self.get(0x607A, 0))
                alpha = 1.0 - math.exp(-dt * 2.0 * math.pi * self.bandwidth_hz)
                self.position += (target - self.position) * alpha
                self.torque = max(
                    -3000.0, min(3000.0, (target - self.position) * self.torque_per_count)
                )
            elif mode == MODE_CST:
                self.torque = float(self.get(0x6071, 0))
                accel = self.torque * self.accel_per_permille - self.damping * self.velocity
                self.velocity += accel * dt
                self.position += self.velocity * dt
        elif self.state == QUICK_STOP_ACTIVE:
            self.torque = 0.0
            self.state = SWITCH_ON_DISABLED  # quick stop option 2: stopped, then disabled
        else:
            self.torque = 0.0
        if mode != MODE_CST or self.state != OPERATION_ENABLED:
            self.velocity = (self.position - before) / dt if dt > 0.0 else 0.0
        counts = int(round(self.position))
        self.set(0x6064, 0, counts)
        self.set(0x606C, 0, int(round(self.velocity)))
        self.set(0x6077, 0, int(round(self.torque)))
        self.set(0x2100, 0, int(round(self.position * self.second_ratio + self.second_offset)))
        self.set(0x6041, 0, self.statusword())
        if self.state == OPERATION_ENABLED and mode == MODE_CSP:
            error = int(self.get(0x607A, 0)) - counts
            self.set(0x60F4, 0, error)
            window = int(self.get(0x6065, 0))
            if window != 0xFFFFFFFF and abs(error) > window:
                if self.fe_since != self.fe_since:
                    self.fe_since = now
                if now - self.fe_since >= int(self.get(0x6066, 0)) * 1e-3:
                    self.fault(0x8611, now)
                    self.set(0x6041, 0, self.statusword())
            else:
                self.fe_since = math.nan

    # ------------------------------------------------------------ SDO server
    def sdo(self, data: bytes, now: float) -> bytes:
        """The answer to one SDO request (an abort when it fails)."""
        self.sdo_requests += 1
        data = bytes(data).ljust(8, b"\x00")
        ccs = data[0] >> 5
        index, sub = struct.unpack_from("<HB", data, 1)
        try:
            if ccs == 1:  # initiate download
                if data[0] & 0x02:  # expedited
                    n = (data[0] >> 2) & 0x3 if data[0] & 0x01 else 0
                    self.sdo_write(index, sub, data[4 : 8 - n], now)
                    self._sdo_down = None
                else:
                    self._var(index, sub)  # a missing object is refused before the data
                    if (index, sub) in self.sdo_aborts:
                        raise _Abort(self.sdo_aborts[(index, sub)])
                    self._sdo_down = (index, sub, bytearray(), 0)
                return struct.pack("<BHB4x", 0x60, index, sub)
            if ccs == 0:  # download segment
                if self._sdo_down is None:
                    raise _Abort(_ABORT_COMMAND)
                index, sub, buf, toggle = self._sdo_down
                if (data[0] >> 4) & 1 != toggle:
                    raise _Abort(_ABORT_TOGGLE)
                n = (data[0] >> 1) & 0x7
                buf += data[1 : 8 - n]
                self._sdo_down = (index, sub, buf, toggle ^ 1)
                if data[0] & 0x01:  # last
                    self._sdo_down = None
                    self.sdo_write(index, sub, bytes(buf), now)
                return bytes([0x20 | (toggle << 4)]) + bytes(7)
            if ccs == 2:  # initiate upload
                value = self.sdo_read(index, sub)
                if len(value) <= 4:
                    head = 0x43 | ((4 - len(value)) << 2)
                    return struct.pack("<BHB", head, index, sub) + value.ljust(4, b"\x00")
                self._sdo_up = (value, 0, 0)
                return struct.pack("<BHBI", 0x41, index, sub, len(value))
            if ccs == 3:  # upload segment
                if self._sdo_up is None:
                    raise _Abort(_ABORT_COMMAND)
                value, offset, toggle = self._sdo_up
                if (data[0] >> 4) & 1 != toggle:
                    raise _Abort(_ABORT_TOGGLE)
                chunk = value[offset : offset + 7]
                last = offset + 7 >= len(value)
                self._sdo_up = None if last else (value, offset + 7, toggle ^ 1)
                head = (toggle << 4) | ((7 - len(chunk)) << 1) | (1 if last else 0)
                return bytes([head]) + chunk.ljust(7, b"\x00")
            if ccs == 4:  # abort from the client
                self._sdo_down = self._sdo_up = None
                return b""
            raise _Abort(_ABORT_COMMAND)
        except _Abort as err:
            self._sdo_down = self._sdo_up = None
            return struct.pack("<BHBI", 0x80, index, sub, err.code)
        except (ValueError, struct.error):
            self._sdo_down = self._sdo_up = None
            return struct.pack("<BHBI", 0x80, index, sub, _ABORT_STATE)

    def describe(self) -> dict[str, Any]:
        code = int(self.get(0x603F, 0))
        return {
            "nmt": NMT_STATES.get(self.nmt, hex(self.nmt)),
            "state": STATE_NAMES.get(self.state, hex(self.state)),
            "position": int(self.get(0x6064, 0)),
            "error_code": f"{code:#06x} {emcy_meaning(code)}",
            "syncs": self.syncs,
            "tpdos": self.tpdos,
            "rpdos": self.rpdos,
            "emcys": self.emcys,
            "quick_stops": self.quick_stops,
        }


class CycleTimes:
    """The master's cycle as the emulated drives receive it, per SYNC (tools/cia402_e2e.py
    reports it; docs/BENCHMARKS.md, "CiA 402 drives"):

    - ``rpdo_to_sync``: from the first RPDO received since the previous SYNC to this SYNC (the
      span of the master's setpoints and SYNC on the bus);
    - ``setpoints_ready``: from the last RPDO received since the previous SYNC to this SYNC (how
      long before the SYNC every setpoint of the cycle was there: the margin a drive has);
    - ``sync_to_tpdo``: from this SYNC's arrival to the emulator's last TPDO answering it
      handed to the bus (the drive's reply time, as a master would see it less the wire).

    Arrival is a frame's receive timestamp (the kernel's on ``udp_multicast`` and SocketCAN; the
    sender's on ``virtual``), so the time a frame waited for the emulator's thread counts in
    ``sync_to_tpdo`` and not in the other two. A SYNC with no RPDO before it (the driver's SYNC
    while not servoing, or a lost cycle) is counted in ``syncs_without_rpdo``. Per frame it costs
    a comparison or two and, per SYNC, two appends to bounded deques; the percentiles are worked
    out only when :meth:`summary` is asked.
    """

    KEEP = 100_000  # SYNCs kept: 200 s at a 2 ms SYNC

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Start again (the tool does so when the motion it watches begins)."""
        self.rpdos = 0
        self.first = self.last = 0.0
        self.syncs = 0
        self.syncs_without_rpdo = 0
        self.rpdo_to_sync: deque[float] = deque(maxlen=self.KEEP)
        self.setpoints_ready: deque[float] = deque(maxlen=self.KEEP)
        self.sync_to_tpdo: deque[float] = deque(maxlen=self.KEEP)

    def copy(self) -> CycleTimes:
        """A copy to summarise away from the emulator's lock."""
        other = CycleTimes()
        other.syncs, other.syncs_without_rpdo = self.syncs, self.syncs_without_rpdo
        other.rpdo_to_sync.extend(self.rpdo_to_sync)
        other.setpoints_ready.extend(self.setpoints_ready)
        other.sync_to_tpdo.extend(self.sync_to_tpdo)
        return other

    def rpdo(self, at: float) -> None:
        if not self.rpdos:
            self.first = at
        self.last = at
        self.rpdos += 1

    def sync(self, at: float, answered: float | None) -> None:
        """A SYNC that arrived ``at``; ``answered``: when its last TPDO was sent (None: none)."""
        self.syncs += 1
        if self.rpdos:
            self.rpdo_to_sync.append(at - self.first)
            self.setpoints_ready.append(at - self.last)
            self.rpdos = 0
        else:
            self.syncs_without_rpdo += 1
        if answered is not None:
            self.sync_to_tpdo.append(answered - at)

    @staticmethod
    def _percentiles(values: Sequence[float]) -> dict[str, float] | None:
        if not values:
            return None
        ordered = sorted(values)
        n = len(ordered)

        def at(q: float) -> float:  # nearest rank
            return round(ordered[min(n - 1, max(0, math.ceil(q * n) - 1))] * 1e6, 1)

        return {"n": n, "min": at(0.0), "p50": at(0.5), "p99": at(0.99), "p99.9": at(0.999),
                "max": round(ordered[-1] * 1e6, 1)}  # fmt: skip

    def summary(self) -> dict[str, Any]:
        """Every figure in µs (count, min, p50, p99, p99.9, max), and the SYNC counts."""
        return {
            "syncs": self.syncs,
            "syncs_without_rpdo": self.syncs_without_rpdo,
            "rpdo_to_sync_us": self._percentiles(self.rpdo_to_sync),
            "setpoints_ready_us": self._percentiles(self.setpoints_ready),
            "sync_to_tpdo_us": self._percentiles(self.sync_to_tpdo),
        }


class DriveEmulator:
    """Emulated CiA 402 drives (one per node id) on one python-can bus (module docstring).

    ``bus`` is an open python-can bus (the emulator shuts it down when stopped), else one is
    opened from ``interface``/``channel``. ``clock`` is the emulator's time (None: the wall
    clock); with one given, a thread answers what needs an answer (SDO, the SYNCs of an
    activation) and :meth:`settle` handles, on the caller's thread, every frame sent before it.
    ``master_id`` is the master's node id, whose heartbeat the nodes may consume.
    """

    def __init__(
        self,
        node_ids: Iterable[int],
        eds: str | Path = DEFAULT_EDS,
        *,
        interface: str = "virtual",
        channel: str = "occ-cia402",
        bus: can.BusABC | None = None,
        clock: Callable[[], float] | None = None,
        master_id: int = 127,
        **node_kwargs: Any,
    ) -> None:
        self._clock = clock or time.monotonic
        self._simulated = clock is not None
        self.master_id = master_id
        self._bus_args = {"interface": interface, "channel": channel}
        self.bus = bus
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.frames_in = 0
        self.frames_out = 0
        self.ignored = 0
        self.errors = 0
        self.nodes: dict[int, EmulatedNode] = {}
        for nid in node_ids:
            self.nodes[nid] = EmulatedNode(
                nid, eds, lambda cob, data: self._send(cob, data), **node_kwargs
            )
        self._rpdo_of: dict[int, tuple[EmulatedNode, int]] = {}
        #: the master's cycle as received (:class:`CycleTimes`)
        self.cycle = CycleTimes()

    # ------------------------------------------------------------ life
    def start(self) -> DriveEmulator:
        if self.bus is None:
            self.bus = can.Bus(**self._bus_args)  # type: ignore[arg-type]
        now = self._clock()
        with self._lock:
            for node in self.nodes.values():
                node.boot(now)
        self._thread = threading.Thread(target=self._run, name="cia402-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if self.bus is not None:
            self.bus.shutdown()
            self.bus = None

    def __enter__(self) -> DriveEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def node(self, node_id: int) -> EmulatedNode:
        return self.nodes[node_id]

    @contextlib.contextmanager
    def held(self) -> Iterator[None]:
        """Inside, the emulated drives answer nothing: the frames sent to them wait on the bus
        and are handled, in order, once it ends (nodes slow to answer). The thread that holds
        them must not :meth:`settle` meanwhile (it would handle them itself)."""
        with self._lock:
            yield

    # ------------------------------------------------------------ frames
    def _send(self, cob: int, data: bytes) -> None:
        bus = self.bus
        if bus is None:
            return
        self.frames_out += 1
        msg = can.Message(arbitration_id=cob, is_extended_id=False, data=data)
        try:
            bus.send(msg, timeout=0.01)
        except can.CanError:
            logger.warning("cia402 emulator: frame %#x not sent", cob)

    def _run(self) -> None:
        while not self._stop.is_set():
            bus = self.bus
            if bus is None:
                return
            if self._simulated:
                # polled under the lock, so settle() never finds a frame taken and not handled
                with self._lock:
                    handled = self._drain(bus)
                if not handled:
                    self._stop.wait(0.0002)
                continue
            try:
                msg = bus.recv(timeout=0.001)
            except (can.CanError, OSError, ValueError):
                if self._stop.is_set():
                    return
                raise
            with self._lock:
                if msg is not None:
                    self.handle(msg)
                    self._drain(bus)
                now = self._clock()
                for node in self.nodes.values():
                    node.timers(now)

    def _drain(self, bus: can.BusABC) -> int:
        handled = 0
        while True:
            msg = bus.recv(timeout=0.0)
            if msg is None:
                break
            self.handle(msg)
            handled += 1
        if handled and self._simulated:
            now = self._clock()
            for node in self.nodes.values():
                node.timers(now)
        return handled

    def settle(self) -> None:
        """Handle, on this thread, every frame sent to the emulator before this call, then run
        the timers at the clock's present time (deterministic tests)."""
        bus = self.bus
        if bus is None:
            return
        with self._lock:
            self._drain(bus)
            now = self._clock()
            for node in self.nodes.values():
                node.timers(now)

    def handle(self, msg: can.Message) -> None:
        """One received frame (a frame the emulator cannot handle is logged and counted: the
        emulator goes on, as a drive would); a SYNC or an RPDO timed (:attr:`cycle`)."""
        sent = self.frames_out
        try:
            self._handle(msg)
        except Exception:  # noqa: BLE001 - one bad frame must not stop the emulated drives
            self.errors += 1
            logger.exception("cia402 emulator: frame %s not handled", msg)
        cob = msg.arbitration_id
        if cob == COB_SYNC or (cob & 0x780) in COB_RPDO:
            self._time(msg, sent)

    def _time(self, msg: can.Message, sent: int) -> None:
        """A SYNC's or an RPDO's arrival into :attr:`cycle` (an RPDO: one to a node emulated
        here; a SYNC: with when its TPDOs went, if it caused any)."""
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        at = msg.timestamp or time.time()
        cob = msg.arbitration_id
        if cob == COB_SYNC:
            self.cycle.sync(at, time.time() if self.frames_out > sent else None)
        elif cob & 0x7F in self.nodes:
            self.cycle.rpdo(at)

    def _handle(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            self.ignored += 1
            return
        self.frames_in += 1
        cob = msg.arbitration_id
        data = bytes(msg.data)
        now = self._clock()
        if cob == COB_SYNC:
            for node in self.nodes.values():
                node.sync(now)
            return
        if cob == COB_NMT:
            if len(data) >= 2:
                for node in self.nodes.values():
                    if data[1] in (0, node.node_id):
                        node.nmt_command(data[0], now)
            return
        if cob == COB_HEARTBEAT + self.master_id:
            for node in self.nodes.values():
                node.master_heartbeat(self.master_id, now)
            return
        node_id = cob & 0x7F
        target = self.nodes.get(node_id)
        if target is None:
            self.ignored += 1  # another node's, or an echo of our own frames
            return
        node = target
        function = cob & 0x780
        if function == COB_SDO_RX:
            answer = node.sdo(data, now)
            if answer:
                self._send(COB_SDO_TX + node_id, answer)
            return
        for k, base in enumerate(COB_RPDO):
            if function == base:
                rx = int(node.get(0x1400 + k, 1))
                if not rx & 0x80000000 and rx & 0x7FF == cob:
                    node.rpdo(k, data, now)
                    return
        self.ignored += 1

    # ------------------------------------------------------------ faults to inject
    def inject_emcy(self, node_id: int, code: int, *, persist: bool = False) -> None:
        """The node faults with ``code`` and says so in an EMCY."""
        with self._lock:
            node = self.nodes[node_id]
            node.persist = persist
            node.fault(code, self._clock())

    def inject_fault_bit(self, node_id: int, code: int = 0x1000, *, persist: bool = False) -> None:
        """The node goes to FAULT without an EMCY: only its statusword tells."""
        with self._lock:
            node = self.nodes[node_id]
            node.persist = persist
            node.fault(code, self._clock(), send_emcy=False)

    def stop_heartbeat(self, node_id: int) -> None:
        with self._lock:
            self.nodes[node_id].heartbeat_on = False

    def mute_tpdos(self, node_id: int) -> None:
        with self._lock:
            self.nodes[node_id].tpdo_on = False

    def pause_tpdos(self, node_id: int, seconds: float) -> None:
        """No TPDO from the node for ``seconds`` on the emulator's clock, then as before."""
        with self._lock:
            self.nodes[node_id].tpdo_paused_until = self._clock() + seconds

    def stall(self, node_id: int, *, persist: bool = True) -> None:
        """The motor stops following: the following error grows until EMCY 0x8611."""
        with self._lock:
            node = self.nodes[node_id]
            node.stalled = True
            node.persist = persist

    def leave_operational(self, node_id: int, state: int = NMT_PRE_OPERATIONAL) -> None:
        """The node changes its NMT state on its own (announced by a heartbeat)."""
        with self._lock:
            self.nodes[node_id].set_nmt(state, self._clock())

    def refuse_enable(self, node_id: int) -> None:
        with self._lock:
            self.nodes[node_id].refuse_enable = True

    def abort_sdo(self, node_id: int, index: int, subindex: int, code: int) -> None:
        with self._lock:
            self.nodes[node_id].sdo_aborts[(index, subindex)] = code

    def offset_second_encoder(self, node_id: int, counts: float) -> None:
        with self._lock:
            self.nodes[node_id].second_offset = counts

    def clear(self, node_id: int) -> None:
        """Every injected cause on the node gone (a fault reset is accepted again)."""
        with self._lock:
            node = self.nodes[node_id]
            node.persist = False
            node.heartbeat_on = node.tpdo_on = True
            node.tpdo_paused_until = -math.inf
            node.stalled = node.refuse_enable = False
            node.second_offset = 0.0
            node.sdo_aborts.clear()

    def command(self, line: str) -> str:
        """One fault command line (module docstring); returns what it did."""
        words = line.split()
        if not words:
            return ""
        verb, args = words[0].lower(), words[1:]
        nums = []
        for a in args:
            try:
                nums.append(int(a, 0))
            except ValueError:
                continue  # a word: on, off, pre, persist...
        try:
            if verb == "emcy":
                self.inject_emcy(nums[0], nums[1], persist="persist" in args)
            elif verb == "fault":
                self.inject_fault_bit(nums[0], persist="persist" in args)
            elif verb == "heartbeat":
                with self._lock:
                    self.nodes[nums[0]].heartbeat_on = "off" not in args
            elif verb == "tpdo":
                with self._lock:
                    self.nodes[nums[0]].tpdo_on = "off" not in args
            elif verb == "pause":
                self.pause_tpdos(nums[0], nums[1] * 1e-3)
            elif verb == "stall":
                self.stall(nums[0])
            elif verb == "nmt":
                state = {"pre": NMT_PRE_OPERATIONAL, "stop": NMT_STOPPED}.get(
                    args[1], NMT_OPERATIONAL
                )
                self.leave_operational(nums[0], state)
            elif verb == "refuse":
                self.refuse_enable(nums[0])
            elif verb == "abort":
                self.abort_sdo(nums[0], nums[1], nums[2], nums[3])
            elif verb == "second":
                self.offset_second_encoder(nums[0], nums[1])
            elif verb == "clear":
                self.clear(nums[0])
            elif verb == "status":
                with self._lock:
                    return "; ".join(f"{n}: {node.describe()}" for n, node in self.nodes.items())
            else:
                return (
                    "commands: emcy N CODE [persist] | fault N [persist] | heartbeat N on|off | "
                    "tpdo N on|off | pause N MS | stall N | nmt N pre|stop|op | refuse N | "
                    "abort N INDEX SUB CODE | second N COUNTS | clear N | status"
                )
        except (IndexError, KeyError, ValueError) as err:
            return f"bad command {line!r}: {err!r}"
        return f"ok: {line.strip()}"


def _fifo(priority: int) -> str:
    """SCHED_FIFO ``priority`` for this thread and the threads it starts after (where
    permitted): what the emulated drives' thread runs with, said in one line."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as err:  # not permitted, or not Linux
        return f"cia402 emulator: SCHED_FIFO {priority} refused ({err}): SCHED_OTHER"
    return f"cia402 emulator: SCHED_FIFO {priority}"


def _timing(emulator: DriveEmulator, line: str) -> str:
    """The process's own commands (not faults): ``timing`` prints the master's cycle as
    received (:class:`CycleTimes`, one JSON line), ``timing reset`` starts it again."""
    words = line.split()
    if not words or words[0].lower() != "timing":
        return ""
    with emulator.held():  # the drives answer nothing meanwhile: only copy
        if words[1:] == ["reset"]:
            emulator.cycle.reset()
            return "ok: timing reset"
        cycle = emulator.cycle.copy()
    return "cia402 emulator timing: " + json.dumps(cycle.summary())


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m occ.drivers.cia402_sim", description="CiA 402 drive emulator"
    )
    parser.add_argument("--interface", default="udp_multicast")
    parser.add_argument("--channel", default="239.74.163.2")
    parser.add_argument("--nodes", default="1,2,3", help="node ids, comma separated")
    parser.add_argument("--eds", default=str(DEFAULT_EDS))
    parser.add_argument("--master-id", type=int, default=127)
    parser.add_argument("--bandwidth-hz", type=float, default=40.0)
    parser.add_argument(
        "--fault",
        action="append",
        default=[],
        help="a fault command run at start (as typed on standard input), e.g. 'emcy 2 0x2310'",
    )
    parser.add_argument(
        "--fifo-priority",
        type=int,
        default=None,
        help="SCHED_FIFO priority (1-99) of the emulated drives, where permitted: drives are "
        "hardware of their own, whose answers no load of the host delays",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    if args.fifo_priority is not None:
        print(_fifo(args.fifo_priority), flush=True)  # before its thread starts: inherited
    ids = [int(n, 0) for n in args.nodes.split(",") if n.strip()]
    emulator = DriveEmulator(
        ids,
        args.eds,
        interface=args.interface,
        channel=args.channel,
        master_id=args.master_id,
        bandwidth_hz=args.bandwidth_hz,
    )
    emulator.start()
    print(f"cia402 emulator: nodes {ids} on {args.interface} {args.channel}", flush=True)
    try:
        for line in args.fault:
            print(emulator.command(line), flush=True)
        for line in sys.stdin:
            out = _timing(emulator, line) or emulator.command(line)
            if out:
                print(out, flush=True)
        # standard input closed (e.g. /dev/null): run until stopped by a signal
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        emulator.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
