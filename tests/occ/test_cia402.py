"""The ``cia402`` driver against the CiA 402 drive emulator, in-process on python-can's
``virtual`` bus, through the public Driver API.

Time is simulated: each tick advances a clock the driver is given as ``now`` and the emulator
reads as its own; after each tick the emulator handles every frame sent to it
(:meth:`DriveEmulator.settle`), so every test is deterministic. Only the state machine's and
SDO's bounds (activate, reset, configure) run on the wall clock, as they do on a robot; no test
asserts a duration.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from occ.drivers import DriverState, create_driver
from occ.drivers.cia402 import DEFAULT_EDS, CiA402Driver, bus_load
from occ.drivers.cia402_protocol import (
    COB_SYNC,
    NMT_PRE_OPERATIONAL,
    cia402_state,
    emcy_meaning,
    frame_bits,
    master_sends,
    sdo_abort_meaning,
)
from occ.drivers.cia402_sim import DriveEmulator
from occ.errors import DriverError, StateError
from occ.joint import Joint, JointLimits

ROOT = Path(__file__).resolve().parents[2]
EDS = DEFAULT_EDS  # shipped with the driver (package data)
_channels = itertools.count()
DT = 0.001


def make_joints(n: int = 3) -> list[Joint]:
    base = [
        Joint("yaw", "revolute", JointLimits(-1.0, 1.0, 1.5, 20.0)),
        Joint("pitch", "revolute", JointLimits(-1.0, 1.0, 1.5, 20.0), home=0.35),
        Joint("insertion", "prismatic", JointLimits(0.0, 0.15, 0.1, 50.0), home=0.05),
    ]
    extra = [Joint(f"j{k}", "revolute", JointLimits(-1.0, 1.0, 1.5, 20.0)) for k in range(3, n)]
    return (base + extra)[:n]


def node_params(n: int = 3) -> dict[str, Any]:
    cpu = [52152.0, 52152.0, 2.0e6] + [52152.0] * (n - 3)
    return {
        j.name: {"node_id": k + 1, "eds": str(EDS), "counts_per_unit": cpu[k]}
        for k, j in enumerate(make_joints(n))
    }


class Rig:
    """A driver and the emulator on one virtual channel, ticked on a simulated clock."""

    def __init__(self, ids: list[int], emu_kwargs: dict[str, Any], **params: Any) -> None:
        self.channel = f"occ-cia402-test-{next(_channels)}"
        self.t = 0.0
        self.emu = DriveEmulator(
            ids, EDS, channel=self.channel, clock=lambda: self.t, **emu_kwargs
        ).start()
        self.joints = make_joints()
        p: dict[str, Any] = {
            "interface": "virtual",
            "channel": self.channel,
            "sync_every": 2,
            "nodes": node_params(),
            "state_timeout_ms": 200.0,
        }
        p.update(params)
        self.drv = CiA402Driver("arm", self.joints, p)

    def tick(self, setpoints: list[float] | None = None) -> None:
        """One loop tick: read, then (ACTIVE, with setpoints) write; the emulator settles."""
        self.t += DT
        try:
            self.drv.read(self.t)
            if setpoints is not None and self.drv.state is DriverState.ACTIVE:
                self.drv.write(setpoints, self.t)
        finally:
            self.emu.settle()

    def ticks(self, n: int, setpoints: list[float] | None = None) -> None:
        for _ in range(n):
            self.tick(setpoints)

    def until_fault(self, most: int, setpoints: Callable[[int], list[float]]) -> DriverError:
        for k in range(most):
            try:
                self.tick(setpoints(k))
            except DriverError as err:
                return err
        raise AssertionError(f"no fault in {most} ticks; driver {self.drv.state}")

    def enabled(self) -> None:
        """Configured, measured, ACTIVE."""
        self.drv.configure()
        self.ticks(4)
        assert all(j.measured for j in self.joints)
        self.drv.activate()
        self.emu.settle()

    def here(self) -> list[float]:
        return [j.position for j in self.joints]

    def close(self) -> None:
        try:
            self.drv.shutdown()
        finally:
            self.emu.stop()


@pytest.fixture
def rig() -> Iterator[Callable[..., Rig]]:
    made: list[Rig] = []

    def make(ids: list[int] | None = None, emu: dict[str, Any] | None = None, **params: Any) -> Rig:
        r = Rig(ids or [1, 2, 3], emu or {}, **params)
        made.append(r)
        return r

    yield make
    for r in made:
        r.close()


# ----------------------------------------------------------------------------- configure
@pytest.mark.req("SR-HW-30")
def test_configure_writes_the_mapping_mode_period_and_heartbeats(rig: Callable[..., Rig]) -> None:
    r = rig(heartbeat_ms=40.0, node_heartbeat_ms=10)
    r.drv.configure()
    assert r.drv.state is DriverState.INACTIVE
    for nid in (1, 2, 3):
        node = r.emu.node(nid)
        # RPDO 1: controlword + target position, synchronous, valid
        assert node.get(0x1600, 0) == 2
        assert [node.get(0x1600, s) for s in (1, 2)] == [0x60400010, 0x607A0020]
        assert node.get(0x1400, 1) == 0x200 + nid and node.get(0x1400, 2) == 1
        # TPDO 1: statusword, position actual, torque actual; TPDO 2: velocity actual
        assert [node.get(0x1A00, s) for s in range(4)] == [3, 0x60410010, 0x60640020, 0x60770010]
        assert [node.get(0x1A01, s) for s in range(2)] == [1, 0x606C0020]
        assert node.get(0x1800, 1) == 0x180 + nid and node.get(0x1800, 2) == 1
        assert node.get(0x1801, 1) == 0x280 + nid and node.get(0x1801, 2) == 1
        # the PDOs the driver does not use are off
        for k in (1, 2, 3):
            assert node.get(0x1400 + k, 1) & 0x80000000
        for k in (2, 3):
            assert node.get(0x1800 + k, 1) & 0x80000000
        assert node.get(0x6060, 0) == 8  # CSP
        assert (node.get(0x60C2, 1), node.get(0x60C2, 2)) == (2, -3)  # 2 ms: sync_every 2
        assert node.get(0x1017, 0) == 10
        assert node.get(0x1016, 1) == (127 << 16) | 40
        assert node.nmt == 0x05  # OPERATIONAL
    r.ticks(4)
    assert [j.measured for j in r.joints] == [True] * 3
    nodes = r.drv.stats()["nodes"]
    assert nodes["pitch"]["cia402"] == "SWITCH ON DISABLED"
    assert nodes["pitch"]["nmt"] == "OPERATIONAL"


@pytest.mark.req("SR-HW-30")
def test_effort_maps_the_target_torque_in_cst(rig: Callable[..., Rig]) -> None:
    from occ.joint import PIDGains

    r = rig(command_interface="effort")
    for j in r.joints:
        j.gains = PIDGains(kp=1.0)
    r.drv.configure()
    node = r.emu.node(1)
    assert [node.get(0x1600, s) for s in range(3)] == [2, 0x60400010, 0x60710010]
    assert node.get(0x6060, 0) == 10  # CST
    r.ticks(4)
    r.drv.activate()
    r.emu.settle()
    for _ in range(6):
        r.t += DT
        r.drv.read(r.t)
        r.drv.write_effort([0.5, 0.0, 0.0], r.t)  # rated torque 1: 500 per mille
        r.emu.settle()
    assert node.get(0x6071, 0) == 500
    assert node.get(0x606C, 0) > 0  # the torque accelerates the emulated mass


@pytest.mark.req("SR-HW-31")
def test_an_sdo_abort_at_configure_names_the_node_the_object_and_the_code(
    rig: Callable[..., Rig],
) -> None:
    r = rig()
    r.emu.abort_sdo(2, 0x6060, 0, 0x06090030)
    with pytest.raises(DriverError) as info:
        r.drv.configure()
    text = str(info.value)
    assert "node 2 (joint pitch)" in text
    assert "6060:00" in text and "Modes of operation" in text
    assert "0x06090030" in text and "invalid value" in text
    assert r.drv.state is DriverState.FAULT


@pytest.mark.req("SR-HW-31")
def test_a_node_that_does_not_answer_at_configure_is_an_sdo_timeout(
    rig: Callable[..., Rig],
) -> None:
    r = rig(ids=[1, 3], sdo_timeout_ms=30.0)  # node 2 is not on the bus
    with pytest.raises(DriverError) as info:
        r.drv.configure()
    text = str(info.value)
    assert "node 2 (joint pitch)" in text and "1000:00" in text and "SDO timeout" in text


def test_sdo_abort_and_emcy_tables() -> None:
    assert sdo_abort_meaning(0x06020000) == "the object does not exist in the object dictionary"
    assert "not a CiA 301" in sdo_abort_meaning(0x12345678)
    assert emcy_meaning(0x8611) == "position controller: following error"
    assert emcy_meaning(0x7300).startswith("sensor")
    assert "overcurrent" in emcy_meaning(0x2310)
    assert "overvoltage" in emcy_meaning(0x3210)
    assert "temperature" in emcy_meaning(0x4310)
    assert "heartbeat" in emcy_meaning(0x8130)
    assert emcy_meaning(0x5530).startswith("data storage")
    assert emcy_meaning(0x2311) == emcy_meaning(0x2310)  # a sub-code: its code's meaning
    assert emcy_meaning(0x2400) == "current"  # the class, when the code is not in the table
    assert cia402_state(0x0237) == "OPERATION ENABLED"
    assert cia402_state(0x0250) == "SWITCH ON DISABLED"
    assert cia402_state(0x0218) == "FAULT"


# ----------------------------------------------------------------------------- activate
@pytest.mark.req("SR-HW-32")
def test_activate_brings_every_node_to_operation_enabled(rig: Callable[..., Rig]) -> None:
    r = rig()
    r.enabled()
    assert r.drv.state is DriverState.ACTIVE
    for nid in (1, 2, 3):
        node = r.emu.node(nid)
        assert node.describe()["state"] == "OPERATION ENABLED"
        # shutdown, switch on, enable operation, in that order
        assert node.controlwords[:3] == [0x06, 0x07, 0x0F]
    # the target is where the joint was measured: no jump at enable
    assert r.emu.node(2).get(0x607A, 0) == r.emu.node(2).get(0x6064, 0)


@pytest.mark.req("SR-HW-32")
def test_one_node_that_will_not_enable_vetoes_and_the_others_go_down(
    rig: Callable[..., Rig],
) -> None:
    r = rig(state_timeout_ms=50.0)
    r.emu.refuse_enable(3)
    r.drv.configure()
    r.ticks(4)
    with pytest.raises(DriverError) as info:
        r.drv.activate()
    r.emu.settle()
    text = str(info.value)
    assert "node 3 (joint insertion) in SWITCHED ON" in text
    assert "every node switched off again" in text
    assert r.drv.state is DriverState.FAULT
    r.ticks(2)
    for nid in (1, 2, 3):
        node = r.emu.node(nid)
        assert node.controlwords[-1] == 0x00  # disable voltage
        assert node.describe()["state"] == "SWITCH ON DISABLED"


@pytest.mark.req("SR-HW-39")
@pytest.mark.parametrize("how", ["cancel", "safe_stop"])
def test_an_activation_on_another_thread_gives_up_when_cancelled_or_stopped(
    rig: Callable[..., Rig], how: str
) -> None:
    """The robot runs activate on a thread of its own (activation_waits): a cancel (Disable)
    or a safe stop (EStop, the supervisor) from another thread ends it at once, every node
    switched off, while the drives have not answered yet."""
    r = rig()
    assert r.drv.activation_waits
    r.drv.configure()
    r.ticks(4)
    errors: list[Exception] = []

    def power_up() -> None:
        try:
            r.drv.activate()
        except Exception as err:  # noqa: BLE001 - what activate raised, checked below
            errors.append(err)

    with r.emu.held():  # the drives answer nothing: the activation waits for them
        thread = threading.Thread(target=power_up)
        thread.start()
        give_up = time.monotonic() + 5.0
        while not r.drv.activating:
            assert time.monotonic() < give_up
            time.sleep(0.001)
        if how == "cancel":
            assert r.drv.cancel_activation("operator Disable")
        else:
            r.drv.safe_stop("EStop")
        thread.join(2.0)  # it gave up without them
        assert not thread.is_alive()
    r.emu.settle()
    assert len(errors) == 1
    if how == "cancel":
        assert isinstance(errors[0], StateError) and "activation cancelled" in str(errors[0])
        assert r.drv.state is DriverState.INACTIVE
    else:
        assert "safe stop while powering up: EStop" in str(errors[0])
        assert r.drv.state is DriverState.FAULT
        assert all(0x02 in r.emu.node(n).controlwords for n in (1, 2, 3))  # quick stop
    r.ticks(2)
    for nid in (1, 2, 3):
        assert r.emu.node(nid).describe()["state"] == "SWITCH ON DISABLED"
    assert not r.drv.cancel_activation("late")  # nothing under way any more


def test_positions_round_trip_in_counts_per_unit(rig: Callable[..., Rig]) -> None:
    r = rig()
    r.enabled()
    start = r.here()
    goal = [0.1, 0.3, 0.06]
    for k in range(1000):  # ramps within the velocity limits, then held
        f = min(1.0, k / 800.0)
        r.tick([s + (g - s) * f for s, g in zip(start, goal, strict=True)])
    assert r.emu.node(1).get(0x607A, 0) == round(0.1 * 52152.0)
    assert r.emu.node(3).get(0x607A, 0) == round(0.06 * 2.0e6)
    assert r.here() == pytest.approx(goal, abs=2e-5)
    assert r.joints[0].velocity == pytest.approx(0.0, abs=1e-3)
    stats = r.drv.stats()
    assert stats["sync_frames"] > 0 and stats["tpdo_frames"] > 0
    assert stats["nodes"]["yaw"]["cia402"] == "OPERATION ENABLED"
    r.drv.deactivate()
    r.ticks(2)
    assert r.emu.node(1).describe()["state"] == "SWITCH ON DISABLED"
    assert r.emu.node(1).controlwords[-1] == 0x00


# ----------------------------------------------------------------------------- faults
def _move(r: Rig) -> Callable[[int], list[float]]:
    start = r.here()
    return lambda k: [start[0] + min(0.2, 0.001 * k), start[1], start[2]]


FAULTS: dict[str, tuple[Callable[[DriveEmulator], None], dict[str, Any], list[str]]] = {
    "emcy": (
        lambda e: e.inject_emcy(2, 0x2310),
        {},
        ["node 2 (joint pitch)", "EMCY 0x2310", "overcurrent"],
    ),
    "temperature": (
        lambda e: e.inject_emcy(3, 0x4310),
        {},
        ["node 3 (joint insertion)", "EMCY 0x4310", "temperature"],
    ),
    "fault_bit": (
        lambda e: e.inject_fault_bit(2),
        {},
        ["node 2 (joint pitch)", "statusword", "FAULT (fault bit set)"],
    ),
    "heartbeat": (
        lambda e: e.stop_heartbeat(2),
        {},
        ["node 2 (joint pitch)", "heartbeat consumer timeout"],
    ),
    "tpdo_missing": (
        lambda e: e.mute_tpdos(3),
        {},
        ["node 3 (joint insertion)", "no TPDO for", "feedback_timeout 10 ms"],
    ),
    "tpdo_late": (lambda e: e.pause_tpdos(1, 0.05), {}, ["node 1 (joint yaw)", "no TPDO for"]),
    # the drive's own following error (its window 0x6065 set to 500 counts here); the base's
    # check is off in this case so that the drive's EMCY is what faults
    "following_error": (
        lambda e: (e.node(1).set(0x6065, 0, 500), e.stall(1)),
        {"following_error": None, "frozen_feedback_ms": 0},
        ["node 1 (joint yaw)", "EMCY 0x8611", "following error"],
    ),
    "nmt": (
        lambda e: e.leave_operational(2),
        {},
        ["node 2 (joint pitch)", "left NMT OPERATIONAL", "PRE-OPERATIONAL"],
    ),
}


@pytest.mark.req("SR-HW-33")
@pytest.mark.parametrize("kind", sorted(FAULTS))
def test_each_fault_latches_fault_naming_the_node_and_quick_stops_every_node(
    rig: Callable[..., Rig], kind: str
) -> None:
    inject, params, words = FAULTS[kind]
    r = rig(**params)
    r.enabled()
    move = _move(r)
    r.ticks(10, move(0))
    inject(r.emu)
    err = r.until_fault(200, lambda k: move(k + 10))
    assert r.drv.state is DriverState.FAULT
    reason = r.drv.fault_reason or ""
    assert str(err) in reason
    assert "cia402 driver 'arm'" in reason
    for word in words:
        assert word in reason, (word, reason)
    with pytest.raises(StateError):
        r.drv.write(r.here(), r.t)
    r.ticks(2)  # FAULT: still read (and SYNCed)
    for nid in (1, 2, 3):
        node = r.emu.node(nid)
        assert 0x02 in node.controlwords, (nid, node.controlwords)  # quick stop sent to each
        assert node.describe()["state"] != "OPERATION ENABLED", nid
    assert r.drv.stats()["quick_stops"] >= 1


@pytest.mark.req("SR-HW-33")
def test_an_emcy_is_in_the_stats_with_its_meaning(rig: Callable[..., Rig]) -> None:
    r = rig()
    r.enabled()
    r.emu.inject_emcy(1, 0x7300)
    r.until_fault(20, lambda k: r.here())
    r.ticks(2)
    emcy = r.drv.stats()["nodes"]["yaw"]["last_emcy"]
    assert emcy["code"] == "0x7300" and emcy["meaning"].startswith("sensor")
    assert r.drv.stats()["nodes"]["yaw"]["cia402"] == "FAULT"


@pytest.mark.req("SR-HW-38")
def test_a_driver_that_stops_its_heartbeat_is_stopped_by_the_drive(rig: Callable[..., Rig]) -> None:
    """The device-side heartbeat: the drives consume the master's heartbeat (0x1016); a master
    frozen for longer than ``heartbeat_ms`` finds its drives stopped (EMCY 0x8130)."""
    r = rig(heartbeat_ms=20.0)
    r.enabled()
    r.ticks(10, r.here())
    r.t += 0.05  # the loop frozen for 50 ms: no heartbeat, no command
    r.emu.settle()  # the emulator's time passes
    assert all(r.emu.node(n).describe()["state"] == "FAULT" for n in (1, 2, 3))
    with pytest.raises(DriverError) as info:
        r.tick(r.here())
    assert "EMCY 0x8130" in str(info.value) and "heartbeat" in str(info.value)


# ----------------------------------------------------------------------------- reset
@pytest.mark.req("SR-HW-34")
def test_reset_is_refused_while_the_fault_persists_and_accepted_once_cleared(
    rig: Callable[..., Rig],
) -> None:
    r = rig(state_timeout_ms=60.0)
    r.enabled()
    r.emu.inject_emcy(2, 0x3210, persist=True)
    r.until_fault(20, lambda k: r.here())
    with pytest.raises(DriverError) as info:
        r.drv.reset()
    text = str(info.value)
    assert "fault reset refused" in text and "node 2 (joint pitch): still FAULT" in text
    assert "0x3210" in text and "overvoltage" in text
    assert r.drv.state is DriverState.FAULT
    assert r.emu.node(2).fault_resets_refused >= 1
    r.emu.settle()
    r.emu.clear(2)
    r.drv.reset()
    assert r.drv.state is DriverState.INACTIVE
    r.ticks(4)  # the fresh reads after the reset pass
    assert r.emu.node(2).describe()["state"] == "SWITCH ON DISABLED"
    r.drv.activate()
    r.emu.settle()
    r.ticks(4, r.here())
    assert r.drv.state is DriverState.ACTIVE


@pytest.mark.req("SR-HW-34")
def test_a_node_still_silent_after_reset_fails_the_first_read(rig: Callable[..., Rig]) -> None:
    r = rig()
    r.enabled()
    r.emu.stop_heartbeat(1)
    r.until_fault(100, lambda k: r.here())
    r.drv.reset()  # its TPDOs answer: the fault reset itself passes
    with pytest.raises(DriverError) as info:
        r.ticks(2)
    assert "node 1 (joint yaw): heartbeat consumer timeout" in str(info.value)


# ----------------------------------------------------------------------------- bus budget
@pytest.mark.req("SR-HW-35")
def test_the_bus_budget_takes_three_nodes_and_refuses_eight() -> None:
    # the figure: 55 + 10 bits per data byte, worst-case stuffing (Davis et al. 2007)
    assert frame_bits(8) == 135 and frame_bits(0) == 55
    base = {"interface": "virtual", "channel": "unused", "bitrate": 1_000_000, "period": 0.001}
    three = CiA402Driver("arm", make_joints(3), {**base, "sync_every": 2, "nodes": node_params(3)})
    assert three.bus_load == pytest.approx(0.57, abs=0.01)
    with pytest.raises(ValueError) as info:
        CiA402Driver("arm", make_joints(8), {**base, "sync_every": 2, "nodes": node_params(8)})
    text = str(info.value)
    assert "bus load 146% exceeds bus_load_limit 70%" in text
    assert "8 nodes" in text and "at most 3 nodes per bus" in text and "sync_every: 5 (62%)" in text
    # a SYNC every tick at 1 kHz: three nodes do not fit either, and the advice says what does
    with pytest.raises(ValueError) as info:
        CiA402Driver("arm", make_joints(3), {**base, "sync_every": 1, "nodes": node_params(3)})
    assert "bus load 111%" in str(info.value) and "sync_every: 2 (57%)" in str(info.value)
    load, _ = bus_load(nodes=3, period=0.001, sync_every=1, bitrate=1_000_000)
    assert load == pytest.approx(1.115, abs=0.005)


@pytest.mark.req("SR-HW-35")
def test_occd_check_takes_the_cia402_slave_and_refuses_an_overloaded_bus(tmp_path: Path) -> None:
    import yaml

    from occ.core.loader import load_config
    from occ.errors import ConfigError

    path = ROOT / "configs" / "slave-cia402.yaml"
    config = load_config(path)
    assert config.robot.drivers[0].plugin == "cia402"
    raw = yaml.safe_load(path.read_text())
    raw["robot"]["drivers"][0]["params"]["sync_every"] = 1
    bad = tmp_path / "slave.yaml"
    bad.write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError) as info:
        load_config(bad)
    assert "bus load" in "\n".join(info.value.errors)


def test_occd_check_puts_a_drivers_refusal_on_the_line_of_what_it_names(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A refusal that names a node or a key of the driver's params is reported on that line;
    one of the whole driver on its ``params:`` line; an unknown plugin on its ``plugin:``
    line. An operator fixing the file goes straight to the line at fault."""
    import yaml

    from occ.cli import main

    shipped = (ROOT / "configs" / "slave-cia402.yaml").read_text()
    cases = [
        # (what is spoilt, the text that finds the line, the path reported)
        ("eds: drive.eds, counts_per_unit: 2.0e6", "insertion:", "params.nodes.insertion"),
        ("sync_every: 2", "sync_every:", "params.sync_every"),
        ("plugin: cia402", "plugin:", "plugin"),
    ]
    spoilt = {
        "eds: drive.eds, counts_per_unit: 2.0e6": "eds: none.eds, counts_per_unit: 2.0e6",
        "sync_every: 2": "sync_every: 0",
        "plugin: cia402": "plugin: cia403",
    }
    for old, finder, reported in cases:
        assert shipped.count(old) == 1, old
        path = tmp_path / "spoilt.yaml"
        path.write_text(shipped.replace(old, spoilt[old]))
        yaml.safe_load(path.read_text())  # still YAML: only the value is wrong
        capsys.readouterr()
        assert main(["--check", str(path)]) == 2
        err = capsys.readouterr().err
        line = next(i for i, t in enumerate(path.read_text().splitlines(), 1) if finder in t)
        assert f"{path}:{line} robot.drivers[0].{reported}:" in err, (old, err)


