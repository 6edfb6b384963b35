"""The ``cia402`` driver against the emulator, the cases mutation testing found unproved
(issue 42, docs/VERIFICATION.md): the safe stop of a supervisor, the fault reset's words and
its NMT restart, a reset that no TPDO answers, the ages counted after a reset that took the
loop's time, the second sensor after a reset. The rig is test_cia402.py's: python-can's
``virtual`` bus, simulated time.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable

import can
import pytest

from occ.drivers import DriverState
from occ.drivers.cia402 import CiA402Driver
from occ.drivers.cia402_protocol import NMT_OPERATIONAL
from occ.errors import DriverError
from tests.occ import test_cia402
from tests.occ.test_cia402 import DT, Rig, _move, make_joints, node_params

rig = test_cia402.rig  # the fixture: a driver and the emulator on a virtual channel


@pytest.mark.req("SR-HW-33")
def test_the_supervisors_safe_stop_quick_stops_every_node_at_once(rig: Callable[..., Rig]) -> None:
    r = rig()
    r.enabled()
    move = _move(r)
    for k in range(20):  # moving: the last target is ahead of where the motor is
        r.tick(move(k))
    before = r.drv.stats()
    with can.Bus(interface="virtual", channel=r.channel) as sniffer:
        r.drv.safe_stop("EStop")  # from the supervisor: no read, no write
        frames = []
        while (msg := sniffer.recv(timeout=0.0)) is not None:
            frames.append(msg)
    held = [struct.pack("<Hi", 0x02, n.counts) for n in r.drv._nodes]
    assert [bytes(m.data) for m in frames if 0x201 <= m.arbitration_id <= 0x203] == held
    assert held[0] != struct.pack("<Hi", 0x02, r.drv._nodes[0].target)
    assert r.drv.state is DriverState.FAULT and r.drv.stop_failed is None
    r.emu.settle()
    for nid in (1, 2, 3):
        node = r.emu.node(nid)
        assert node.controlwords[-1] == 0x02, (nid, node.controlwords)
        assert node.quick_stops == 1
    stats = r.drv.stats()
    assert stats["quick_stops"] == before["quick_stops"] + 1
    assert stats["rpdo_frames"] == before["rpdo_frames"] + 3
    assert stats["sync_frames"] == before["sync_frames"] + 1


@pytest.mark.req("SR-HW-34")
def test_a_fault_reset_sends_the_edge_to_the_node_in_fault_and_counts_it(
    rig: Callable[..., Rig],
) -> None:
    r = rig()
    r.enabled()
    r.ticks(15, r.here())  # every node's heartbeat heard (each 10 ms)
    r.emu.inject_emcy(2, 0x2310)
    r.until_fault(20, lambda k: r.here())
    r.ticks(2)
    sent = {nid: len(r.emu.node(nid).controlwords) for nid in (1, 2, 3)}
    r.drv.reset()
    # the nodes that stayed OPERATIONAL were not restarted: their NMT state is still known
    assert {n["nmt"] for n in r.drv.stats()["nodes"].values()} == {"OPERATIONAL"}
    r.emu.settle()
    assert r.drv.state is DriverState.INACTIVE
    assert r.drv.stats()["fault_resets"] == 1
    # the node in FAULT: bit 7 low, then its rising edge; the others: voltage off only
    assert r.emu.node(2).controlwords[sent[2] :][:2] == [0x00, 0x80]
    for nid in (1, 3):
        assert set(r.emu.node(nid).controlwords[sent[nid] :]) == {0x00}, nid
    r.ticks(4)
    r.drv.activate()
    r.emu.settle()
    r.ticks(4, r.here())
    assert r.drv.state is DriverState.ACTIVE
    r.emu.inject_fault_bit(3)
    r.until_fault(20, lambda k: r.here())
    r.drv.reset()
    assert r.drv.stats()["fault_resets"] == 2 and r.drv.stats()["quick_stops"] == 2


def test_the_stats_show_the_bus_load_and_the_last_fault(rig: Callable[..., Rig]) -> None:
    r = rig()
    assert round(r.drv.bus_load, 4) != round(r.drv.bus_load, 3)  # the figure has more digits
    r.enabled()
    stats = r.drv.stats()
    assert stats["bus_load"] == round(r.drv.bus_load, 3) and 0.5 < stats["bus_load"] < 0.6
    assert "last_fault" not in stats
    r.emu.inject_emcy(3, 0x4310)
    err = r.until_fault(20, lambda k: r.here())
    assert r.drv.stats()["last_fault"] == str(err)


@pytest.mark.req("SR-HW-34")
def test_a_reset_starts_a_node_that_left_operational_again(rig: Callable[..., Rig]) -> None:
    r = rig()
    r.enabled()
    r.emu.leave_operational(2)
    err = r.until_fault(20, lambda k: r.here())
    assert "node 2 (joint pitch): left NMT OPERATIONAL" in str(err)
    r.ticks(2)
    r.drv.reset()
    r.emu.settle()
    assert r.emu.node(2).nmt == NMT_OPERATIONAL
    assert r.drv.state is DriverState.INACTIVE
    r.ticks(40)  # its heartbeats say OPERATIONAL again: no fault
    assert r.drv.stats()["nodes"]["pitch"]["nmt"] == "OPERATIONAL"
    assert r.drv.stats()["fault_resets"] == 1


@pytest.mark.req("SR-HW-34")
def test_a_reset_that_no_tpdo_answers_is_refused_naming_the_node(rig: Callable[..., Rig]) -> None:
    r = rig(state_timeout_ms=40.0)
    r.enabled()
    r.emu.mute_tpdos(3)
    err = r.until_fault(40, lambda k: r.here())
    assert "node 3 (joint insertion): no TPDO for" in str(err)
    with pytest.raises(DriverError) as info:
        r.drv.reset()
    text = str(info.value)
    assert "fault reset refused within 40 ms" in text
    assert "node 3 (joint insertion): no TPDO answered the reset's SYNC" in text
    assert "node 1" not in text and "node 2" not in text
    assert r.drv.state is DriverState.FAULT


@pytest.mark.req("SR-HW-34")
def test_the_first_read_after_a_reset_that_took_the_loop_s_time_counts_from_itself(
    rig: Callable[..., Rig],
) -> None:
    """A reset runs off the loop thread (occ/core/powerup.py): the loop's next read of the
    driver comes when the reset has ended, maybe later than a heartbeat's timeout after the
    last read; the heartbeats heard while the reset waited are as fresh as that read."""
    r = rig()
    r.enabled()
    r.ticks(15, r.here())  # every node's heartbeat heard (each 10 ms)
    r.emu.inject_emcy(1, 0x7300)
    r.until_fault(20, lambda k: r.here())
    r.ticks(2)
    r.t += 0.035  # the drives' time goes on while the reset runs: they send heartbeats
    r.drv.reset()  # what it hears is stamped with the last read's now, 35 ms before
    r.drv.read(r.t)  # node_heartbeat_timeout_ms 30: their age is counted from here
    r.emu.settle()
    r.ticks(4)
    assert r.drv.state is DriverState.INACTIVE


@pytest.mark.req("SR-HW-36")
def test_a_second_sensor_still_off_after_a_reset_waits_its_latency_again(
    rig: Callable[..., Rig],
) -> None:
    nodes = node_params()
    nodes["yaw"]["second_sensor"] = {
        "index": 0x2100, "counts_per_unit": 52152.0, "tolerance": 0.002, "latency_ms": 5.0,
    }  # fmt: skip
    r = rig(nodes=nodes)
    r.enabled()
    move = _move(r)
    r.ticks(10, move(0))
    r.emu.offset_second_encoder(1, 0.01 * 52152.0)
    r.until_fault(20, lambda k: move(0))
    r.ticks(2)
    r.drv.reset()
    r.emu.settle()
    r.ticks(4)  # within the latency: not yet
    assert r.drv.state is DriverState.INACTIVE
    err = r.until_fault(20, lambda k: move(0))
    assert "joint yaw: second position sensor disagrees by 0.01" in str(err)


def test_a_sync_and_the_rpdos_go_out_every_sync_every_th_write(rig: Callable[..., Rig]) -> None:
    r = rig(sync_every=2)
    r.enabled()
    r.ticks(2, r.here())
    before = r.drv.stats()
    r.ticks(10, r.here())
    stats = r.drv.stats()
    assert stats["sync_frames"] - before["sync_frames"] == 5
    assert stats["rpdo_frames"] - before["rpdo_frames"] == 15  # three nodes each SYNC
    assert r.emu.node(1).syncs == r.emu.node(3).syncs


def test_a_target_beyond_32_bits_of_counts_is_sent_as_the_bound(rig: Callable[..., Rig]) -> None:
    """A fine encoder on a long axis can count past a signed 32-bit target: the target sent is
    the nearest bound, never a wrapped (far, opposite) value."""
    r = rig()
    r.drv.configure()
    r.ticks(4)
    node = r.drv._nodes[2]  # insertion, 2e6 counts/m
    for metres, counts in ((1100.0, 2**31 - 1), (-1100.0, -(2**31)), (0.5, 10**6)):
        r.t += 0.001
        r.drv._write(
            [0.0, 0.0, metres], r.t
        )  # the hook itself: the base's limits are not under test
        r.t += 0.001
        r.drv._write([0.0, 0.0, metres], r.t)  # sync_every 2: packed on the second
        assert node.target == counts, metres
        assert struct.unpack("<Hi", bytes(node.rpdo)) == (0x0F, counts)


@pytest.mark.req("SR-HW-34")
def test_a_node_heard_before_and_silent_since_fails_the_first_read_after_a_reset(
    rig: Callable[..., Rig],
) -> None:
    """The reset's own frames are as fresh as the read after it; a heartbeat last heard before
    the fault is not: a node that stopped its heartbeat is judged on its real age."""
    r = rig()
    r.enabled()
    r.ticks(15, r.here())  # every node's heartbeat heard (each 10 ms)
    r.emu.stop_heartbeat(1)
    err = r.until_fault(100, lambda k: r.here())
    assert "node 1 (joint yaw): heartbeat consumer timeout" in str(err)
    r.drv.reset()  # its TPDOs answer: the fault reset itself passes
    r.t += 0.001
    with pytest.raises(DriverError) as info:
        r.drv.read(r.t)
    assert "node 1 (joint yaw): heartbeat consumer timeout" in str(info.value)


@pytest.mark.req("SR-HW-34")
def test_a_node_restarted_by_the_reset_and_silent_since_fails_the_first_read(
    rig: Callable[..., Rig],
) -> None:
    """A node that left OPERATIONAL and stopped its heartbeat: the reset's NMT start brings its
    TPDOs back, but no heartbeat has said it is OPERATIONAL since its last, 40 ms old."""
    r = rig()
    r.enabled()
    r.ticks(15, r.here())
    r.emu.leave_operational(2)
    r.emu.stop_heartbeat(2)
    err = r.until_fault(20, lambda k: r.here())
    assert "node 2 (joint pitch): left NMT OPERATIONAL" in str(err)
    r.ticks(40)  # latched: its silence is not judged meanwhile
    r.drv.reset()
    r.emu.settle()
    assert r.emu.node(2).nmt == NMT_OPERATIONAL  # started again, answering the reset's SYNC
    r.t += 0.001
    with pytest.raises(DriverError) as info:
        r.drv.read(r.t)
    assert "node 2 (joint pitch): heartbeat consumer timeout: no heartbeat for 4" in str(info.value)


@pytest.mark.req("SR-HW-34")
def test_two_resets_before_a_read_count_what_either_heard_from_the_read(
    rig: Callable[..., Rig],
) -> None:
    """A reset refused, then another before the loop read: the heartbeats heard in the first
    (stamped with the read before both, 35 ms ago) are as fresh as the read after them."""
    r = rig(state_timeout_ms=40.0)
    r.enabled()
    r.ticks(15, r.here())
    r.emu.inject_emcy(1, 0x7300, persist=True)
    r.until_fault(20, lambda k: r.here())
    r.ticks(2)
    r.t += 0.035  # the drives' time goes on: their heartbeats come during the first reset
    hb = r.drv.stats()["heartbeat_frames"]
    with pytest.raises(DriverError, match="node 1 \\(joint yaw\\): still FAULT"):
        r.drv.reset()
    assert r.drv.stats()["heartbeat_frames"] > hb
    r.emu.clear(1)
    hb = r.drv.stats()["heartbeat_frames"]
    r.drv.reset()  # again, before any read: accepted, and no heartbeat heard in it
    assert r.drv.stats()["heartbeat_frames"] == hb
    r.t += 0.001
    r.drv.read(r.t)
    r.emu.settle()
    r.ticks(4)
    assert r.drv.state is DriverState.INACTIVE


@pytest.mark.req("SR-HW-34")
def test_a_node_whose_tpdos_stop_after_the_reset_fails_within_its_feedback_timeout(
    rig: Callable[..., Rig],
) -> None:
    """Heartbeating, answering the reset's SYNC, then no TPDO: the SYNCs of the reads after
    the reset are owed from those reads, and the feedback timeout (10 ms) judges them."""
    r = rig()
    r.enabled()
    r.ticks(15, r.here())
    r.emu.inject_emcy(2, 0x2310)
    r.until_fault(20, lambda k: r.here())
    r.ticks(2)
    r.drv.reset()
    r.emu.settle()
    r.emu.mute_tpdos(3)
    r.ticks(2)
    err = r.until_fault(12, lambda k: None)  # 10 ms, and the SYNC every 2 ticks
    assert "node 3 (joint insertion): no TPDO for 1" in str(err)
    assert r.drv.stats()["nodes"]["insertion"]["nmt"] == "OPERATIONAL"


@pytest.mark.req("SR-HW-34")
def test_a_node_silent_in_its_tpdos_through_a_cancelled_enable_fails_the_first_read(
    rig: Callable[..., Rig],
) -> None:
    """An Enable that waited 15 ms of the loop's time, on its thread, for a node whose TPDOs had
    stopped, then cancelled (INACTIVE): the TPDO it owes since the last read is owed from then
    at the first read after it, not from that read (the others answered: owed from it)."""
    r = rig()
    r.drv.configure()
    r.ticks(4)  # the last read's SYNC is answered by every node
    r.emu.mute_tpdos(3)
    r.t += 0.015  # the loop's time goes on while the Enable waits on its thread
    syncs = r.drv.stats()["sync_frames"]
    errors: list[Exception] = []

    def power_up() -> None:
        try:
            r.drv.activate()
        except Exception as err:  # noqa: BLE001 - what activate raised, checked below
            errors.append(err)

    thread = threading.Thread(target=power_up)
    thread.start()
    give_up = time.monotonic() + 5.0
    while r.drv.stats()["sync_frames"] == syncs:  # its first step sent: node 3 never answers
        assert time.monotonic() < give_up
        time.sleep(0.001)
    assert r.drv.cancel_activation("operator Disable")
    thread.join(2.0)
    assert not thread.is_alive() and len(errors) == 1
    assert r.drv.state is DriverState.INACTIVE
    r.t += 0.001
    with pytest.raises(DriverError) as info:
        r.drv.read(r.t)
    assert "node 3 (joint insertion): no TPDO for 16.0 ms" in str(info.value)


@pytest.mark.req("SR-HW-32")
def test_an_enable_before_any_position_is_refused_naming_every_node(
    rig: Callable[..., Rig],
) -> None:
    r = rig()
    r.drv.configure()  # no read yet: no TPDO taken
    with pytest.raises(DriverError) as info:
        r.drv.activate()
    assert str(info.value) == (
        "cia402 driver 'arm': node 1 (joint yaw), node 2 (joint pitch), node 3 (joint "
        "insertion): no position reported yet"
    )
    r.emu.settle()
    assert all(r.emu.node(n).describe()["state"] != "OPERATION ENABLED" for n in (1, 2, 3))


@pytest.mark.req("SR-HW-32")
def test_two_nodes_that_will_not_enable_are_both_named(rig: Callable[..., Rig]) -> None:
    r = rig(state_timeout_ms=50.0)
    r.emu.refuse_enable(2)
    r.emu.refuse_enable(3)
    r.drv.configure()
    r.ticks(4)
    with pytest.raises(DriverError) as info:
        r.drv.activate()
    assert str(info.value).startswith(
        "cia402 driver 'arm': not OPERATION ENABLED within 50 ms: node 2 (joint pitch) in "
        "SWITCHED ON (statusword 0x0233); node 3 (joint insertion) in SWITCHED ON "
        "(statusword 0x0233); every node switched off again"
    )


@pytest.mark.req("SR-HW-32")
def test_an_enable_refused_for_a_silent_node_names_it_first(rig: Callable[..., Rig]) -> None:
    """A node whose TPDOs stopped while its heartbeat goes on, its last statusword still
    OPERATION ENABLED: the Enable waits on it until the timeout (the other nodes get no further
    step meanwhile); the refusal names the silent node first, not as enabled, then the others."""
    r = rig(state_timeout_ms=40.0)
    r.enabled()
    r.ticks(15, r.here())
    r.emu.mute_tpdos(3)  # node 3 stops its TPDOs; its heartbeat goes on
    r.drv.deactivate()  # every node off; node 3 never says so
    r.emu.settle()
    with pytest.raises(DriverError) as info:
        r.drv.activate()
    msg = str(info.value)
    assert msg.startswith(
        "cia402 driver 'arm': not OPERATION ENABLED within 40 ms: node 3 (joint insertion): "
        "no TPDO answered any SYNC of it (its last statusword 0x"
    ), msg
    silent, *others = msg.split(": not OPERATION ENABLED within 40 ms: ")[1].split("; ")
    assert "OPERATION ENABLED" in silent  # what its old statusword said, told as old
    # each other node once, and no node twice (the silent one is not short of it as well)
    assert [o.split(" in ")[0] for o in others[:-1]] == [
        "node 1 (joint yaw)",
        "node 2 (joint pitch)",
    ]
    assert msg.endswith("; every node switched off again")


@pytest.mark.req("SR-HW-32")
def test_a_node_that_faults_while_enabling_vetoes_it_at_once(rig: Callable[..., Rig]) -> None:
    r = rig(state_timeout_ms=5000.0)
    r.drv.configure()
    r.ticks(4)
    r.emu.inject_emcy(2, 0x2310)  # its EMCY waits on the bus: the activation takes it
    with pytest.raises(DriverError) as info:
        r.drv.activate()
    assert str(info.value).startswith(
        "cia402 driver 'arm': node 2 (joint pitch): EMCY 0x2310 (continuous overcurrent (motor "
        "side)), error register 0x03; not enabled; every node switched off again"
    )


def test_the_master_s_heartbeat_goes_on_while_an_activation_waits(rig: Callable[..., Rig]) -> None:
    """Activate waits on the drives off the loop thread: it sends the master's heartbeat
    itself (every quarter of heartbeat_ms), or a drive already enabled would stop (0x8130)."""
    r = rig(heartbeat_ms=20.0, state_timeout_ms=150.0)
    r.drv.configure()
    r.ticks(4)
    with can.Bus(interface="virtual", channel=r.channel) as sniffer:
        with r.emu.held(), pytest.raises(DriverError):  # the drives answer nothing
            r.drv.activate()
        beats = 0
        while (msg := sniffer.recv(timeout=0.0)) is not None:
            beats += msg.arbitration_id == 0x77F
    assert beats >= 5  # every 5 ms of a 150 ms wait, whatever the load


def test_the_stop_frames_have_the_mapped_length_and_an_empty_sync(rig: Callable[..., Rig]) -> None:
    from occ.joint import PIDGains

    r = rig(command_interface="effort")
    for j in r.joints:
        j.gains = PIDGains(kp=1.0)
    r.enabled()
    with can.Bus(interface="virtual", channel=r.channel) as sniffer:
        for _ in range(2):  # a SYNC's worth of writes: the cycle's RPDOs, 4 bytes each
            r.t += DT
            r.drv.read(r.t)
            r.drv.write_effort([0.0, 0.0, 0.0], r.t)
        cycle = [m for m in iter(lambda: sniffer.recv(timeout=0.0), None)]
        assert [m.dlc for m in cycle if 0x201 <= m.arbitration_id <= 0x203] == [4, 4, 4]
        r.drv.safe_stop("EStop")
        frames = []
        while (msg := sniffer.recv(timeout=0.0)) is not None:
            frames.append(msg)
    rpdos = [m for m in frames if 0x201 <= m.arbitration_id <= 0x203]
    assert [bytes(m.data) for m in rpdos] == [bytes([0x02, 0, 0, 0])] * 3  # CST: 4 bytes
    syncs = [m for m in frames if m.arbitration_id == 0x080]
    assert len(syncs) == 1 and syncs[0].dlc == 0 and not syncs[0].is_extended_id
    r.emu.settle()
    assert all(r.emu.node(n).controlwords[-1] == 0x02 for n in (1, 2, 3))


@pytest.mark.req("SR-HW-34")
def test_a_reset_with_a_heartbeat_waiting_on_the_bus_reads_fine_after(
    rig: Callable[..., Rig],
) -> None:
    r = rig()
    r.enabled()
    r.ticks(15, r.here())
    r.emu.inject_emcy(1, 0x7300)
    r.until_fault(20, lambda k: r.here())
    r.t += 0.010
    r.emu.settle()  # the nodes' heartbeats, sent since the last read, wait on the bus
    r.drv.reset()
    r.ticks(4)
    assert r.drv.state is DriverState.INACTIVE


@pytest.mark.req("SR-HW-34")
def test_a_reset_of_nodes_never_heard_is_refused_naming_each(rig: Callable[..., Rig]) -> None:
    r = rig(state_timeout_ms=40.0)
    r.emu.mute_tpdos(2)
    r.emu.mute_tpdos(3)
    r.drv.configure()
    err = r.until_fault(40, lambda k: r.here())
    assert "no TPDO for" in str(err)
    with pytest.raises(DriverError) as info:
        r.drv.reset()
    assert str(info.value) == (
        "cia402 driver 'arm': fault reset refused within 40 ms: node 2 (joint pitch): no TPDO "
        "answered the reset's SYNC; node 3 (joint insertion): no TPDO answered the reset's SYNC"
    )
    with pytest.raises(DriverError) as again:  # they still hold 0: never heard, never moved
        r.drv.reset()
    assert str(again.value) == str(info.value)


@pytest.mark.req("SR-HW-32")
def test_heartbeats_heard_while_enabling_are_judged_as_fresh(rig: Callable[..., Rig]) -> None:
    r = rig()
    r.drv.configure()
    r.ticks(4)
    r.t += 0.02  # the drives' time goes on: they send heartbeats while the activation waits
    r.drv.activate()
    r.emu.settle()
    r.ticks(10, r.here())
    assert r.drv.state is DriverState.ACTIVE


@pytest.mark.req("SR-HW-37")
def test_each_frame_is_taken_counted_or_ignored_by_its_cob_id(rig: Callable[..., Rig]) -> None:
    r = rig()
    r.drv.configure()
    r.ticks(4)
    before = r.drv.stats()
    r.ticks(10)
    stats = r.drv.stats()
    syncs = stats["sync_frames"] - before["sync_frames"]
    assert syncs == 5 and stats["tpdo_frames"] - before["tpdo_frames"] == 6 * syncs
    std = {"is_extended_id": False}
    with can.Bus(interface="virtual", channel=r.channel) as other:
        for msg in (
            can.Message(arbitration_id=0x04, is_error_frame=True),  # a warning: counted
            can.Message(arbitration_id=0x04, is_error_frame=True),
            can.Message(arbitration_id=0x181, is_remote_frame=True, **std),  # ignored
            can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=True),  # ignored
            can.Message(arbitration_id=0x189, data=bytes(8), **std),  # node 9: not ours
            can.Message(arbitration_id=0x209, data=bytes(6), **std),  # a master's RPDO: echo
            can.Message(arbitration_id=0x080, **std),  # a SYNC: its own, echoed
            can.Message(arbitration_id=0x181, data=bytes(7), **std),  # TPDO 1 too short
            can.Message(arbitration_id=0x281, data=bytes(3), **std),  # TPDO 2 too short
            can.Message(arbitration_id=0x081, data=bytes(2), **std),  # EMCY too short
            can.Message(arbitration_id=0x701, **std),  # an empty heartbeat
        ):
            other.send(msg)
        before = r.drv.stats()
        r.t += DT
        r.drv.read(r.t)
    stats = r.drv.stats()
    got = {k: stats[k] - before[k] for k in ("error_frames", "ignored_frames", "echoes")}
    assert got == {"error_frames": 2, "ignored_frames": 6, "echoes": 2}
    assert stats["tpdo_frames"] == before["tpdo_frames"] + 6  # the last SYNC's, whole
    assert stats["emcy_frames"] == 0 and stats["heartbeat_frames"] == before["heartbeat_frames"]
    assert r.drv.state is DriverState.INACTIVE
    with can.Bus(interface="virtual", channel=r.channel) as other:
        for _ in range(2):  # an EMCY of code 0 (the node's error reset) and a heartbeat
            other.send(can.Message(arbitration_id=0x081, data=bytes(8), **std))
            other.send(can.Message(arbitration_id=0x701, data=bytes([0x05]), **std))
        r.t += DT
        r.drv.read(r.t)
    stats = r.drv.stats()
    assert stats["emcy_frames"] == 2
    assert stats["heartbeat_frames"] == before["heartbeat_frames"] + 2


def test_a_read_takes_at_most_64_frames_a_node(rig: Callable[..., Rig]) -> None:
    """A babbling bus costs a read a bounded number of frames; the rest wait for the next."""
    r = rig()
    r.drv.configure()
    r.ticks(4)
    with r.emu.held(), can.Bus(interface="virtual", channel=r.channel) as other:
        r.t += DT
        r.drv.read(r.t)  # what the emulator sent is taken: the bus holds only what follows
        for _ in range(64 * 3 + 5):
            other.send(can.Message(arbitration_id=0x189, data=bytes(8), is_extended_id=False))
        counts = []
        for _ in range(2):
            before = r.drv.stats()["ignored_frames"]
            r.t += DT
            r.drv.read(r.t)
            counts.append(r.drv.stats()["ignored_frames"] - before)
    assert counts == [192, 5]


def test_no_master_heartbeat_while_an_activation_waits_with_the_heartbeat_off(
    rig: Callable[..., Rig],
) -> None:
    r = rig(heartbeat_ms=0.0, state_timeout_ms=60.0)
    r.drv.configure()
    r.ticks(4)
    with can.Bus(interface="virtual", channel=r.channel) as sniffer:
        with r.emu.held(), pytest.raises(DriverError):
            r.drv.activate()
        r.ticks(10)
        beats = 0
        while (msg := sniffer.recv(timeout=0.0)) is not None:
            beats += msg.arbitration_id == 0x77F
    assert beats == 0


def test_the_master_s_heartbeat_every_quarter_of_heartbeat_ms(rig: Callable[..., Rig]) -> None:
    r = rig(heartbeat_ms=40.0)  # every 10 ms of reads and writes
    r.drv.configure()
    r.ticks(4)
    with can.Bus(interface="virtual", channel=r.channel) as sniffer:
        r.ticks(40)
        beats = [
            m for m in iter(lambda: sniffer.recv(timeout=0.0), None) if m.arbitration_id == 0x77F
        ]
    assert len(beats) == 4 and all(bytes(m.data) == bytes([0x05]) for m in beats)


@pytest.mark.req("SR-HW-33")
def test_a_drive_that_leaves_operation_enabled_on_its_own_faults_the_driver(
    rig: Callable[..., Rig],
) -> None:
    from occ.drivers.cia402_sim import QUICK_STOP_ACTIVE

    r = rig()
    r.enabled()
    r.ticks(4, r.here())
    with r.emu.held():
        r.emu.node(2).state = QUICK_STOP_ACTIVE  # stopped by itself (a local stop input)
    err = r.until_fault(10, lambda k: r.here())
    assert (
        "node 2 (joint pitch): statusword 0x0240: left OPERATION ENABLED, now SWITCH ON "
        "DISABLED" in str(err)
    )


@pytest.mark.req("SR-HW-32")
def test_a_node_in_quick_stop_active_is_switched_off_first_when_enabling_and_named_once() -> None:
    """A drive whose quick stop option keeps it in QUICK STOP ACTIVE (CiA 402 options 5-8; the
    emulator's option 2 leaves it at once) is told disable voltage, the way to SWITCH ON
    DISABLED, then the enable steps. The hook alone, with no bus: its controlwords are packed,
    nothing answers, the state machine's bound ends it."""
    drv = CiA402Driver("arm", make_joints(), {"sync_every": 2, "nodes": node_params(),
                                              "state_timeout_ms": 20.0})  # fmt: skip
    for node, word in zip(drv._nodes, (0x0207, 0x0237, 0x0233), strict=True):
        node.counts, node.statusword = 0, word
    with pytest.raises(DriverError) as info:
        drv._activate()
    assert (
        "node 1 (joint yaw): no TPDO answered any SYNC of it (its last statusword 0x0207, "
        "QUICK STOP ACTIVE)" in str(info.value)
    )
    # every node silent and short of OPERATION ENABLED: each named once
    assert [str(info.value).count(f"node {n} (joint") for n in (1, 2, 3)] == [1, 1, 1]
    # the step each was told last: voltage off (out of QUICK STOP ACTIVE), enable, enable
    assert [n.rpdo[0] for n in drv._nodes] == [0x00, 0x0F, 0x0F]


@pytest.mark.req("SR-HW-33")
def test_a_node_silent_after_a_disable_is_caught_by_the_feedback_deadline(
    rig: Callable[..., Rig],
) -> None:
    """Disable's SYNC asks every node for a TPDO too: one that does not answer is late by
    feedback_timeout from that SYNC, not before."""
    r = rig()
    r.enabled()
    r.ticks(4, r.here())
    r.t += DT
    r.drv.read(r.t)  # every TPDO owed taken: none owed when Disable comes
    r.emu.mute_tpdos(2)
    r.drv.deactivate()
    r.tick()  # 1 ms after: within feedback_timeout (10 ms)
    assert r.drv.state is DriverState.INACTIVE
    err = r.until_fault(20, lambda k: [])
    assert "node 2 (joint pitch): no TPDO for" in str(err)


@pytest.mark.req("SR-HW-39")
def test_heartbeats_taken_while_an_activation_waits_are_as_fresh_as_its_read(
    rig: Callable[..., Rig],
) -> None:
    """While activate waits for the drives' TPDOs, what it takes is stamped with the last
    read's ``now``: the heartbeats heard then are judged with it (and at the next read)."""
    r = rig()
    r.drv.configure()
    r.ticks(4)
    errors: list[Exception] = []

    def power_up() -> None:
        try:
            r.drv.activate()
        except Exception as err:  # noqa: BLE001 - what activate raised, checked below
            errors.append(err)

    with can.Bus(interface="virtual", channel=r.channel) as other:
        with r.emu.held():  # the drives answer nothing yet: the activation waits
            thread = threading.Thread(target=power_up)
            thread.start()
            give_up = time.monotonic() + 5.0
            while (msg := other.recv(timeout=0.01)) is None or msg.arbitration_id != 0x080:
                assert time.monotonic() < give_up  # its first SYNC: it waits for the TPDOs
            # ahead of every TPDO on the bus: the wait takes them, whenever it polls
            for nid in (1, 2, 3):
                other.send(can.Message(arbitration_id=0x700 + nid, data=bytes([0x05]),
                                       is_extended_id=False))  # fmt: skip
        thread.join(5.0)
    assert not thread.is_alive() and errors == []
    r.emu.settle()
    r.ticks(4, r.here())
    assert r.drv.state is DriverState.ACTIVE


def _returns(call: Callable[[], None]) -> bool:
    """Whether ``call`` returned within 5 s on a thread of its own (a send that would wait for
    ever does not)."""
    thread = threading.Thread(target=call, daemon=True)
    thread.start()
    thread.join(5.0)
    return not thread.is_alive()


@pytest.mark.parametrize("active", [False, True])
def test_a_jammed_bus_faults_the_cycle_instead_of_blocking_the_loop(
    rig: Callable[..., Rig], active: bool
) -> None:
    """A receiver whose queue is full (nothing gets through): the SYNC of a read (not ACTIVE)
    or the RPDOs of a write (ACTIVE) give up at once and the driver faults."""
    r = rig(heartbeat_ms=0.0)  # no master heartbeat: the cycle's own frames are what is sent
    if active:
        r.enabled()
    else:
        r.drv.configure()
    r.ticks(4, r.here() if active else None)
    failures: list[str] = []

    def cycle() -> None:
        for _ in range(4):  # two SYNCs (sync_every 2): the first frame fills the jam
            r.t += DT
            try:
                r.drv.read(r.t)
                if active:
                    r.drv.write(r.here(), r.t)
            except DriverError as err:
                failures.append(str(err))
                return

    with can.Bus(interface="virtual", channel=r.channel, rx_queue_size=1) as jam:
        jam_free = _returns(cycle)
        while jam.recv(timeout=0.0) is not None:  # unblocks a send that would wait for ever
            pass
        assert jam_free
    sent = "send of 0x20" if active else "send of 0x080 failed"  # an RPDO, or the SYNC
    assert failures and sent in failures[0]
    assert r.drv.state is DriverState.FAULT
