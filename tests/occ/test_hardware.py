"""The HardwareSet alone (occ/hardware.py): every operation reaches every drive and reports the
failures by drive, action and cause; power is all or nothing; a write checks every drive first.
The robot-level outcomes are tests/occ/test_fault_matrix.py's."""

from __future__ import annotations

import math

import pytest

from occ.drivers.base import DriverState
from occ.drivers.sim import SimDriver
from occ.hardware import HardwareFailure, HardwareSet, describe
from occ.joint import Joint, JointLimits


def _joints(names: str) -> list[Joint]:
    return [Joint(n, "revolute", JointLimits(-1.0, 1.0, 1.0, 50.0)) for n in names]


def _set() -> tuple[HardwareSet, SimDriver, SimDriver]:
    a = SimDriver("a", _joints("xy"), {"heartbeat_ms": 0})
    b = SimDriver("b", _joints("z"), {"heartbeat_ms": 0})
    return HardwareSet([(a, [0, 1]), (b, [2])]), a, b


def test_failures_name_the_drive_the_action_and_the_cause() -> None:
    f = HardwareFailure("arm", "activate", "no power")
    assert str(f) == "driver arm: activate failed: no power"
    g = HardwareFailure("tool", "read", "feedback lost")
    assert describe([f, g]) == (
        "driver arm: activate failed: no power; driver tool: read failed: feedback lost"
    )
    assert describe([]) == ""


def test_configure_tries_every_drive_and_names_each_failure() -> None:
    hw, a, b = _set()
    a.inject("configure")
    (fail,) = hw.configure()
    assert (fail.driver, fail.action) == ("a", "configure")
    assert "no answer at configure" in fail.cause
    assert a.state is DriverState.FAULT and b.state is DriverState.INACTIVE
    assert hw.failures == 1
    assert hw.configure() == []  # nothing left unconfigured: nothing tried
    a.clear_faults()
    assert hw.reset() == []  # reset, then configured again
    assert a.state is DriverState.INACTIVE
    hw.shutdown()


def test_activation_is_all_or_nothing() -> None:
    hw, a, b = _set()
    assert hw.configure() == []
    b.inject("activate")
    (fail,) = hw.activate()
    assert (fail.driver, fail.action) == ("b", "activate")
    # a came up and went off again; b is latched FAULT by its base
    assert a.state is DriverState.INACTIVE and b.state is DriverState.FAULT
    assert hw.all_safe()
    lat = hw.last_fault_to_safe_s
    assert lat is not None and lat >= 0.0
    assert hw.stats()["last_fault_to_safe_us"] == round(lat * 1e6, 1)
    # a drive already latched FAULT cannot be powered, and says why
    (again,) = hw.activate()
    assert again == HardwareFailure(
        "b", "activate", "sim driver 'b': simulated fault: the power stage did not come up"
    )  # its fault reason, not an attempt
    assert [f.driver for f in hw.faulted()] == ["b"]
    b.clear_faults()
    assert hw.reset() == [] and hw.activate() == []
    assert a.state is DriverState.ACTIVE and b.state is DriverState.ACTIVE
    assert hw.faulted() == [] and not hw.all_safe()
    assert hw.deactivate() == [] and hw.all_safe()
    hw.shutdown()


def test_an_unconfigured_drive_is_not_powered() -> None:
    hw, a, b = _set()
    a.configure()
    (fail,) = hw.activate()
    assert fail == HardwareFailure("b", "activate", "drive is unconfigured")
    assert a.state is DriverState.INACTIVE
    hw.shutdown()


def test_every_drive_is_read_and_each_failure_named() -> None:
    hw, a, b = _set()
    hw.configure()
    assert hw.read(0.0) is None
    a.inject("hook")
    failures = hw.read(0.001)
    assert failures is not None and [f.driver for f in failures] == ["a"]
    assert "exception in the drive's read hook" in failures[0].cause
    assert b.joints[0].measured and b.stats()["reads"] == 2  # b still read
    # unconfigured drives are not read
    hw2, c, d = _set()
    c.configure()
    assert hw2.read(0.0) is None and d.stats()["reads"] == 0 and c.stats()["reads"] == 1
    hw.shutdown()
    hw2.shutdown()


def test_a_write_checks_every_drive_before_writing_any() -> None:
    hw, a, b = _set()
    hw.configure()
    hw.read(0.0)
    assert hw.activate() == []
    assert hw.write([0.0, 0.1, 0.2], 0.001) is None
    assert a.stats()["writes"] == 1 and b.stats()["writes"] == 1
    assert [j.command_position for j in a.joints + b.joints] == pytest.approx([0.0, 0.001, 0.001])
    b.safe_stop("test")  # b latched FAULT by itself
    fail = hw.write([0.0, 0.1, 0.2], 0.002)
    assert fail is not None and (fail.driver, fail.action) == ("b", "write")
    assert fail.cause == "not active (safe stop: test)"
    assert a.stats()["writes"] == 1  # nothing was written to a either
    hw.shutdown()


def test_a_write_that_raises_is_a_failure_of_that_drive() -> None:
    hw, a, b = _set()
    hw.configure()
    hw.read(0.0)
    hw.activate()
    b.inject("write")
    fail = hw.write([0.0, 0.0, 0.0], 0.001)
    assert fail is not None and fail.driver == "b" and "write failed" in fail.cause
    assert hw.failures == 1
    assert hw.deactivate() == [] and hw.all_safe()
    assert hw.last_fault_to_safe_s is not None
    hw.shutdown()


def test_efforts_go_to_every_drive_as_efforts() -> None:
    joints_a = _joints("xy")
    a = SimDriver("a", joints_a, {"heartbeat_ms": 0, "command_interface": "effort"})
    hw = HardwareSet([(a, [0, 1])])
    hw.configure()
    hw.read(0.0)
    hw.activate()
    assert hw.write([1.5, -2.0], 0.001, effort=True) is None
    assert [j.command_effort for j in joints_a] == [1.5, -2.0]
    assert math.isnan(joints_a[0].command_position)  # no position was commanded
    hw.shutdown()


def test_unmeasured_joints_are_named_with_their_drive() -> None:
    hw, a, b = _set()
    joints = a.joints + b.joints
    assert hw.unmeasured(joints) == "driver a joints ['x', 'y']; driver b joints ['z']"
    b.inject("nan")  # b never reports its joint
    hw.configure()
    hw.read(0.0)
    assert hw.unmeasured(joints) == "driver b joints ['z']"
    hw.shutdown()


def test_stats_per_drive_and_states() -> None:
    hw, a, b = _set()
    st = hw.stats()
    assert st["states"] == {"a": "unconfigured", "b": "unconfigured"}
    assert set(st["drivers"]) == {"a", "b"} and st["failures"] == 0
    assert st["last_fault_to_safe_us"] is None
    hw.shutdown()
    assert hw.stats()["states"] == {"a": "shutdown", "b": "shutdown"}
