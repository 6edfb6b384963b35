"""The other arms of a cell, for the whole-arm collision check (occ/kinematics/collision.py).

A peer arm is another robot beside this one (several arms around one patient, issue 40): its
link geometry is built from its ``frame`` configuration by the own arm's rules
(occ/kinematics/armgeom.py: hulls, capsules where its URDF has none, an optional tool), and its
*state* is what the cell link last said of it: joint positions in its URDF's order, its base
pose (world <- its base link, metres: the frame and units of this robot's ``RobotData.base``)
and the time the positions were measured, on this robot's clock.

A state is old by the time a check uses it. How far the peer can have moved since is bounded
by :attr:`PeerArm.speed`: the fastest any point of its geometry can move, ``sum_i v_i R_i``
(its joints' velocity limits ``v_i`` times their reach ``R_i``: the own arm's motion bound,
occ/kinematics/collision.py ``CollisionModel.bound``, at the velocity limits for one second).
A state is swapped whole (one reference), so the loop thread updates it in O(1) while a checker
on another thread reads it once per check.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from occ.errors import ConfigError
from occ.kinematics.armgeom import ArmGeometry, load_arm

if TYPE_CHECKING:
    from occ.config import FrameConfig

__all__ = ["PeerArm", "PeerState", "build_peer", "peer_frame"]


@dataclass(frozen=True, slots=True)
class PeerState:
    """Where a peer arm was: joint positions (its URDF's order), its base pose (world <- its
    base link, metres) and when the positions were measured (this robot's clock, s)."""

    q: tuple[float, ...]
    base: Any  # np.ndarray (4, 4)
    t: float


class PeerArm:
    """Another arm of the cell: its geometry, its speed bound and its last known state.

    ``present`` is False after :meth:`gone` (it left the cell: not checked) until the next
    :meth:`update`; a present arm without a state is an unknown obstacle."""

    def __init__(self, name: str, arm: ArmGeometry, velocities: Sequence[float]) -> None:
        self.name = name
        self.arm = arm
        self.nq = int(arm.model.nq)
        #: the fastest any point of its geometry can move at its velocity limits (m/s)
        self.speed = sum(v * r for v, r in zip(velocities, arm.reach, strict=True))
        self.state: PeerState | None = None
        self.present = True

    def update(self, q: Sequence[float], base: Any, t: float) -> bool:
        """A new state (the loop thread, O(joints)); True when the arm was gone and is back.
        ValueError for positions or a pose that cannot be used (nothing changes)."""
        qt = tuple(float(v) for v in q)
        if len(qt) != self.nq:
            raise ValueError(f"arm {self.name!r}: {len(qt)} positions for {self.nq} joints")
        if not all(math.isfinite(v) for v in qt) or not math.isfinite(t):
            raise ValueError(f"arm {self.name!r}: a joint position or the time is not finite")
        b = np.array(base, dtype=float)
        if b.shape != (4, 4) or not np.isfinite(b).all():
            raise ValueError(f"arm {self.name!r}: the base pose is not a finite 4x4 transform")
        self.state = PeerState(qt, b, float(t))
        back = not self.present
        self.present = True
        return back

    def gone(self) -> None:
        """It left the cell: not checked until its next update."""
        self.present = False
        self.state = None

    def describe(self) -> dict[str, Any]:
        return {
            "links": [lk.name for lk in self.arm.links],
            "speed_m_s": round(self.speed, 4),
            "present": self.present,
            "t": None if self.state is None else self.state.t,
        }


def peer_frame(frame_cfg: FrameConfig, key: str) -> Any:
    """The kinematics (occ/kinematics/frame.py ``Frame``) of a ``frame:`` configuration, as the
    robot builds its own (occ/core/assembly.py); ConfigError naming ``key``."""
    from occ.errors import KinematicsError
    from occ.kinematics.frame import Frame

    try:
        if frame_cfg.model is not None:
            return Frame.builtin(frame_cfg.model)
        path = frame_cfg.urdf_path()
        assert path is not None and frame_cfg.tip_link is not None  # the schema's rule
        return Frame.from_urdf(path, frame_cfg.tip_link, frame_cfg.base_link)
    except (KinematicsError, ValueError) as err:
        raise ConfigError(f"{key}: {err}") from err


def build_peer(
    name: str,
    frame_cfg: FrameConfig,
    *,
    convex: bool,
    link_radius: float,
    velocities: Sequence[float] | None = None,
    tool: tuple[float, float] | None = None,
) -> PeerArm:
    """A peer arm from its ``frame:`` configuration (the robot section's schema), its geometry
    by the own arm's rules; ``velocities`` its joints' limits (rad/s or m/s, its URDF's order;
    None: the URDF's). ConfigError naming the arm for what cannot be used."""
    if not name or ":" in name or any(c.isspace() for c in name) or name == "self":
        raise ConfigError(f"peer arm {name!r}: a name without ':' or spaces, not 'self'")
    key = f"peer arm {name!r}"
    frame = peer_frame(frame_cfg, key)
    arm = load_arm(frame_cfg, frame, convex=convex, link_radius=link_radius, tool=tool, key=key)
    nq = int(arm.model.nq)
    if velocities is None:
        velocities = [float(v) for v in arm.model.velocityLimit]
        if not all(math.isfinite(v) and v > 0.0 for v in velocities):
            raise ConfigError(f"{key}: its URDF gives no velocity limits; give them")
    vel = [float(v) for v in velocities]
    if len(vel) != nq:
        raise ConfigError(f"{key}: {len(vel)} velocity limits for {nq} joints")
    if not all(math.isfinite(v) and v > 0.0 for v in vel):
        raise ConfigError(f"{key}: every velocity limit must be a number > 0, got {vel}")
    return PeerArm(name, arm, vel)
