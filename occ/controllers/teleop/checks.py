"""The teleop controllers' config checks (``occd --check``): what a master's and a slave's
parameters must agree with in the rest of the daemon's config."""

from __future__ import annotations

import math
from typing import Any

from occ.config import DaemonConfig
from occ.controllers import Problem
from occ.controllers.teleop.common import interfaces_exist
from occ.haptics.fixture_defs import DefinitionError, from_markups_file
from occ.haptics.forceviz import check_outputs


def check_master(params: Any, config: DaemonConfig) -> list[Problem]:
    problems = interfaces_exist(params, config, ("input_interface",))
    if params.input == "igtl" and params.input_interface is None:
        problems.append((("input_interface",), "required with input: igtl"))
    teleop = {itf.name for itf in config.interfaces for o in itf.outputs if o.source == "teleop"}
    for i, name in enumerate(params.slaves):
        if name not in teleop:
            problems.append((("slaves", i), f"interface '{name}' has no output with source teleop"))
    if params.slave is not None and params.slave not in params.slaves:
        problems.append((("slave",), f"'{params.slave}' is not one of slaves"))
    if params.tip_grace_ms < 3.25 * params.tip_period_ms:
        problems.append((("tip_grace_ms",), "must be at least the deadline (3.25 x tip_period_ms)"))
    g = params.gripper
    if g is not None and g.source == "joint":
        joints = [j.name for j in config.robot.joints]
        if g.joint is None:
            problems.append((("gripper", "joint"), "required with source: joint"))
        elif g.joint not in joints:
            problems.append((("gripper", "joint"), f"no joint '{g.joint}' ({joints})"))
        if g.open == g.closed:
            problems.append((("gripper", "closed"), "must differ from open"))
    if params.force_output and params.input != "driver":
        problems.append((("force_output",), "needs input: driver (a hand-moved master)"))
    for i, f in enumerate(params.fixture_files):
        try:
            from_markups_file(f.file, kind=f.kind, radius_mm=f.radius_mm)
        except DefinitionError as err:
            problems.append((("fixture_files", i, "file"), str(err)))
    return problems


def check_slave(params: Any, config: DaemonConfig) -> list[Problem]:
    problems = interfaces_exist(params, config, ("input_interface", "base_interface"))
    if params.orientation == "rcm" and params.rcm_mm is None:
        problems.append((("rcm_mm",), "required with orientation: rcm"))
    f = params.force
    if (
        f is not None
        and "tissue" in f.sources
        and (config.environment is None or not config.environment.contacts)
    ):
        problems.append((("force", "sources"), "tissue needs an environment with contacts"))
    n = len(config.robot.joints)
    for key in ("effort_damping", "effort_inertia"):
        values = getattr(f, key, None)
        if values is not None and len(values) != n:
            problems.append((("force", key), f"needs {n} values, one per joint"))
    if f is not None and "sensor" in f.sources:
        names = {i.name for i in config.interfaces}
        if f.sensor_interface is None:
            problems.append((("force", "sensor_interface"), "required with source sensor"))
        elif f.sensor_interface not in names:
            problems.append((("force", "sensor_interface"), f"no interface '{f.sensor_interface}'"))
    if f is not None and f.tool_mass_kg > 0.0:
        if "sensor" not in f.sources:
            problems.append(
                (
                    ("force", "tool_mass_kg"),
                    "the weight beyond the sensor is removed from the sensor's readings: "
                    "needs `sensor` in sources (or 0)",
                )
            )
        g = math.sqrt(sum(v * v for v in f.gravity_mps2))
        if not 9.76 <= g <= 9.84:  # the Earth's surface: 9.78 (equator) to 9.83 (poles)
            problems.append(
                (
                    ("force", "gravity_mps2"),
                    f"magnitude {g:.4g} m/s^2: the Earth's is 9.78-9.83 m/s^2 (a unit or "
                    "sign slip would compensate a weight that is not there)",
                )
            )
    g = params.gripper
    if g is not None:
        joints = {j.name: j for j in config.robot.joints}
        jc = joints.get(g.joint)
        if jc is None:
            problems.append((("gripper", "joint"), f"no joint '{g.joint}' ({list(joints)})"))
        else:
            lo, hi = jc.limits.min, jc.limits.max
            for key in ("open", "closed"):
                v = getattr(g, key)
                if not lo <= v <= hi:
                    problems.append(
                        (
                            ("gripper", key),
                            f"{v:g} is outside joint '{g.joint}' [{lo:g}, {hi:g}]",
                        )
                    )
        if g.open == g.closed:
            problems.append((("gripper", "closed"), "must differ from open"))
    if f is None and "max_tissue_force_n" in params.model_fields_set:
        if params.max_tissue_force_n is not None:
            problems.append(
                (("max_tissue_force_n",), "needs `force` (a measured contact force to limit)")
            )
    return problems + check_outputs(config, f is not None)
