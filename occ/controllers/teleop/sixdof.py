"""The slave's tool orientation (a 6-DOF arm): following the handle's rotation, or through a
port (``orientation: rcm``), and the full pose solved within the velocity limits."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import pinocchio as pin

from occ.controllers.teleop.common import MM
from occ.errors import KinematicsError
from occ.samples import quaternion_to_rotation

Vec3 = tuple[float, float, float]

#: how much farther than the last slowed step went at the velocity limits a port's next slowed
#: step is taken (then scaled back to the limits)
REACH_AHEAD = 1.05


class SixDof:
    """The orientation half of the slave's mapping: ``rotation`` (master to slave axes),
    ``rotation_scale`` (of the handle's angle), ``rcm_mm`` (the port, or None). The master's
    quaternion comes with each sample; the references are taken at each re-index."""

    def __init__(self, rotation: np.ndarray, rotation_scale: float, rcm_mm: Any) -> None:
        self.rotation = rotation
        self.rotation_scale = rotation_scale
        self.rcm_mm = rcm_mm
        self.master_quat: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
        #: at the re-index: the handle's rotation and the tool's (base frame)
        self.rm_ref: np.ndarray | None = None
        self.rs_ref: np.ndarray | None = None
        self.data: Any = None
        self.ctx: Any = None
        #: through a port, slowed: how far the tip may go in a tick at the limits (m), from
        #: the last slowed step; None when the last solve was not slowed
        self._reach: float | None = None

    def bind(self, data: Any, ctx: Any) -> None:
        self.data, self.ctx = data, ctx

    def reindex(self, here: Sequence[float]) -> None:
        """The references of a re-index, the tool at joint values ``here``."""
        self._reach = None
        self.rm_ref = quaternion_to_rotation(self.master_quat)
        self.rs_ref = np.asarray(self.ctx.frame.fk(here))[:3, :3].copy()

    def rcm_rotation(self, target: Vec3, last: Sequence[float] | None = None) -> np.ndarray:
        """The tool's orientation for a tip at ``target`` (base frame) through the port: its z
        axis from the port to the tip, its x axis the current one's projection (the roll
        kept); the current one at ``last`` (the last solution), else where the drives are
        told to be."""
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None and self.rcm_mm is not None
        b = data.base
        port = b[:3, :3].T @ (np.asarray(self.rcm_mm, dtype=float) * MM - b[:3, 3])
        z = np.asarray(target) - port
        n = float(np.linalg.norm(z))
        if n < 1e-6:
            raise KinematicsError("the tip is at the port: the tool's axis is not defined")
        z /= n
        here = last if last is not None else data.commanded()
        x = np.asarray(ctx.frame.fk(here))[:3, 0]
        x = x - float(x @ z) * z
        if float(np.linalg.norm(x)) < 1e-9:  # x along the new axis: any perpendicular
            x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
        x /= float(np.linalg.norm(x))
        return np.column_stack((x, np.cross(z, x), z))

    def target_rotation(self) -> np.ndarray:
        """The tool's orientation target (base frame): the handle's rotation since the
        re-index, ``dR = R_m R_m0^T`` (scaled in angle by ``rotation_scale``), seen in the
        slave's axes through ``rotation`` (``A dR A^T``), applied to the tool's orientation at
        the re-index."""
        assert self.rm_ref is not None and self.rs_ref is not None
        d = quaternion_to_rotation(self.master_quat) @ self.rm_ref.T
        if self.rotation_scale != 1.0:
            d = pin.exp3(self.rotation_scale * pin.log3(d))
        a = self.rotation
        return np.asarray(a @ d @ a.T @ self.rs_ref)

    def rotation_at(self, target: Vec3, last: Sequence[float] | None) -> np.ndarray:
        """The tool's orientation for a tip at ``target``: through the port when there is one
        (:meth:`rcm_rotation`), else the handle's (:meth:`target_rotation`)."""
        if self.rcm_mm is not None:
            return self.rcm_rotation(target, last)
        return self.target_rotation()

    def pose_solution(
        self, target: Vec3, rotation: np.ndarray, seed: Sequence[float]
    ) -> tuple[list[float], bool]:
        """The joints for the tool at ``target`` (base frame, m) turned to ``rotation``, by
        damped least squares from ``seed`` (the joint limits held): (joints, clamped)."""
        ctx = self.ctx
        assert ctx is not None
        pose = np.eye(4)
        pose[:3, :3] = rotation
        pose[:3, 3] = target
        res = ctx.frame.solve_ik(pose, seed, clamp=True, method="dls")
        return res.q.tolist(), bool(res.clamped)

    def ratio(self, prev: Sequence[float], q: Sequence[float]) -> float:
        """The step from ``prev`` to ``q`` over the one a tick allows (0.9 of each joint's
        velocity limit), the largest over the joints: more than 1 is too fast."""
        ctx = self.ctx
        assert ctx is not None
        ratio = 0.0
        for i, lim in enumerate(ctx.joint_limits):
            r = abs(q[i] - prev[i]) / (0.9 * lim.velocity * ctx.period_s)
            if r > ratio:
                ratio = r
        return ratio

    def solve(self, target: Vec3, last: Sequence[float] | None) -> tuple[list[float], bool, bool]:
        """The full pose (position ``target`` and :meth:`rotation_at`) by damped least squares
        from the last solution ``last`` (the joint limits held), then slowed to the velocity
        limits: (joints, clamped, slowed).

        Slowed, all joints are scaled alike (the tool keeps its direction; a drive clamping
        each joint on its own would bend the path) so that the largest step is 0.9 of its
        joint's limit in one tick. Through a port, the slowed step is not a share of the joint
        line to a far solution (the tool's axis leaves the port by that share of the line's
        curvature: 1.7 mm with the UR5 asked for 1.6 rad/s): the tip goes a share of the
        straight way toward ``target`` instead (:meth:`_port_step`)."""
        data = self.data
        assert data is not None
        prev = last if last is not None else data.commanded()
        if self.rcm_mm is not None and self._reach is not None:
            step = self._port_step(target, last, prev, None)
            if step is not None:
                return step
        seed = last if last is not None else data.q
        q, clamped = self.pose_solution(target, self.rotation_at(target, last), seed)
        ratio = self.ratio(prev, q)
        if ratio <= 1.0:
            self._reach = None
            return q, clamped, False
        if self.rcm_mm is not None:
            step = self._port_step(target, last, prev, (q, ratio))
            assert step is not None
            return step
        return self.scaled(prev, q, ratio), clamped, True

    @staticmethod
    def scaled(prev: Sequence[float], q: Sequence[float], ratio: float) -> list[float]:
        """The step from ``prev`` to ``q`` divided by ``ratio`` in every joint alike."""
        return [p + (v - p) / ratio for p, v in zip(prev, q, strict=True)]

    def _port_step(
        self,
        target: Vec3,
        last: Sequence[float] | None,
        prev: Sequence[float],
        full: tuple[list[float], float] | None,
    ) -> tuple[list[float], bool, bool] | None:
        """A slowed step through the port: the tip a share of the straight way from where it
        is told to be (``prev``) toward ``target``, the pose there solved through the port,
        what is still over the limits scaled (a fraction of one tick's step, leaving the port
        only to second order in it). The share: that of the full solution ``full`` (joints,
        ratio) when given; else as far as the last slowed step went at the limits (no full
        solve while the tool keeps being slowed), or None when the target is nearer than that
        (then the full solve decides)."""
        ctx = self.ctx
        assert ctx is not None
        x, y, z = ctx.frame.tip_position(prev)
        dx, dy, dz = target[0] - x, target[1] - y, target[2] - z
        dist = math.sqrt(dx * dx + dy * dy + dz * dz)
        if full is not None:
            q_full, ratio = full
            share = 1.0 / ratio
            seed = [p + share * (v - p) for p, v in zip(prev, q_full, strict=True)]
        else:
            assert self._reach is not None
            if dist <= self._reach:
                return None
            share = self._reach / dist
            seed = list(prev)
        way = (x + share * dx, y + share * dy, z + share * dz)
        q, clamped = self.pose_solution(way, self.rcm_rotation(way, last), seed)
        ratio = self.ratio(prev, q)
        # the next slowed step a little farther than this one would have gone at the limits
        # (REACH_AHEAD): scaled back, it is at them, not short of them by the change of the
        # arm's Jacobian from one tick to the next (about 1 %)
        self._reach = REACH_AHEAD * share * dist / ratio if ratio > 1e-9 else None
        if ratio > 1.0:
            q = self.scaled(prev, q, ratio)
        return q, clamped, True
