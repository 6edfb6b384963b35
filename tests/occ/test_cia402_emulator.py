"""The CiA 402 drive emulator on its own (occ/drivers/cia402_sim.py; issue 42: found by
mutation testing, docs/VERIFICATION.md). The driver's tests (test_cia402.py) prove the driver
against the emulator; these prove the emulator plays a drive as its docstring says, so that a
fault the driver's tests inject is the fault a drive would show: the device state machine and
its statusword, a fault and its EMCY, the fault reset, NMT and the heartbeats, the PDOs at a
SYNC, the following error, and every fault injected, by method and by command line.

No bus: a node's frames go to a list, and a DriveEmulator that is not started sends none.
Every ``now`` is passed in.
"""

from __future__ import annotations

import math
import struct
import time
from typing import Any

import can
import pytest

from occ.drivers.cia402_protocol import (
    NMT_OPERATIONAL,
    NMT_PRE_OPERATIONAL,
    NMT_STOPPED,
)
from occ.drivers.cia402_setup import DEFAULT_EDS
from occ.drivers.cia402_sim import (
    FAULT,
    OPERATION_ENABLED,
    QUICK_STOP_ACTIVE,
    READY_TO_SWITCH_ON,
    SWITCH_ON_DISABLED,
    SWITCHED_ON,
    DriveEmulator,
    EmulatedNode,
)

Frames = list[tuple[int, bytes]]


def make_node(node_id: int = 4, **kwargs: Any) -> tuple[EmulatedNode, Frames]:
    sent: Frames = []
    node = EmulatedNode(node_id, DEFAULT_EDS, lambda cob, data: sent.append((cob, data)), **kwargs)
    return node, sent


def emcys(sent: Frames, node_id: int = 4) -> list[bytes]:
    return [data for cob, data in sent if cob == 0x080 + node_id]


# ----------------------------------------------------------------------------- fault and EMCY
def test_a_fault_enters_fault_with_its_code_register_and_emcy() -> None:
    node, sent = make_node()
    node.state, node.velocity = OPERATION_ENABLED, 1234.0
    node.fault(0x2311, 0.0)  # current: the register's current bit too
    assert node.state == FAULT and node.velocity == 0.0
    assert node.get(0x603F, 0) == 0x2311 and node.get(0x1001, 0) == 0x03
    assert emcys(sent) == [bytes([0x11, 0x23, 0x03, 0, 0, 0, 0, 0])]
    assert node.emcys == 1
    node.fault(0x4310, 0.0)  # temperature: the generic bit only
    assert node.get(0x603F, 0) == 0x4310 and node.get(0x1001, 0) == 0x01
    assert emcys(sent)[-1] == bytes([0x10, 0x43, 0x01, 0, 0, 0, 0, 0])
    assert node.emcys == 2
    node.fault(0x1000, 0.0, send_emcy=False)  # the fault bit alone
    assert node.get(0x603F, 0) == 0x1000 and len(emcys(sent)) == 2 and node.emcys == 2


def test_a_fault_reset_is_a_rising_edge_of_bit_7_refused_while_the_cause_persists() -> None:
    node, sent = make_node()
    node.persist = True
    node.fault(0x3210, 0.0)
    node._controlword(0x00)
    node._controlword(0x80)
    assert node.state == FAULT and node.fault_resets_refused == 1
    assert emcys(sent)[-1] == bytes([0x10, 0x32, 0x01, 0, 0, 0, 0, 0])  # said again
    node._controlword(0x80)  # no edge: nothing
    assert node.fault_resets_refused == 1 and len(emcys(sent)) == 2
    node._controlword(0x00)
    node._controlword(0x80)
    assert node.fault_resets_refused == 2 and len(emcys(sent)) == 3
    node.persist = False
    node._controlword(0x0F)  # not a reset: FAULT stays
    assert node.state == FAULT
    node._controlword(0x8F)  # the edge, whatever else is set
    assert node.state == SWITCH_ON_DISABLED
    assert node.get(0x603F, 0) == 0 and node.get(0x1001, 0) == 0
    assert emcys(sent)[-1] == bytes(8)  # error reset: code 0, register 0
    assert node.controlwords[-1] == 0x8F


# ----------------------------------------------------------------------------- injected, by method
def emulator(t: list[float]) -> DriveEmulator:
    return DriveEmulator([1, 2, 3], DEFAULT_EDS, channel="occ-cia402-unused", clock=lambda: t[0])


