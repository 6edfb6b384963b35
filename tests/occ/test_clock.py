"""Clock tests: SimClock semantics; RealClock's sleep-then-spin logic with a faked time module."""

from __future__ import annotations

import pytest

from occ import clock as clock_mod
from occ.clock import Clock, RealClock, SimClock


def test_both_clocks_satisfy_the_protocol() -> None:
    assert isinstance(RealClock(), Clock)
    assert isinstance(SimClock(), Clock)


def test_simclock_jumps_to_deadline_and_never_backwards() -> None:
    c = SimClock(start=10.0)
    assert c.now() == 10.0
    c.sleep_until(10.5)
    assert c.now() == 10.5
    c.sleep_until(10.2)  # already passed: returns at once, time unchanged
    assert c.now() == 10.5
    assert c.sleeps == 2


def test_simclock_advance_and_set() -> None:
    c = SimClock()
    c.advance(0.25)
    c.advance(0.0)
    assert c.now() == 0.25
    with pytest.raises(ValueError):
        c.advance(-1e-9)
    c.set(1.0)
    assert c.now() == 1.0
    with pytest.raises(ValueError):
        c.set(0.5)


def test_simclock_inject_delay_applies_to_next_wake_only_and_accumulates() -> None:
    c = SimClock()
    c.inject_delay(0.001)
    c.inject_delay(0.0005)
    c.sleep_until(0.010)
    assert c.now() == pytest.approx(0.0115)
    c.sleep_until(0.020)
    assert c.now() == 0.020
    with pytest.raises(ValueError):
        c.inject_delay(-0.1)


def test_simclock_inject_delay_applies_even_when_deadline_passed() -> None:
    c = SimClock(start=1.0)
    c.inject_delay(0.002)
    c.sleep_until(0.5)
    assert c.now() == pytest.approx(1.002)


def test_simclock_wake_latency_callback() -> None:
    seen: list[float] = []

    def latency(deadline: float) -> float:
        seen.append(deadline)
        return 1e-4

    c = SimClock(wake_latency=latency)
    c.sleep_until(1.0)
    c.sleep_until(2.0)
    assert seen == [1.0, 2.0]
    assert c.now() == pytest.approx(2.0001)


def test_simclock_wall_time_is_epoch_plus_now() -> None:
    c = SimClock(start=2.0, wall_epoch=1_000.0)
    assert c.wall_time() == 1_002.0
    c.advance(0.5)
    assert c.wall_time() == 1_002.5


class _FakeTime:
    """perf_counter advances 10 µs per read; sleep advances by its argument."""

    def __init__(self) -> None:
        self.t = 0.0
        self.sleeps: list[float] = []
        self.yields = 0
        self.reads = 0

    def perf_counter(self) -> float:
        self.reads += 1
        self.t += 10e-6
        return self.t

    def sleep(self, dt: float) -> None:
        if dt == 0:
            self.yields += 1  # RealClock's spin releases the GIL with sleep(0): not a sleep
            return
        self.sleeps.append(dt)
        self.t += dt

    def time(self) -> float:
        return 1_700_000_000.0 + self.t


@pytest.fixture
def fake_time(monkeypatch: pytest.MonkeyPatch) -> _FakeTime:
    fake = _FakeTime()
    monkeypatch.setattr(clock_mod.time, "perf_counter", fake.perf_counter)
    monkeypatch.setattr(clock_mod.time, "sleep", fake.sleep)
    monkeypatch.setattr(clock_mod.time, "time", fake.time)
    return fake


def test_realclock_sleeps_to_spin_margin_then_spins(fake_time: _FakeTime) -> None:
    c = RealClock(spin_us=200)
    c.sleep_until(1.0)
    assert len(fake_time.sleeps) == 1
    # one perf_counter read (10 µs) before sleeping, then sleep to 200 µs before the deadline
    assert fake_time.sleeps[0] == pytest.approx(1.0 - 10e-6 - 200e-6)
    assert fake_time.t >= 1.0
    assert fake_time.t - 1.0 <= 10e-6  # spun up to the deadline, not past one read
    assert fake_time.reads > 10  # the last 200 µs were spun


def test_realclock_returns_at_once_for_a_past_deadline(fake_time: _FakeTime) -> None:
    fake_time.t = 5.0
    RealClock().sleep_until(4.0)
    assert fake_time.sleeps == []
    assert fake_time.reads == 1


def test_realclock_spin_only_when_deadline_within_margin(fake_time: _FakeTime) -> None:
    RealClock(spin_us=200).sleep_until(100e-6)
    assert fake_time.sleeps == []
    assert fake_time.t >= 100e-6


def test_realclock_spin_zero_is_plain_sleep(fake_time: _FakeTime) -> None:
    RealClock(spin_us=0).sleep_until(0.5)
    assert fake_time.sleeps == [pytest.approx(0.5 - 10e-6)]


def test_realclock_wall_time_and_validation(fake_time: _FakeTime) -> None:
    c = RealClock(spin_us=50)
    assert c.spin_us == pytest.approx(50)
    assert c.wall_time() == pytest.approx(1_700_000_000.0)
    with pytest.raises(ValueError):
        RealClock(spin_us=-1)


def test_realclock_spin_yields_the_gil_only_when_asked(fake_time: _FakeTime) -> None:
    clock_mod.RealClock(spin_us=200, yield_gil=True).sleep_until(100e-6)
    assert fake_time.yields > 0
    fake_time.yields = 0
    clock_mod.RealClock(spin_us=200).sleep_until(fake_time.t + 100e-6)
    assert fake_time.yields == 0
