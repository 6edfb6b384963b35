"""The slave's ``absolute`` mapping (an external command source, CRTK ``servo_cp``): each
sample is the tip's target in the patient frame, checked against where the tip is told to be
(``max_jump_mm``) and solved once."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

from occ.errors import KinematicsError

if TYPE_CHECKING:
    from occ.controllers import ControllerContext
    from occ.core.data import RobotData

log = logging.getLogger("occ.controllers.teleop.slave")


class ServoTarget:
    """A new target's check and solution; ``refused`` counts the targets refused (a jump over
    ``max_jump`` m), told once per run of them."""

    def __init__(self, max_jump: float) -> None:
        self.max_jump = max_jump
        self._refusing = False
        self.refused = 0

    def solve(
        self,
        p: tuple[float, float, float],
        here: Sequence[float],
        data: RobotData,
        ctx: ControllerContext,
    ) -> tuple[list[float] | None, bool, bool]:
        """The joints for target ``p`` (world frame, m), the joints told to be at ``here``:
        (the solution or None when none is taken, clamped to the limits, an IK failure)."""
        b = data.base
        # world -> base frame: R^T (p - t)
        dx, dy, dz = p[0] - b[0, 3], p[1] - b[1, 3], p[2] - b[2, 3]
        target = (
            float(b[0, 0] * dx + b[1, 0] * dy + b[2, 0] * dz),
            float(b[0, 1] * dx + b[1, 1] * dy + b[2, 1] * dz),
            float(b[0, 2] * dx + b[1, 2] * dy + b[2, 2] * dz),
        )
        if not all(math.isfinite(v) for v in target):
            return None, False, True
        tx, ty, tz = ctx.frame.tip_position(here)
        jump = math.sqrt((target[0] - tx) ** 2 + (target[1] - ty) ** 2 + (target[2] - tz) ** 2)
        if jump > self.max_jump:
            self.refused += 1
            if not self._refusing:
                self._refusing = True
                text = (
                    f"servo target {jump * 1e3:.1f} mm from the tip refused (max_jump_mm "
                    f"{self.max_jump * 1e3:g}): holding"
                )
                log.warning("%s", text)
                alert = ctx.alert
                if alert is not None:
                    alert("ServoTarget", text, 2)
            return None, False, False
        try:
            q, clamped = ctx.frame.ik_clamped(target, list(here))
        except (KinematicsError, ValueError):
            return None, False, True
        self._refusing = False
        return q, bool(clamped), False