def test_the_faults_injected_by_method_and_cleared() -> None:
    t = [2.0]
    emu = emulator(t)
    emu.inject_emcy(1, 0x2310)
    one = emu.node(1)
    assert one.state == FAULT and one.get(0x603F, 0) == 0x2310 and not one.persist
    one._controlword(0x80)
    assert one.state == SWITCH_ON_DISABLED  # not persistent: reset at once
    emu.inject_fault_bit(2)
    two = emu.node(2)
    assert two.state == FAULT and two.get(0x603F, 0) == 0x1000 and not two.persist
    assert two.emcys == 0
    emu.inject_fault_bit(2, 0x7300, persist=True)
    assert two.get(0x603F, 0) == 0x7300 and two.persist
    emu.stall(3)
    three = emu.node(3)
    assert three.stalled and three.persist is True
    emu.stop_heartbeat(3)
    emu.mute_tpdos(3)
    emu.pause_tpdos(3, 0.05)
    emu.refuse_enable(3)
    emu.offset_second_encoder(3, 250.0)
    emu.abort_sdo(3, 0x6060, 0, 0x06090030)
    assert three.heartbeat_on is False and three.tpdo_on is False
    assert three.tpdo_paused_until == pytest.approx(2.05) and three.refuse_enable
    assert three.second_offset == 250.0 and three.sdo_aborts == {(0x6060, 0): 0x06090030}
    emu.leave_operational(3, NMT_STOPPED)
    assert three.nmt == NMT_STOPPED
    emu.clear(3)
    assert three.persist is False and three.stalled is False and three.refuse_enable is False
    assert three.heartbeat_on is True and three.tpdo_on is True
    assert three.tpdo_paused_until == -math.inf and three.second_offset == 0.0
    assert three.sdo_aborts == {}
    assert emu.node(1).heartbeat_on and emu.node(2).persist  # the others' left alone


# ----------------------------------------------------------------------------- injected, by line
HELP = (
    "commands: emcy N CODE [persist] | fault N [persist] | heartbeat N on|off | "
    "tpdo N on|off | pause N MS | stall N | nmt N pre|stop|op | refuse N | "
    "abort N INDEX SUB CODE | second N COUNTS | clear N | status"
)


def test_the_command_lines_inject_on_the_node_they_name() -> None:
    t = [3.0]
    emu = emulator(t)
    one, two, three = emu.node(1), emu.node(2), emu.node(3)
    assert emu.command("") == "" and emu.command("   ") == ""
    assert emu.command("emcy 2 0x2310") == "ok: emcy 2 0x2310"
    assert two.state == FAULT and two.get(0x603F, 0) == 0x2310 and not two.persist
    assert one.state != FAULT and three.state != FAULT
    assert emu.command("EMCY 3 0x4310 persist\n") == "ok: EMCY 3 0x4310 persist"
    assert three.get(0x603F, 0) == 0x4310 and three.persist and three.emcys == 1
    assert emu.command("fault 1") == "ok: fault 1"
    assert one.state == FAULT and one.get(0x603F, 0) == 0x1000 and one.emcys == 0
    assert not one.persist
    emu.command("fault 1 persist")
    assert one.persist
    assert emu.command("fault bit 3") == "ok: fault bit 3"  # the docstring's way: words skipped
    assert three.get(0x603F, 0) == 0x1000
    assert emu.command("heartbeat 2 off").startswith("ok")
    assert two.heartbeat_on is False and one.heartbeat_on is True
    emu.command("heartbeat 2 on")
    assert two.heartbeat_on is True
    emu.command("tpdo 3 off")
    assert three.tpdo_on is False and two.tpdo_on is True
    emu.command("tpdo 3 on")
    assert three.tpdo_on is True
    emu.command("pause 2 50")
    assert two.tpdo_paused_until == pytest.approx(3.05) and one.tpdo_paused_until == -math.inf
    emu.command("stall 3")
    assert three.stalled and not two.stalled
    for word, state in (
        ("pre", NMT_PRE_OPERATIONAL),
        ("stop", NMT_STOPPED),
        ("op", NMT_OPERATIONAL),
    ):
        emu.command(f"nmt 2 {word}")
        assert two.nmt == state, word
    assert one.nmt == 0x00  # BOOT: the emulator was not started, and node 2 only was named
    emu.command("second 1 500")
    assert one.second_offset == 500 and two.second_offset == 0.0
    assert emu.command("refuse 3").startswith("ok") and three.refuse_enable
    status = emu.command("status")
    assert status.startswith(
        "1: {'nmt': 'BOOT-UP', 'state': 'FAULT', 'position': 0, "
        "'error_code': '0x1000 generic error'"
    )
    assert "; 2: {" in status and "; 3: {" in status
    assert emu.command("help") == HELP and emu.command("bogus 1") == HELP
    assert emu.command("nmt 2") == "bad command 'nmt 2': IndexError('list index out of range')"
    assert emu.command("stall 9").startswith("bad command 'stall 9': KeyError(9)")


