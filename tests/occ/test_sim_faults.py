"""The simulated drive's hardware faults and what it reports (occ/drivers/sim.py; issue 26's
fault matrix plays them, occ_testkit/faultmatrix.py): faults given in the params, each on its joint,
the errors that name a bad one, a jump of exactly a fifth of the range, a drive that holds where it
is when powered, the heartbeat deadline to the tick and every loss reported, and the encoder's,
the load's and the averaged effort's readings the robot sees. All in simulated time: every
``now`` is passed in.

Written to catch faults the fault matrix let through (mutation testing, docs/VERIFICATION.md
``simfaults``).
"""

from __future__ import annotations

import math
import re

import pytest

from occ.drivers import DriverState
from occ.drivers.sim import SIM_FAULTS, SimDriver
from occ.errors import DriverError
from occ.joint import Joint, JointLimits


def joints(n: int = 2, lo: float = -1.0, hi: float = 1.0) -> list[Joint]:
    return [Joint(f"j{i}", "revolute", JointLimits(lo, hi, 100.0, 50.0)) for i in range(n)]


def started(d: SimDriver, now: float = 0.0) -> SimDriver:
    d.configure()
    d.read(now)
    d.activate()
    return d


def test_faults_in_the_params_strike_from_the_start_each_on_its_joint() -> None:
    js = joints(3)
    d = SimDriver("s", js, {"faults": ["nan:1"], "encoder_resolution": 0.0})
    d.configure()
    d.read(0.0)
    assert [j.measured for j in js] == [True, False, True]  # only joint 1 never measured
    js = joints(3)
    d = SimDriver("s", js, {"faults": ["nan"], "encoder_resolution": 0.0})  # joint 0 by default
    d.configure()
    d.read(0.0)
    assert [j.measured for j in js] == [False, True, True]


def test_a_bad_fault_is_refused_naming_it() -> None:
    kinds = ", ".join(SIM_FAULTS)
    cases = [
        ("nan", "sim param 'faults' must be a list of fault kinds, got 'nan'"),
        ({"nan": 1}, "sim param 'faults' must be a list of fault kinds, got {'nan': 1}"),
        (["nan:3"], "sim param 'faults': joint index 3 out of range for driver 's'"),
        (["smoke"], f"sim param 'faults': unknown fault 'smoke'; faults are: {kinds}"),
    ]
    for faults, text in cases:
        with pytest.raises(ValueError, match=f"^{re.escape(text)}$"):
            SimDriver("s", joints(3), {"faults": faults})
    assert kinds == "configure, activate, hook, write, heartbeat, nan, frozen, jump, drift, slip"
    d = SimDriver("s", joints(2))
    for joint in (2, -1):
        with pytest.raises(ValueError, match=f"^joint index {joint} out of range for driver 's'$"):
            d.inject("nan", joint)
    d.inject("nan", 1)  # the last joint is one


def test_an_injected_jump_is_a_fifth_of_the_range_on_its_joint_only() -> None:
    js = joints(2, lo=-0.5, hi=1.5)
    params = {"faults": ["jump:1"], "encoder_resolution": 0.0, "initial_positions": [0.25, 0.75]}
    d = SimDriver("s", js, params)
    d.configure()
    d.read(0.0)
    assert js[0].position == 0.25
    assert js[1].position == 0.75 + 0.2 * (1.5 - -0.5)  # 0.4 further than it is
    assert d.true_positions == [0.25, 0.75]


def test_a_hook_fault_is_reported_as_the_drive_raised_it() -> None:
    d = started(SimDriver("s", joints(1)))
    d.inject("hook")
    with pytest.raises(DriverError):
        d.read(0.001)
    assert d.state is DriverState.FAULT
    assert d.fault_reason == (
        "driver 's': read failed: RuntimeError(\"simulated fault: exception in the drive's "
        'read hook")'
    )


