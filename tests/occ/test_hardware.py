"""The HardwareSet alone (occ/core/hardware.py): every operation reaches every drive and reports the
failures by drive, action and cause; power is all or nothing; a write checks every drive first.
The robot-level outcomes are tests/occ/test_fault_matrix.py's."""

from __future__ import annotations

import math
import threading
import time

import pytest

from occ.core.hardware import HardwareFailure, HardwareSet, describe
from occ.drivers.base import DriverState
from occ.drivers.sim import SimDriver
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
    assert fail == HardwareFailure(
        "b", "activate", "sim driver 'b': simulated fault: the power stage did not come up"
    )
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
    assert failures is not None and [(f.driver, f.action) for f in failures] == [("a", "read")]
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


class Brittle(SimDriver):
    """A simulated drive whose deactivate, reset or shutdown hook raises on demand (an
    exception without a message, the hardest to name), and which records its activations."""

    def __init__(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        super().__init__(*args, **kwargs)
        self.breaks: set[str] = set()
        self.activations = 0

    def _activate(self) -> None:
        self.activations += 1
        super()._activate()

    def _deactivate(self) -> None:
        if "deactivate" in self.breaks:
            raise RuntimeError()
        super()._deactivate()

    def _reset(self) -> None:
        if "reset" in self.breaks:
            raise OSError("the drive does not clear its fault")
        super()._reset()

    def _read(self, now: float):  # type: ignore[no-untyped-def]
        if "read" in self.breaks:
            raise OSError("encoder silent")
        return super()._read(now)

    def _shutdown(self) -> None:
        if "shutdown" in self.breaks:
            raise OSError("bus gone")
        super()._shutdown()


def _brittle() -> tuple[HardwareSet, Brittle, Brittle]:
    a = Brittle("a", _joints("xy"), {"heartbeat_ms": 0})
    b = Brittle("b", _joints("z"), {"heartbeat_ms": 0})
    return HardwareSet([(a, [0, 1]), (b, [2])]), a, b


def test_a_drive_that_fails_to_stop_is_named_and_the_others_still_stop() -> None:
    hw, a, b = _brittle()
    hw.configure()
    hw.read(0.0)
    hw.activate()
    a.breaks.add("deactivate")
    (fail,) = hw.deactivate()
    assert fail == HardwareFailure(
        "a",
        "deactivate",
        "driver 'a': deactivate failed: RuntimeError() (still powered: its switch-off failed "
        "twice)",
    )
    assert a.state is DriverState.FAULT and b.state is DriverState.INACTIVE
    # latched, but not safe: its power stage was never proven off (issue 36)
    assert not hw.all_safe() and hw.failures == 1
    assert hw.unsafe() == [
        HardwareFailure("a", "switch-off", "switch-off failed: RuntimeError()")
    ] and hw.stats()["unsafe"] == {"a": "switch-off failed: RuntimeError()"}
    (latched,) = hw.faulted()
    assert latched == HardwareFailure("a", "drive", a.fault_reason or "")
    a.breaks.clear()
    hw.shutdown()


def test_only_the_drives_that_need_it_are_touched_the_rest_still_are() -> None:
    hw, a, b = _brittle()
    hw.configure()
    hw.read(0.0)
    a.activate()  # already on: activation goes on to b
    assert hw.activate() == [] and b.state is DriverState.ACTIVE and a.activations == 1
    a.deactivate()  # already off: deactivation goes on to b
    assert hw.deactivate() == [] and b.state is DriverState.INACTIVE
    # a latched drive does not stop the others from being tried (then all go off again)
    a.activate()
    a.safe_stop("test")
    (fail,) = hw.activate()
    assert fail.driver == "a" and b.activations == 2 and b.state is DriverState.INACTIVE
    # an unconfigured drive first: the next is still read
    hw2, c, d = _brittle()
    d.configure()
    assert hw2.read(0.0) is None and d.stats()["reads"] == 1
    hw.shutdown()
    hw2.shutdown()


def test_a_reset_that_fails_is_named_and_an_unconfigured_drive_still_configured() -> None:
    hw, a, b = _brittle()
    b.configure()
    b.activate()
    b.safe_stop("x")  # latched FAULT
    b.breaks.add("reset")
    failures = hw.reset()  # a (never configured) is configured; b's reset fails
    assert failures == [
        HardwareFailure(
            "b", "reset", "driver 'b': reset failed: OSError('the drive does not clear its fault')"
        )
    ]
    assert a.state is DriverState.INACTIVE and b.state is DriverState.FAULT
    assert hw.failures == 1
    b.breaks.clear()
    hw.shutdown()


def test_shutdown_reaches_every_drive_and_names_the_failures() -> None:
    hw, a, b = _brittle()
    hw.configure()
    a.breaks.add("shutdown")
    failures = hw.shutdown()
    assert len(failures) == 1 and failures[0].driver == "a" and failures[0].action == "shutdown"
    assert "bus gone" in failures[0].cause
    assert a.state is DriverState.SHUTDOWN and b.state is DriverState.SHUTDOWN
    assert hw.shutdown() == []  # twice: nothing left to do


def test_failures_are_counted_across_operations_and_the_time_to_safe_is_sane() -> None:
    hw, a, b = _set()
    hw.configure()
    a.inject("hook")
    hw.read(0.0)
    hw.read(0.001)
    assert hw.failures == 2
    a.clear_faults()
    hw.reset()
    hw.read(0.002)
    hw.activate()
    b.inject("write")
    hw.write([0.0, 0.0, 0.0], 0.003)
    hw.write([0.0, 0.0, 0.0], 0.004)  # b is latched: refused before writing
    assert hw.failures == 4
    hw.deactivate()
    lat = hw.last_fault_to_safe_s
    assert lat is not None and 0.0 <= lat < 1.0  # from the detection, on one clock
    hw.shutdown()


def test_a_cause_without_words_is_named_by_its_type() -> None:
    from occ.core.hardware import _cause

    assert _cause(RuntimeError()) == "RuntimeError"
    assert _cause(OSError("bus gone")) == "bus gone"


def test_a_safe_stop_from_the_supervisor_reaches_every_drive() -> None:
    hw, a, b = _set()
    hw.configure()
    hw.read(0.0)
    hw.activate()
    hw.safe_stop("loop hung")
    assert [d.state for d in (a, b)] == [DriverState.FAULT, DriverState.FAULT]
    assert [f.cause for f in hw.faulted()] == ["safe stop: loop hung"] * 2
    hw.shutdown()


def test_one_drive_in_another_joint_order_gets_each_setpoint_on_its_own_joint() -> None:
    """A single drive whose joints are listed in another order than the robot's: each value
    still reaches its joint (only one drive with every joint *in order* takes the values as
    they come)."""
    d = SimDriver("d", _joints("zxy"), {"heartbeat_ms": 0})
    hw = HardwareSet([(d, [2, 0, 1])])  # robot order x, y, z; the drive's z, x, y
    hw.configure()
    hw.read(0.0)
    assert hw.activate() == []
    assert hw.write([0.0005, 0.0, -0.0005], 0.001) is None  # x, y, z
    z, x, y = d.joints
    assert (x.command_position, y.command_position, z.command_position) == pytest.approx(
        (0.0005, 0.0, -0.0005)
    )
    in_order = SimDriver("o", _joints("xyz"), {"heartbeat_ms": 0})
    whole = HardwareSet([(in_order, [0, 1, 2])])
    whole.configure()
    whole.read(0.0)
    whole.activate()
    assert whole.write([0.0005, 0.0, -0.0005], 0.001) is None
    assert [j.command_position for j in in_order.joints] == pytest.approx([0.0005, 0.0, -0.0005])
    hw.shutdown()
    whole.shutdown()


def test_a_single_drive_not_active_is_refused_before_its_write_and_says_why() -> None:
    d = SimDriver("arm", _joints("xyz"), {"heartbeat_ms": 0})
    hw = HardwareSet([(d, [0, 1, 2])])
    hw.configure()
    hw.read(0.0)
    hw.activate()
    d.safe_stop("test")
    fail = hw.write([0.0, 0.0, 0.0], 0.001)
    assert fail == HardwareFailure("arm", "write", "not active (safe stop: test)")
    assert d.stats()["writes"] == 0
    hw.shutdown()


def test_a_drive_faulted_without_words_is_still_named_with_a_cause() -> None:
    hw, a, b = _set()
    hw.configure()
    a._enter_fault("")  # a plugin's fault with an empty message
    assert hw.faulted() == [HardwareFailure("a", "drive", "fault")]
    hw.shutdown()


def test_stats_give_the_time_to_safe_in_us_and_the_world_when_there_is_one() -> None:
    hw, a, b = _set()
    hw.last_fault_to_safe_s = 1.23456789
    assert hw.stats()["last_fault_to_safe_us"] == 1234567.9
    assert "environment" not in hw.stats()

    class World:
        def stats(self) -> dict[str, int]:
            return {"contacts": 2}

    hw.environment = World()
    assert hw.stats()["environment"] == {"contacts": 2}
    hw.shutdown()


def test_a_failed_shutdown_is_logged_naming_the_drive(caplog: pytest.LogCaptureFixture) -> None:
    hw, a, b = _brittle()
    hw.configure()
    a.breaks.add("shutdown")
    with caplog.at_level("ERROR", logger="occ.core.hardware"):
        hw.shutdown()
    assert [r.getMessage() for r in caplog.records] == ["driver a: shutdown failed"]


def test_await_measured_reads_once_on_simulated_time_and_polls_on_the_real_clock(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """After configure: one read; on the real clock, reads every 5 ms until every joint is
    measured or the wait is over."""
    slept: list[float] = []
    monkeypatch.setattr("occ.core.hardware.time.sleep", slept.append)
    joints = _joints("xy")
    hw = HardwareSet([])
    reads: list[float] = []
    clock = [0.0]
    measured_at = [3]  # the read that measures both joints (0: never)

    def now() -> float:
        clock[0] += 0.001
        return clock[0]

    def read(t: float) -> None:
        reads.append(t)
        if len(reads) == measured_at[0]:
            joints[0].measured = joints[1].measured = True

    hw.await_measured(joints, read, now, 1.0, real=False)
    assert len(reads) == 1  # simulated time: once
    hw.await_measured(joints, read, now, 1.0, real=True)
    assert len(reads) == 3  # until both were measured (the third read), not the whole second
    assert slept == [0.005]  # one poll: the second read of this call measured them
    joints[0].measured = False
    reads.clear()
    measured_at[0] = 0
    hw.await_measured(joints, read, now, 0.004, real=True)
    # gives up once the wait is over: reads at +1 ms, then every poll (each now() +1 ms)
    assert 2 <= len(reads) <= 3 and not joints[0].measured


class Hung(SimDriver):
    """A simulated drive whose stop hangs until ``release`` is set (a hook stuck on a lock its
    hung read holds), or raises with ``fail``; it notes the thread each stop ran on."""

    def __init__(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        super().__init__(*args, **kwargs)
        self.release: threading.Event | None = None
        self.fail = False
        self.threads: list[tuple[str, bool]] = []

    def _safe_stop(self) -> None:
        t = threading.current_thread()
        self.threads.append((t.name, t.daemon))
        if self.release is not None:
            self.release.wait()
        if self.fail:
            raise OSError("relay stuck")
        super()._safe_stop()


def test_a_safe_stop_names_the_drive_that_does_not_confirm_and_the_one_whose_stop_failed() -> None:
    a = Hung("a", _joints("xy"), {"heartbeat_ms": 0})
    b = Hung("b", _joints("z"), {"heartbeat_ms": 0})
    hw = HardwareSet([(a, [0, 1]), (b, [2])])
    hw.configure()
    hw.read(0.0)
    assert hw.activate() == []
    a.release = threading.Event()
    b.fail = True
    try:
        # a's stop hangs: b is stopped all the same, each on a daemon thread of its own
        assert hw.safe_stop("loop hung") == [
            HardwareFailure("a", "safe stop", "not confirmed within 10 ms"),
            HardwareFailure("b", "safe stop", "safe stop failed: OSError('relay stuck')"),
        ]
        assert b.state is DriverState.FAULT
        assert a.threads == [("occ-safe-stop-a", True)] and b.threads == [("occ-safe-stop-b", True)]
        # the bound is the caller's, and named; b's failed stop is still reported
        assert hw.safe_stop("again", bound_s=0.02) == [
            HardwareFailure("a", "safe stop", "not confirmed within 20 ms"),
            HardwareFailure("b", "safe stop", "safe stop failed: OSError('relay stuck')"),
        ]
    finally:
        a.release.set()
    for t in threading.enumerate():
        if t.name == "occ-safe-stop-a":
            t.join()
    assert a.state is DriverState.FAULT and a.stop_failed is None
    hw.shutdown()


def test_a_hung_stop_holds_the_supervisor_for_its_bound_not_longer() -> None:
    """The supervisor waits for a drive whose stop hangs only as long as the bound it gives: a
    ratio of two bounds, not a wall-clock limit (5 ms against 400 ms; a floor under the wait,
    such as one second, would make both the same)."""
    a = Hung("a", _joints("xy"), {"heartbeat_ms": 0})
    hw = HardwareSet([(a, [0, 1])])
    hw.configure()
    hw.read(0.0)
    assert hw.activate() == []
    a.release = threading.Event()

    def waited(bound_s: float) -> float:
        t = time.perf_counter()
        assert hw.safe_stop("loop hung", bound_s=bound_s)[0].driver == "a"
        return time.perf_counter() - t

    try:
        short = min(waited(0.005) for _ in range(3))
        long = waited(0.4)
    finally:
        a.release.set()
    for t in threading.enumerate():
        if t.name == "occ-safe-stop-a":
            t.join()
    assert long >= 0.4 and short < long / 8, (short, long)
    hw.shutdown()


def test_a_drive_being_powered_up_elsewhere_is_left_alone_and_the_others_go_on() -> None:
    """A drive held by the power-up's thread (``hold``) is not read, powered or reset by the
    loop; the drives after it still are; a power-up or reset that meets it fails naming it."""
    hw, a, b = _brittle()
    hw.configure()
    hw.read(0.0)
    hw.hold([a])
    assert hw.read(0.001) is None
    assert a.stats()["reads"] == 1 and b.stats()["reads"] == 2  # a skipped, b still read
    assert hw.activate() == [HardwareFailure("a", "activate", "being powered up already")]
    assert b.activations == 1 and b.state is DriverState.INACTIVE  # tried, then off again
    a.safe_stop("x")  # not ACTIVE: nothing to do
    b.activate()
    b.safe_stop("y")
    a._state = DriverState.FAULT  # latched while its power-up ran
    assert hw.reset() == [HardwareFailure("a", "reset", "still being powered up")]
    assert b.state is DriverState.INACTIVE  # reset though a came first
    hw.release([a])
    a._state = DriverState.INACTIVE
    hw.shutdown()


def test_what_failed_on_other_threads_stops_an_activation_and_is_counted_once() -> None:
    hw, a, b = _brittle()
    hw.configure()
    hw.read(0.0)
    prior = [HardwareFailure("c", "activate", "node 3 never enabled")]
    assert hw.activate(prior) == prior
    assert a.activations == 0 and b.activations == 0  # nothing else powered
    assert hw.failures == 1
    # a roll-back whose switch-off fails: both failures, each counted once
    b.inject("activate")
    a.breaks.add("deactivate")
    failures = hw.activate()
    assert [(f.driver, f.action) for f in failures] == [("b", "activate"), ("a", "deactivate")]
    assert hw.failures == 3
    a.breaks.clear()
    hw.shutdown()


def test_a_reset_counts_each_failure_once() -> None:
    hw, a, b = _set()
    b.configure()
    a.inject("configure")  # a never configured: the reset configures it, and that fails
    (fail,) = hw.reset()
    assert (fail.driver, fail.action) == ("a", "configure") and hw.failures == 1
    a.clear_faults()
    assert hw.reset() == [] and hw.failures == 1
    hw.shutdown()
    # the drive resets but its fresh read fails: named as the reset's, counted once
    hw, a, b = _brittle()
    hw.configure()
    b.breaks.add("read")
    (fail,) = hw.read(0.0) or ()
    assert fail.driver == "b" and hw.failures == 1
    (fail,) = hw.reset(0.001)
    assert fail == HardwareFailure(
        "b", "reset", "a fresh read failed: driver 'b': read failed: OSError('encoder silent')"
    )
    assert hw.failures == 2
    b.breaks.clear()
    hw.shutdown()


def test_a_switch_off_that_fails_once_is_not_called_still_powered() -> None:
    hw, a, b = _brittle()
    hw.configure()
    hw.read(0.0)
    hw.activate()
    calls = [0]
    real = Brittle._deactivate

    def once(self: Brittle) -> None:
        calls[0] += 1
        if calls[0] == 1:
            raise RuntimeError()
        real(self)

    a._deactivate = once.__get__(a)  # type: ignore[method-assign]
    (fail,) = hw.deactivate()
    # the base's second try switched it off: latched FAULT, safe, nothing appended
    assert fail == HardwareFailure(
        "a", "deactivate", "driver 'a': deactivate failed: RuntimeError()"
    )
    assert a.stop_failed is None and hw.all_safe() and hw.unsafe() == []
    hw.shutdown()


class Recorded(SimDriver):
    """A simulated drive that notes every write (positions or efforts)."""

    def __init__(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        super().__init__(*args, **kwargs)
        self.told: list[tuple[str, list[float]]] = []

    def write(self, values, now):  # type: ignore[no-untyped-def]
        self.told.append(("position", list(values)))
        super().write(values, now)

    def write_effort(self, values, now):  # type: ignore[no-untyped-def]
        self.told.append(("effort", list(values)))
        super().write_effort(values, now)


def test_verify_reads_then_holds_the_joints_where_they_are_or_at_zero_effort() -> None:
    joints = _joints("xyz")
    a = Recorded("a", joints[:2], {"heartbeat_ms": 0, "initial_positions": [0.1, -0.2]})
    b = Recorded("b", joints[2:], {"heartbeat_ms": 0, "initial_positions": [0.3]})
    hw = HardwareSet([(a, [0, 1]), (b, [2])])
    hw.configure()
    hw.read(0.0)
    hw.activate()
    assert hw.verify(joints, 0.001) == []
    # where the fresh read put them (the drives' start, quantised), not zero
    here = [j.position for j in joints]
    assert here == pytest.approx([0.1, -0.2, 0.3], abs=1e-4)
    assert a.told == [("position", here[:2])] and b.told == [("position", here[2:])]
    hw.shutdown()
    # an effort drive away from zero: zero effort, not its position
    c = Recorded(
        "c",
        _joints("xy"),
        {"heartbeat_ms": 0, "initial_positions": [0.1, -0.2]},
        command_interface="effort",
    )
    hw = HardwareSet([(c, [0, 1])])
    hw.configure()
    hw.read(0.0)
    hw.activate()
    assert hw.verify(c.joints, 0.001, effort=True) == []
    assert c.joints[0].position == pytest.approx(0.1, abs=1e-4)
    assert c.told == [("effort", [0.0, 0.0])]
    hw.shutdown()


def test_verify_names_a_drive_left_not_active_once_with_why() -> None:
    hw, a, b = _set()
    hw.configure()
    hw.read(0.0)
    hw.activate()
    a.inject("hook")  # a's read fails: named by its read, not again
    b.safe_stop("overcurrent")  # b stopped itself: named by verify with its reason
    failures = hw.verify(_joints("xyz"), 0.001)
    assert [(f.driver, f.action) for f in failures] == [("a", "read"), ("b", "verify")]
    assert failures[1].cause == "left ACTIVE: safe stop: overcurrent"
    hw.shutdown()
    hw, a, b = _set()
    hw.configure()
    hw.read(0.0)
    hw.activate()
    a.inject("hook")
    b.deactivate()  # off without a fault: its state is the reason
    failures = hw.verify(_joints("xyz"), 0.001)
    assert failures[1] == HardwareFailure("b", "verify", "left ACTIVE: inactive")
    hw.shutdown()