# ----------------------------------------------------------------------------- the state machine
def powered(state: int) -> tuple[EmulatedNode, Frames]:
    node, sent = make_node()
    node.boot(0.0)
    node.state = state
    return node, sent


@pytest.mark.parametrize(
    ("start", "cw", "end"),
    [
        (SWITCH_ON_DISABLED, 0x06, READY_TO_SWITCH_ON),
        (READY_TO_SWITCH_ON, 0x07, SWITCHED_ON),
        (SWITCHED_ON, 0x0F, OPERATION_ENABLED),
        (READY_TO_SWITCH_ON, 0x0F, OPERATION_ENABLED),  # switch on and enable at once
        (OPERATION_ENABLED, 0x07, SWITCHED_ON),  # disable operation
        (OPERATION_ENABLED, 0x06, READY_TO_SWITCH_ON),
        (SWITCHED_ON, 0x06, READY_TO_SWITCH_ON),
        (OPERATION_ENABLED, 0x02, QUICK_STOP_ACTIVE),
        (OPERATION_ENABLED, 0x0B, QUICK_STOP_ACTIVE),  # quick stop with the others set
        (SWITCHED_ON, 0x02, SWITCH_ON_DISABLED),
        (QUICK_STOP_ACTIVE, 0x02, QUICK_STOP_ACTIVE),
        (OPERATION_ENABLED, 0x00, SWITCH_ON_DISABLED),
        (OPERATION_ENABLED, 0x0D, SWITCH_ON_DISABLED),  # bit 1 clear: disable voltage
        (SWITCH_ON_DISABLED, 0x07, SWITCH_ON_DISABLED),  # not from there
        (SWITCH_ON_DISABLED, 0x0F, SWITCH_ON_DISABLED),
        (QUICK_STOP_ACTIVE, 0x06, QUICK_STOP_ACTIVE),
        (READY_TO_SWITCH_ON, 0x86, READY_TO_SWITCH_ON),  # bit 7 set: no transition
        (0x0000, 0x06, 0x0000),  # NOT READY TO SWITCH ON: nothing taken
    ],
)
def test_the_controlword_drives_the_device_state_machine(start: int, cw: int, end: int) -> None:
    node, _ = powered(start)
    node.position = 1234.4
    node.fe_since = 5.0
    node._controlword(cw)
    assert node.state == end
    assert node.controlwords == [cw]
    if end == OPERATION_ENABLED and start != end:
        assert node.get(0x607A, 0) == 1234 and math.isnan(node.fe_since)  # no jump at enable
    if end == QUICK_STOP_ACTIVE and start == OPERATION_ENABLED:
        assert node.quick_stops == 1
    else:
        assert node.quick_stops == 0


def test_each_quick_stop_is_counted() -> None:
    node, _ = powered(OPERATION_ENABLED)
    for k in (1, 2):
        node.state = OPERATION_ENABLED
        node._controlword(0x02)
        assert node.state == QUICK_STOP_ACTIVE and node.quick_stops == k


def test_an_enable_refused_stays_switched_on() -> None:
    node, _ = powered(SWITCHED_ON)
    node.refuse_enable = True
    node._controlword(0x0F)
    assert node.state == SWITCHED_ON
    node, _ = powered(READY_TO_SWITCH_ON)
    node.refuse_enable = True
    node._controlword(0x0F)
    assert node.state == SWITCHED_ON


@pytest.mark.parametrize(
    ("state", "word"),
    [
        (0x0000, 0x0200),
        (SWITCH_ON_DISABLED, 0x0240),
        (READY_TO_SWITCH_ON, 0x0231),
        (SWITCHED_ON, 0x0233),
        (QUICK_STOP_ACTIVE, 0x0217),
        (FAULT, 0x0208),
    ],
)
def test_the_statusword_shows_the_state_remote_voltage_and_quick_stop(
    state: int, word: int
) -> None:
    node, _ = powered(state)
    assert node.statusword() == word


def test_the_statusword_in_csp_shows_following_target_reached_and_following_error() -> None:
    node, _ = powered(OPERATION_ENABLED)
    node.set(0x6060, 0, 8)
    node.set(0x607A, 0, 100)
    node.position = 99.5
    assert node.statusword() == 0x1637  # follows the target, reached (within a count)
    node.position = 99.0
    assert node.statusword() == 0x1237  # a count away: not reached
    node.fe_since = 1.0
    assert node.statusword() == 0x3237
    node.set(0x6060, 0, 10)  # CST: none of the CSP bits
    assert node.statusword() == 0x0237


