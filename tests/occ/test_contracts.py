"""Contract tests every registered driver and controller plugin must pass (issue 9, item 6).

python-can runs one back-to-back test against every bus backend (``test/back2back_test.py``);
this module does the same for our plugins: it is parametrized over ``available_drivers()`` and
``available_controllers()`` at collection, so a plugin added to a built-in table or by an entry
point is tested without anyone editing this file. What a plugin needs besides itself (the ``can``
driver: a simulated drive node on a python-can ``virtual`` channel; a controller: the robot it
expects and the inputs it follows) comes from the factory tables :data:`DRIVER_RIGS` and
:data:`CONTROLLER_RIGS` below. A plugin missing from its table fails, with a message saying how
to add it: a plugin nobody wrote a rig for must not pass by being skipped.

Drivers: lifecycle (ros2_control's UNCONFIGURED -> INACTIVE -> ACTIVE, FAULT latched, SHUTDOWN
twice), limits (clamp or fault, position and velocity, non-finite setpoints), the safe state
(``safe_stop`` from another thread; the device-side heartbeat) and parameters (unknown keys
refused at construction and at load with FILE:LINE). Time is simulated: the loop's ``now`` is
passed explicitly, and a device with its own clock (the CAN node) is given the same simulated
clock; where a thread answers on a bus, the test waits for it with a bounded wait on the node's
counters, never a sleep.

Controllers: typed ``Params`` (unknown keys refused, defaults construct, FILE:LINE at load),
interfaces and their single owner, no setpoint reaching the drivers while not RUNNING, no jump
on entering RUNNING, well-formed ``update`` results and ``stats``, unknown commands refused.
"""

from __future__ import annotations

import itertools
import json
import math
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import pytest
import yaml
from pydantic import BaseModel, ValidationError

from occ.net.commands import Request
from occ.config import ControllerConfig, DaemonConfig
from occ.controllers import (
    Controller,
    available_controllers,
    create_controller,
    load_controller_class,
)
from occ.drivers import Driver, DriverState, available_drivers, create_driver, load_driver_class
from occ.drivers.base import LimitPolicy
from occ.drivers.params import BASE_PARAMS
from occ.drivers.can_sim import DriveAxis, SimulatedDriveNode
from occ.errors import CommandError, ConfigError, DriverError, LimitError, OCCError, StateError
from occ.joint import Joint, JointLimits, PIDGains
from occ.core.loader import parse_config
from occ.core.safety import RobotState
from occ_testkit.testing import SimPeer, SimRobot

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"

#: how long a test waits for a thread on a bus before calling the device dead (never reached
#: when things work: every wait returns as soon as the awaited frame has been handled)
BUS_TIMEOUT = 5.0
#: position tolerance: the sim's 17-bit encoder quantum is 4.8e-5 rad, the CAN rig's 1e-5
TOL = 1e-4
BAD_KEY = "no_such_param"


# ============================================================================== driver rigs
class DriverRig:
    """What a driver plugin's contract tests need besides the driver: its device.

    The default is a driver whose device is a model advanced by the ``now`` the loop passes
    (``sim``): nothing to start, nothing to wait for. A rig for a driver whose device runs
    elsewhere (a thread on a bus) overrides :meth:`at` (the device's clock), :meth:`settle`
    (wait until the device has handled everything sent) and :meth:`wait_device` (a bounded
    wait for its next report).
    """

    def __init__(self, plugin: str) -> None:
        self.plugin = plugin
        self._drivers: list[Driver] = []

    def params(self, joints: list[Joint]) -> dict[str, Any]:
        """The parameters the plugin needs to reach its device (none for a model)."""
        return {}

    def make(
        self,
        joints: list[Joint],
        params: Mapping[str, Any] | None = None,
        on_limit: LimitPolicy = "clamp",
    ) -> Driver:
        drv = create_driver(
            self.plugin,
            "contract",
            joints,
            {**self.params(joints), **(params or {})},
            on_limit=on_limit,
        )
        self._drivers.append(drv)
        return drv

    def at(self, now: float) -> None:
        """The device's clock reads ``now`` from here on."""

    def settle(self) -> None:
        """Return once the device has handled every command sent so far and answered it."""

    def wait_device(self) -> None:
        """Block (bounded) until the device reports something new."""

    def close(self) -> None:
        for drv in self._drivers:
            try:
                drv.shutdown()
            except OCCError:
                pass  # a shutdown failure is the lifecycle test's business


