"""The slave's ``absolute`` mapping (an external command source, CRTK ``servo_cp``): each
sample is the tip's target in the patient frame, checked against where the tip is told to be
(``max_jump_mm``), then approached within the velocity limits, all joints together.

The way to a target, by the arm's ``orientation``:

- ``off`` (a 3-DOF arm) and ``follow`` (a 6-DOF arm, the tool turned as it was when the source
  took control: the sample's orientation is not used): the target's joints are solved once, and
  every tick all joints step together along the straight line toward them (as a re-entry does,
  occ/core/motion.py), the largest step 0.9 of its joint's velocity limit: every joint arrives
  on the same tick, none detours ahead of the others.
- ``rcm`` (a laparoscopic tool through a port): every tick the pose is solved through the port
  for the tip a tick's share of the straight way on (:meth:`SixDof.solve`), so the tool's axis
  stays in the port on the whole way, not just at its ends.

A target farther than ``max_jump_mm`` from where the tip is told to be is refused, never
clipped to the sphere nor approached in several servo steps: a servo command is a small step of
a stream, and a far goal is a ``move_cp``, planned, checked and acknowledged (a stream that jumps
is a source gone wrong, and moving toward its jump would follow it). The robot holds where it
was told to be and stays RUNNING; the operators get one ALERT per run of refused samples
(``ServoTarget``, the distance and the limit), GetStats counts each (``servo_refused``), and the
next target within reach is taken from there.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from occ.errors import KinematicsError
from occ.joint import step_together

if TYPE_CHECKING:
    from occ.controllers import ControllerContext
    from occ.controllers.teleop.sixdof import SixDof
    from occ.core.data import RobotData

log = logging.getLogger("occ.controllers.teleop.slave")

Vec3 = tuple[float, float, float]


class ServoTarget:
    """A new target's check (:meth:`take`) and the way to it (:meth:`step`); ``refused``
    counts the targets refused (a jump over ``max_jump`` m), told once per run of them.
    ``six``: the slave's orientation half, used when ``orientation`` is ``follow`` or
    ``rcm``."""

    def __init__(self, max_jump: float, six: SixDof, orientation: str) -> None:
        self.max_jump = max_jump
        self.six = six
        self.orientation = orientation
        self._refusing = False
        self.refused = 0
        #: the joints to step to (``off``, ``follow``), or the tip to go to (``rcm``: base
        #: frame), for the target taken last; None once there (``rcm``) or without one
        self._q_goal: list[float] | None = None
        self._tip_goal: Vec3 | None = None
        #: ``follow``: the tool's orientation kept (base frame), taken when control starts
        self._rotation: np.ndarray | None = None
        self._first_solve = False
        #: the target taken last (base frame) and whether its joints were clamped: the same
        #: target again (a source repeating its last command) goes on along the same way
        self._taken: Vec3 | None = None
        self._taken_clamped = False
        self._steps: list[float] = []
        self.data: RobotData | None = None
        self.ctx: ControllerContext | None = None

    def bind(self, data: RobotData, ctx: ControllerContext) -> None:
        self.data, self.ctx = data, ctx
        # the drivers' check allows the limit itself; 0.9 keeps clear of it
        self._steps = [0.9 * lim.velocity * ctx.period_s for lim in ctx.joint_limits]

    def drop(self) -> None:
        """No target (a stopped source, the clutch, a stop): hold where told."""
        self._q_goal = None
        self._tip_goal = None
        self._taken = None

    def take(self, p: Vec3, here: Sequence[float], first: bool) -> tuple[bool, bool, bool]:
        """A new target ``p`` (world frame, m), the joints told to be at ``here``, ``first``
        after control started: (taken, clamped to the joint limits, an IK failure). Not
        taken: refused (too far) or no target (not finite, unsolvable); the robot holds."""
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        target = self._to_base(p, data.base)
        if target is not None and target == self._taken and not first:
            return True, self._taken_clamped, False  # its way goes on, not solved again
        self.drop()
        if target is None:
            return False, False, True
        if not self._within_reach(target, here, ctx):
            return False, False, False
        if first or self._rotation is None:
            self._rotation = np.asarray(ctx.frame.fk(here))[:3, :3].copy()
        self._taken, self._taken_clamped = target, False
        if self.orientation == "rcm":
            self._tip_goal = target
            self._first_solve = True
            return True, False, False
        try:
            if self.orientation == "follow":
                q, clamped = self.six.pose_solution(target, self._rotation, here)
            else:
                q, clamped = ctx.frame.ik_clamped(target, list(here))
        except (KinematicsError, ValueError):
            self._taken = None
            return False, False, True
        self._q_goal = q
        self._taken_clamped = bool(clamped)
        return True, self._taken_clamped, False

    def step(self, here: Sequence[float]) -> tuple[list[float] | None, bool, bool, bool]:
        """This tick's joints on the way to the target from ``here``: (joints or None to
        hold, slowed to the velocity limits, clamped, an IK failure)."""
        goal = self._q_goal
        if goal is not None:
            out = list(here)
            return out, step_together(out, goal, self._steps), False, False
        tip = self._tip_goal
        if tip is None:
            return None, False, False, False
        try:
            q, clamped, slowed = self.six.solve(tip, here)
        except (KinematicsError, ValueError):
            self.drop()
            return None, False, False, True
        if not slowed:
            self._tip_goal = None  # there: its pose solved, nothing left to do until the next
        self._taken_clamped = self._taken_clamped or clamped
        clamped, self._first_solve = clamped and self._first_solve, False
        return q, slowed, clamped, False

    @staticmethod
    def _to_base(p: Vec3, b: np.ndarray) -> Vec3 | None:
        """World -> base frame, ``R^T (p - t)``; None when not a point (NaN, inf)."""
        dx, dy, dz = p[0] - b[0, 3], p[1] - b[1, 3], p[2] - b[2, 3]
        target = (
            float(b[0, 0] * dx + b[1, 0] * dy + b[2, 0] * dz),
            float(b[0, 1] * dx + b[1, 1] * dy + b[2, 1] * dz),
            float(b[0, 2] * dx + b[1, 2] * dy + b[2, 2] * dz),
        )
        return target if all(math.isfinite(v) for v in target) else None

    def _within_reach(self, target: Vec3, here: Sequence[float], ctx: ControllerContext) -> bool:
        """Is ``target`` within ``max_jump`` of the tip told (else refused, told once)?"""
        tx, ty, tz = ctx.frame.tip_position(here)
        jump = math.sqrt((target[0] - tx) ** 2 + (target[1] - ty) ** 2 + (target[2] - tz) ** 2)
        if jump <= self.max_jump:
            self._refusing = False
            return True
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
        return False