# ----------------------------------------------------------------------------- NMT, heartbeats
def test_nmt_commands_and_the_heartbeat_on_each_change() -> None:
    node, sent = make_node()
    node.boot(0.0)
    assert sent == [(0x704, bytes([0x00]))]  # boot-up
    assert node.nmt == NMT_PRE_OPERATIONAL and node.state == SWITCH_ON_DISABLED
    node.set(0x1017, 0, 10)
    node.nmt_command(0x01, 1.0)
    assert node.nmt == NMT_OPERATIONAL and sent[-1] == (0x704, bytes([NMT_OPERATIONAL]))
    assert node.hb_next == pytest.approx(1.01)  # the producer restarts from the change
    node.nmt_command(0x01, 1.5)  # no change: no heartbeat
    assert len(sent) == 2 and node.hb_next == pytest.approx(1.01)
    node.nmt_command(0x02, 2.0)
    assert node.nmt == NMT_STOPPED and sent[-1] == (0x704, bytes([NMT_STOPPED]))
    assert node.hb_next == pytest.approx(2.01)
    node.nmt_command(0x80, 3.0)
    assert node.nmt == NMT_PRE_OPERATIONAL and len(sent) == 4
    assert node.hb_next == pytest.approx(3.01)
    node.heartbeat_on = False
    node.nmt_command(0x01, 0.0)
    assert node.nmt == NMT_OPERATIONAL and len(sent) == 4  # a heartbeat stopped says nothing


def test_a_reset_node_forgets_its_configuration_a_reset_communication_keeps_it() -> None:
    node, sent = make_node()
    node.boot(0.0)
    node.set(0x6060, 0, 8)
    node.position = 777.0
    node.state = OPERATION_ENABLED
    node.nmt_command(0x82, 1.0)  # reset communication
    assert node.get(0x6060, 0) == 8 and node.nmt == NMT_PRE_OPERATIONAL
    assert sent[-1] == (0x704, bytes([0x00])) and node.hb_next == 1.0
    node.nmt_command(0x81, 2.0)  # reset node: the object dictionary's defaults
    assert node.get(0x6060, 0) != 8 and node.position == 777.0
    assert node.state == SWITCH_ON_DISABLED and node.nmt == NMT_PRE_OPERATIONAL
    node.nmt_command(0x33, 3.0)  # no such command
    assert node.nmt == NMT_PRE_OPERATIONAL


def test_the_heartbeat_producer_every_producer_time() -> None:
    node, sent = make_node()
    node.boot(0.0)
    sent.clear()
    node.timers(0.5)  # producer time 0: none
    assert sent == []
    node._write_object(0x1017, 0, 10, 1.0)  # restarts the producer at once
    node.timers(1.0)
    assert sent == [(0x704, bytes([NMT_PRE_OPERATIONAL]))] and node.hb_next == pytest.approx(1.01)
    node.timers(1.0099)
    assert len(sent) == 1
    node.timers(1.01)
    assert len(sent) == 2
    node.heartbeat_on = False
    node.timers(1.03)
    assert len(sent) == 2 and node.hb_next == pytest.approx(1.04)
    node.heartbeat_on = True
    node._write_object(0x1017, 0, 1, 2.0)  # 1 ms: the shortest producer time
    node.timers(2.0)
    node.timers(2.0005)
    assert len(sent) == 3 and node.hb_next == pytest.approx(2.001)
    node.timers(2.001)
    assert len(sent) == 4


def test_the_heartbeat_consumer_faults_an_enabled_drive_once_per_loss() -> None:
    node, sent = make_node()
    node.boot(0.0)
    node.set(0x1016, 1, (127 << 16) | 20)
    node.timers(5.0)  # no master heard yet: nothing to judge
    assert node.state == SWITCH_ON_DISABLED
    node.master_heartbeat(126, 0.0)  # another master's
    assert math.isnan(node.master_seen)
    node.master_heartbeat(127, 0.0)
    node.state = OPERATION_ENABLED
    node.timers(0.02)
    assert node.state == OPERATION_ENABLED  # exactly the consumer time: in time
    node.timers(0.0201)
    assert node.state == FAULT and node.get(0x603F, 0) == 0x8130
    assert emcys(sent) == [bytes([0x30, 0x81, 0x01, 0, 0, 0, 0, 0])]
    node.timers(1.5)
    assert len(emcys(sent)) == 1  # once
    node.master_heartbeat(127, 2.0)
    node.state = SWITCHED_ON
    node.timers(2.5)  # lost while not enabled: no fault
    assert node.state == SWITCHED_ON and math.isnan(node.master_seen)
    node.set(0x1016, 1, (5 << 16) | 20)  # the consumer of master 5 does not hear 127
    node.master_seen = math.nan
    node.master_heartbeat(127, 3.0)
    assert math.isnan(node.master_seen)
    node.set(0x1016, 1, 127 << 16)  # consumer time 0: off
    node.master_heartbeat(127, 3.0)
    node.state = OPERATION_ENABLED
    node.timers(9.0)
    assert node.state == OPERATION_ENABLED