class DeviceClock:
    """A simulated clock shared by the test (which sets it) and a device thread (which reads
    it): the device's heartbeat then trips in simulated time, exactly when the test says."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


class CANRig(DriverRig):
    """The ``can`` driver against :class:`SimulatedDriveNode` on a python-can ``virtual``
    channel of its own. A spy bus on the channel sees every command frame the driver sends
    (the virtual bus delivers before ``send`` returns), so :meth:`settle` knows how many the
    node must have handled."""

    COUNTS_PER_UNIT = 100_000.0  # 1e-5 rad or m per count: below TOL
    _channels = itertools.count()

    def __init__(self, plugin: str) -> None:
        super().__init__(plugin)
        self.channel = f"occ-contract-{next(self._channels)}"
        self.clock = DeviceClock()
        self.node: SimulatedDriveNode | None = None
        self.spy: can.BusABC | None = None
        self._can_ids: set[int] = set()
        self._sent = 0

    def params(self, joints: list[Joint]) -> dict[str, Any]:
        return {
            "interface": "virtual",
            "channel": self.channel,
            "joints": {
                j.name: {
                    "can_id": 0x101 + i,
                    "feedback_id": 0x181 + i,
                    "counts_per_unit": self.COUNTS_PER_UNIT,
                }
                for i, j in enumerate(joints)
            },
            # the node answers commands only (no cyclic feedback), and simulated time jumps
            # between reads: the feedback timeout is not part of this contract
            # (tests/occ/test_can_driver.py checks it)
            "feedback_timeout": 1e3,
        }

    def make(
        self,
        joints: list[Joint],
        params: Mapping[str, Any] | None = None,
        on_limit: LimitPolicy = "clamp",
    ) -> Driver:
        if self.node is None:
            axes = [
                DriveAxis(0x101 + i, 0x181 + i, position=j.home * self.COUNTS_PER_UNIT)
                for i, j in enumerate(joints)
            ]
            self._can_ids = {a.can_id for a in axes}
            # tau = 0: the drive is exactly where it was told, so "no further motion" is exact
            self.node = SimulatedDriveNode(axes, channel=self.channel, tau=0.0, clock=self.clock)
            self.node.start()
            self.spy = can.Bus(interface="virtual", channel=self.channel)
        return super().make(joints, params, on_limit)

    def at(self, now: float) -> None:
        self.clock.t = now

    def settle(self) -> None:
        node, spy = self.node, self.spy
        assert node is not None and spy is not None
        while (msg := spy.recv(timeout=0.0)) is not None:
            if msg.arbitration_id in self._can_ids:
                self._sent += 1
        assert node.wait_commands(self._sent, BUS_TIMEOUT), "the drive node did not get commands"
        # one feedback per command, one per heartbeat trip: then the last answer is queued
        trips = sum(a.heartbeat_trips for a in node.axes)
        assert node.wait_feedback(node.commands_received + trips, BUS_TIMEOUT), "no feedback"

    def wait_device(self) -> None:
        assert self.node is not None
        self.node.wait_feedback(self.node.feedback_sent + 1, timeout=0.05)

    def close(self) -> None:
        super().close()
        if self.node is not None:
            self.node.stop()
            assert self.node.error is None, self.node.error
        if self.spy is not None:
            self.spy.shutdown()


class CiA402Rig(DriverRig):
    """The ``cia402`` driver against the CiA 402 drive emulator (occ/drivers/cia402_sim.py) on
    a python-can ``virtual`` channel of its own, on the test's clock. The emulator answers SDO
    and the activation's SYNCs from its thread; :meth:`settle` has it handle, on the test's
    thread, every frame sent so far (its TPDOs are then queued for the driver)."""

    COUNTS_PER_UNIT = 100_000.0  # 1e-5 rad or m per count: below TOL
    _channels = itertools.count()

    def __init__(self, plugin: str) -> None:
        super().__init__(plugin)
        self.channel = f"occ-contract-cia402-{next(self._channels)}"
        self.clock = DeviceClock()
        self.emulator: Any = None

    def params(self, joints: list[Joint]) -> dict[str, Any]:
        return {
            "interface": "virtual",
            "channel": self.channel,
            "nodes": {
                j.name: {"node_id": i + 1, "counts_per_unit": self.COUNTS_PER_UNIT}
                for i, j in enumerate(joints)
            },
            # a SYNC every write, whatever the bus load (tests/occ/test_cia402.py checks the
            # budget); the activation's bound on the wall clock, generous
            "bus_load_limit": 10.0,
            "state_timeout_ms": 2000.0,
        }

    def make(
        self,
        joints: list[Joint],
        params: Mapping[str, Any] | None = None,
        on_limit: LimitPolicy = "clamp",
    ) -> Driver:
        if self.emulator is None:
            from occ.drivers.cia402_sim import DriveEmulator

            # a servo far faster than a tick: the drive is where it was told at each SYNC
            self.emulator = DriveEmulator(
                range(1, len(joints) + 1), channel=self.channel, clock=self.clock,
                bandwidth_hz=1e6,
            ).start()  # fmt: skip
        return super().make(joints, params, on_limit)

    def at(self, now: float) -> None:
        self.clock.t = now

    def settle(self) -> None:
        assert self.emulator is not None
        self.emulator.settle()

    def wait_device(self) -> None:
        time.sleep(0.001)

    def close(self) -> None:
        super().close()
        if self.emulator is not None:
            self.emulator.stop()
            assert self.emulator.errors == 0


class SimHandRig(DriverRig):
    """``sim-hand`` takes efforts only; under the position contract its joints get PID gains
    (the base turns setpoints into efforts) and the hand lets go (no stiffness, no motion)."""

    def make(
        self,
        joints: list[Joint],
        params: Mapping[str, Any] | None = None,
        on_limit: LimitPolicy = "clamp",
    ) -> Driver:
        for j in joints:
            j.gains = PIDGains(kp=2000.0, ki=0.0, kd=80.0)
        hand = {
            "hand_stiffness": 0.0,
            "hand_damping": 0.0,
            "intent_amplitude": 0.0,
            "intent_offset": 0.0,
            "inertia": 0.1,
            "damping": 1.0,
        }
        return super().make(joints, {**hand, **(params or {})}, on_limit)


#: plugin name -> rig factory. A new driver plugin adds its line here: ``DriverRig`` when its
#: device is a model advanced by ``now``, else a subclass like ``CANRig`` that starts a
#: simulated device and says how to wait for it.
DRIVER_RIGS: dict[str, Callable[[str], DriverRig]] = {
    "sim": DriverRig,
    "can": CANRig,
    "sim-hand": SimHandRig,
    "cia402": CiA402Rig,
}


def driver_rig_factory(plugin: str) -> Callable[[str], DriverRig]:
    """The plugin's rig factory; a failure saying how to add it when there is none."""
    factory = DRIVER_RIGS.get(plugin)
    if factory is None:
        pytest.fail(
            f"driver plugin {plugin!r} has no rig: add `{plugin!r}: <factory>` to DRIVER_RIGS in "
            "tests/occ/test_contracts.py (DriverRig if its device is a model advanced by `now`, "
            "else a DriverRig subclass that starts a simulated device, like CANRig)",
            pytrace=False,
        )
    return factory