@pytest.mark.req("SR-HW-35")
@pytest.mark.parametrize("sync_every", [1, 2])
def test_occd_check_refuses_eight_nodes_on_one_bus_with_the_load(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], sync_every: int
) -> None:
    """The shipped slave with five more joints on its one 1 Mbit/s bus, at 1 kHz: ``occd
    --check`` (the console script's function) refuses it, exit 2, with the load and the advice
    on the driver's line; the shipped three pass the same command."""
    import yaml

    from occ.cli import main

    assert main(["--check", str(ROOT / "configs" / "slave-cia402.yaml")]) == 0
    raw = yaml.safe_load((ROOT / "configs" / "slave-cia402.yaml").read_text())
    robot = raw["robot"]
    assert robot["rate_hz"] == 1000
    limits = {"min": -1.0, "max": 1.0, "velocity": 1.5, "effort": 20.0}
    extra = [f"j{k}" for k in range(3, 8)]
    robot["joints"] += [{"name": n, "type": "revolute", "limits": limits} for n in extra]
    params = robot["drivers"][0]["params"]
    assert params["bitrate"] == 1_000_000 and params["period"] == 0.001
    params["sync_every"] = sync_every
    robot["drivers"][0]["joints"] += extra
    for k, n in enumerate(extra, 4):
        params["nodes"][n] = {"node_id": k, "eds": "drive.eds", "counts_per_unit": 52152.0}
    path = tmp_path / "eight.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    capsys.readouterr()
    assert main(["--check", str(path)]) == 2
    err = capsys.readouterr().err
    load, most = {1: ("287%", "1 node"), 2: ("146%", "3 nodes")}[sync_every]
    assert f"bus load {load} exceeds bus_load_limit 70%" in err, err
    assert "8 nodes x" in err and f"at most {most} per bus" in err
    assert "sync_every: 5 (62%)" in err
    # a refusal of the whole bus sits on the driver's params, not on its plugin name
    line = next(i for i, t in enumerate(path.read_text().splitlines(), 1) if "params:" in t)
    assert f"{path}:{line} robot.drivers[0].params: cia402 driver" in err, err


