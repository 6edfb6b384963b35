"""Assembling a robot's hardware side from its configuration: joints, kinematics, drivers,
and the loss monitor of its watched stream (what :class:`~occ.core.robot.Robot` is built from)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

from occ.config import (
    EnvironmentConfig,
    FrameConfig,
    LossConfig,
    RealtimeConfig,
    RobotConfig,
    WatchdogConfig,
)
from occ.core.safety import LossMonitor, Watchdog
from occ.drivers import create_driver
from occ.drivers.base import Driver
from occ.errors import ConfigError, OCCError
from occ.haptics.contact import Contact, Environment
from occ.joint import Joint, JointLimits, PIDGains
from occ.kinematics.frame import Frame


def attach_environment(
    env: EnvironmentConfig | None,
    pairs: Sequence[tuple[Driver, list[int]]],
    frame: Frame,
    base: Callable[[], Any],
) -> Environment | None:
    """The simulated world (occ/haptics/contact.py) attached to the one ``sim`` driver that has
    every joint (it computes the load from the whole arm's pose); None without contacts. ConfigError
    when no driver can carry it. ``environment: {contacts: []}`` is a world without tissue yet
    (3D Slicer may define some at run time)."""
    if env is None:
        return None
    n = frame.nq
    carriers = [d for d, idx in pairs if hasattr(d, "environment") and len(idx) == n]
    if len(pairs) != 1 or not carriers:
        raise ConfigError(
            "environment: the simulated tissue needs one `sim` driver with every joint "
            f"(the robot has {len(pairs)} driver(s): "
            f"{', '.join(f'{d.name} ({type(d).__name__})' for d, _ in pairs)})"
        )
    world = Environment([Contact.from_config(c) for c in env.contacts], frame, base)
    carriers[0].environment = world
    return world


def build_joint(jc: Any) -> Joint:
    """A :class:`Joint` from its ``robot.joints[]`` entry."""
    gains = None
    if jc.pid is not None:
        out_limit = jc.pid.out_limit if jc.pid.out_limit is not None else jc.limits.effort
        gains = PIDGains(
            kp=jc.pid.kp,
            ki=jc.pid.ki,
            kd=jc.pid.kd,
            i_limit=jc.pid.i_limit if jc.pid.i_limit is not None else math.inf,
            out_limit=out_limit if out_limit is not None else math.inf,
        )
    lim = jc.limits
    effort = lim.effort if lim.effort is not None else math.inf
    return Joint(
        jc.name, jc.type, JointLimits(lim.min, lim.max, lim.velocity, effort), jc.home, gains
    )


def frame_for(fc: FrameConfig) -> Frame:
    """The kinematic model of a ``frame:`` section (the robot's, or a cell member's)."""
    if fc.model is not None:
        return Frame.builtin(fc.model)
    assert fc.tip_link is not None  # the schema requires it with urdf
    path = fc.urdf_path()
    assert path is not None
    return Frame.from_urdf(path, fc.tip_link, fc.base_link)


def build_hardware(rc: RobotConfig) -> tuple[list[Joint], Frame, list[tuple[Driver, list[int]]]]:
    """The joints, the kinematic model and the drivers (each with the indices of its joints),
    drivers UNCONFIGURED. OCCError when the configured joints are not the model's."""
    joints = [build_joint(jc) for jc in rc.joints]
    frame = frame_for(rc.frame)
    # The configured joints are the kinematic model's, in its order: FK and IK index them.
    names = [j.name for j in joints]
    if list(frame.joint_names) != names:
        raise OCCError(
            f"robot.joints {names} do not match the joints of the kinematic model "
            f"{frame.name!r} {list(frame.joint_names)} (same names, same order)"
        )
    # the IK keeps to what the drivers accept: the configured limits, within the URDF's
    try:
        frame.set_limits([j.limits.min for j in joints], [j.limits.max for j in joints])
    except ValueError as err:
        raise OCCError(str(err)) from err
    index = {n: i for i, n in enumerate(names)}
    drivers: list[tuple[Driver, list[int]]] = []
    for dc in rc.drivers:
        idx = [index[n] for n in dc.joints]
        mine = [joints[i] for i in idx]
        drv = create_driver(dc.plugin, dc.name, mine, dict(dc.params), on_limit=dc.on_limit)
        drivers.append((drv, idx))
    return joints, frame, drivers


def build_loss_monitor(ls: LossConfig, *, watched: str | None = None) -> LossMonitor | None:
    """The packet-loss monitor of ``safety.loss`` (None when disabled or nothing watched);
    ``watched`` builds one with these parameters for that stream whatever ``ls.input`` says
    (a collaborative slave's masters: one monitor each)."""
    if not ls.enabled or (ls.input is None and watched is None):
        return None
    tol = ls.timestamp_tolerance_ms
    return LossMonitor(
        ls.period_ms * 1e-3,
        ls.max_consecutive,
        ls.deadline_ms * 1e-3 if ls.deadline_ms is not None else None,
        grace_s=ls.grace_ms * 1e-3,
        strict=ls.strict,
        timestamp_tolerance_s=tol * 1e-3 if tol is not None else None,
    )


def build_loss_monitors(ls: LossConfig, masters: tuple[str, ...] | None) -> dict[str, LossMonitor]:
    """Every watched stream's monitor, by interface name: ``safety.loss.input``'s, or with
    ``collaboration`` one per master (all with ``safety.loss``'s parameters)."""
    names = masters if masters is not None else ((ls.input,) if ls.input is not None else ())
    out: dict[str, LossMonitor] = {}
    for name in names:
        monitor = build_loss_monitor(ls, watched=name)
        if monitor is not None:
            out[name] = monitor
    return out


def build_watchdog(
    wd: WatchdogConfig,
    period_s: float,
    *,
    on_alert: Callable[[str, int], None],
    on_stop: Callable[[str, str], None],
) -> Watchdog:
    """The loop-period watchdog of ``safety.watchdog``."""
    return Watchdog(
        wd.budget_us * 1e-6,
        alert_run=wd.alert_run,
        stop_run=wd.stop_run,
        hard_gap_s=wd.hard_gap_ms * 1e-3,
        policy=wd.policy,
        on_alert=on_alert,
        on_stop=on_stop,
        period_limit_s=max(2.0 * period_s, wd.budget_us * 1e-6),
    )


def realtime_settings(rt: RealtimeConfig) -> dict[str, Any]:
    """``robot.realtime`` as the control loop takes it."""
    switch = rt.switch_interval_us
    return {
        "fifo_priority": rt.fifo_priority,
        "cpu": rt.cpu,
        "gc": rt.gc,
        "switch_interval_s": switch * 1e-6 if switch is not None else None,
    }
