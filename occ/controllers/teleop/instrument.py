"""The slave's instrument: its force source built from the ``force`` parameters, its tare
(``ForceTare``), and the simulated tissue 3D Slicer defines (``kind=tissue``)."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import numpy as np

from occ.controllers.teleop.common import as_m
from occ.errors import CommandError, caused
from occ.haptics.contact import tissue_from_event
from occ.haptics.forces import SlaveForce

if TYPE_CHECKING:
    from occ.controllers import ControllerContext
    from occ.core.data import RobotData

log = logging.getLogger("occ.controllers.teleop.slave")


def build_force(fp: Any, data: RobotData, ctx: ControllerContext) -> SlaveForce:
    """The slave's tip force (occ/haptics/forces.py) from its ``force`` parameters."""
    return SlaveForce(
        fp.sources,
        sensor_interface=fp.sensor_interface,
        sensor_device=fp.sensor_device,
        sensor_frame=fp.sensor_frame,
        sensor_timeout_s=fp.sensor_timeout_ms * 1e-3,
        damping=fp.damping,
        effort_damping=fp.effort_damping,
        effort_inertia=fp.effort_inertia,
        environment=ctx.environment,
        alert=ctx.alert,
        pose=lambda: (data.tip, data.base),
        tool_mass_kg=fp.tool_mass_kg,
        tool_com_m=as_m(fp.tool_com_mm),
        gravity=fp.gravity_mps2,
        tare_window_s=fp.tare_window_ms * 1e-3,
        tare_max_speed=fp.tare_max_speed_mm_s * 1e-3,
        tare_max_spread_n=fp.tare_max_spread_n,
        tare_max_offset_n=fp.tare_max_offset_n,
    )


def tare(force: SlaveForce, data: RobotData, ctx: ControllerContext, now: float) -> str:
    """``ForceTare``: at rest and touching nothing, or refused (occ/haptics/forces.py: a tare
    in contact hides a real force from then on)."""
    v = ctx.frame.jacobian(data.q)[:3] @ np.asarray(data.qdot, dtype=float)
    env = ctx.environment
    contact = None
    if env is not None and env.in_contact:
        deep = max(env.depth_mm.items(), key=lambda kv: kv[1])
        contact = f"simulated tissue {deep[0]!r} {deep[1]:.2f} mm deep"
    try:
        return force.tare_all(now, data.effort, float(np.linalg.norm(v)), contact)
    except ValueError as err:
        raise caused(CommandError(str(err)), err) from err


def define_tissue(event: Any, ctx: ControllerContext | None) -> bool:
    """A tissue definition from 3D Slicer (``kind=tissue``: occ/haptics/contact.py) for the
    simulated world: True when it was one (CommandError when it is wrong, or when this
    robot has no simulated world to put it in)."""
    try:
        found = tissue_from_event(event)
    except ValueError as err:
        raise caused(CommandError(str(err)), err) from err
    if found is None:
        return False
    env = ctx.environment if ctx is not None else None
    if env is None:
        raise CommandError(
            f"tissue {found[0]!r}: this robot has no simulated world (config `environment`)"
        )
    env.define(*found)
    log.info("tissue %r: %d shape(s) from 3D Slicer", found[0], len(found[1]))
    return True