# ----------------------------------------------------------------------------- PDOs and SYNC
def mapped(node: EmulatedNode, rpdo_type: int = 1, tpdo_type: int = 1) -> None:
    """RPDO 1: controlword, target position; TPDO 1: statusword, position actual."""
    for index, entries in ((0x1600, [0x60400010, 0x607A0020]), (0x1A00, [0x60410010, 0x60640020])):
        for sub, entry in enumerate(entries, 1):
            node.set(index, sub, entry)
        node.set(index, 0, len(entries))
    node.set(0x1400, 1, 0x204)
    node.set(0x1400, 2, rpdo_type)
    node.set(0x1800, 1, 0x184)
    node.set(0x1800, 2, tpdo_type)
    node.set(0x6060, 0, 8)
    node.nmt = NMT_OPERATIONAL


def rpdo(cw: int, target: int) -> bytes:
    return cw.to_bytes(2, "little") + target.to_bytes(4, "little", signed=True)


def test_a_synchronous_rpdo_waits_for_the_sync_an_asynchronous_one_does_not() -> None:
    node, sent = make_node()
    node.boot(0.0)
    mapped(node, rpdo_type=240)
    node.state = OPERATION_ENABLED
    node.rpdo(0, rpdo(0x0F, 500), 0.0)
    assert node.rpdos == 1 and node.get(0x607A, 0) != 500  # pending
    node.sync(0.001)
    assert node.get(0x607A, 0) == 500 and node.syncs == 1
    node.set(0x1400, 2, 241)  # above 240: not synchronous, at once
    node.rpdo(0, rpdo(0x0F, -600), 0.002)
    assert node.get(0x607A, 0) == -600 and node.rpdos == 2
    assert node.get(0x6040, 0) == 0x0F  # the controlword object too
    node.rpdo(0, rpdo(0x0F, 1)[:5], 0.003)  # too short: EMCY 0x8210, not applied
    assert node.get(0x607A, 0) == -600
    assert emcys(sent)[-1] == bytes([0x10, 0x82, 0x00, 0, 0, 0, 0, 0])
    node.nmt = NMT_PRE_OPERATIONAL  # PDOs are not taken out of OPERATIONAL
    node.rpdo(0, rpdo(0x00, 9), 0.004)
    node.sync(0.005)
    assert node.rpdos == 3 and node.get(0x607A, 0) == -600 and node.syncs == 1
    assert node.state == OPERATION_ENABLED


def test_the_controlword_of_an_rpdo_is_applied_after_its_target() -> None:
    node, _ = make_node()
    node.boot(0.0)
    mapped(node)
    node.state = SWITCHED_ON
    node.position = 321.2
    node.rpdo(0, rpdo(0x0F, 9999), 0.0)
    node.sync(0.001)
    # enabled with the target it came with replaced by where the motor is: no jump
    assert node.state == OPERATION_ENABLED and node.get(0x607A, 0) == 321
    node.rpdo(0, rpdo(0x02, 400), 0.001)
    node.sync(0.002)
    assert node.controlwords == [0x0F, 0x02] and node.get(0x607A, 0) == 400
    assert node.state == SWITCH_ON_DISABLED  # quick stop, then disabled (option 2)


