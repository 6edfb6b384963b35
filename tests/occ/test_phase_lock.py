"""Deadline shifting (ControlLoop.shift) and the slave's phase lock to the master's stream."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from occ.clock import SimClock
from occ.controllers import ControllerContext
from occ.controllers.teleop import SlaveController
from occ.kinematics.frame import Frame
from occ.core.loop import ControlLoop

# controllers that never use their frame still get a real one (a compiled ControllerContext checks
# the type of each field)
SLAVE_FRAME = Frame.builtin("occ_slave")


def test_shift_moves_every_later_deadline() -> None:
    clock = SimClock()
    starts: list[float] = []
    loop: ControlLoop

    def tick(now: float, k: int) -> None:
        starts.append(now)
        if k == 10:
            loop.shift(0.0003)

    loop = ControlLoop(1000, tick, clock=clock)
    loop.run(ticks=20)
    assert starts[10] - starts[0] == pytest.approx(0.010)
    assert starts[11] - starts[10] == pytest.approx(0.0013)  # one longer period, then steady
    assert starts[19] - starts[11] == pytest.approx(0.008)
    assert loop.shifts == 1
    with pytest.raises(ValueError):
        loop.shift(0.002)


def test_phase_lock_brings_arrivals_to_the_target_phase() -> None:
    shifts: list[float] = []
    fake_loop = SimpleNamespace(t0=0.0, period_s=0.001, shift=shifts.append)
    ctrl = SlaveController({"phase_lock_us": 200.0})
    ctrl.ctx = ControllerContext(
        clock=SimClock(),
        frame=SLAVE_FRAME,
        rate_hz=1000.0,
        interfaces=(),  # type: ignore[arg-type]
        loop_t0=lambda: fake_loop.t0,
        period_s=0.001,
        shift=shifts.append,
    )
    # packets arrive 0.35 ms after each deadline: they would wait 0.65 ms for the next tick
    for i in range(250):
        ctrl.phase.track(i * 0.002 + 0.00035 + (1e-5 if i % 7 == 0 else 0.0), ctrl.ctx)
    assert len(shifts) == 1
    # target (phase_lock_us=200): arrive 0.2 ms before a deadline, at phase 0.8 ms -> shift -0.45 ms
    assert shifts[0] == pytest.approx(-0.00045, abs=1e-6)
    # once locked (arrivals around phase 0.8 ms), no further shifts
    fake_loop.t0 = shifts[0]
    for i in range(250):
        ctrl.phase.track(i * 0.002 + 0.00035 + (0.00015, -0.00015, 0.0)[i % 3], ctrl.ctx)
    assert len(shifts) == 1 and abs(ctrl.phase.error_us or 0.0) < 1.0


def test_phase_lock_median_survives_the_wrap_around() -> None:
    shifts: list[float] = []
    fake_loop = SimpleNamespace(t0=0.0, period_s=0.001, shift=shifts.append)
    ctrl = SlaveController({"phase_lock_us": 50.0})
    ctrl.ctx = ControllerContext(
        clock=SimClock(),
        frame=SLAVE_FRAME,
        rate_hz=1000.0,
        interfaces=(),  # type: ignore[arg-type]
        loop_t0=lambda: fake_loop.t0,
        period_s=0.001,
        shift=shifts.append,
    )
    # target phase 0.95 ms; arrivals at 0.95 +- 0.15 ms, half of them past the deadline (0.1)
    for i in range(250):
        ctrl.phase.track(i * 0.002 + 0.00095 + (0.00015, -0.00015, 0.0)[i % 3], ctrl.ctx)
    assert shifts == [] and abs(ctrl.phase.error_us or 0.0) < 1.0


def _locked_slave(shifts: list[float]) -> SlaveController:
    ctrl = SlaveController({"phase_lock_us": 200.0})
    # neither the wall clock's epoch nor the loop clock's time a whole number of periods: an
    # offset taken the wrong way round then shows as another phase
    clock = SimClock(wall_epoch=1_700_000_000.0003)
    clock.set(0.5003)
    ctrl.ctx = ControllerContext(
        clock=clock,
        frame=SLAVE_FRAME,
        rate_hz=1000.0,
        interfaces=(),  # type: ignore[arg-type]
        loop_t0=lambda: 0.0,
        period_s=0.001,
        shift=shifts.append,
    )
    return ctrl


@pytest.mark.parametrize("stamped", [True, False])
def test_the_phase_is_the_masters_sample_time_else_the_reception_time(stamped: bool) -> None:
    """Samples go through on_sample: with a header timestamp the phase is when the master
    sampled (its wall-clock stamp moved onto the loop's clock), not when the datagram was
    read; without one (0), the reception time. Either way 0.35 ms after the deadlines here."""
    import igtl
    from occ.net.decoders import pose_sample

    shifts: list[float] = []
    ctrl = _locked_slave(shifts)
    clock = ctrl.ctx.clock  # type: ignore[union-attr]
    offset = clock.wall_time() - clock.now()  # wall = loop clock + offset
    for i in range(250):
        sampled = i * 0.002 + 0.00035
        # read 0.3 ms after it was sampled: the reception time would be another phase
        t_rx = sampled + (0.0003 if stamped else 0.0)
        msg = igtl.PositionMessage(
            (0.0, 0.0, 0.0),
            (0.0, 0.0, 0.0, 1.0),
            24,
            device_name="Master",
            timestamp=sampled + offset if stamped else 0.0,
            header_version=2,
            message_id=i + 1,
        )
        ctrl.on_sample(pose_sample("master", None, msg, t_rx), t_rx)  # type: ignore[arg-type]
    assert shifts == [pytest.approx(-0.00045, abs=2e-6)]
    assert ctrl.phase.shifts == 1 and ctrl.stats()["phase_error_us"] == pytest.approx(-450.0, abs=2)
    assert ctrl.samples == 250 and ctrl.last_seq == 250 and ctrl.last_sample_t == t_rx
    assert (ctrl.pending_ts is not None) is stamped


def test_a_small_positive_timestamp_is_a_timestamp() -> None:
    import igtl
    from occ.net.decoders import pose_sample

    shifts: list[float] = []
    ctrl = _locked_slave(shifts)
    for i in range(250):  # stamped 0.5 s + phase 0.35 ms on a clock whose offset is 0
        ctrl.ctx.clock.wall_epoch = 0.0  # type: ignore[union-attr]
        msg = igtl.PositionMessage(
            (0.0, 0.0, 0.0),
            (0.0, 0.0, 0.0, 1.0),
            24,
            device_name="Master",
            timestamp=0.5 + i * 0.002 + 0.00035,
            header_version=2,
            message_id=i + 1,
        )
        ctrl.on_sample(pose_sample("master", None, msg, 0.0), 0.0)  # type: ignore[arg-type]
    assert shifts == [pytest.approx(-0.00045, abs=2e-6)]
    assert ctrl.pending_ts == pytest.approx(0.5 + 249 * 0.002 + 0.00035)


@pytest.mark.parametrize(
    ("period", "lock_us", "shift"),
    [
        # a 1.5 ms loop (666.7 Hz): target phase 1.5 - 0.2 = 1.3 ms; arrivals at 0.35 ms are
        # 0.55 ms past it, wrapped into [-0.75, 0.75) ms
        (0.0015, 200.0, 0.00055),
        # 1 kHz with a lock given to the half nanosecond: target 0.8999995 ms
        (0.001, 100.0005, 0.00035 - 0.0008999995 + 0.001),
    ],
)
def test_the_phase_lock_at_other_rates_and_fractional_locks(period, lock_us, shift) -> None:
    """The lock is in microseconds whatever the loop's period: the shift is the wrapped
    distance from the arrivals' phase to ``period - phase_lock_us``."""
    import igtl
    from occ.net.decoders import pose_sample

    shifts: list[float] = []
    ctrl = SlaveController({"phase_lock_us": lock_us})
    ctrl.ctx = ControllerContext(
        clock=SimClock(),
        frame=SLAVE_FRAME,
        rate_hz=1.0 / period,  # type: ignore[arg-type]
        interfaces=(),
        loop_t0=lambda: 0.0,
        period_s=period,
        shift=shifts.append,
    )
    for i in range(250):
        t_rx = i * 2 * period + 0.00035  # unstamped: the phase is the reception time's
        msg = igtl.PositionMessage(
            (0.0, 0.0, 0.0),
            (0.0, 0.0, 0.0, 1.0),
            24,
            device_name="Master",
            timestamp=0.0,
            header_version=2,
            message_id=i + 1,
        )
        ctrl.on_sample(pose_sample("master", None, msg, t_rx), t_rx)  # type: ignore[arg-type]
    assert shifts == [pytest.approx(shift, abs=2e-6)]
