"""The time-domain passivity observer and controller (occ/passivity.py), number by number.

The observer sums ``-f . v dt`` (the energy the operator put into the network); the controller
adds a damper ``-alpha v`` exactly when the force about to be displayed would make that sum
negative, with ``alpha = -E / (|v|^2 dt)`` capped at ``max_damping``, and the sum after it is
zero (or what the cap leaves)."""

from __future__ import annotations

import pytest

from occ.passivity import PassivityController

pytestmark = pytest.mark.req("SR-FORCE-1")


def test_energy_the_operator_puts_in_is_observed_and_the_force_is_left_alone() -> None:
    pc = PassivityController()
    # pressing into a spring: the force against the motion (f = -2 N on x, v = +0.1 m/s)
    f = pc.step((-2.0, 0.0, 0.0), (0.1, 0.0, 0.0), 0.001)
    assert f == (-2.0, 0.0, 0.0)
    assert pc.energy == pytest.approx(2e-4)  # -(-2 * 0.1) * 1 ms
    f = pc.step((0.0, -1.0, 3.0), (0.0, 0.5, -0.2), 0.002)
    assert f == (0.0, -1.0, 3.0)
    assert pc.energy == pytest.approx(2e-4 + (0.5 + 0.6) * 0.002)
    assert pc.active_ticks == 0 and pc.dissipated == 0.0 and pc.last_damping == 0.0


def test_a_force_that_would_give_energy_back_gets_exactly_the_damper_that_cancels_it() -> None:
    pc = PassivityController(max_damping=1e6)
    pc.step((-1.0, 0.0, 0.0), (0.1, 0.0, 0.0), 0.001)  # E = 1e-4 J in
    e0 = pc.energy
    # released: the force along the motion would take 3 N * 0.2 m/s * 1 ms = 6e-4 J out
    f = pc.step((3.0, 0.0, 0.0), (0.2, 0.0, 0.0), 0.001)
    e_pred = e0 - 3.0 * 0.2 * 0.001
    alpha = -e_pred / (0.2**2 * 0.001)
    assert pc.last_damping == pytest.approx(alpha)
    assert f == pytest.approx((3.0 - alpha * 0.2, 0.0, 0.0))
    assert pc.energy == pytest.approx(0.0, abs=1e-15)
    assert pc.dissipated == pytest.approx(alpha * 0.04 * 0.001)
    assert pc.active_ticks == 1


def test_the_damper_acts_on_every_axis_against_the_velocity() -> None:
    pc = PassivityController(max_damping=1e6)
    v = (0.1, -0.2, 0.3)
    f = pc.step((1.0, -1.0, 1.0), v, 0.001)  # all along the motion: energy out from E = 0
    alpha = pc.last_damping
    assert alpha > 0.0
    assert f == pytest.approx((1.0 - alpha * 0.1, -1.0 + alpha * 0.2, 1.0 - alpha * 0.3))
    assert pc.energy == pytest.approx(0.0, abs=1e-15)


def test_the_damping_is_capped_and_the_rest_stays_observed() -> None:
    pc = PassivityController(max_damping=5.0)
    f = pc.step((10.0, 0.0, 0.0), (0.1, 0.0, 0.0), 0.001)  # wants alpha = 100 N s/m
    assert pc.last_damping == 5.0
    assert f == pytest.approx((10.0 - 0.5, 0.0, 0.0))
    assert pc.energy == pytest.approx(-1e-3 + 5.0 * 0.01 * 0.001)
    assert pc.dissipated == pytest.approx(5.0 * 0.01 * 0.001)


def test_no_damper_without_motion_or_time() -> None:
    pc = PassivityController()
    pc.energy = -1.0
    assert pc.step((1.0, 2.0, 3.0), (0.0, 0.0, 0.0), 0.001) == (1.0, 2.0, 3.0)
    assert pc.step((1.0, 2.0, 3.0), (0.1, 0.0, 0.0), 0.0) == (1.0, 2.0, 3.0)
    assert pc.active_ticks == 0


def test_observe_only_and_reset_and_stats() -> None:
    pc = PassivityController()
    pc.observe((2.0, 0.0, 0.0), (0.5, 0.0, 0.0), 0.001)  # off: the network's gift shows
    assert pc.energy == pytest.approx(-1e-3)
    pc.observe((0.0, -2.0, 1.0), (0.0, 0.5, 1.0), 0.001)
    assert pc.energy == pytest.approx(-1e-3 + 1e-3 - 1e-3)
    st = pc.stats()
    assert st == {"energy_mj": round(pc.energy * 1e3, 4), "dissipated_mj": 0.0,
                  "active_ticks": 0, "damping": 0.0}  # fmt: skip
    pc.last_damping = 3.0
    pc.reset()
    assert pc.energy == 0.0 and pc.last_damping == 0.0


def test_the_controllers_counts_add_up_over_ticks() -> None:
    pc = PassivityController(max_damping=1e6)
    for _ in range(3):  # every tick the force would give energy back: damped each time
        pc.step((1.0, 0.0, 0.0), (0.1, 0.0, 0.0), 0.001)
    assert pc.active_ticks == 3
    assert pc.dissipated == pytest.approx(3 * 1.0 * 0.1 * 0.001)
    pc.energy, pc.dissipated, pc.last_damping = 1.23456789e-3, 9.87654321e-3, 12.34567
    assert pc.stats() == {"energy_mj": 1.2346, "dissipated_mj": 9.8765, "active_ticks": 3,
                          "damping": 12.346}  # fmt: skip
    assert PassivityController().max_damping == 200.0