@pytest.mark.parametrize("interface", ["position", "effort"])
def test_a_configured_drive_reports_no_effort_and_holds_where_it_is_when_powered(
    interface: str,
) -> None:
    """Power-up is not a move: the servo's target is where the joint is (position), the
    effort zero (effort interface); before, a configured drive reports no effort."""
    js = joints(1)
    params = {"encoder_resolution": 0.0, "initial_positions": [0.3]}
    d = SimDriver("s", js, params, command_interface=interface)  # type: ignore[arg-type]
    d.configure()
    d.read(0.0)
    assert (js[0].position, js[0].velocity, js[0].effort) == (0.3, 0.0, 0.0)
    d.activate()
    for k in range(1, 41):  # 40 ms powered, no command yet (within the heartbeat)
        d.read(k * 0.001)
    assert js[0].position == pytest.approx(0.3, abs=1e-12)
    assert js[0].velocity == pytest.approx(0.0, abs=1e-9)


@pytest.mark.req("SR-HB-1")
def test_the_heartbeat_deadline_is_exact_and_every_loss_is_reported() -> None:
    """A command exactly at the deadline keeps the drive; one later stops it, reported once
    by the read that finds it, with the silence and the limit; after a reset the next loss is
    reported again, and a write that finds the loss reports it too; each trip is counted."""
    js = joints(1)
    d = started(SimDriver("s", js, {"encoder_resolution": 0.0, "heartbeat_ms": 62.5}))
    d.write([0.0], 0.5)
    d.write([0.0], 0.5625)  # exactly 62.5 ms later (binary-exact times): not late
    d.read(0.5625)
    assert d.state is DriverState.ACTIVE and d.stats()["heartbeat_trips"] == 0
    text = "heartbeat lost: no command for 125.0 ms (limit 62.5 ms); the drive stopped itself"
    with pytest.raises(DriverError, match=re.escape(f"sim driver 's': {text}")):
        d.read(0.6875)
    assert d.stats()["heartbeat_trips"] == 1
    d.read(0.7)  # reported once
    d.reset()
    d.activate()
    d.write([0.0], 1.0)
    with pytest.raises(DriverError, match="heartbeat lost: no command for 250.0 ms"):
        d.read(1.25)
    assert d.stats()["heartbeat_trips"] == 2
    d.reset()
    d.activate()
    d.write([0.0], 2.0)
    with pytest.raises(DriverError):
        d.write([0.0], 2.125)  # no read between: the write finds the loss
    assert d.state is DriverState.FAULT
    assert d.fault_reason is not None
    assert "sim driver 's': heartbeat lost: no command for 125.0 ms" in d.fault_reason
    assert d.stats()["heartbeat_trips"] == 3


def test_a_command_acts_from_its_time_on() -> None:
    """Zero-order hold: a command written at ``now`` acts from ``now``; the previous one acts
    until then even without a read between, and a read repeated at the same time reports
    the same measurement (effort included) whatever was commanded meanwhile."""
    js = joints(1)
    d = started(SimDriver("s", js, {"encoder_resolution": 0.0, "heartbeat_ms": 0}))
    d.write([0.0], 0.0)
    d.write([0.5], 0.05)  # the hold at 0 acted for 50 ms: nothing moved
    d.read(0.05)
    assert js[0].position == 0.0 and js[0].effort == 0.0
    d.read(0.1)
    first = (js[0].position, js[0].velocity, js[0].effort)
    assert first[0] > 0.1  # then it moved toward 0.5
    d.write([-0.5], 0.1)
    d.read(0.1)
    assert (js[0].position, js[0].velocity, js[0].effort) == first


class ConstantLoad:
    """The world pressing on every joint with the same effort (the interface of
    occ/haptics/contact.py)."""

    def __init__(self, effort: float) -> None:
        self.effort = effort

    def efforts(self, q: list[float], qd: list[float]) -> list[float]:
        return [self.effort] * len(q)