@pytest.mark.parametrize("plugin", available_drivers())
def test_every_driver_plugin_has_a_rig(plugin: str) -> None:
    # the fixture below errors for such a plugin too; this makes it one plain failure
    driver_rig_factory(plugin)


@pytest.fixture(params=available_drivers())
def rig(request: pytest.FixtureRequest) -> Iterator[DriverRig]:
    plugin = request.param
    r = driver_rig_factory(plugin)(plugin)
    try:
        yield r
    finally:
        r.close()


def make_joints(velocity: float = 1000.0) -> list[Joint]:
    """A revolute and a prismatic joint at home 0 (the prismatic one on its lower limit);
    ``velocity`` high by default so that only the limit under test acts."""
    return [
        Joint("yaw", "revolute", JointLimits(-1.0, 1.0, velocity, 50.0), home=0.0),
        Joint("insertion", "prismatic", JointLimits(0.0, 0.15, velocity, 50.0), home=0.0),
    ]


def read(rig: DriverRig, drv: Driver, now: float) -> list[float]:
    """The loop's read at ``now``, once the device has answered; the measured positions."""
    rig.at(now)
    rig.settle()
    drv.read(now)
    return [j.position for j in drv.joints]


def write(rig: DriverRig, drv: Driver, values: list[float], now: float) -> None:
    """The loop's write at ``now``; the device handles it (or the fault's stop) before return."""
    rig.at(now)
    try:
        drv.write(values, now)
    finally:
        rig.settle()


def active(rig: DriverRig, **kw: Any) -> Driver:
    drv = rig.make(make_joints(kw.pop("velocity", 1000.0)), **kw)
    drv.configure()
    read(rig, drv, 0.0)
    drv.activate()
    return drv


def read_until_error(rig: DriverRig, drv: Driver, now: float) -> DriverError | None:
    """Read at ``now`` until the device reports an error (a device on a bus reports it
    asynchronously: poll, bounded)."""
    end = time.monotonic() + BUS_TIMEOUT
    while True:
        try:
            read(rig, drv, now)
        except DriverError as err:
            return err
        if time.monotonic() > end:
            return None
        rig.wait_device()