def test_tpdos_every_nth_sync_unless_muted_or_paused() -> None:
    node, sent = make_node()
    node.boot(0.0)
    mapped(node, tpdo_type=2)
    sent.clear()
    for k in range(1, 7):
        node.sync(k * 0.001)
    tpdos = [data for cob, data in sent if cob == 0x184]
    assert len(tpdos) == 3 and node.tpdos == 3
    assert tpdos[-1] == struct.pack("<Hi", node.statusword(), 0)
    node.tpdo_on = False
    node.sync(0.007)
    node.sync(0.008)
    assert node.tpdos == 3
    node.tpdo_on = True
    node.set(0x1800, 2, 1)
    node.tpdo_paused_until = 0.010
    node.sync(0.009)
    node.sync(0.0095)
    assert node.tpdos == 3
    node.sync(0.010)  # the pause ends at its time
    assert node.tpdos == 4
    node.set(0x1800, 1, 0x80000184)  # off
    node.sync(0.012)
    node.sync(0.013)
    assert node.tpdos == 4
    # TPDO 2 on while TPDO 1 is off: still sent
    node.set(0x1A01, 1, 0x606C0020)
    node.set(0x1A01, 0, 1)
    node.set(0x1801, 1, 0x284)
    node.set(0x1801, 2, 1)
    node.sync(0.014)
    assert node.tpdos == 5 and sent[-1][0] == 0x284


@pytest.mark.parametrize(("kind", "count"), [(240, 1), (241, 0), (0, 0)])
def test_a_tpdo_of_type_240_is_the_slowest_synchronous_one(kind: int, count: int) -> None:
    node, _ = make_node()
    node.boot(0.0)
    mapped(node, tpdo_type=kind)
    for k in range(241):
        node.sync(k * 0.001)
    assert node.tpdos == count


def test_rpdo_2_is_mapped_and_typed_by_its_own_objects() -> None:
    node, _ = make_node()
    node.boot(0.0)
    mapped(node)
    node.set(0x1601, 1, 0x60710010)  # target torque
    node.set(0x1601, 0, 1)
    node.set(0x1401, 1, 0x304)
    node.set(0x1401, 2, 255)
    node.rpdo(1, (-250).to_bytes(2, "little", signed=True), 0.0)
    assert node.get(0x6071, 0) == -250


# ----------------------------------------------------------------------------- the motor
def enabled_in(mode: int, **kwargs: Any) -> tuple[EmulatedNode, Frames]:
    node, sent = make_node(**kwargs)
    node.boot(0.0)
    node.set(0x6060, 0, mode)
    node.state = OPERATION_ENABLED
    return node, sent


def test_csp_follows_the_target_first_order_and_shows_it_in_the_objects() -> None:
    node, _ = enabled_in(8, bandwidth_hz=40.0, torque_per_count=0.05, second_ratio=2.0)
    assert node.interpolation_period() == pytest.approx(0.001)  # 1 x 10^-3 (the EDS)
    node.set(0x60C2, 1, 2)
    assert node.interpolation_period() == pytest.approx(0.002)
    node.set(0x607A, 0, 1000)
    node.second_offset = 7.0
    node.step(0.002, 0.0)
    alpha = 1.0 - math.exp(-0.002 * 2.0 * math.pi * 40.0)
    assert node.position == pytest.approx(1000.0 * alpha, rel=1e-12)
    assert node.velocity == pytest.approx(1000.0 * alpha / 0.002, rel=1e-12)
    assert node.torque == pytest.approx(1000.0 * (1.0 - alpha) * 0.05, rel=1e-12)
    counts = round(1000.0 * alpha)
    assert node.get(0x6064, 0) == counts and node.get(0x606C, 0) == round(node.velocity)
    assert node.get(0x6077, 0) == round(node.torque)
    assert node.get(0x2100, 0) == round(node.position * 2.0 + 7.0)
    assert node.get(0x60F4, 0) == 1000 - counts
    assert node.get(0x6041, 0) == node.statusword()
    node.set(0x607A, 0, 10**9)
    node.step(0.002, 0.002)
    assert node.torque == 3000.0  # the drive's torque limit
    node.set(0x607A, 0, -(10**9))
    node.step(0.002, 0.004)
    assert node.torque == -3000.0


def test_cst_drives_a_damped_mass_with_the_target_torque() -> None:
    node, _ = enabled_in(10, accel_per_permille=2000.0, damping=20.0)
    node.set(0x6071, 0, 100)
    node.step(0.001, 0.0)
    assert node.torque == 100.0
    assert node.velocity == pytest.approx(200.0) and node.position == pytest.approx(0.2)
    node.step(0.001, 0.001)
    v = 200.0 + (200000.0 - 20.0 * 200.0) * 0.001
    assert node.velocity == pytest.approx(v) and node.position == pytest.approx(0.2 + v * 0.001)


