"""The two-port time-domain passivity scheme (occ/haptics/passivity.py), number by number.

Each port's account splits its flow into energy in (sent to the peer, never decreasing) and out;
the master's controller cuts the displayed force along the handle's motion so its energy out
stays within both the slave's energy in as received and its own energy in (the hand's balance);
the slave's shortens a commanded step into the tissue to the master's energy in as received.
Loss and delay only ever leave a receiver with an older, smaller sum."""

from __future__ import annotations

import math

import pytest

from occ.haptics.passivity import EnergyAccount, MasterPort, OnePort, SlavePort

pytestmark = pytest.mark.req("SR-FORCE-1")


def test_an_account_splits_the_flow_and_its_budget_is_the_peers_energy_since_the_reset() -> None:
    a = EnergyAccount()
    a.flow(2e-3)  # in
    a.flow(-0.5e-3)  # out
    assert (a.e_in, a.session_in, a.e_out) == (2e-3, 2e-3, 0.5e-3)
    assert a.net == pytest.approx(1.5e-3)
    assert a.budget == pytest.approx(-0.5e-3)  # nothing received: out is a debt
    a.receive(3e-3)
    assert a.budget == pytest.approx(2.5e-3)
    a.reset()  # a new session: what the peer sent so far, and what this port gave, forgotten
    assert (a.budget, a.net, a.e_in) == (0.0, 0.0, 2e-3)
    a.receive(4e-3)
    assert a.budget == pytest.approx(1e-3)
    st = a.stats()
    assert st == {"in_mj": 0.0, "out_mj": 0.0, "budget_mj": 1.0, "peer_in_mj": 1.0,
                  "energy_mj": 0.0, "restarts": 0}  # fmt: skip


def test_a_lost_or_late_sample_only_leaves_an_older_smaller_budget() -> None:
    """The peer's sums only grow: whatever subset of its samples arrives, in order, the
    budget is never more than with all of them."""
    sent = [i * 1e-4 for i in range(50)]
    full, lossy = EnergyAccount(), EnergyAccount()
    for i, e in enumerate(sent):
        full.receive(e)
        if i % 7 not in (2, 3, 4):  # runs of three lost
            lossy.receive(e)
        assert lossy.budget <= full.budget
    assert lossy.received < full.received


def test_a_peer_whose_sum_went_down_started_afresh() -> None:
    a = EnergyAccount()
    a.receive(5e-3)
    a.flow(-4e-3)
    a.receive(1e-3)  # a restarted peer: not a budget of -4 mJ for ever, a new session
    assert a.restarts == 1 and a.budget == 0.0
    a.receive(1.5e-3)
    assert a.budget == pytest.approx(0.5e-3)


def test_energy_the_hand_puts_in_is_observed_exactly_and_the_force_left_alone() -> None:
    port = MasterPort()
    port.account.receive(1.0)  # plenty from the slave
    # pressing into the tissue: the force against the motion
    f = port.step((-2.0, 0.0, 0.0), (0.1, 0.0, 0.0), 0.001)
    assert f == (-2.0, 0.0, 0.0)
    port.displayed(f)
    port.observe((1e-4, 0.0, 0.0))  # the handle moved 0.1 mm under it
    assert port.account.e_in == pytest.approx(2e-4)
    assert port.account.e_out == 0.0 and port.active_ticks == 0


def test_the_force_is_cut_along_the_motion_to_the_smaller_of_the_two_bounds() -> None:
    port = MasterPort(max_damping=1e6)
    port.account.flow(3e-4)  # the hand put 0.3 mJ in
    port.account.receive(1e-4)  # the slave's tissue gave back 0.1 mJ
    v = (0.2, 0.0, 0.0)
    f = port.step((3.0, 1.0, 0.0), v, 0.001)  # would give 3 * 0.2 * 1 ms = 0.6 mJ
    allowed = 1e-4
    alpha = (6e-4 - allowed) / (0.04 * 0.001)
    assert port.last_damping == pytest.approx(alpha)
    assert f == pytest.approx((3.0 - alpha * 0.2, 1.0, 0.0))
    assert (f[0] * v[0]) * 0.001 == pytest.approx(allowed)  # exactly the budget goes out
    assert port.dissipated == pytest.approx(5e-4) and port.damped_ticks == 1
    # the other way round: the hand's own balance is the smaller
    port = MasterPort(max_damping=1e6)
    port.account.flow(1e-4)
    port.account.receive(5e-4)
    f = port.step((3.0, 0.0, 0.0), v, 0.001)
    assert f[0] * 0.2 * 0.001 == pytest.approx(1e-4)