# -------------------------------------------------------------------------- driver lifecycle
def _illegal(drv: Driver, calls: list[tuple[str, Callable[[], object]]]) -> None:
    """Each call must raise StateError and change neither the state nor any counter."""
    for name, call in calls:
        state, stats = drv.state, drv.stats()
        with pytest.raises(StateError):
            call()
        assert (drv.state, drv.stats()) == (state, stats), f"{name} in {state} changed something"


def test_driver_lifecycle(rig: DriverRig) -> None:
    drv = rig.make(make_joints())
    assert drv.state is DriverState.UNCONFIGURED
    _illegal(
        drv,
        [
            ("activate", drv.activate),
            ("deactivate", drv.deactivate),
            ("reset", drv.reset),
            ("read", lambda: drv.read(0.0)),
            ("write", lambda: drv.write([0.0, 0.0], 0.0)),
        ],
    )
    drv.configure()
    assert drv.state is DriverState.INACTIVE
    read(rig, drv, 0.0)  # states readable
    _illegal(
        drv,
        [
            ("configure", drv.configure),
            ("deactivate", drv.deactivate),
            ("reset", drv.reset),
            ("write", lambda: drv.write([0.1, 0.01], 0.001)),
        ],
    )
    drv.activate()
    assert drv.state is DriverState.ACTIVE
    _illegal(drv, [("configure", drv.configure), ("activate", drv.activate), ("reset", drv.reset)])
    for k in range(1, 21):
        write(rig, drv, [0.001 * k, 0.0005 * k], 0.001 * k)
        read(rig, drv, 0.001 * k)
    assert drv.stats()["writes"] == 20
    drv.deactivate()
    assert drv.state is DriverState.INACTIVE
    _illegal(drv, [("write", lambda: drv.write([0.02, 0.01], 0.021))])
    read(rig, drv, 0.021)  # still readable
    drv.shutdown()
    assert drv.state is DriverState.SHUTDOWN
    drv.shutdown()  # safe twice
    assert drv.state is DriverState.SHUTDOWN
    _illegal(
        drv,
        [
            ("configure", drv.configure),
            ("activate", drv.activate),
            ("deactivate", drv.deactivate),
            ("reset", drv.reset),
            ("read", lambda: drv.read(0.03)),
            ("write", lambda: drv.write([0.0, 0.0], 0.03)),
        ],
    )


def test_driver_shutdown_from_active_and_as_context_manager(rig: DriverRig) -> None:
    drv = active(rig)
    write(rig, drv, [0.01, 0.01], 0.001)
    with drv:
        pass
    assert drv.state is DriverState.SHUTDOWN
    drv.shutdown()
    assert drv.stats()["errors"] == 0


# -------------------------------------------------------------------------- driver limits
def _fault_latched(rig: DriverRig, drv: Driver, now: float) -> None:
    """FAULT holds until reset(): commands and activation refused, reads allowed; then the
    driver recovers."""
    assert drv.state is DriverState.FAULT and drv.fault_reason
    _illegal(
        drv,
        [
            ("write", lambda: drv.write([0.0, 0.0], now)),
            ("activate", drv.activate),
            ("configure", drv.configure),
            ("deactivate", drv.deactivate),
        ],
    )
    read(rig, drv, now)
    assert drv.state is DriverState.FAULT
    drv.reset()
    assert drv.state is DriverState.INACTIVE and drv.fault_reason is None
    drv.activate()
    write(rig, drv, [j.position for j in drv.joints], now + 0.001)
    assert drv.state is DriverState.ACTIVE


@pytest.mark.req("SR-LIM-1")
def test_position_limit_clamps(rig: DriverRig) -> None:
    drv = active(rig)
    for k in range(1, 101):  # 0.5 s at 200 Hz: the device has settled where it was sent
        write(rig, drv, [1.5, -0.2], 0.005 * k)
        assert [j.command_position for j in drv.joints] == [1.0, 0.0]
    assert drv.stats()["limit_events"] == 200 and drv.state is DriverState.ACTIVE
    pos = read(rig, drv, 0.5)
    assert pos[0] == pytest.approx(1.0, abs=TOL) and pos[0] <= 1.0 + TOL
    assert pos[1] == pytest.approx(0.0, abs=TOL)


@pytest.mark.req("SR-LIM-1")
def test_position_limit_faults(rig: DriverRig) -> None:
    drv = active(rig, on_limit="fault")
    write(rig, drv, [0.5, 0.01], 0.001)
    with pytest.raises(LimitError, match=r"yaw: position 1\.5 outside limits"):
        write(rig, drv, [1.5, 0.01], 0.002)
    _fault_latched(rig, drv, 0.003)