def test_params_are_checked_when_the_driver_is_built() -> None:
    base = {"interface": "virtual", "channel": "unused", "sync_every": 2}
    with pytest.raises(ValueError, match="params\\['nodes'\\] is required"):
        CiA402Driver("arm", make_joints(3), base)
    nodes = node_params(3)
    nodes["pitch"] = {**nodes["pitch"], "node_id": 1}
    with pytest.raises(ValueError, match="node_id values must be distinct"):
        CiA402Driver("arm", make_joints(3), {**base, "nodes": nodes})
    nodes = node_params(3)
    nodes["yaw"] = {**nodes["yaw"], "eds": "no/such.eds"}
    with pytest.raises(ValueError, match="eds file"):
        CiA402Driver("arm", make_joints(3), {**base, "nodes": nodes})
    nodes = node_params(3)
    nodes["yaw"] = {**nodes["yaw"], "second_sensor": {"index": 0x6041, "counts_per_unit": 1.0}}
    with pytest.raises(ValueError, match="not a mappable 32-bit object"):
        CiA402Driver("arm", make_joints(3), {**base, "nodes": nodes})
    with pytest.raises(ValueError, match="feedback_timeout"):
        CiA402Driver(
            "arm", make_joints(3), {**base, "nodes": node_params(3), "feedback_timeout": 1}
        )
    drv = create_driver("cia402", "arm", make_joints(3), {**base, "nodes": node_params(3)})
    assert isinstance(drv, CiA402Driver)