def test_a_motor_not_enabled_or_stalled_does_not_move() -> None:
    node, _ = enabled_in(8)
    node.set(0x607A, 0, 1000)
    node.stalled = True
    node.step(0.001, 0.0)
    assert node.position == 0.0 and node.velocity == 0.0 and node.torque == 0.0
    node, _ = enabled_in(10)
    node.state = SWITCHED_ON
    node.set(0x6071, 0, 500)
    node.velocity = 50.0  # coasting is not modelled: a disabled motor holds
    node.step(0.001, 0.0)
    assert node.position == 0.0 and node.velocity == 0.0 and node.torque == 0.0
    node.state = QUICK_STOP_ACTIVE
    node.torque = 12.0
    node.step(0.001, 0.001)  # quick stop option 2: stopped, then SWITCH ON DISABLED
    assert node.state == SWITCH_ON_DISABLED and node.torque == 0.0
    node.step(0.0, 0.002)
    assert node.velocity == 0.0


def test_a_following_error_past_the_window_for_the_time_out_faults_0x8611() -> None:
    node, sent = enabled_in(8)
    node.set(0x6065, 0, 100)  # window, counts
    node.set(0x6066, 0, 4)  # time out, ms
    node.stalled = True
    node.set(0x607A, 0, 100)
    node.step(0.001, 0.0)
    assert math.isnan(node.fe_since)  # the window exactly: no error
    node.set(0x607A, 0, 101)
    node.step(0.001, 0.0)
    assert node.fe_since == 0.0 and node.state == OPERATION_ENABLED
    assert node.statusword() & 0x2000  # following error shown (in the TPDO of the next SYNC)
    node.step(0.001, 0.0039)
    assert node.state == OPERATION_ENABLED and node.get(0x6041, 0) & 0x2000
    node.step(0.001, 0.004)  # the time out reached, exactly
    assert node.state == FAULT and node.get(0x603F, 0) == 0x8611
    assert node.get(0x6041, 0) == node.statusword() and node.get(0x6041, 0) & 0x08
    assert emcys(sent) == [bytes([0x11, 0x86, 0x01, 0, 0, 0, 0, 0])]
    node, _ = enabled_in(8)
    node.set(0x6065, 0, 100)
    node.stalled = True
    node.set(0x607A, 0, 500)
    node.step(0.001, 1.0)
    node.set(0x607A, 0, 50)  # back within the window: the time out starts again
    node.step(0.001, 1.001)
    assert math.isnan(node.fe_since)
    node.state = SWITCHED_ON  # not enabled: no following error is judged
    node.set(0x6065, 0, 100)
    node.set(0x607A, 0, 10**6)
    node.step(0.001, 2.0)
    node.step(0.001, 3.0)
    assert node.state == SWITCHED_ON and math.isnan(node.fe_since)
    node.state = OPERATION_ENABLED
    node.set(0x6065, 0, 0xFFFFFFFF)  # no window at all
    node.set(0x607A, 0, 10**6)
    node.step(0.001, 2.0)
    node.step(0.001, 3.0)
    assert node.state == OPERATION_ENABLED and math.isnan(node.fe_since)


# ----------------------------------------------------------------------------- frames in
def frame(cob: int, data: bytes = b"", **kw: Any) -> can.Message:
    return can.Message(arbitration_id=cob, data=data, is_extended_id=False, **kw)


def test_the_emulator_takes_each_frame_to_the_node_and_object_it_names() -> None:
    t = [1.0]
    emu = emulator(t)
    one, two, three = emu.node(1), emu.node(2), emu.node(3)
    emu.handle(frame(0x000, bytes([0x01, 0x00])))  # NMT start, every node
    assert {n.nmt for n in (one, two, three)} == {NMT_OPERATIONAL}
    emu.handle(frame(0x000, bytes([0x80, 0x02])))  # enter pre-operational, node 2 only
    assert (one.nmt, two.nmt, three.nmt) == (NMT_OPERATIONAL, NMT_PRE_OPERATIONAL, NMT_OPERATIONAL)
    assert emu.frames_in == 2 and emu.ignored == 0
    for bad in (
        can.Message(arbitration_id=0x000, is_error_frame=True),
        can.Message(arbitration_id=0x201, is_remote_frame=True, is_extended_id=False),
        can.Message(arbitration_id=0x201, data=bytes(6), is_extended_id=True),
    ):
        emu.handle(bad)
    assert emu.ignored == 3 and emu.frames_in == 2
    emu.handle(frame(0x209, bytes(6)))  # node 9 is not emulated
    assert emu.ignored == 4 and emu.frames_in == 3
    for node in (one, three):
        mapped(node)
        node.set(0x1400, 1, 0x200 + node.node_id)
        node.set(0x1400, 2, 255)
        node.state = OPERATION_ENABLED
    one.set(0x1601, 1, 0x60710010)
    one.set(0x1601, 0, 1)
    one.set(0x1401, 1, 0x301)
    one.set(0x1401, 2, 255)
    emu.handle(frame(0x301, (-250).to_bytes(2, "little", signed=True)))  # RPDO 2 of node 1
    assert one.get(0x6071, 0) == -250 and one.rpdos == 1
    three.set(0x1400, 1, 0x80000203)  # RPDO 1 of node 3 off: its frames are not taken
    emu.handle(frame(0x203, rpdo(0x0F, 777)))
    assert three.rpdos == 0 and three.get(0x607A, 0) != 777 and emu.ignored == 5
    emu.handle(frame(0x7F0 & 0x780 | 0x01, bytes([0x05])))  # a heartbeat of node 1: not ours
    assert emu.ignored == 6 and emu.errors == 0


