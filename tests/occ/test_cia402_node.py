"""The pieces of the ``cia402`` driver below the bus (issue 42: found by mutation testing,
docs/VERIFICATION.md): what it knows of one node (occ/drivers/cia402_setup.py ``Node``: the
frames it takes, the faults it judges, the words of a reset), a joint's second position
sensor as configured, the protocol's tables, and an SDO failure's text. No bus, no clock: every
``now`` is passed in.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path
from typing import Any

import can
import pytest

from occ.drivers.cia402_protocol import (
    CW_DISABLE_VOLTAGE,
    CW_FAULT_RESET,
    NMT_OPERATIONAL,
    NMT_PRE_OPERATIONAL,
    cia402_state,
    emcy_meaning,
    frame_bits,
    master_sends,
    sdo_abort_meaning,
)
from occ.drivers.cia402_setup import (
    DEFAULT_EDS,
    Node,
    Settings,
    load_od,
    parse_second,
    read_settings,
    sdo_error,
)
from occ.joint import Joint, JointLimits

YAW = Joint("yaw", "revolute", JointLimits(-1.0, 1.0, 1.5, 20.0))
SLIDE = Joint("insertion", "prismatic", JointLimits(0.0, 0.15, 0.1, 50.0))
WHERE = "cia402 driver 'arm'"


def make_node(cpu: float = 1000.0, joint: Joint = YAW, **spec: Any) -> Node:
    node = Node(0, joint, {"node_id": 5, "counts_per_unit": cpu, **spec}, effort=False)
    node.od = load_od(str(DEFAULT_EDS))
    return node


def settings(**over: Any) -> Settings:
    p: dict[str, Any] = {
        "interface": "virtual", "channel": "x", "bitrate": 1_000_000, "bus_kwargs": {},
        "sync_every": 1, "feedback_timeout": 10.0, "node_heartbeat_ms": 10,
        "node_heartbeat_timeout_ms": 30.0, "master_node_id": 127, "sdo_timeout_ms": 300.0,
        "state_timeout_ms": 300.0,
    }  # fmt: skip
    p.update(over)
    return read_settings(WHERE, p, 0.001, 0.05, False)


def tpdo1(sw: int, counts: int, torque: int = 0) -> bytes:
    return struct.pack("<Hih", sw, counts, torque)


# ----------------------------------------------------------------------------- frames
@pytest.mark.req("SR-HW-33")
def test_an_emcy_of_exactly_three_bytes_is_taken_and_a_shorter_one_is_not() -> None:
    node = make_node()
    assert not node.take_emcy(b"\x10\x23")  # two bytes: no error register
    assert node.emcys == 0 and node.emcy_pending is None
    assert node.take_emcy(b"\x10\x23\x05")  # code and register: an EMCY's least
    assert node.emcy_pending == (0x2310, 0x05) and node.emcys == 1
    assert node.take_emcy(struct.pack("<HB5x", 0x4310, 0x09))
    assert node.emcys == 2
    assert node.emcy_pending == (0x2310, 0x05)  # the first not yet acted on is kept
    assert node.last_emcy == (0x4310, 0x09)
    assert node.take_emcy(struct.pack("<HB5x", 0, 0))  # the node's error reset
    assert node.emcys == 3 and node.last_emcy == (0x4310, 0x09)


def test_tpdos_scale_counts_to_units_and_per_mille_to_effort() -> None:
    node = make_node(cpu=-2000.0, rated_torque=4.0)  # mounted reversed
    assert node.take_tpdo1(tpdo1(0x0237, 1000, 250)[:7], 1.0) is None  # short
    assert node.tpdo1 == 0 and node.counts is None
    pos, eff = node.take_tpdo1(tpdo1(0x0237, 1000, 250), 1.0) or (math.nan, math.nan)
    assert pos == -0.5 and eff == -1.0  # 250 per mille of 4 N m, reversed with the counts
    assert node.counts == 1000 and node.statusword == 0x0237 and node.tpdo1 == 1
    assert node.take_tpdo2(b"\x00\x00\x00") is None and node.tpdo2 == 0
    assert node.take_tpdo2(struct.pack("<i", 4000)) == -2.0 and node.tpdo2 == 1
    node.second = (0x2100, 0, 1000.0, 0.01, 0.005)
    assert node.take_tpdo2(struct.pack("<ii", 4000, 777)) == -2.0
    assert node.second_counts == 777 and node.tpdo2 == 2
    assert node.take_tpdo2(struct.pack("<i", 2000)) == -1.0  # velocity only: still taken
    assert node.second_counts == 777


def test_a_fine_drive_below_one_count_per_unit_keeps_its_torque_s_sense() -> None:
    node = make_node(cpu=0.5, rated_torque=2.0)
    assert node.take_tpdo1(tpdo1(0x0237, 10, 500), 0.0) == (20.0, 1.0)


def test_a_tpdo_is_stamped_at_the_sync_it_answers() -> None:
    node = make_node()
    node.take_tpdo1(tpdo1(0x0237, 0), 1.0)
    assert node.sampled_at == 1.0 and node.tpdo_at == 1.0  # none owed: its arrival
    node.owed_since = 1.002
    node.take_tpdo1(tpdo1(0x0237, 0), 1.005)
    assert node.sampled_at == 1.002 and node.tpdo_at == 1.005
    assert math.isnan(node.owed_since)


def test_a_heartbeat_takes_the_nmt_state_without_the_toggle_bit() -> None:
    node = make_node()
    assert not node.take_heartbeat(b"", 1.0) and node.heartbeats == 0 and node.nmt is None
    assert math.isnan(node.hb_at)
    assert node.take_heartbeat(bytes([0x80 | NMT_OPERATIONAL]), 2.0)
    assert node.nmt == NMT_OPERATIONAL and node.hb_at == 2.0 and node.heartbeats == 1
    assert node.take_heartbeat(bytes([NMT_PRE_OPERATIONAL]), 3.0) and node.heartbeats == 2


# ----------------------------------------------------------------------------- faults
@pytest.mark.req("SR-HW-33")
def test_a_node_s_faults_in_their_order_and_at_their_deadlines() -> None:
    s = settings()  # heartbeat timeout 30 ms, feedback_timeout 10 ms
    hb, fb = s.node_hb_timeout, s.feedback_timeout
    node = make_node()
    assert node.fault(0.5299, False, 0.5, s, 0.0) is None  # none heard: counted from t0
    assert "no heartbeat for 30.1 ms" in (node.fault(0.5301, False, 0.5, s, 0.0) or "")
    node.take_heartbeat(bytes([NMT_OPERATIONAL]), 0.0)
    assert node.fault(hb, True, 0.5, s, 0.0) is None  # exactly the timeout: in time
    assert node.fault(0.0301, True, 0.5, s, 0.0) == (
        "heartbeat consumer timeout: no heartbeat for 30.1 ms (producer time 10 ms, timeout 30 ms)"
    )
    node.take_heartbeat(bytes([NMT_OPERATIONAL]), 1.0)
    node.owed_since = 0.0
    assert node.fault(fb, True, 0.0, s, 0.0) is None  # exactly feedback_timeout: in time
    node.owed_since = 1.0
    assert node.fault(1.0105, True, 0.0, s, 0.0) == (
        "no TPDO for 10.5 ms since a SYNC asked for one (feedback_timeout 10 ms)"
    )
    node.owed_since = 1.0
    node.take_heartbeat(bytes([NMT_OPERATIONAL]), 1.1)
    assert (node.fault(1.1, True, 0.0, s, 0.0) or "").startswith("no TPDO for 100.0 ms")
    node.take_heartbeat(bytes([NMT_OPERATIONAL]), 1.0)
    assert (node.fault(1.1, True, 0.0, s, 0.0) or "").startswith(
        "heartbeat consumer timeout: no heartbeat for 100.0 ms"
    )
    node.take_tpdo1(tpdo1(0x0237, 0), 1.0105)  # OPERATION ENABLED
    assert node.fault(1.011, True, 0.0, s, 0.0) is None
    node.take_tpdo1(tpdo1(0x0233, 0), 1.011)  # SWITCHED ON: fine unless active
    assert node.fault(1.011, False, 0.0, s, 0.0) is None
    assert node.fault(1.011, True, 0.0, s, 0.0) == (
        "statusword 0x0233: left OPERATION ENABLED, now SWITCHED ON"
    )
    node.take_heartbeat(bytes([0x7F]), 1.011)
    assert node.fault(1.011, False, 0.0, s, 0.0) == (
        "left NMT OPERATIONAL: its heartbeat says PRE-OPERATIONAL"
    )
    node.take_heartbeat(bytes([0x33]), 1.011)  # no NMT state at all
    assert node.fault(1.011, False, 0.0, s, 0.0) == (
        "left NMT OPERATIONAL: its heartbeat says 0x33"
    )
    node.take_tpdo1(tpdo1(0x0218, 0), 1.011)
    assert node.fault(1.011, False, 0.0, s, 0.0) == ("statusword 0x0218: FAULT (fault bit set)")
    node.take_emcy(struct.pack("<HB", 0x7300, 0x81))
    assert node.fault(1.011, False, 0.0, s, 0.0) == (
        "EMCY 0x7300 (sensor (position or velocity feedback) error), error register 0x81"
    )


@pytest.mark.req("SR-HW-36")
def test_a_second_sensor_is_judged_against_its_tolerance_and_latency() -> None:
    node = make_node(cpu=1024.0)
    node.second = (0x2100, 0, 1024.0, 2.0**-7, 0.0625)
    assert node.second_check(0.5, 10.0) is None  # no second reading yet
    node.second_counts = 520  # 0.5078125: 2**-7 from 0.5, the tolerance exactly
    assert node.second_check(0.5, 10.0) is None and math.isnan(node.second_since)
    assert node.second_check(math.nan, 10.0) is None  # no first reading
    node.second_counts = 512  # 0.5 read by both: in agreement wherever they are
    assert node.second_check(0.5, 10.0) is None
    node.second_counts = 521
    assert node.second_check(0.5, 10.0) is None  # the disagreement starts
    assert node.second_since == 10.0
    assert node.second_check(0.5, 10.0625) is None  # the latency exactly: still waited
    text = node.second_check(0.5, 10.125)
    assert text == (
        "joint yaw: second position sensor disagrees by 0.00878906 (first 0.5, second "
        "0.508789; tolerance 0.0078125 for more than latency_ms 62.5, now 125.0 ms)"
    )
    node.second_counts = 512  # back in agreement: the latency starts again next time
    assert node.second_check(0.5, 10.25) is None and math.isnan(node.second_since)
    node.second_counts = 521
    assert node.second_check(0.5, 10.5) is None


@pytest.mark.req("SR-HW-36")
def test_a_second_sensor_that_disagrees_from_its_first_reading_waits_its_latency() -> None:
    """Right after a configuration (``forget``), a disagreement from the very first reading
    starts the latency there and faults after it, as a later one does."""
    node = make_node(cpu=1024.0)
    node.second = (0x2100, 0, 1024.0, 2.0**-7, 0.0625)
    node.forget()
    node.second_counts = 600
    assert node.second_check(0.5, 3.0) is None and node.second_since == 3.0
    assert node.second_check(0.5, 3.0625) is None
    assert (node.second_check(0.5, 3.07) or "").startswith("joint yaw: second position sensor")


# ----------------------------------------------------------------------------- stop and reset
def test_a_controlword_goes_by_sdo_only_to_a_node_out_of_operational() -> None:
    node = make_node()
    assert node.controlword_by_sdo(0x02) is None  # no heartbeat yet: PDOs
    node.take_heartbeat(bytes([NMT_OPERATIONAL]), 0.0)
    assert node.controlword_by_sdo(0x02) is None
    node.take_heartbeat(bytes([NMT_PRE_OPERATIONAL]), 0.0)
    msg = node.controlword_by_sdo(0x02)
    assert msg is not None
    assert msg.arbitration_id == 0x605 and not msg.is_extended_id
    # expedited download of two bytes (0x2B) to 0x6040:00, the quick stop word
    assert bytes(msg.data) == bytes([0x2B, 0x40, 0x60, 0x00, 0x02, 0x00, 0x00, 0x00])


@pytest.mark.req("SR-HW-34")
def test_a_fault_reset_is_a_rising_edge_and_refused_while_the_cause_persists() -> None:
    node = make_node()
    assert node.fault_reset_word(False) == (CW_DISABLE_VOLTAGE, False)  # nothing to reset
    assert node.fault_reset_word(True) == (CW_DISABLE_VOLTAGE, False)
    node.take_tpdo1(tpdo1(0x0237, 0), 0.0)  # OPERATION ENABLED: bits 0-2 and 5, not 3
    assert node.fault_reset_word(True) == (CW_DISABLE_VOLTAGE, False)
    node.take_tpdo1(tpdo1(0x0218, 0), 0.0)  # FAULT
    assert node.fault_reset_word(False) == (CW_DISABLE_VOLTAGE, True)  # low first
    assert node.fault_reset_word(True) == (CW_FAULT_RESET, False)  # then the edge
    assert node.reset_refusal(False) == "node 5 (joint yaw): no TPDO answered the reset's SYNC"
    assert node.reset_refusal(True) == "node 5 (joint yaw): still FAULT"
    node.take_emcy(struct.pack("<HB", 0x3210, 0x05))
    assert node.reset_refusal(True) == (
        "node 5 (joint yaw): still FAULT (EMCY 0x3210: DC link overvoltage)"
    )
    node.take_tpdo1(tpdo1(0x0250, 0), 0.0)  # out of FAULT, the EMCY not acted on
    assert node.reset_refusal(True) == (
        "node 5 (joint yaw): still SWITCH ON DISABLED (EMCY 0x3210: DC link overvoltage)"
    )
    node.emcy_pending = None  # the reset clears it (the driver's _reset)
    assert node.reset_refusal(True) is None
    node.take_tpdo1(tpdo1(0x0237, 0), 0.0)  # any state out of FAULT, bit 0 set or not
    assert node.reset_refusal(True) is None
    node.take_tpdo1(tpdo1(0x0218, 0), 0.0)  # FAULT again, no new EMCY: the last one said
    assert node.reset_refusal(True) == (
        "node 5 (joint yaw): still FAULT (EMCY 0x3210: DC link overvoltage)"
    )


def test_a_node_described_and_in_the_stats() -> None:
    node = make_node()
    assert node.state() == "NO STATUSWORD YET" and not node.enabled()
    # silent since the wait began (none answered yet): told so, with what it said last
    assert node.described() == (
        "node 5 (joint yaw): no TPDO answered any SYNC of it (its last statusword 0x0000, "
        "NO STATUSWORD YET)"
    )
    assert node.stats() == {
        "node_id": 5, "cia402": "NO STATUSWORD YET", "statusword": None, "nmt": None,
        "last_emcy": None, "tpdos": 0, "emcys": 0, "heartbeats": 0,
    }  # fmt: skip
    node.take_tpdo1(tpdo1(0x0000, 0), 0.0)
    assert node.described() == "node 5 (joint yaw) in NOT READY TO SWITCH ON (statusword 0x0000)"
    node.take_tpdo1(tpdo1(0x0233, 0), 0.0)
    assert node.described() == "node 5 (joint yaw) in SWITCHED ON (statusword 0x0233)"
    assert not node.enabled()
    node.take_tpdo1(tpdo1(0x1637, 0), 0.0)
    assert node.enabled()
    node.mark()  # a wait begins: silent until its next TPDO 1, whatever it said before
    assert node.silent() and node.described().endswith(
        "(its last statusword 0x1637, OPERATION ENABLED)"
    )
    node.take_tpdo1(tpdo1(0x1637, 0), 0.0)
    assert not node.silent()
    node.take_tpdo2(struct.pack("<i", 0))
    node.take_heartbeat(bytes([0x42]), 0.0)
    node.take_emcy(struct.pack("<HB", 0x8611, 0x21))
    assert node.stats() == {
        "node_id": 5, "cia402": "OPERATION ENABLED", "statusword": "0x1637", "nmt": "0x42",
        "last_emcy": {"code": "0x8611", "meaning": "position controller: following error",
                      "register": "0x21"},
        "tpdos": 5, "emcys": 1, "heartbeats": 1,
    }  # fmt: skip
    node.take_heartbeat(bytes([NMT_OPERATIONAL]), 0.0)
    assert node.stats()["nmt"] == "OPERATIONAL"


# ----------------------------------------------------------------------------- second sensor
def _second(joint: Joint = YAW, eds: Path | None = None, **raw: Any) -> Any:
    node = make_node(joint=joint)
    if eds is not None:
        node.eds, node.od = eds, load_od(str(eds))
    return parse_second(WHERE, joint, node, raw)


@pytest.fixture
def eds_with_a_record(tmp_path: Path) -> Path:
    """The shipped EDS plus 0x2200: a record whose sub 1 is a mappable UNSIGNED32."""
    text = DEFAULT_EDS.read_text()
    listed = "[ManufacturerObjects]\nSupportedObjects=1\n1=0x2100\n"
    assert listed in text
    text = text.replace(listed, "[ManufacturerObjects]\nSupportedObjects=2\n1=0x2100\n2=0x2200\n")
    text += (
        "\n[2200]\nParameterName=Second encoder record\nObjectType=0x9\nSubNumber=2\n"
        "\n[2200sub0]\nParameterName=Number of entries\nObjectType=0x7\nDataType=0x0005\n"
        "AccessType=ro\nDefaultValue=1\nPDOMapping=0\n"
        "\n[2200sub1]\nParameterName=Position\nObjectType=0x7\nDataType=0x0007\n"
        "AccessType=ro\nDefaultValue=0\nPDOMapping=1\n"
    )
    path = tmp_path / "record.eds"
    path.write_text(text)
    return path


@pytest.mark.req("SR-HW-36")
def test_a_second_sensor_s_defaults_and_its_mapping_check(eds_with_a_record: Path) -> None:
    assert _second(index=0x2100, counts_per_unit=100.0) == (0x2100, 0, 100.0, 0.01, 0.005)
    assert _second(SLIDE, index=0x2100, counts_per_unit=100.0)[3] == 0.001
    got = _second(index=0x2100, subindex=0, counts_per_unit=-3.0, tolerance=0.5, latency_ms=0)
    assert got == (0x2100, 0, -3.0, 0.5, 0.0)  # no latency: judged at once
    # a sub-index other than 0, an UNSIGNED32
    rec = _second(eds=eds_with_a_record, index=0x2200, subindex=1, counts_per_unit=1.0)
    assert rec[:2] == (0x2200, 1)
    with pytest.raises(ValueError, match="0x2200:00 is not a mappable 32-bit"):
        _second(eds=eds_with_a_record, index=0x2200, counts_per_unit=1.0)


@pytest.mark.req("SR-HW-36")
@pytest.mark.parametrize(
    ("raw", "words"),
    [
        ({"counts_per_unit": 1.0}, "a mapping {index, subindex"),
        ({"index": 0x2100}, "a mapping {index, subindex"),
        (["index", "counts_per_unit"], "a mapping {index, subindex"),
        ({"index": 0x2100, "counts_per_unit": 1.0, "tolerence": 1.0}, "unknown keys ['tolerence']"),
        ({"index": 0x2100, "counts_per_unit": 0.0}, "counts_per_unit != 0"),
        ({"index": 0x2100, "counts_per_unit": math.inf}, "counts_per_unit != 0"),
        ({"index": 0x2100, "counts_per_unit": 1.0, "tolerance": 0.0}, "tolerance > 0"),
        ({"index": 0x2100, "counts_per_unit": 1.0, "latency_ms": -1.0}, "latency_ms >= 0"),
        ({"index": 0x2999, "counts_per_unit": 1.0}, "object 0x2999:00 is not a mappable"),
        (
            {"index": 0x6041, "counts_per_unit": 1.0},
            f"object 0x6041:00 is not a mappable 32-bit object of {str(DEFAULT_EDS)!r}",
        ),
        ({"index": 0x1016, "subindex": 1, "counts_per_unit": 1.0}, "0x1016:01 is not a mappable"),
    ],
)
def test_a_second_sensor_that_cannot_be_read_is_refused(raw: Any, words: str) -> None:
    node = make_node()
    with pytest.raises(ValueError) as info:
        parse_second(WHERE, YAW, node, raw)
    text = str(info.value)
    assert text.startswith(f"{WHERE}: nodes.yaw.second_sensor: ") and words in text, text


# ----------------------------------------------------------------------------- tables
def test_the_protocol_s_tables_and_bounds() -> None:
    assert sdo_abort_meaning(0x12345678) == "not a CiA 301 abort code (manufacturer specific?)"
    assert emcy_meaning(0x0000) == "error reset or no error"
    assert emcy_meaning(0x8612) == "position controller: reference limit"  # exact before class
    assert emcy_meaning(0x84F1) == "velocity controller: deviation too large"  # by 0xFF00
    assert emcy_meaning(0x3999) == "voltage"  # by 0xF000
    assert emcy_meaning(0xA123) == "unknown error code"
    assert cia402_state(0x0000) == "NOT READY TO SWITCH ON"
    assert cia402_state(0x0221) == "READY TO SWITCH ON"
    assert cia402_state(0x0223) == "SWITCHED ON"
    assert cia402_state(0x0207) == "QUICK STOP ACTIVE"
    assert cia402_state(0x020F) == "FAULT REACTION ACTIVE"
    assert cia402_state(0x0001) == "UNKNOWN"
    assert frame_bits(1) == 65
    # the master's frames of every node id, and nothing of node 0 or a node's own
    assert master_sends(0x27F, 5) and master_sends(0x401, 5) and master_sends(0x67F, 5)
    assert master_sends(0x705, 5) and not master_sends(0x77F, 5)
    assert master_sends(0x305, 5) and master_sends(0x37F, 5)  # RPDO 2 too
    for cob in (0x200, 0x300, 0x600, 0x080 + 5, 0x180 + 5, 0x580 + 5, 0x700 + 5 + 1, 0x680 + 1):
        assert not master_sends(cob, 5), hex(cob)


def test_an_sdo_failure_says_what_became_of_the_transfer() -> None:
    node = make_node()

    class Aborted(Exception):
        code = 0x06090030

    args = (WHERE, 1.0, node, 0x6060, 0, "Modes of operation", "write 0x8")
    assert str(sdo_error(*args, Aborted())) == (
        f"{WHERE}: node 5 (joint yaw): configure: SDO write 0x8 to 6060:00 (Modes of "
        "operation) aborted by the node with 0x06090030: invalid value (download only)"
    )
    assert str(sdo_error(*args, can.CanError("queue full"))).endswith(
        "(Modes of operation) not sent: queue full"
    )
    assert str(sdo_error(*args, TimeoutError("nothing"))).endswith(
        "(Modes of operation) no answer within 1000 ms (SDO timeout: nothing)"
    )
