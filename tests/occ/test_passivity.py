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


# ------------------------------------------------------------------ three axes, number by number
F = (1.0, 2.0, 3.0)
V = (0.1, 0.2, 0.3)  # f . v = 1.4 W
DT = 0.01  # 14 mJ over the tick


def _dot(a: tuple[float, float, float], b: tuple[float, float, float]) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def test_an_energy_sent_with_the_samples_is_finite_and_not_negative() -> None:
    from occ.haptics.passivity import parse_energy

    assert parse_energy("0") == 0.0 and parse_energy("1.5e-3") == 1.5e-3
    for bad in ("-1e-9", "-1", "inf", "nan", "-inf", "1 mJ", ""):
        assert parse_energy(bad) is None, bad


def test_an_account_counts_each_sample_and_each_restart_and_sums_every_flow() -> None:
    a = EnergyAccount()
    assert a.received == 0
    a.receive(2e-3)
    a.receive(2e-3)  # the same sum again: no restart
    assert (a.received, a.restarts) == (2, 0)
    a.receive(1e-3)
    a.receive(0.5e-3)
    assert (a.received, a.restarts) == (4, 2)
    b = EnergyAccount()
    b.flow(1e-3)
    b.flow(2e-3)
    b.flow(-0.25e-3)
    b.flow(-0.5e-3)
    assert (b.e_in, b.e_out) == (pytest.approx(3e-3), pytest.approx(0.75e-3))
    b.receive(5e-3)
    b.reset()
    b.receive(7.123456e-3)
    b.flow(1.23456789e-3)
    b.flow(-0.5e-3)
    assert b.stats() == {
        "in_mj": 1.2346,
        "out_mj": 0.5,
        "budget_mj": 1.6235,
        "peer_in_mj": 2.1235,
        "energy_mj": 0.7346,
        "restarts": 0,
    }


def test_the_masters_cut_on_three_axes_gives_exactly_the_allowed_energy() -> None:
    port = MasterPort()
    assert port.max_damping == 200.0  # N s/m, the default cap
    assert port.shown == (0.0, 0.0, 0.0)
    port.observe((0.1, 0.2, 0.3))  # nothing displayed yet: no work
    assert port.account.e_in == 0.0 and port.account.e_out == 0.0
    assert port.stats() == {
        "in_mj": 0.0, "out_mj": 0.0, "budget_mj": 0.0, "peer_in_mj": 0.0, "energy_mj": 0.0,
        "restarts": 0, "dissipated_mj": 0.0, "active_ticks": 0, "damped_ticks": 0,
        "force_limited_ticks": 0, "damping": 0.0,
    }  # fmt: skip
    port.account.receive(4e-3)  # the slave's budget: 4 mJ
    port.account.flow(6e-3)  # the hand's own: 6 mJ
    f = port.step(F, V, DT)
    assert _dot(f, V) * DT == pytest.approx(4e-3)  # the smaller bound, exactly
    alpha = (14e-3 - 4e-3) / (0.14 * DT)
    assert port.last_damping == pytest.approx(alpha)
    assert f == pytest.approx(tuple(fi - alpha * vi for fi, vi in zip(F, V, strict=True)))
    assert port.dissipated == pytest.approx(10e-3)
    assert (port.active_ticks, port.damped_ticks, port.limited_ticks) == (1, 1, 0)
    port.step(F, V, DT)  # nothing out allowed since (the account is not fed here): cut again
    assert port.dissipated == pytest.approx(10e-3 + 14e-3 - 4e-3)
    assert (port.active_ticks, port.damped_ticks, port.limited_ticks) == (2, 2, 0)
    st = port.stats()
    assert (st["dissipated_mj"], st["active_ticks"], st["damped_ticks"]) == (20.0, 2, 2)
    assert st["damping"] == round(alpha, 3) and st["force_limited_ticks"] == 0
    port.reset()
    assert port.last_damping == 0.0 and port.shown == (0.0, 0.0, 0.0)


def test_the_masters_damper_at_its_cap_is_counted_damped_beyond_it_limited() -> None:
    alpha = 14e-3 / (0.14 * DT)  # nothing allowed: the whole 14 mJ cut
    at_cap = MasterPort(max_damping=alpha)
    at_cap.step(F, V, DT)
    assert at_cap.last_damping == alpha and (at_cap.damped_ticks, at_cap.limited_ticks) == (1, 0)
    below = MasterPort(max_damping=1.0)
    below.step(F, V, DT)
    below.step(F, V, DT)
    assert (below.damped_ticks, below.limited_ticks, below.active_ticks) == (0, 2, 2)
    assert below.stats()["force_limited_ticks"] == 2


def test_a_force_across_the_motion_is_not_cut_nor_counted() -> None:
    """No energy either way (f . v = 0) with nothing allowed: nothing to cut."""
    port = MasterPort()
    assert port.step((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), DT) == (1.0, 0.0, 0.0)
    assert (port.active_ticks, port.last_damping) == (0, 0.0)
    one = OnePort()
    assert one.step((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), DT) == (1.0, 0.0, 0.0)
    assert (one.active_ticks, one.last_damping) == (0, 0.0)
    slave = SlavePort()
    assert slave.step((0.0, 0.0, 0.0), (1e-3, 0.0, 0.0)) == (1e-3, 0.0, 0.0)
    assert slave.limited == 0