def test_a_load_moves_the_servoed_joint_to_its_equilibrium() -> None:
    """A world's load (e.g. tissue) on a servoed joint: it settles where the servo's effort
    balances it, ``te / kp`` off the command (kp = J wn^2), not on the command."""
    js = joints(1)
    # (held off its command for good: not a frozen encoder)
    params = {"encoder_resolution": 0.0, "heartbeat_ms": 0, "frozen_feedback_ms": 0}
    d = SimDriver("s", js, params)
    d.environment = ConstantLoad(0.5)
    started(d)
    for k in range(1, 1001):
        d.read(k * 0.001)
        d.write([0.2], k * 0.001)
    kp = 0.01 * (2.0 * math.pi * 10.0) ** 2
    assert js[0].position == pytest.approx(0.2 + 0.5 / kp, abs=1e-6)
    assert js[0].effort == pytest.approx(-0.5, abs=1e-5)  # the servo holds the load


def test_the_averaged_effort_is_the_mean_over_its_window() -> None:
    """``effort_average_ms``: the reported effort is the mean over the window (a drive's
    filtered current), here one tick: the momentum balance over it, J dv/dt + b dx/dt,
    not the effort at its end."""
    js = joints(1)
    params = {"encoder_resolution": 0.0, "heartbeat_ms": 0, "effort_average_ms": 1.0}
    d = started(SimDriver("s", js, params))
    d.write([0.3], 0.0)
    x0, v0 = d.true_positions[0], js[0].velocity
    d.read(0.001)
    x1, v1 = d.true_positions[0], js[0].velocity
    mean = 0.01 * (v1 - v0) / 0.001 + 0.1 * (x1 - x0) / 0.001
    assert js[0].effort == pytest.approx(mean, rel=1e-9)
    kp, kd = 0.01 * (2.0 * math.pi * 10.0) ** 2, 2.0 * 2.0 * math.pi * 10.0 * 0.01 - 0.1
    end = kp * (0.3 - x1) - kd * v1
    assert abs(js[0].effort - end) > 0.01 * abs(end)  # the mean, not the end value


def test_a_noisy_encoder_reads_the_position_to_its_nearest_count() -> None:
    """Gaussian noise (zero mean, seeded) is added to the position and the sum rounded to
    the encoder's count; a joint with no quantum reads the noisy position itself."""
    js = joints(2)
    params = {
        "noise_std": 1e-7,
        "encoder_resolution": [1e-3, 0.0],
        "initial_positions": [0.1234, 0.2],
    }
    d = SimDriver("s", js, params)
    d.configure()
    seen = set()
    for k in range(20):
        d.read(k * 0.001)
        assert js[0].position == pytest.approx(0.123, abs=1e-12)  # 123.4 counts -> 123
        assert js[1].position == pytest.approx(0.2, abs=1e-6)
        seen.add(js[1].position)
    assert len(seen) > 10  # the noise is there


def test_a_slip_and_a_drift_move_their_joint_by_their_amounts() -> None:
    """``slip`` adds its amount (from the params' ``kind:joint:amount``, else
    ``FAULT_AMOUNTS``) to its joint's reading; ``drift`` its rate times the time since it
    began, from the first read when it was injected before any."""
    js = joints(2)
    params = {
        "faults": ["slip:1:0.25"],
        "encoder_resolution": 0.0,
        "initial_positions": [0.25, 0.5],
    }
    d = SimDriver("s", js, params)
    d.configure()
    d.read(0.0)
    assert [j.position for j in js] == [0.25, 0.75]
    js = joints(2)
    d = SimDriver("s", js, {"encoder_resolution": 0.0, "initial_positions": [0.25, 0.5]})
    d.configure()
    d.read(0.0)
    d.inject("slip")  # joint 0, the default amount
    d.read(0.001)
    assert [j.position for j in js] == [0.25 + 0.0005, 0.5]
    js = joints(1)
    d = SimDriver("s", js, {"encoder_resolution": 0.0, "initial_positions": [0.25]})
    d.inject("drift", 0, 2.0)  # before the model's first step
    d.configure()
    d.read(0.0)
    assert js[0].position == 0.25
    d.read(0.01)
    assert js[0].position == pytest.approx(0.25 + 2.0 * 0.01)