@pytest.mark.req("SR-LIM-2")
def test_velocity_limit_clamps(rig: DriverRig) -> None:
    drv = active(rig, velocity=1.0)  # 1 mm or 1 mrad per 1 ms tick
    for k in range(1, 11):
        write(rig, drv, [0.5, 0.1], 0.001 * k)
        assert [j.command_position for j in drv.joints] == pytest.approx([0.001 * k] * 2)
    assert drv.stats()["limit_events"] == 20
    pos = read(rig, drv, 0.010)
    assert all(p <= 0.010 + TOL for p in pos), pos  # the unclamped step never reached the device


@pytest.mark.req("SR-LIM-2")
def test_velocity_limit_faults(rig: DriverRig) -> None:
    drv = active(rig, velocity=1.0, on_limit="fault")
    write(rig, drv, [0.001, 0.001], 0.001)
    with pytest.raises(LimitError, match=r"yaw: velocity 99 exceeds limit 1"):
        write(rig, drv, [0.1, 0.001], 0.002)
    _fault_latched(rig, drv, 0.003)


@pytest.mark.parametrize("policy", ["clamp", "fault"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.req("SR-LIM-3")
def test_non_finite_setpoint_faults(rig: DriverRig, policy: LimitPolicy, bad: float) -> None:
    drv = active(rig, on_limit=policy)
    write(rig, drv, [0.01, 0.01], 0.001)
    before = read(rig, drv, 0.001)
    with pytest.raises(LimitError, match="setpoint"):
        write(rig, drv, [0.01, bad], 0.002)
    # nothing of that command reached the device: it holds where it was
    assert read(rig, drv, 0.100) == pytest.approx(before, abs=TOL)
    _fault_latched(rig, drv, 0.101)


# -------------------------------------------------------------------------- driver safe state
@pytest.mark.req("SR-SAFE-1")
def test_safe_stop_from_another_thread(rig: DriverRig) -> None:
    drv = active(rig, params={"heartbeat_ms": 0})  # only the safe stop may stop it here
    for k in range(1, 51):  # moving when stopped: a ramp toward 0.5 / 0.1
        write(rig, drv, [0.01 * k, 0.002 * k], 0.001 * k)
        read(rig, drv, 0.001 * k)
    t = threading.Thread(target=drv.safe_stop, args=("contract",))
    t.start()
    t.join(BUS_TIMEOUT)
    assert not t.is_alive()
    drv.safe_stop("again")  # idempotent: the first reason stays, counted once
    assert drv.state is DriverState.FAULT
    assert drv.fault_reason == "safe stop: contract" and drv.stats()["safe_stops"] == 1
    with pytest.raises(StateError):
        drv.write([0.5, 0.1], 0.052)
    # no further motion once the drive has braked
    stopped = read(rig, drv, 0.060)
    assert read(rig, drv, 0.500) == stopped
    assert read(rig, drv, 2.000) == stopped


@pytest.mark.req("SR-HB-1")
def test_heartbeat_stops_the_drive_and_is_reported_once(rig: DriverRig) -> None:
    hb = 0.020
    drv = active(rig, params={"heartbeat_ms": hb * 1e3})
    # refreshed faster than the heartbeat: never trips (each step < hb, on the device's clock)
    t = 0.0
    for _ in range(20):
        t += hb / 2
        write(rig, drv, [t, t / 10], t)
        read(rig, drv, t)
    assert drv.state is DriverState.ACTIVE
    # the host goes silent while the drive moves: it stops itself and says so, once
    write(rig, drv, [t + hb, (t + hb) / 10], t + hb / 2)
    t += hb / 2
    err = read_until_error(rig, drv, t + 10 * hb)
    assert err is not None, "the drive did not report its heartbeat stop"
    assert "heartbeat" in str(err)
    assert drv.state is DriverState.FAULT and "heartbeat" in (drv.fault_reason or "")
    stopped = read(rig, drv, t + 11 * hb)  # reported once: readable again
    assert read(rig, drv, t + 100 * hb) == stopped  # and braked
    assert drv.state is DriverState.FAULT
    drv.reset()
    drv.activate()
    write(rig, drv, stopped, t + 101 * hb)
    assert drv.state is DriverState.ACTIVE


# -------------------------------------------------------------------------- driver parameters
def test_unknown_param_is_refused_at_construction(rig: DriverRig) -> None:
    cls = load_driver_class(rig.plugin)
    assert cls.DEFAULT_PARAMS is not None, (
        f"{cls.__name__} must declare DEFAULT_PARAMS: without it the base cannot refuse a "
        "misspelt key"
    )
    with pytest.raises((ValueError, OCCError)) as info:
        rig.make(make_joints(), {BAD_KEY: 1})
    text = str(info.value)
    assert BAD_KEY in text and "known" in text
    for key in {*cls.DEFAULT_PARAMS, *BASE_PARAMS}:
        assert key in text, f"the error does not list the known param {key!r}: {text}"


def test_bad_param_at_load_names_file_and_line(rig: DriverRig) -> None:
    data = yaml.safe_load((CONFIGS / "slave.yaml").read_text(encoding="utf-8"))
    data.pop("controller")  # one `params:` in the file: the driver's
    driver = data["robot"]["drivers"][0]
    joints = [
        Joint(j["name"], j.get("type", "revolute"), JointLimits(-1.0, 1.0, 1.0), home=0.0)
        for j in data["robot"]["joints"]
    ]
    driver["plugin"] = rig.plugin
    driver["params"] = {**rig.params(joints), BAD_KEY: 1}
    text = yaml.safe_dump(data, sort_keys=False)
    (line,) = [n for n, s in enumerate(text.splitlines(), 1) if s.strip() == "params:"]
    with pytest.raises(ConfigError) as info:
        parse_config(text, source="contract.yaml", base_dir=CONFIGS)
    errors = info.value.errors
    assert len(errors) == 1, errors
    assert errors[0].startswith(f"contract.yaml:{line} robot.drivers[0].params: "), errors
    assert BAD_KEY in errors[0]


# ============================================================================ controller rigs
@dataclass(frozen=True)
class ControllerRig:
    """The robot a controller plugin expects and the inputs it follows.

    ``config``: a shipped config whose robot suits the plugin (its ``controller:`` is replaced);
    ``params``: the plugin's params there; ``feed``: given the SimRobot, returns what to do
    before every tick (e.g. a master streaming POSITION), or None for a controller that makes
    its own motion.
    """

    config: Path
    params: Mapping[str, Any] = field(default_factory=dict)
    feed: Callable[[SimRobot], Callable[[], None]] | None = None
    #: replaces the config's ``robot.drivers`` (YAML form) when the plugin needs other ones
    drivers: tuple[Mapping[str, Any], ...] | None = None
    #: output sources of another controller that the config names (left out)
    without_sources: tuple[str, ...] = ()

    def yaml_data(self) -> dict[str, Any]:
        data = yaml.safe_load(self.config.read_text(encoding="utf-8"))
        if self.drivers is not None:
            data["robot"]["drivers"] = [dict(d) for d in self.drivers]
        for itf in data["interfaces"]:
            if "outputs" in itf:
                itf["outputs"] = [
                    o for o in itf["outputs"] if o["source"] not in self.without_sources
                ]
        return data  # type: ignore[no-any-return]


def master_stream(sim: SimRobot) -> Callable[[], None]:
    """The master's POSITION stream at 500 Hz, moving (a 10 mm circle at 1 Hz), so that a
    controller that jumps to where the master went while it was held would show it."""
    master = sim.peer("master", address=("127.0.0.1", 40000))
    seq = itertools.count(1)

    def feed() -> None:
        if sim.k % 2 == 0:
            w = 2.0 * math.pi * sim.now
            master.send_position(
                (10.0 * math.sin(w), 50.0 + 10.0 * math.cos(w), 270.0), seq=next(seq)
            )

    return feed


#: plugin name -> the robot it runs in. A new controller plugin adds its line here.
CONTROLLER_RIGS: dict[str, ControllerRig] = {
    # the slave's return channel (source teleop-return) is teleop-slave's
    "hold": ControllerRig(CONFIGS / "slave.yaml", without_sources=("teleop-return",)),
    "teleop-slave": ControllerRig(
        CONFIGS / "slave.yaml", {"input_interface": "master"}, master_stream
    ),
    # the position-commanded master (the paper's motion played as setpoints on the sim
    # driver); the shipped haptic master (sim-hand, efforts) is tests/occ/test_haptic_master.py's
    "teleop-master": ControllerRig(
        CONFIGS / "master.yaml",
        {"input": "sim"},
        drivers=(
            {
                "name": "sim",
                "plugin": "sim",
                "joints": ["x", "y", "z"],
                "params": {"bandwidth_hz": 30.0},
            },
        ),
    ),
    "keyframe": ControllerRig(
        CONFIGS / "keyframe.yaml", {"file": str(CONFIGS / "keyframes" / "demo.yaml")}
    ),
}


class ControllerRun:
    """A SimRobot with the plugin as its controller, its inputs fed before every tick, and an
    operator peer."""

    def __init__(self, plugin: str, rig: ControllerRig) -> None:
        self.plugin = plugin
        self.rig = rig
        self.sim = SimRobot(config_with(rig, [(plugin, rig.params)]))
        self.robot = self.sim.robot
        (self.ctrl,) = self.robot.controller.controllers
        self._feed = rig.feed(self.sim) if rig.feed is not None else None
        operator = next(i.name for i in self.sim.config.interfaces if i.role == "operator")
        self.operator: SimPeer = self.sim.peer(operator)

    def tick(self, n: int = 1, after: Callable[[], None] | None = None) -> None:
        for _ in range(n):
            if self._feed is not None:
                self._feed()
            self.sim.tick()
            if after is not None:
                after()

    def command(self, name: str) -> Any:
        cid = self.operator.send_command(name)
        self.tick()
        reply = self.operator.reply_to(cid)
        assert reply is not None, f"no reply to {name}"
        return reply

    def state_command(self, name: str, expect: RobotState) -> None:
        reply = self.command(name)
        assert reply.metadata["Status"] == "SUCCESS", reply
        assert self.robot.state is expect

    def commanded(self) -> list[float]:
        return [j.command_position for j in self.robot.joints]

    def driver_writes(self) -> int:
        return sum(d.stats()["writes"] for d in self.robot.hardware.drivers)

    def limit_events(self) -> int:
        return sum(d.stats()["limit_events"] for d in self.robot.hardware.drivers)

    def close(self) -> None:
        self.sim.close()


def config_with(
    rig: ControllerRig, controllers: list[tuple[str, Mapping[str, Any]]]
) -> DaemonConfig:
    cfg = parse_config(
        yaml.safe_dump(rig.yaml_data(), sort_keys=False),
        source=str(rig.config),
        base_dir=rig.config.parent,
    )
    ccs = tuple(ControllerConfig(plugin=p, params=dict(params)) for p, params in controllers)
    return cfg.model_copy(update={"controller": ccs[0] if len(ccs) == 1 else ccs})


def require_controller_rig(name: str) -> None:
    if name not in CONTROLLER_RIGS:
        pytest.fail(
            f"controller plugin {name!r} has no rig: add `{name!r}: ControllerRig(config, "
            "params, feed)` to CONTROLLER_RIGS in tests/occ/test_contracts.py (the shipped config "
            "whose robot it drives, its params, and the inputs it follows, if any)",
            pytrace=False,
        )


@pytest.mark.parametrize("name", available_controllers())
def test_every_controller_plugin_has_a_rig(name: str) -> None:
    require_controller_rig(name)


@pytest.fixture(params=available_controllers())
def plugin(request: pytest.FixtureRequest) -> str:
    name: str = request.param
    require_controller_rig(name)
    return name


@pytest.fixture
def run(plugin: str) -> Iterator[ControllerRun]:
    r = ControllerRun(plugin, CONTROLLER_RIGS[plugin])
    try:
        yield r
    finally:
        r.close()


# -------------------------------------------------------------------------- controller params
def test_controller_params_model(plugin: str) -> None:
    cls = load_controller_class(plugin)
    assert issubclass(cls, Controller)
    assert isinstance(cls.Params, type) and issubclass(cls.Params, BaseModel)
    cls.Params()  # the defaults construct
    with pytest.raises(ValidationError, match=BAD_KEY):
        cls.Params.model_validate({**CONTROLLER_RIGS[plugin].params, BAD_KEY: 1})
    with pytest.raises(ConfigError, match=BAD_KEY):
        create_controller(plugin, {BAD_KEY: 1})
    assert isinstance(create_controller(plugin, CONTROLLER_RIGS[plugin].params), cls)


def test_controller_bad_param_at_load_names_file_and_line(plugin: str) -> None:
    rig = CONTROLLER_RIGS[plugin]
    data = rig.yaml_data()
    data["controller"] = {"plugin": plugin, "params": {**rig.params, BAD_KEY: 1}}
    text = yaml.safe_dump(data, sort_keys=False)
    (line,) = [n for n, s in enumerate(text.splitlines(), 1) if s.strip() == f"{BAD_KEY}: 1"]
    with pytest.raises(ConfigError) as info:
        parse_config(text, source="contract.yaml", base_dir=rig.config.parent)
    assert info.value.errors == [
        f"contract.yaml:{line} controller.params.{BAD_KEY}: unknown field '{BAD_KEY}'"
    ]


# -------------------------------------------------------------------------- controller interfaces
def test_controller_interfaces_in_a_robot(run: ControllerRun) -> None:
    joints = run.robot.data.joint_names
    commands = run.ctrl.command_interfaces()
    states = run.ctrl.state_interfaces()
    assert set(commands) <= {f"{j}/position" for j in joints}, commands
    assert len(set(commands)) == len(commands), commands
    assert set(states) <= {f"{j}/{k}" for j in joints for k in ("position", "velocity", "effort")}


@pytest.mark.req("SR-OWN-2")
def test_two_owners_of_a_command_interface_are_refused(plugin: str) -> None:
    rig = CONTROLLER_RIGS[plugin]
    cfg = config_with(rig, [(plugin, rig.params), (plugin, rig.params)])
    with SimRobot(config_with(rig, [(plugin, rig.params)])) as single:
        claimed = single.robot.controller.controllers[0].command_interfaces()
    if not claimed:  # commands nothing: two of them cannot fight
        SimRobot(cfg).close()
        return
    with pytest.raises(ConfigError, match=r"command interface .* claimed by controllers") as info:
        SimRobot(cfg).close()
    assert "one owner" in str(info.value) and claimed[0] in str(info.value)


# -------------------------------------------------------------------------- controller in the loop
@pytest.mark.req("SR-HOLD-1")
def test_setpoints_reach_the_drivers_only_while_running(run: ControllerRun) -> None:
    data = run.robot.data
    run.tick(200)  # READY: drivers off, nothing written
    assert run.driver_writes() == 0

    def holds() -> None:
        assert run.commanded() == data.hold_setpoint

    run.state_command("Enable", RobotState.ENABLED)
    held = list(data.hold_setpoint)
    run.tick(300, after=holds)
    assert data.hold_setpoint == held
    run.state_command("Run", RobotState.RUNNING)
    run.tick(300)
    run.state_command("Stop", RobotState.STOPPED)
    held = list(data.hold_setpoint)
    run.tick(300, after=holds)
    assert data.hold_setpoint == held
    run.state_command("Enable", RobotState.ENABLED)
    run.tick(100, after=holds)


@pytest.mark.req("SR-HOLD-1")
def test_entering_running_never_jumps(run: ControllerRun) -> None:
    data = run.robot.data
    max_step = [j.limits.velocity * run.sim.period * (1 + 1e-9) for j in run.robot.joints]

    def enter_running() -> None:
        held = list(data.hold_setpoint)
        events = run.limit_events()
        run.state_command("Run", RobotState.RUNNING)
        first = list(data.setpoint)
        steps = [abs(a - b) for a, b in zip(first, held, strict=True)]
        assert all(s <= m for s, m in zip(steps, max_step, strict=True)), (first, held)
        assert run.limit_events() == events  # the drivers had nothing to clamp

    run.state_command("Enable", RobotState.ENABLED)
    run.tick(200)
    enter_running()
    run.tick(300)
    run.state_command("Stop", RobotState.STOPPED)
    run.tick(500)  # the inputs move on while the robot holds
    enter_running()
    run.tick(50)
    assert run.robot.state is RobotState.RUNNING


def test_update_results_and_stats_are_well_formed(run: ControllerRun) -> None:
    n = len(run.robot.joints)
    results: list[Any] = []
    # recorded through the robot's controller set, whose one member is run.ctrl (a compiled
    # controller's methods cannot be replaced on the instance)
    assert run.robot.controller.controllers == [run.ctrl]
    update = run.robot.controller.update

    def recording(now: float, current: Any) -> Any:
        out = update(now, current)
        results.append(out)
        return out

    json.dumps(run.ctrl.stats())
    run.robot.controller.update = recording  # type: ignore[method-assign]
    run.state_command("Enable", RobotState.ENABLED)
    run.state_command("Run", RobotState.RUNNING)
    run.tick(500)
    assert len(results) == 501  # the tick that entered RUNNING updated too
    for out in results:
        if out is not None:
            assert len(out) == n and all(math.isfinite(float(v)) for v in out), out
    json.dumps(run.ctrl.stats())  # no default=: every value must already be JSON


def test_unknown_command_is_refused_and_changes_nothing(run: ControllerRun) -> None:
    with pytest.raises(CommandError):
        run.ctrl.on_command(Request("command", "NoSuchContractCommand"), run.sim.now)
    run.state_command("Enable", RobotState.ENABLED)
    run.state_command("Run", RobotState.RUNNING)
    run.tick(20)
    reply = run.command("NoSuchContractCommand")
    assert reply.metadata["Status"] == "FAIL" and "NoSuchContractCommand" in reply.metadata["Error"]
    assert run.robot.state is RobotState.RUNNING
    run.tick(20)
    assert run.robot.state is RobotState.RUNNING