def test_the_one_port_on_three_axes_observes_and_cuts_exactly() -> None:
    port = OnePort()
    assert port.max_damping == 2.0  # N m s/rad, the default cap
    assert port.stats() == {
        "in_mj": 0.0, "out_mj": 0.0, "budget_mj": 0.0, "peer_in_mj": 0.0, "energy_mj": 0.0,
        "restarts": 0, "dissipated_mj": 0.0, "active_ticks": 0, "damping": 0.0,
    }  # fmt: skip
    port.observe((-1.0, -2.0, -3.0), V, DT)  # the hand drove against it: 14 mJ in
    assert port.account.e_in == pytest.approx(14e-3) and port.account.e_out == 0.0
    # within the hand's balance: returned as it is, its work observed
    t = port.step((0.5, 1.0, 1.5), V, DT)  # 7 mJ out
    assert t == (0.5, 1.0, 1.5) and port.last_damping == 0.0
    assert port.account.e_out == pytest.approx(7e-3)
    # 14 mJ asked, 7 mJ left: cut along the motion to exactly the balance
    big = OnePort(max_damping=1e6)
    big.observe((-1.0, -2.0, -3.0), V, DT)
    big.account.flow(-7e-3)
    t = big.step(F, V, DT)
    assert _dot(t, V) * DT == pytest.approx(7e-3)
    alpha = 7e-3 / (0.14 * DT)
    assert big.last_damping == pytest.approx(alpha)
    assert t == pytest.approx(tuple(fi - alpha * vi for fi, vi in zip(F, V, strict=True)))
    assert big.dissipated == pytest.approx(7e-3)
    big.step(F, V, DT)  # nothing left: the whole component along the motion
    assert big.dissipated == pytest.approx(21e-3) and big.active_ticks == 2
    st = big.stats()
    assert (st["dissipated_mj"], st["active_ticks"]) == (21.0, 2)
    assert st["damping"] == round(14e-3 / (0.14 * DT), 4)
    # past what is along the motion, never more: a near-still handle on three axes
    near = OnePort(max_damping=1e12)
    v = (1e-6, 2e-6, -1e-6)
    t = near.step(F, v, DT)
    assert _dot(t, v) == pytest.approx(0.0, abs=1e-18)
    along = _dot(F, v) / _dot(v, v)
    assert t == pytest.approx(tuple(fi - along * vi for fi, vi in zip(F, v, strict=True)))
    big.reset()
    assert big.last_damping == 0.0


def test_the_slave_port_on_three_axes_and_a_budget_spent_before() -> None:
    port = SlavePort()
    assert port.stats() == {
        "in_mj": 0.0, "out_mj": 0.0, "budget_mj": 0.0, "peer_in_mj": 0.0, "energy_mj": 0.0,
        "restarts": 0, "withheld_mj": 0.0, "limited_ticks": 0,
    }  # fmt: skip
    port.account.receive(4e-3)
    force = (-1.0, -2.0, -3.0)
    step = (1e-3, 2e-3, 3e-3)  # into the tissue: 14 mJ
    d = port.step(force, step)
    assert -_dot(force, d) == pytest.approx(4e-3)
    c = 10e-3 / 14.0
    assert d == pytest.approx(tuple(s + c * f for s, f in zip(step, force, strict=True)))
    assert port.account.e_out == pytest.approx(4e-3)
    port.step(force, step)  # nothing left: 14 mJ withheld more
    assert port.withheld == pytest.approx(24e-3) and port.limited == 2
    st = port.stats()
    assert (st["withheld_mj"], st["limited_ticks"], st["out_mj"]) == (24.0, 2, 4.0)
    # a budget already overspent (negative) allows nothing, not a negative step
    spent = SlavePort()
    spent.account.flow(-1e-3)
    d = spent.step(force, step)
    assert _dot(force, d) == pytest.approx(0.0, abs=1e-15) and spent.limited == 1
    # out of the tissue on three axes: energy in, as given
    back = SlavePort()
    assert back.step(force, (-1e-3, -2e-3, -3e-3)) == (-1e-3, -2e-3, -3e-3)
    assert back.account.e_in == pytest.approx(14e-3)


def test_the_statistics_give_millijoules_to_four_places_and_the_damping_as_documented() -> None:
    third = 1e-3 / 3.0  # s: a third of a millisecond
    master = MasterPort()
    master.step((1.0, 0.0, 0.0), (1.0, 0.0, 0.0), third)  # a third of a mJ, none allowed
    st = master.stats()
    assert (st["dissipated_mj"], st["damping"]) == (0.3333, 1.0)
    master.account.flow(-third)
    assert master.stats()["out_mj"] == 0.3333
    one = OnePort(max_damping=1.0 / 3.0)  # the cap binds: a third of the torque along
    one.step((1.0, 0.0, 0.0), (1.0, 0.0, 0.0), third)
    st = one.stats()
    assert (st["damping"], st["dissipated_mj"]) == (0.3333, 0.1111)
    slave = SlavePort()
    slave.step((-1.0, 0.0, 0.0), (third, 0.0, 0.0))  # a third of a mJ into the tissue, none allowed
    assert slave.stats()["withheld_mj"] == 0.3333