def test_past_the_damping_cap_the_force_is_cut_never_more_than_its_component_along_the_motion() -> (
    None
):
    """A handle nearly at rest would need a huge damper; the controller cuts the force's
    component along the motion instead (counted apart), and never pushes the hand: the force
    it leaves along the motion is >= 0 whatever the budget (issue 37: a capped damper left the
    rest in the hand)."""
    port = MasterPort(max_damping=200.0)
    v = (1e-4, -1e-4, 0.0)
    f = port.step((5.0, -3.0, 2.0), v, 0.001)  # no budget at all
    assert port.last_damping > 200.0 and port.limited_ticks == 1 and port.damped_ticks == 0
    along = (f[0] * v[0] + f[1] * v[1]) / math.hypot(*v)
    assert along == pytest.approx(0.0, abs=1e-9)  # all of it cut, not reversed
    assert f[2] == 2.0  # across the motion: untouched
    port.account.flow(-1.0)  # a deficit: still no more than the force's own component is cut
    f = port.step((5.0, -3.0, 2.0), v, 0.001)
    along = (f[0] * v[0] + f[1] * v[1]) / math.hypot(*v)
    assert along == pytest.approx(0.0, abs=1e-9)


def test_no_cut_without_motion_or_time_and_against_the_motion_is_never_cut() -> None:
    port = MasterPort()
    assert port.step((1.0, 2.0, 3.0), (0.0, 0.0, 0.0), 0.001) == (1.0, 2.0, 3.0)
    assert port.step((1.0, 2.0, 3.0), (0.1, 0.0, 0.0), 0.0) == (1.0, 2.0, 3.0)
    assert port.step((-1.0, 0.0, 0.0), (0.1, 0.0, 0.0), 0.001) == (-1.0, 0.0, 0.0)
    assert port.active_ticks == 0


def test_the_observer_accounts_what_was_displayed_over_the_handles_displacement() -> None:
    port = MasterPort()
    port.displayed((2.0, 0.0, -1.0))
    port.observe((1e-3, 0.0, 1e-3))  # -f . dx = -(2e-3 - 1e-3): 1 mJ out to the hand
    assert port.account.e_out == pytest.approx(1e-3) and port.account.e_in == 0.0
    assert port.shown == (2.0, 0.0, -1.0)
    port.reset()
    assert port.shown == (0.0, 0.0, 0.0) and port.account.e_out == 0.0
    st = port.stats()
    assert {"energy_mj", "budget_mj", "dissipated_mj", "active_ticks", "damping",
            "force_limited_ticks", "damped_ticks"} <= set(st)  # fmt: skip


def test_the_slave_shortens_a_step_into_the_tissue_to_the_energy_the_hand_put_in() -> None:
    port = SlavePort()
    port.account.receive(2e-4)  # the hand put 0.2 mJ in (J at the instrument)
    force = (-4.0, 0.0, 3.0)  # the tissue pushes the tool out along (-0.8, 0, 0.6)
    step = (1e-4, 1e-4, -1e-4)  # into the tissue: -F . dx = 0.7 mJ out
    d = port.step(force, step)
    assert -(force[0] * d[0] + force[2] * d[2]) == pytest.approx(2e-4)
    assert d[1] == 1e-4  # across the force: untouched
    assert port.account.e_out == pytest.approx(2e-4) and port.limited == 1
    assert port.withheld == pytest.approx(5e-4)
    # no budget left: the next step into the tissue goes nowhere along the force
    d = port.step(force, step)
    assert force[0] * d[0] + force[2] * d[2] == pytest.approx(0.0, abs=1e-15)
    # out of the tissue: energy in, never shortened
    d = port.step(force, (-1e-4, 0.0, 1e-4))
    assert d == (-1e-4, 0.0, 1e-4)
    assert port.account.e_in == pytest.approx(7e-4)
    # free space: no force, no energy, any step
    assert port.step((0.0, 0.0, 0.0), (1e-3, 0.0, 0.0)) == (1e-3, 0.0, 0.0)


def test_the_torque_channels_one_port_damps_up_to_its_cap_and_observes_the_rest() -> None:
    """OnePort (the displayed torque, no energy from the peer): within ``max_damping`` the
    hand gets back no more than it put in; past it the damper stays at the cap, never more
    than the torque's component along the motion, and the excess shows as energy below 0."""
    v = (0.2, 0.0, 0.0)
    port = OnePort(max_damping=1e6)
    port.account.flow(1e-4)  # the hand put 0.1 mJ in
    t = port.step((3.0, 1.0, 0.0), v, 0.001)  # would give 0.6 mJ
    assert t[0] * 0.2 * 0.001 == pytest.approx(1e-4) and t[1] == 1.0
    assert port.account.net == pytest.approx(0.0, abs=1e-15)
    assert port.dissipated == pytest.approx(5e-4) and port.active_ticks == 1
    port = OnePort(max_damping=2.0)
    t = port.step((3.0, 1.0, 0.0), v, 0.001)
    assert port.last_damping == 2.0 and t == pytest.approx((3.0 - 2.0 * 0.2, 1.0, 0.0))
    assert port.dissipated == pytest.approx(2.0 * 0.04 * 0.001)
    assert port.account.net == pytest.approx(-(3.0 - 0.4) * 0.2 * 0.001)
    port = OnePort(max_damping=1e12)  # a handle nearly at rest: the component along, no more
    t = port.step((3.0, 1.0, 0.0), (1e-6, 0.0, 0.0), 0.001)
    assert t == pytest.approx((0.0, 1.0, 0.0), abs=1e-12)
    assert port.step((1.0, 2.0, 3.0), (0.0, 0.0, 0.0), 0.001) == (1.0, 2.0, 3.0)