# ----------------------------------------------------------------------------- cycle timing
def test_the_masters_cycle_is_timed_from_each_frames_arrival() -> None:
    """:class:`CycleTimes` through :meth:`DriveEmulator.handle`: per SYNC, the first and the
    last RPDO since the previous SYNC to it, from the frames' timestamps; the SYNC to the
    TPDOs it caused, to when they were sent; a SYNC without RPDOs counted, not timed; another
    node's RPDO and the emulator's own TPDOs not taken for setpoints."""
    import json

    from occ.drivers.cia402_sim import _timing

    with can.Bus(interface="virtual", channel="occ-cia402-cycle") as bus:
        emu = DriveEmulator([1, 2], DEFAULT_EDS, bus=bus, clock=lambda: 0.0)
        for nid in (1, 2):
            node = emu.node(nid)
            for sub, entry in enumerate((0x60400010, 0x607A0020), 1):
                node.set(0x1600, sub, entry)
            node.set(0x1600, 0, 2)
            node.set(0x1A00, 1, 0x60410010)
            node.set(0x1A00, 0, 1)
            node.set(0x1400, 1, 0x200 + nid)
            node.set(0x1400, 2, 1)
            node.set(0x1800, 1, 0x180 + nid)
            node.set(0x1800, 2, 1)
            node.nmt = NMT_OPERATIONAL
        t0 = 1_000_000.0  # the frames' own timestamps: what is timed is their differences

        def sync(at: float) -> tuple[float, float]:
            before = time.time()
            emu.handle(frame(0x080, timestamp=at))
            return before - at, time.time() - at

        sync(t0)  # no RPDO before it
        emu.handle(frame(0x201, rpdo(0x0F, 10), timestamp=t0 + 0.0100))
        emu.handle(frame(0x202, rpdo(0x0F, 20), timestamp=t0 + 0.0101))
        emu.handle(frame(0x203, rpdo(0x0F, 30), timestamp=t0 + 0.0102))  # node 3: not ours
        low, high = sync(t0 + 0.0103)
        emu.handle(frame(0x181, bytes(2), timestamp=t0 + 0.0104))  # a TPDO echoed: no setpoint
        emu.handle(frame(0x202, rpdo(0x0F, 21), timestamp=t0 + 0.0120))
        emu.node(1).nmt = emu.node(2).nmt = NMT_PRE_OPERATIONAL  # no TPDO answers the next
        sync(t0 + 0.0125)
        cycle = emu.cycle
        assert cycle.syncs == 3 and cycle.syncs_without_rpdo == 1
        assert [round(v * 1e6, 1) for v in cycle.rpdo_to_sync] == [300.0, 500.0]
        assert [round(v * 1e6, 1) for v in cycle.setpoints_ready] == [200.0, 500.0]
        assert len(cycle.sync_to_tpdo) == 2  # the first two SYNCs: two TPDOs each
        assert low <= cycle.sync_to_tpdo[1] <= high
        assert emu.node(1).get(0x607A, 0) == 10 and emu.node(2).get(0x607A, 0) == 20
        summary = cycle.summary()
        assert summary["rpdo_to_sync_us"] == {
            "n": 2, "min": 300.0, "p50": 300.0, "p99": 500.0, "p99.9": 500.0, "max": 500.0
        }  # fmt: skip
        assert summary["setpoints_ready_us"]["p50"] == 200.0
        line = _timing(emu, "timing")
        assert line.startswith("cia402 emulator timing: ")
        assert json.loads(line.split(": ", 1)[1]) == summary
        assert _timing(emu, "timing reset") == "ok: timing reset"
        assert emu.cycle.syncs == 0 and not emu.cycle.rpdo_to_sync and not emu.cycle.sync_to_tpdo
        assert emu.cycle.summary()["sync_to_tpdo_us"] is None
        assert _timing(emu, "status") == "" and _timing(emu, "") == ""