# ----------------------------------------------------------------------------- second sensor
@pytest.mark.req("SR-HW-36")
def test_a_second_sensor_that_disagrees_faults_naming_the_joint_and_the_distance(
    rig: Callable[..., Rig],
) -> None:
    nodes = node_params()
    nodes["yaw"]["second_sensor"] = {
        "index": 0x2100, "subindex": 0, "counts_per_unit": 52152.0,
        "tolerance": 0.002, "latency_ms": 5.0,
    }  # fmt: skip
    r = rig(nodes=nodes)
    r.drv.configure()
    assert [r.emu.node(1).get(0x1A01, s) for s in range(3)] == [2, 0x606C0020, 0x21000020]
    r.ticks(4)
    r.drv.activate()
    r.emu.settle()
    move = _move(r)
    r.ticks(50, move(0))  # in agreement while moving
    r.emu.offset_second_encoder(1, 0.001 * 52152.0)  # 1 mrad: within the tolerance
    r.ticks(20, move(0))
    assert r.drv.state is DriverState.ACTIVE
    r.emu.offset_second_encoder(1, 0.01 * 52152.0)  # 10 mrad
    err = r.until_fault(20, lambda k: move(0))
    text = str(err)
    assert "joint yaw: second position sensor disagrees by 0.01" in text
    assert "tolerance 0.002" in text and "latency_ms 5" in text
    assert r.drv.state is DriverState.FAULT


