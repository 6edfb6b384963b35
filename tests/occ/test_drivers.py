"""Driver registry, the base lifecycle and limit policy, and the simulated driver's dynamics."""

from __future__ import annotations

import gc
import math
import random
import re
from collections.abc import Sequence

import pytest

import occ.drivers as drivers
from occ.drivers import Driver, DriverState, available_drivers, create_driver, register_driver
from occ.drivers.sim import SimDriver
from occ.errors import DriverError, LimitError, StateError
from occ.joint import Joint, JointLimits, PIDGains


def joints(n: int = 2, velocity: float = 100.0, gains: PIDGains | None = None) -> list[Joint]:
    return [
        Joint(f"j{i}", "revolute", JointLimits(-1.0, 1.0, velocity, 50.0), gains=gains)
        for i in range(n)
    ]


class MirrorDriver(Driver):
    """ros2_control's mock system: commands become states. Records hook calls."""

    supported_interfaces = ("position", "effort")

    def __init__(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        super().__init__(*args, **kwargs)
        self.calls: list[str] = []
        self.last: list[float] = [j.home for j in self.joints]
        self.fail_read = False

    def _configure(self) -> None:
        self.calls.append("configure")

    def _activate(self) -> None:
        self.calls.append("activate")

    def _deactivate(self) -> None:
        self.calls.append("deactivate")

    def _shutdown(self) -> None:
        self.calls.append("shutdown")

    def _read(self, now: float) -> tuple[Sequence[float], Sequence[float], Sequence[float]]:
        if self.fail_read:
            raise OSError("bus gone")
        n = len(self.last)
        return self.last, [0.0] * n, [0.0] * n

    def _write(self, values: Sequence[float], now: float) -> None:
        self.last = list(values)


def test_write_effort_direct_clamped_and_checked() -> None:
    d = MirrorDriver("m", joints(), command_interface="effort")
    d.configure()
    with pytest.raises(StateError):
        d.write_effort([1.0, 1.0], 0.0)  # not ACTIVE
    d.activate()
    d.write_effort([3.0, -80.0], 0.001)  # the effort limit is 50
    assert d.last == [3.0, -50.0] and d.stats()["limit_events"] == 1
    assert [j.command_effort for j in d.joints] == [3.0, -50.0]
    with pytest.raises(LimitError):
        d.write_effort([math.nan, 0.0], 0.002)
    assert d.state is DriverState.FAULT
    d.shutdown()
    p = MirrorDriver("p", joints())
    p.configure()
    p.activate()
    with pytest.raises(StateError, match="not efforts"):
        p.write_effort([0.0, 0.0], 0.0)  # a position driver takes no efforts
    p.shutdown()


# ---------------------------------------------------------------------------- registry
def test_registry_builtins_and_unknown_name() -> None:
    names = available_drivers()
    assert {"sim", "can"} <= set(names)
    with pytest.raises(DriverError, match="known: .*sim"):
        create_driver("nope", "x", joints())


def test_register_driver_class_and_lazy_string() -> None:
    register_driver("mirror", MirrorDriver)
    d = create_driver("mirror", "m", joints())
    assert isinstance(d, MirrorDriver) and "mirror" in available_drivers()
    register_driver("lazy_mirror", "tests.occ.test_drivers:MirrorDriver")
    assert drivers.load_driver_class("lazy_mirror").__name__ == "MirrorDriver"
    register_driver("broken", "no_such_module_xyz:Driver")
    with pytest.raises(DriverError, match="cannot import") as info:
        create_driver("broken", "b", joints())
    assert isinstance(info.value.__cause__, ImportError)
    with pytest.raises(ValueError):
        register_driver("bad", "not-a-target")


def test_entry_points_are_read_lazily(monkeypatch: pytest.MonkeyPatch) -> None:
    from importlib.metadata import EntryPoint

    fake = [
        EntryPoint("extdrv", "tests.occ.test_drivers:MirrorDriver", "occ.drivers"),
        EntryPoint("sim", "evil:Driver", "occ.drivers"),  # may not shadow a built-in
    ]
    from occ import plugins

    monkeypatch.setattr(drivers._REGISTRY, "_entry_point_table", None)
    monkeypatch.setattr(plugins, "entry_points", lambda group: fake)
    assert "extdrv" in available_drivers()
    assert drivers.load_driver_class("extdrv") is MirrorDriver
    assert drivers.load_driver_class("sim") is SimDriver


# ---------------------------------------------------------------------------- lifecycle
def test_lifecycle_and_state_errors() -> None:
    d = MirrorDriver("m", joints())
    assert d.state is DriverState.UNCONFIGURED
    with pytest.raises(StateError):
        d.read(0.0)
    with pytest.raises(StateError):
        d.activate()
    d.configure()
    d.read(0.0)  # INACTIVE: states readable
    with pytest.raises(StateError, match="refused"):
        d.write([0.0, 0.0], 0.0)
    d.activate()
    d.write([0.0, 0.0], 0.001)
    d.deactivate()
    assert d.state is DriverState.INACTIVE
    d.shutdown()
    d.shutdown()  # safe twice
    assert d.state is DriverState.SHUTDOWN
    assert d.calls == ["configure", "activate", "deactivate", "shutdown"]
    assert d.stats() == {"reads": 1, "writes": 1, "limit_events": 0, "errors": 0, "safe_stops": 0}


def test_context_manager_shuts_down_active_driver() -> None:
    with MirrorDriver("m", joints()) as d:
        d.configure()
        d.activate()
    assert d.state is DriverState.SHUTDOWN and d.calls[-2:] == ["deactivate", "shutdown"]


@pytest.mark.req("SR-SAFE-1")
def test_hook_error_latches_fault_until_reset() -> None:
    d = MirrorDriver("m", joints())
    d.configure()
    d.activate()
    d.fail_read = True
    with pytest.raises(DriverError, match="read failed") as info:
        d.read(0.0)
    assert isinstance(info.value.__cause__, OSError)
    assert d.state is DriverState.FAULT and "bus gone" in (d.fault_reason or "")
    assert d.calls[-1] == "deactivate"  # hardware told to stop on fault
    with pytest.raises(StateError, match="reset"):
        d.activate()
    d.fail_read = False
    d.reset()
    assert d.state is DriverState.INACTIVE and d.stats()["errors"] == 1
    d.activate()
    d.shutdown()


def test_bad_arguments() -> None:
    with pytest.raises(ValueError):
        MirrorDriver("m", joints(), on_limit="ignore")  # type: ignore[arg-type]
    # an effort driver without PID gains takes direct efforts only (a haptic master)
    e = MirrorDriver("m", joints(), command_interface="effort")
    assert e.missing_gains == ["j0", "j1"]
    e.configure()
    e.activate()
    with pytest.raises(ValueError, match="PID gains"):
        e.write([0.0, 0.0], 0.0)
    e.shutdown()
    with pytest.raises(ValueError, match="duplicate"):
        MirrorDriver("m", [Joint("a"), Joint("a")])
    d = MirrorDriver("m", joints())
    d.configure()
    d.activate()
    with pytest.raises(ValueError, match="expected 2"):
        d.write([0.0], 0.0)
    d.shutdown()


# ---------------------------------------------------------------------------- limits
def active(on_limit: str, velocity: float = 100.0) -> MirrorDriver:
    d = MirrorDriver("m", joints(velocity=velocity), on_limit=on_limit)  # type: ignore[arg-type]
    d.configure()
    d.read(0.0)
    d.activate()
    return d


@pytest.mark.req("SR-LIM-1")
def test_clamp_position_counts_events() -> None:
    d = active("clamp")
    d.write([1.5, -0.5], 0.001)
    assert d.last == [pytest.approx(0.1), -0.1]  # position clamp, then velocity ramp 100 rad/s
    d = active("clamp", velocity=1e6)
    d.write([1.5, -2.0], 0.001)
    assert d.last == [1.0, -1.0] and d.stats()["limit_events"] == 2
    assert d.joints[0].command_position == 1.0


@pytest.mark.req("SR-LIM-2")
def test_clamp_velocity_against_previous_setpoint() -> None:
    d = active("clamp", velocity=1.0)  # 1 rad/s -> 1 mrad per 1 ms tick
    d.write([0.0, 0.0], 0.001)
    d.write([0.5, -0.0005], 0.002)
    assert d.last[0] == pytest.approx(0.001) and d.last[1] == pytest.approx(-0.0005)
    d.write([0.5, 0.0], 0.004)  # 2 ms later: 2 mrad allowed
    assert d.last[0] == pytest.approx(0.003)
    assert d.stats()["limit_events"] == 2


@pytest.mark.req("SR-LIM-1")
def test_fault_policy_raises_limit_error_and_latches() -> None:
    d = active("fault")
    with pytest.raises(LimitError, match=r"joint j1: position 1\.2 outside limits \[-1, 1\]"):
        d.write([0.0, 1.2], 0.001)
    assert d.state is DriverState.FAULT
    with pytest.raises(StateError):
        d.write([0.0, 0.0], 0.002)
    d.reset()
    d.activate()
    d.write([0.0, 0.0], 0.003)
    with pytest.raises(LimitError, match="velocity 500 exceeds limit 100"):
        d.write([0.5, 0.0], 0.004)


@pytest.mark.req("SR-LIM-1")
def test_first_write_after_activation_is_checked_against_measurement() -> None:
    d = active("fault")
    with pytest.raises(LimitError, match="velocity"):
        d.write([0.9, 0.0], 0.0)  # 0.9 rad in one 1 ms period from the measured 0


@pytest.mark.req("SR-LIM-1")
def test_one_mrad_past_either_position_limit_is_over() -> None:
    d = active("fault", velocity=1e6)
    d.write([1.0, -1.0], 0.001)  # on the limits: allowed
    assert d.last == [1.0, -1.0] and d.stats()["limit_events"] == 0
    for bad in ([1.001, 0.0], [0.0, -1.001]):
        d = active("fault", velocity=1e6)
        with pytest.raises(LimitError, match="outside limits"):
            d.write(bad, 0.001)
        assert d.state is DriverState.FAULT
    d = active("clamp", velocity=1e6)
    d.write([1.001, -1.001], 0.001)
    assert d.last == [1.0, -1.0] and d.stats()["limit_events"] == 2


@pytest.mark.req("SR-LIM-2")
def test_one_percent_past_the_velocity_limit_is_over() -> None:
    d = active("fault", velocity=1.0)  # 1 mrad per 1 ms tick
    d.write([0.00099, -0.00099], 0.001)  # just inside
    assert d.stats()["limit_events"] == 0
    with pytest.raises(LimitError, match="velocity"):
        d.write([0.00099 + 0.00101, 0.0], 0.002)
    d = active("clamp", velocity=1.0)
    d.write([0.00101, -0.00101], 0.001)
    assert d.last == [pytest.approx(0.001), pytest.approx(-0.001)]
    assert d.stats()["limit_events"] == 2


@pytest.mark.req("SR-LIM-2")
def test_a_step_of_exactly_the_velocity_limit_is_allowed() -> None:
    # binary-exact numbers: 0.5 rad in 0.5 s at 1 rad/s is on the limit, either way
    d = active("fault", velocity=1.0)
    d.write([0.0, 0.0], 0.5)
    d.write([0.5, -0.5], 1.0)
    assert d.last == [0.5, -0.5] and d.stats()["limit_events"] == 0


@pytest.mark.req("SR-LIM-2")
def test_the_first_write_is_checked_only_against_a_measured_position() -> None:
    # nothing read yet: no reference to take a velocity from (the position limits still hold)
    d = MirrorDriver("m", joints(velocity=1.0), on_limit="fault")
    d.configure()
    d.activate()
    d.write([0.9, -0.9], 0.001)
    assert d.last == [0.9, -0.9] and d.stats()["limit_events"] == 0
    d.shutdown()


@pytest.mark.req("SR-LIM-2")
def test_no_time_means_no_motion() -> None:
    # a second write at the same instant, or one whose clock went back, may not move
    d = active("fault", velocity=1.0)
    d.write([0.0, 0.0], 0.002)
    with pytest.raises(LimitError, match="velocity inf exceeds limit 1"):
        d.write([0.001, 0.0], 0.002)
    d = active("clamp", velocity=1.0)
    d.write([0.0, 0.0], 0.002)
    d.write([0.5, -0.5], 0.001)  # the clock went back 1 ms
    d.write([0.5, -0.5], 0.001)
    assert d.last == [0.0, 0.0] and d.stats()["limit_events"] == 4


@pytest.mark.req("SR-SAFE-1")
def test_a_write_hook_that_raises_faults_with_its_error() -> None:
    d = active("fault")

    def broken(values: Sequence[float], now: float) -> None:
        raise OSError("bus off")

    d._write = broken  # type: ignore[method-assign]
    with pytest.raises(DriverError, match=r"driver 'm': write failed: OSError\('bus off'\)"):
        d.write([0.0, 0.0], 0.001)
    assert d.state is DriverState.FAULT and d.stats()["errors"] == 1


@pytest.mark.req("SR-LIM-3")
def test_non_finite_setpoint_always_faults() -> None:
    d = active("clamp")
    with pytest.raises(LimitError):
        d.write([math.nan, 0.0], 0.001)
    assert d.state is DriverState.FAULT


def test_effort_interface_uses_joint_pid() -> None:
    gains = PIDGains(kp=10.0)
    d = MirrorDriver("m", joints(gains=gains), command_interface="effort")
    d.configure()
    d.read(0.0)
    d.activate()
    d.write([0.05, -0.02], 0.001)
    assert d.last == [pytest.approx(0.5), pytest.approx(-0.2)]


# ---------------------------------------------------------------------------- sim dynamics
def run_step(params: dict, step: float = 0.01, ticks: int = 400) -> tuple[list[float], SimDriver]:
    js = joints(1)
    d = create_driver("sim", "sim", js, params)
    assert isinstance(d, SimDriver)
    d.configure()
    d.read(0.0)
    d.activate()
    trace = []
    for k in range(ticks):
        now = k * 0.001
        d.read(now)
        trace.append(js[0].position)
        d.write([step], now)
    d.shutdown()
    return trace, d


def settling_time(trace: list[float], final: float, band: float) -> float:
    last_out = max(i for i, x in enumerate(trace) if abs(x - final) > band * abs(final))
    return (last_out + 1) * 0.001


@pytest.mark.parametrize("bandwidth", [5.0, 10.0, 20.0])
def test_sim_step_settles_at_bandwidth_implied_time(bandwidth: float) -> None:
    # Critically damped 2nd order: 2 % settling at wn * t = 5.834 (1 - (1 + x) e^-x = 0.98).
    trace, _ = run_step({"bandwidth_hz": bandwidth, "encoder_resolution": 0.0}, ticks=600)
    expected = 5.834 / (2 * math.pi * bandwidth)
    assert settling_time(trace, 0.01, 0.02) == pytest.approx(expected, rel=0.06)
    assert max(trace) <= 0.01 * 1.001  # no overshoot at zeta = 1


def test_sim_underdamped_overshoot() -> None:
    trace, _ = run_step({"damping_ratio": 0.5, "encoder_resolution": 0.0})
    overshoot = max(trace) / 0.01 - 1.0
    assert overshoot == pytest.approx(math.exp(-math.pi * 0.5 / math.sqrt(0.75)), abs=0.01)


def test_sim_encoder_quantisation() -> None:
    trace, d = run_step({"encoder_resolution": 0.001}, step=0.0123)
    assert all(abs(x / 0.001 - round(x / 0.001)) < 1e-9 for x in trace)
    assert trace[-1] == pytest.approx(0.012)
    assert d.true_positions[0] == pytest.approx(0.0123, abs=1e-6)


def test_sim_deterministic_with_seed_and_simulated_clock() -> None:
    a, _ = run_step({"noise_std": 1e-4, "seed": 7})
    b, _ = run_step({"noise_std": 1e-4, "seed": 7})
    c, _ = run_step({"noise_std": 1e-4, "seed": 8})
    assert a == b and a != c


def test_sim_substeps_make_large_dt_equivalent() -> None:
    js = joints(1)
    d = SimDriver("s", js, {"encoder_resolution": 0.0, "heartbeat_ms": 0})
    d.configure()
    d.read(0.0)
    d.activate()
    d.write([0.01], 0.0)
    d.read(0.5)  # one big jump: integrated in substeps, stays stable
    assert js[0].position == pytest.approx(0.01, abs=1e-5)
    assert d.substep <= 0.0005


@pytest.mark.parametrize("zeta", [0.3, 1.0, 2.5])
def test_sim_exact_step_matches_the_analytic_servo_response(zeta: float) -> None:
    """Inside its effort limit a servoed joint moves in one exact step per tick: the response
    to a small step is the closed-loop second-order system's, to float precision, at every
    tick (what the substep integrator approximated to about 1 %)."""
    wn = 2 * math.pi * 10.0
    trace, d = run_step({"damping_ratio": zeta, "encoder_resolution": 0.0}, step=0.001, ticks=300)
    assert d._step_h == pytest.approx(0.001)  # the exact path ran (cached for 1 ms)

    def analytic(t: float) -> float:  # unit step response of wn^2 / (s^2 + 2 zeta wn s + wn^2)
        if zeta < 1.0:
            wd = wn * math.sqrt(1 - zeta * zeta)
            return 1 - math.exp(-zeta * wn * t) * (
                math.cos(wd * t) + zeta * wn / wd * math.sin(wd * t)
            )
        if zeta == 1.0:
            return 1 - (1 + wn * t) * math.exp(-wn * t)
        r = math.sqrt(zeta * zeta - 1)
        p1, p2 = -wn * (zeta - r), -wn * (zeta + r)
        return 1 + (p2 * math.exp(p1 * t) - p1 * math.exp(p2 * t)) / (p1 - p2)

    # trace[k] is read at k ms; the step was first commanded at 0 ms
    for k, x in enumerate(trace):
        assert x == pytest.approx(0.001 * analytic(k * 0.001), abs=1e-12)


def test_sim_exact_step_with_jittered_ticks_matches_the_analytic_servo_response() -> None:
    """Ticks that start up to 100 µs late (as a real loop's): the servo's response read at
    each tick's own time is the analytic one, as with exact ticks."""
    import random

    wn, zeta = 2 * math.pi * 10.0, 0.7
    js = joints(1)
    d = create_driver("sim", "sim", js, {"damping_ratio": zeta, "encoder_resolution": 0.0})
    d.configure()
    d.read(0.0)
    d.activate()
    rng = random.Random(3)
    wd = wn * math.sqrt(1 - zeta * zeta)
    for k in range(300):
        now = 0.0 if k == 0 else k * 0.001 + rng.uniform(0.0, 100e-6)
        d.read(now)
        want = 0.001 * (
            1
            - math.exp(-zeta * wn * now)
            * (math.cos(wd * now) + zeta * wn / wd * math.sin(wd * now))
        )
        assert js[0].position == pytest.approx(want, abs=1e-11)
        d.write([0.001], now)


def _underdamped(e0: float, zeta: float, wn: float, t: float) -> float:
    """e(t) of e'' + 2 zeta wn e' + wn^2 e = 0 from rest at e0 (zeta < 1)."""
    wd = wn * math.sqrt(1 - zeta * zeta)
    return e0 * math.exp(-zeta * wn * t) * (math.cos(wd * t) + zeta * wn / wd * math.sin(wd * t))


def test_sim_joints_with_different_poles_each_get_their_own_exact_step() -> None:
    """Joints share one exact step only when their poles are the same: two bandwidths, two
    analytic responses, jittered ticks."""
    import random

    zeta = 0.7
    js = joints(3)
    d = create_driver(
        "sim",
        "sim",
        js,
        {"damping_ratio": zeta, "encoder_resolution": 0.0, "bandwidth_hz": [10.0, 25.0, 10.0]},
    )
    d.configure()
    d.read(0.0)
    d.activate()
    rng = random.Random(5)
    for k in range(200):
        now = 0.0 if k == 0 else k * 0.001 + rng.uniform(0.0, 100e-6)
        d.read(now)
        for j, f in zip(js, (10.0, 25.0, 10.0), strict=True):
            want = 0.001 + _underdamped(-0.001, zeta, 2 * math.pi * f, now)
            assert j.position == pytest.approx(want, abs=1e-11)
        d.write([0.001, 0.001, 0.001], now)


def test_sim_hand_exact_step_matches_the_analytic_handle_response() -> None:
    """The simulated hand (no intended motion, a constant displayed effort): the handle is a
    mass on the hand's spring-damper, m x'' = u + K (x0 - x) - (B + b) x'. Read at jittered
    tick times it follows the analytic response, effort on and off."""
    import random

    m, b, kh, bh, u = 0.5, 1.0, 300.0, 20.0, 2.0
    js = [Joint("x", type="prismatic", limits=JointLimits(-1.0, 1.0, velocity=10.0, effort=20.0))]
    d = create_driver(
        "sim-hand",
        "hand",
        js,
        {
            "inertia": m,
            "damping": b,
            "hand_stiffness": kh,
            "hand_damping": bh,
            "intent_amplitude": [0.0],
            "intent_phase_deg": [0.0],
            "intent_offset": [0.0],
            "encoder_resolution": 0.0,
            "heartbeat_ms": 0,
        },
    )
    d.configure()
    d.read(0.0)
    d.activate()
    wn = math.sqrt(kh / m)
    zeta = (bh + b) / m / (2 * wn)
    rng = random.Random(7)
    d.write_effort([u], 0.0)
    for k in range(1, 400):
        now = k * 0.001 + rng.uniform(0.0, 100e-6)
        d.read(now)
        want = u / kh + _underdamped(-u / kh, zeta, wn, now)
        assert js[0].position == pytest.approx(want, abs=1e-11)
        d.write_effort([u], now)


def test_sim_saturating_step_falls_back_to_substeps_and_reports_the_limit() -> None:
    """A step too big for the effort limit is not linear: the interval is integrated in
    substeps and the effort reported is the limit."""
    js = [Joint("j", limits=JointLimits(-1.0, 1.0, velocity=100.0, effort=0.5))]
    d = SimDriver("s", js, {"encoder_resolution": 0.0, "heartbeat_ms": 0})
    d.configure()
    d.read(0.0)
    d.activate()
    d.write([0.5], 0.0)
    d.read(0.001)
    assert js[0].effort == pytest.approx(0.5)  # saturated
    assert 0.0 < js[0].position < 0.001


def test_sim_common_read_reports_what_the_general_path_does() -> None:
    """The servoed drive's common interval is read in one pass (model step and encoder
    together); a drive forced through the general path (a world that applies no load) must
    read the same, saturated joints, end stops and the encoder's quantum included."""

    class NoLoad:
        def efforts(self, q: list[float], qd: list[float]) -> None:
            return None

    def trace(world: object) -> list[tuple[float, ...]]:
        js = [
            Joint("a", limits=JointLimits(-1.0, 1.0, velocity=100.0, effort=0.5)),
            Joint("b", limits=JointLimits(-0.02, 0.02, velocity=100.0, effort=50.0)),
            Joint("c", type="prismatic", limits=JointLimits(0.0, 0.1, velocity=1.0, effort=50.0)),
        ]
        # a saturated servo cannot follow and one at its end stop does not move: the feedback
        # checks that judge this (following error, frozen) are tested elsewhere
        params = {
            "encoder_resolution": [1e-4, 2e-5, 0.0],
            "heartbeat_ms": 0,
            "following_error": None,
            "frozen_feedback_ms": 0,
        }
        d = SimDriver("s", js, params)
        d.environment = world
        d.configure()
        d.read(0.0)
        d.activate()
        rng = random.Random(3)
        out = []
        for k in range(1, 400):
            now = k * 0.001 + rng.uniform(0.0, 3e-5)
            d.read(now)
            out.append(tuple(j.position for j in js) + tuple(j.effort for j in js))
            target = 0.3 if k < 200 else -0.3  # saturates a; b runs into its end stop
            d.write([target, 0.05 if k < 200 else 0.0, 0.05], now)
        d.shutdown()
        return out

    fast, general = trace(None), trace(NoLoad())
    # the same to the last bit but for rounding: the general path forms the effort from the
    # position, the common one from the error (x - r)
    assert [row[:3] for row in fast] == [row[:3] for row in general]
    assert [row[3:] for row in fast] == [
        pytest.approx(row[3:], rel=1e-12, abs=1e-15) for row in general
    ]
    assert any(abs(row[3]) == pytest.approx(0.5) for row in fast)  # a saturated
    assert max(row[1] for row in fast) == pytest.approx(0.02)  # b at its end stop
    assert all(abs(row[0] / 1e-4 - round(row[0] / 1e-4)) < 1e-6 for row in fast)


def test_sim_effort_interface_tracks_with_pid() -> None:
    gains = PIDGains(kp=4.0, ki=2.0, kd=0.2)
    js = joints(1, gains=gains)
    d = create_driver("sim", "s", js, {"command_interface": "effort", "encoder_resolution": 0.0})
    d.configure()
    d.read(0.0)
    d.activate()
    for k in range(2000):
        d.read(k * 0.001)
        d.write([0.1], k * 0.001)
    assert js[0].position == pytest.approx(0.1, abs=2e-3)
    d.shutdown()


def test_sim_brakes_hold_when_inactive_and_params_are_validated() -> None:
    js = joints(1)
    d = SimDriver("s", js, {"initial_positions": [0.3], "encoder_resolution": 0.0})
    d.configure()
    d.read(0.0)
    d.read(1.0)
    assert js[0].position == 0.3 and js[0].velocity == 0.0
    with pytest.raises(ValueError, match="unknown params"):
        SimDriver("s", joints(1), {"bandwidth": 3})
    with pytest.raises(ValueError, match="expected 1 values"):
        SimDriver("s", joints(1), {"inertia": [1.0, 2.0]})


def test_sim_per_joint_mapping_params() -> None:
    js = [
        Joint("rot", "revolute", JointLimits(-1.0, 1.0, 100.0, 50.0)),
        Joint("lin", "prismatic", JointLimits(0.0, 0.1, 1.0, 50.0)),
    ]
    params = {"encoder_resolution": {"rot": 0.01}, "initial_positions": {"lin": 0.05}}
    d = SimDriver("s", js, params)
    d.configure()
    d.read(0.0)
    assert js[0].position == 0.0 and js[1].position == pytest.approx(0.05)
    assert d._resolution == [0.01, 1e-6]
    d.shutdown()


# -- device-side heartbeat and safe stop ----------------------------------------------------


@pytest.mark.req("SR-HB-1")
def test_sim_drive_stops_itself_without_heartbeat_and_reports_it() -> None:
    js = joints(1)
    d = SimDriver("s", js, {"encoder_resolution": 0.0, "heartbeat_ms": 20, "bandwidth_hz": 30.0})
    ref = SimDriver(
        "r", joints(1), {"encoder_resolution": 0.0, "heartbeat_ms": 0, "bandwidth_hz": 30.0}
    )
    for drv in (d, ref):
        drv.configure()
        drv.read(0.0)
        drv.activate()
    # both follow a ramp for 100 ms at 1 kHz, then the host freezes (no commands) for 200 ms
    for k in range(100):
        for drv in (d, ref):
            drv.read(k * 0.001)
            drv.write([0.0005 * k], k * 0.001)
    last = 0.099
    # where the drive is at the heartbeat deadline, had it kept the last command
    ref.read(last + 0.020)
    at_deadline = ref.true_positions[0]
    with pytest.raises(DriverError, match="heartbeat lost: no command for 200.0 ms"):
        d.read(last + 0.200)
    assert d.state is DriverState.FAULT and "heartbeat lost" in d.fault_reason
    # it moved only until the deadline, then braked and held
    assert d.true_positions[0] == pytest.approx(at_deadline, abs=1e-12)
    assert d.stats()["heartbeat_trips"] == 1
    d.read(last + 0.250)  # reported once; then where the robot is stays readable
    assert js[0].position == pytest.approx(at_deadline, abs=1e-12)
    with pytest.raises(StateError):
        d.write([0.0], last + 0.201)
    d.reset()
    d.read(last + 0.300)  # reset clears the device's latch
    assert d.state is DriverState.INACTIVE


@pytest.mark.req("SR-HB-1")
def test_sim_heartbeat_refreshed_every_tick_never_trips() -> None:
    d = SimDriver("s", joints(1), {"heartbeat_ms": 5})
    d.configure()
    d.activate()
    for k in range(1000):
        d.read(k * 0.001)
        d.write([0.0], k * 0.001)
    assert d.state is DriverState.ACTIVE and d.stats()["heartbeat_trips"] == 0


@pytest.mark.req("SR-HB-1")
def test_heartbeat_param_is_every_drivers_and_checked() -> None:
    assert SimDriver("s", joints(1)).heartbeat_s == pytest.approx(0.050)
    assert SimDriver("s", joints(1), {"heartbeat_ms": None}).heartbeat_s == 0.0
    with pytest.raises(ValueError, match="heartbeat_ms must be a number >= 0"):
        SimDriver("s", joints(1), {"heartbeat_ms": -1})


@pytest.mark.req("SR-SAFE-1")
def test_safe_stop_from_another_thread_while_the_loop_writes() -> None:
    import threading

    js = joints(2)
    d = SimDriver("s", js, {"heartbeat_ms": 0})
    d.configure()
    d.activate()
    refused = threading.Event()
    started = threading.Event()

    def loop() -> None:
        k = 0
        while True:
            k += 1
            try:
                d.read(k * 0.001)
                d.write([0.001 * k, 0.0], k * 0.001)
            except (StateError, DriverError):
                refused.set()
                return
            started.set()

    t = threading.Thread(target=loop)
    t.start()
    assert started.wait(5.0)
    d.safe_stop("loop hung")
    d.safe_stop("again")  # idempotent
    assert refused.wait(5.0)
    t.join(5.0)
    assert d.state is DriverState.FAULT
    assert d.fault_reason == "safe stop: loop hung"
    assert d.stats()["safe_stops"] == 1
    # braked: the model no longer follows anything
    x = d.true_positions
    d.read(100.0)
    assert d.true_positions == x
    d.reset()
    assert d.state is DriverState.INACTIVE


@pytest.mark.req("SR-SAFE-1")
def test_safe_stop_of_an_inactive_driver_changes_nothing() -> None:
    d = SimDriver("s", joints(1))
    d.configure()
    d.safe_stop("nothing to stop")
    assert d.state is DriverState.INACTIVE and d.stats()["safe_stops"] == 0


# -- what mutation testing found unchecked (docs/VERIFICATION.md, occ/drivers/base.py) -----
class FlakyDriver(MirrorDriver):
    """A mirror whose hooks raise on demand (``fail`` holds the names of the failing hooks);
    records the ``now`` each write hook was given."""

    def __init__(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        super().__init__(*args, **kwargs)
        self.fail: set[str] = set()
        self.nows: list[float] = []

    def _maybe(self, hook: str) -> None:
        self.calls.append(hook)
        if hook in self.fail:
            raise OSError(f"{hook} broke")

    def _configure(self) -> None:
        self._maybe("configure")

    def _activate(self) -> None:
        self._maybe("activate")

    def _deactivate(self) -> None:
        self._maybe("deactivate")

    def _reset(self) -> None:
        self._maybe("reset")

    def _safe_stop(self) -> None:
        self._maybe("safe_stop")

    def _shutdown(self) -> None:
        self._maybe("shutdown")

    def _write(self, values: Sequence[float], now: float) -> None:
        self._maybe("write")
        self.nows.append(now)
        self.last = list(values)


def flaky(**kwargs) -> FlakyDriver:  # type: ignore[no-untyped-def]
    return FlakyDriver("m", joints(), **kwargs)


def test_bad_arguments_are_refused_with_what_is_wrong() -> None:
    with pytest.raises(ValueError, match="driver 'm': needs at least one joint"):
        MirrorDriver("m", [])
    with pytest.raises(
        ValueError, match=r"driver 'm': on_limit must be one of \('clamp', 'fault'\)"
    ):
        MirrorDriver("m", joints(), on_limit="ignore")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"driver 'm': duplicate joint names \['a', 'a'\]"):
        MirrorDriver("m", [Joint("a"), Joint("a")])
    for bad in (-1, "soon", [50]):
        with pytest.raises(
            ValueError, match=rf"driver 'm': heartbeat_ms .* got {re.escape(repr(bad))}"
        ):
            MirrorDriver("m", joints(), {"heartbeat_ms": bad})
    for period in (0.0, -0.001):
        with pytest.raises(ValueError, match=rf"driver 'm': period must be > 0, got {period}"):
            MirrorDriver("m", joints(), {"period": period})
    with pytest.raises(
        ValueError,
        match=r"driver 's' \(SimDriver\): unknown params \['bandwidth'\]; "
        r"known: \[.*'bandwidth_hz'.*'heartbeat_ms'",
    ):
        SimDriver("s", joints(1), {"bandwidth": 3})
    for iface in ("velocity", "effort"):
        # sim takes both; a position-only backend refuses efforts, nobody takes velocity
        with pytest.raises(
            ValueError,
            match=rf"driver 'p' \(PositionOnly\): command_interface "
            rf"'{iface}' not supported; choose one of \('position',\)",
        ):
            PositionOnly("p", joints(), command_interface=iface)  # type: ignore[arg-type]


class PositionOnly(MirrorDriver):
    supported_interfaces = ("position",)


def test_params_defaults_and_the_interface_from_params() -> None:
    # the base's own parameters are read when the backend declares none
    d = MirrorDriver("m", joints(), {"period": 0.002, "command_interface": "effort"})
    assert d.period == 0.002 and d.command_interface == "effort"
    assert d.params == {
        "heartbeat_ms": 50.0,
        "feedback_jump": 2.0,
        "frozen_feedback_ms": 50.0,
        "feedback_noise": None,
        "limit_margin": None,
        "following_error": {},
        "period": 0.002,
        "command_interface": "effort",
    }
    assert MirrorDriver("m", joints()).period == 0.001
    # the argument wins over the params
    assert (
        MirrorDriver(
            "m", joints(), {"command_interface": "effort"}, command_interface="position"
        ).command_interface
        == "position"
    )
    s = SimDriver("s", joints(1), {"heartbeat_ms": 20})
    assert s.heartbeat_s == pytest.approx(0.020) and s.params["heartbeat_ms"] == 20


def test_refused_transitions_name_the_action_the_state_and_the_fault() -> None:
    d = flaky()
    for call, action in (
        (d.activate, "activate"),
        (d.deactivate, "deactivate"),
        (d.reset, "reset"),
    ):
        with pytest.raises(
            StateError,
            match=rf"^driver 'm': cannot {action} in state "
            r"unconfigured$",
        ):
            call()
    with pytest.raises(StateError, match=r"^driver 'm': cannot read in state unconfigured$"):
        d.read(0.0)
    d.configure()
    with pytest.raises(StateError, match=r"^driver 'm': cannot configure in state inactive$"):
        d.configure()
    with pytest.raises(StateError, match=r"^driver 'm': commands refused in state inactive$"):
        d.write([0.0, 0.0], 0.0)
    d.activate()
    d.safe_stop("loop hung")
    with pytest.raises(
        StateError,
        match=r"^driver 'm': cannot activate in state fault "
        r"\(safe stop: loop hung\); reset\(\) first$",
    ):
        d.activate()
    d.shutdown()
    with pytest.raises(StateError, match=r"^driver 'm': cannot read in state shutdown$"):
        d.read(0.0)


@pytest.mark.req("SR-SAFE-1")
@pytest.mark.parametrize("hook", ["configure", "activate", "deactivate", "reset"])
def test_a_failing_lifecycle_hook_faults_naming_the_action(hook: str) -> None:
    d = flaky()
    if hook == "reset":
        d.configure()
        d.activate()
        d.safe_stop("first")
    else:
        if hook != "configure":
            d.configure()
        if hook == "deactivate":
            d.activate()
    d.fail.add(hook)
    error = rf"^driver 'm': {hook} failed: OSError\('{hook} broke'\)$"
    with pytest.raises(DriverError, match=error) as info:
        getattr(d, hook)()
    assert isinstance(info.value.__cause__, OSError)
    assert d.state is DriverState.FAULT
    assert d.fault_reason == f"driver 'm': {hook} failed: OSError('{hook} broke')" or (
        hook == "reset" and d.fault_reason == "safe stop: first"  # a fault keeps its first reason
    )
    # a failing deactivation is tried once more on entering FAULT (the hardware must stop)
    assert d.stats()["errors"] == (2 if hook == "deactivate" else 1)


class PowerUp(FlakyDriver):
    """A flaky mirror whose power-up runs ``during`` (what another thread asks meanwhile)
    and records what the driver says of itself while it is coming up."""

    def __init__(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        super().__init__(*args, **kwargs)
        self.during: list[tuple[str, str]] = []
        self.seen: list[tuple[bool, bool]] = []

    def _activate(self) -> None:
        self.seen.append((self.activating, self.activation_cancelled))
        for ask, reason in self.during:
            if ask == "cancel":
                assert self.cancel_activation(reason) is True
            else:
                self.safe_stop(reason)
        self.seen.append((self.activating, self.activation_cancelled))
        self._maybe("activate")


@pytest.mark.req("SR-HW-39", "SR-SAFE-1")
def test_a_safe_stop_while_powering_up_switches_it_off_again_and_faults() -> None:
    d = PowerUp("m", joints())
    assert d.activating is False and d.cancel_activation("nothing under way") is False
    d.configure()
    assert d.activating is False and d.cancel_activation("nothing under way") is False
    d.during = [("stop", "loop hung")]
    error = "driver 'm': safe stop while powering up: loop hung; switched off"
    with pytest.raises(DriverError) as info:
        d.activate()
    assert str(info.value) == error
    assert d.seen == [(True, False), (True, True)]  # the hook can see it and give up
    assert d.state is DriverState.FAULT and d.fault_reason == error
    assert d.calls == ["configure", "activate", "deactivate"]  # off again once it was up
    assert d.stats() == {"reads": 0, "writes": 0, "limit_events": 0, "errors": 1, "safe_stops": 0}
    assert d.activating is False and d.stop_failed is None
    # after the reset a power-up with nothing asked is a plain one
    d.reset()
    d.during = []
    d.seen.clear()
    d.activate()
    assert d.state is DriverState.ACTIVE and d.seen == [(True, False), (True, False)]
    assert d.activating is False and d.stats()["errors"] == 1
    # a second one is counted on top of the first
    d.deactivate()
    d.during = [("stop", "loop hung again")]
    with pytest.raises(DriverError, match="loop hung again"):
        d.activate()
    assert d.stats()["errors"] == 2


@pytest.mark.req("SR-HW-39")
def test_a_cancelled_power_up_ends_switched_off_and_inactive() -> None:
    d = PowerUp("m", joints())
    d.configure()
    d.during = [("cancel", "disable asked"), ("cancel", "a second reason")]
    with pytest.raises(StateError) as info:
        d.activate()
    # the first reason is kept
    assert str(info.value) == "driver 'm': activation cancelled: disable asked; switched off again"
    assert d.seen == [(True, False), (True, True)]
    assert d.state is DriverState.INACTIVE and d.fault_reason is None
    assert d.calls == ["configure", "activate", "deactivate"]
    assert d.stats()["errors"] == 0 and d.activating is False
    assert d.cancel_activation("too late") is False
    # a stop and a cancel both asked: the stop wins (FAULT, not INACTIVE)
    d.during = [("cancel", "disable asked"), ("stop", "estop")]
    with pytest.raises(DriverError, match="safe stop while powering up: estop; switched off$"):
        d.activate()
    assert d.state is DriverState.FAULT


@pytest.mark.req("SR-HW-17")
def test_a_failed_switch_off_is_kept_until_one_succeeds() -> None:
    d = flaky()
    d.configure()
    d.activate()
    d.deactivate()
    assert d.stop_failed is None
    d.activate()
    d.fail = {"safe_stop"}
    d.safe_stop("loop hung")
    assert d.stop_failed == "safe stop failed: OSError('safe_stop broke')"
    # a reset switches it off first, and is refused while it cannot
    d.fail = {"deactivate"}
    error = "driver 'm': reset (switch-off) failed: OSError('deactivate broke')"
    with pytest.raises(DriverError) as info:
        d.reset()
    assert str(info.value) == error and d.state is DriverState.FAULT
    assert d.stop_failed == "safe stop failed: OSError('safe_stop broke')"
    d.fail = set()
    d.calls.clear()
    d.reset()
    assert d.calls == ["deactivate", "reset"] and d.stop_failed is None
    assert d.state is DriverState.INACTIVE
    # a fault from ACTIVE switches off; a failure of that is kept, a success clears it
    d.activate()
    d.fail = {"write", "deactivate"}
    with pytest.raises(DriverError, match="write failed"):
        d.write([0.0, 0.0], 0.001)
    assert d.stop_failed == "switch-off failed: OSError('deactivate broke')"
    d.fail = set()
    d.reset()
    d.activate()
    d.fail = {"write"}
    with pytest.raises(DriverError, match="write failed"):
        d.write([0.0, 0.0], 0.002)
    assert d.state is DriverState.FAULT and d.stop_failed is None


def test_the_last_reading_is_kept_as_the_hook_returned_it_and_none_before_any() -> None:
    d = MirrorDriver("m", joints())
    assert d.raw == ((), (), ()) and math.isnan(d.raw_now)  # the black box: nothing read yet
    d.configure()
    d.last = [0.25, -0.5]
    d.read(0.003)
    assert d.raw == ([0.25, -0.5], [0.0, 0.0], [0.0, 0.0]) and d.raw_now == 0.003


def test_every_failing_hook_is_told_to_the_tap() -> None:
    told: list[tuple[str, str, str]] = []
    d = flaky()
    d.hook_tap = lambda name, action, err: told.append((name, action, repr(err)))
    d.fail = {"configure"}
    with pytest.raises(DriverError):
        d.configure()
    d.fail = set()
    d.reset()
    d.configure()
    assert told == [("m", "configure", "OSError('configure broke')")]


def test_a_driver_that_never_configured_resets_to_unconfigured() -> None:
    d = flaky()
    d.fail.add("configure")
    with pytest.raises(DriverError, match="configure failed"):
        d.configure()
    d.fail.clear()
    d.reset()
    assert d.state is DriverState.UNCONFIGURED and d.fault_reason is None
    d.configure()  # and may try again
    assert d.state is DriverState.INACTIVE


@pytest.mark.req("SR-SAFE-1")
def test_every_error_and_safe_stop_is_counted() -> None:
    d = flaky()
    d.configure()
    d.activate()
    d.fail.add("safe_stop")  # a safe stop whose hook fails still latches FAULT, counted
    d.safe_stop("one")
    assert d.state is DriverState.FAULT and d.fault_reason == "safe stop: one"
    assert d.stats()["safe_stops"] == 1 and d.stats()["errors"] == 1
    d.reset()
    d.activate()
    d.safe_stop("two")
    assert d.stats()["safe_stops"] == 2 and d.stats()["errors"] == 2
    d.reset()
    d.fail = {"read"}
    d.fail_read = True
    with pytest.raises(DriverError, match="read failed"):
        d.read(0.0)
    assert d.stats()["errors"] == 3
    d.fail_read = False
    d.reset()
    # a limit fault whose deactivation fails: the limit is the reason, the failure counted
    d2 = FlakyDriver("m", joints(), on_limit="fault")
    d2.configure()
    d2.fail_read = True
    with pytest.raises(DriverError):
        d2.read(0.0)  # one error before
    d2.fail_read = False
    d2.reset()
    d2.activate()
    d2.fail.add("deactivate")
    with pytest.raises(LimitError, match="outside limits"):
        d2.write([0.0, 1.5], 0.001)
    assert d2.fault_reason == "driver 'm': joint j1: position 1.5 outside limits [-1, 1]"
    assert d2.stats()["errors"] == 2


def test_shutdown_releases_everything_and_reports_the_first_error() -> None:
    d = flaky()
    d.configure()
    d.fail_read = True
    with pytest.raises(DriverError):
        d.read(0.0)  # one error before shutdown
    d.fail_read = False
    d.reset()
    d.activate()
    d.fail = {"deactivate", "shutdown"}
    error = r"^driver 'm': shutdown failed: deactivate broke$"
    with pytest.raises(DriverError, match=error) as info:
        d.shutdown()
    assert str(info.value.__cause__) == "deactivate broke"
    assert d.state is DriverState.SHUTDOWN
    assert d.calls[-2:] == ["deactivate", "shutdown"]  # the hardware was released anyway
    assert d.stats()["errors"] == 3
    d.shutdown()  # once shut down, nothing more
    # only the release fails
    e = flaky()
    e.configure()
    e.fail = {"shutdown"}
    with pytest.raises(DriverError, match=r"^driver 'm': shutdown failed: shutdown broke$"):
        e.shutdown()
    assert e.state is DriverState.SHUTDOWN and e.stats()["errors"] == 1


def test_read_stamps_and_counts_every_read() -> None:
    d = MirrorDriver("m", joints())
    d.configure()
    d.last = [0.25, math.nan]  # the second joint has not reported yet
    d.read(0.5)
    d.read(0.75)
    assert d.joints[0].position == 0.25 and d.joints[0].stamp == 0.75
    assert d.joints[0].measured and not d.joints[1].measured
    assert math.isnan(d.joints[1].stamp)
    assert d.stats()["reads"] == 2


# -- write_effort: a haptic master's force, clamped to the effort limit ---------------------
def effort_driver(effort: float = 0.5, **kwargs) -> FlakyDriver:  # type: ignore[no-untyped-def]
    js = [
        Joint(f"j{i}", "prismatic", JointLimits(-1.0, 1.0, 100.0, effort), **kwargs)
        for i in range(2)
    ]
    d = FlakyDriver("m", js, command_interface="effort")
    d.configure()
    d.activate()
    return d


def test_write_effort_clamps_to_either_effort_limit_exactly() -> None:
    d = effort_driver(0.5)
    d.write_effort([0.5, -0.5], 0.001)  # exactly on the limits: not clamped
    assert d.last == [0.5, -0.5] and d.stats()["limit_events"] == 0
    d.write_effort([0.8, -0.8], 0.002)  # just over, either sign
    assert d.last == [0.5, -0.5] and d.stats()["limit_events"] == 2
    d.write_effort([0.5000001, -0.4], 0.003)
    assert d.last == [0.5, -0.4] and d.stats()["limit_events"] == 3
    assert [j.command_effort for j in d.joints] == [0.5, -0.4]
    assert d.nows == [0.001, 0.002, 0.003] and d.stats()["writes"] == 3
    assert d.state is DriverState.ACTIVE
    big = effort_driver(50.0)
    big.write_effort([80.0, 0.0], 0.001)  # a positive force over a limit above 1 N
    assert big.last == [50.0, 0.0]


@pytest.mark.req("SR-SAFE-1")
def test_write_effort_refusals_and_a_failing_hook() -> None:
    d = effort_driver()
    with pytest.raises(ValueError, match=r"^driver 'm': expected 2 efforts, got 1$"):
        d.write_effort([0.0], 0.001)
    with pytest.raises(LimitError, match=r"^driver 'm': joint j1: effort inf$"):
        d.write_effort([0.0, math.inf], 0.001)
    assert d.fault_reason == "driver 'm': joint j1: effort inf"
    with pytest.raises(StateError, match=r"^driver 'm': commands refused in state fault$"):
        d.write_effort([0.0, 0.0], 0.002)
    d.reset()
    d.activate()
    d.fail.add("write")
    with pytest.raises(DriverError, match=r"^driver 'm': write failed: OSError\('write broke'\)$"):
        d.write_effort([0.0, 0.0], 0.003)
    assert d.state is DriverState.FAULT and d.stats()["errors"] == 1
    assert d.stats()["writes"] == 0


@pytest.mark.req("SR-LIM-2")
def test_a_setpoint_after_direct_efforts_is_checked_against_the_measured_position() -> None:
    # an effort driver with gains takes both; while efforts were written the hand moved the
    # joint (to 0.5): the next setpoint there is no motion, not a step from the old setpoint 0
    # (a hand that fast would be a feedback jump: that check is off here)
    js = [Joint("j", "revolute", JointLimits(-1.0, 1.0, 1.0, 50.0), gains=PIDGains(kp=10.0))]
    d = FlakyDriver("m", js, {"feedback_jump": 0}, command_interface="effort")
    d.configure()
    d.read(0.0)
    d.activate()
    d.write([0.0], 0.001)
    d.write_effort([2.0], 0.002)
    d.last = [0.5]
    d.read(0.003)
    d.write([0.5], 0.003)
    assert js[0].command_position == 0.5 and d.last == [0.0]  # on target: no effort
    assert d.stats()["limit_events"] == 0 and d.stats()["writes"] == 3
    d.shutdown()


def test_repr_names_the_driver_its_joints_state_and_interface() -> None:
    d = MirrorDriver("m", joints(), command_interface="effort")
    assert repr(d) == (
        "MirrorDriver('m', joints=['j0', 'j1'], state=unconfigured, interface=effort)"
    )


# ---------------------------------------------------------------------------- the driver's log
# What an operator reads in the daemon's log is part of the behaviour: each line names the
# driver, the state change or the fault with its reason, at its level.


def _records(caplog: pytest.LogCaptureFixture) -> list[tuple[str, str]]:
    return [(r.levelname, r.getMessage()) for r in caplog.records if r.name == "occ.drivers.base"]


def test_the_log_names_every_transition_and_fault_with_its_reason(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level("INFO", logger="occ.drivers.base")
    gc.collect()  # earlier tests' drivers left in cycles warn when collected: not here
    caplog.clear()
    d = MirrorDriver("arm", joints(1))
    d.configure()
    d.activate()
    d.fail_read = True
    with pytest.raises(DriverError):
        d.read(0.0)
    d.fail_read = False
    d.reset()
    d.shutdown()
    fault = "driver 'arm': read failed: OSError('bus gone')"
    assert _records(caplog) == [
        ("INFO", "driver arm: unconfigured -> inactive"),
        ("INFO", "driver arm: inactive -> active"),
        ("ERROR", f"driver arm: FAULT: {fault}"),
        ("INFO", "driver arm: active -> fault"),
        ("INFO", f"driver arm: fault reset (was: {fault})"),
        ("INFO", "driver arm: fault -> inactive"),
        ("INFO", "driver arm: inactive -> shutdown"),
    ]


def test_safe_stop_and_a_failing_deactivate_are_logged_with_the_driver(
    caplog: pytest.LogCaptureFixture,
) -> None:
    class Stubborn(MirrorDriver):
        def _safe_stop(self) -> None:
            raise OSError("amplifier does not answer")

        def _deactivate(self) -> None:
            raise OSError("still powered")

    caplog.set_level("INFO", logger="occ.drivers.base")
    d = Stubborn("arm", joints(1))
    d.configure()
    d.activate()
    gc.collect()  # earlier tests' drivers left in cycles warn when collected: not here
    caplog.clear()
    d.safe_stop("loop hung")
    assert _records(caplog) == [
        ("ERROR", "driver arm: safe stop failed"),
        ("ERROR", "driver arm: FAULT: safe stop: loop hung"),
        ("INFO", "driver arm: active -> fault"),
    ]
    assert caplog.records[0].exc_info is not None  # the hook's traceback is in the log
    e = Stubborn("leg", joints(1))
    e.configure()
    e.activate()
    caplog.clear()
    with pytest.raises(LimitError):  # a non-finite setpoint faults; an ACTIVE drive deactivates
        Stubborn.write(e, [math.nan], 0.001)
    assert ("ERROR", "driver leg: deactivate after fault failed") in _records(caplog)
    d.shutdown()
    e.shutdown()


def test_a_driver_left_configured_warns_once_it_is_collected(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """python-can's leaked-bus warning: a configured driver nobody shut down may still hold
    hardware. One shut down, or never configured, or half built, says nothing."""
    caplog.set_level("WARNING", logger="occ.drivers.base")
    gc.collect()  # earlier tests' drivers left in cycles warn when collected: not here
    caplog.clear()
    leaked = MirrorDriver("leaky", joints(1))
    leaked.configure()
    leaked.__del__()
    assert _records(caplog) == [("WARNING", "driver leaky was not shut down properly")]
    leaked.shutdown()
    caplog.clear()
    for d in (MirrorDriver("idle", joints(1)), leaked):
        d.__del__()  # never configured / shut down
    half = MirrorDriver.__new__(MirrorDriver)  # __init__ failed before any attribute
    half.__del__()
    assert _records(caplog) == []
    half_named = MirrorDriver.__new__(MirrorDriver)
    half_named._configured = True  # configured, state never set: nothing to warn about
    half_named.__del__()
    assert _records(caplog) == []
    # configured and active, but __init__ never got to the name (a compiled Driver's attributes
    # cannot be deleted, so the half-made object is built by hand)
    nameless = MirrorDriver.__new__(MirrorDriver)
    nameless._configured = True
    nameless._state = DriverState.ACTIVE
    nameless.__del__()
    assert _records(caplog) == [("WARNING", "driver ? was not shut down properly")]
    nameless._state = DriverState.SHUTDOWN