# ----------------------------------------------------------------------------- own frames
@pytest.mark.req("SR-HW-37")
def test_its_own_frames_fed_back_change_nothing(rig: Callable[..., Rig]) -> None:
    """python-can's udp_multicast hands a process its own frames; here the virtual bus does the
    same (receive_own_messages): configure, enable, move and a fault work as without."""
    r = rig(bus_kwargs={"receive_own_messages": True})
    r.enabled()
    start = r.here()
    for k in range(100):
        r.tick([start[0] + 0.0005 * k, start[1], start[2]])
    assert r.drv.state is DriverState.ACTIVE
    assert r.here()[0] == pytest.approx(start[0] + 0.0495, abs=0.003)
    stats = r.drv.stats()
    assert stats["echoes"] > 100  # its RPDOs, SYNCs, heartbeats, SDO requests
    assert stats["ignored_frames"] == 0
    r.emu.inject_emcy(3, 0x2310)
    err = r.until_fault(10, lambda k: r.here())
    assert "node 3 (joint insertion): EMCY 0x2310" in str(err)


def test_only_master_frames_count_as_echoes() -> None:
    assert master_sends(COB_SYNC, 127) and master_sends(0x000, 127)
    assert master_sends(0x201, 127) and master_sends(0x57F, 127) and master_sends(0x603, 127)
    assert master_sends(0x77F, 127)
    for node_frame in (0x081, 0x181, 0x281, 0x381, 0x481, 0x581, 0x701):
        assert not master_sends(node_frame, 127), hex(node_frame)


def test_the_emulator_answers_segmented_sdo_and_nmt(rig: Callable[..., Rig]) -> None:
    import canopen

    r = rig()
    r.drv.configure()
    net = canopen.Network()
    net.connect(interface="virtual", channel=r.channel)
    try:
        node = net.add_node(2, str(EDS))
        node.sdo.RESPONSE_TIMEOUT = 1.0
        # 0x1018 sub 1-4 by expedited upload; a string would be segmented: the emulator's
        # segmented path through a 4-byte object forced to segments
        assert node.sdo.upload(0x1018, 2) == (0x402).to_bytes(4, "little")
        node.sdo.download(0x6065, 0, (1234).to_bytes(4, "little"), force_segment=True)
        assert r.emu.node(2).get(0x6065, 0) == 1234
        with pytest.raises(canopen.SdoAbortedError) as info:
            node.sdo.download(0x6041, 0, b"\x00\x00")
        assert info.value.code == 0x06010002  # read-only
        with pytest.raises(canopen.SdoAbortedError) as info:
            node.sdo.upload(0x6999, 0)
        assert info.value.code == 0x06020000
        node.nmt.send_command(0x80)
        r.emu.settle()
        assert r.emu.node(2).nmt == NMT_PRE_OPERATIONAL
    finally:
        net.disconnect()


def test_the_emulator_command_lines() -> None:
    emu = DriveEmulator([1, 2], EDS, channel="occ-cia402-cmd", clock=lambda: 0.0)
    assert emu.command("refuse 2").startswith("ok")
    assert emu.node(2).refuse_enable
    assert emu.command("abort 1 0x6060 0 0x06090030").startswith("ok")
    assert emu.node(1).sdo_aborts == {(0x6060, 0): 0x06090030}
    assert emu.command("clear 1").startswith("ok") and not emu.node(1).sdo_aborts
    assert emu.command("bogus").startswith("commands:")
    assert "bad command" in emu.command("emcy")
    assert math.isnan(emu.node(1).fe_since)


@pytest.mark.req("SR-HW-33")
def test_a_bus_off_error_frame_faults_naming_the_bus(rig: Callable[..., Rig]) -> None:
    import can

    r = rig()
    r.enabled()
    r.ticks(4, r.here())
    with can.Bus(interface="virtual", channel=r.channel) as other:
        other.send(can.Message(arbitration_id=0x04, is_error_frame=True))  # warning: counted
        r.tick(r.here())
        assert r.drv.state is DriverState.ACTIVE and r.drv.stats()["error_frames"] == 1
        other.send(can.Message(arbitration_id=0x40, is_error_frame=True))  # bus-off
        err = r.until_fault(3, lambda k: r.here())
    assert f"bus-off on {r.channel}" in str(err) and "error frame 0x40" in str(err)
    r.ticks(2)
    assert all(0x02 in r.emu.node(n).controlwords for n in (1, 2, 3))
    r.drv.reset()  # the bus-off was acted on: a bus that is back takes a reset
    r.ticks(2)
    assert r.drv.state is DriverState.INACTIVE
