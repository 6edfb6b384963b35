"""Test-only: the other arms' states carried to each arm's collision guard, as the cell link
will carry them (occ/kinematics/collision.py ``CollisionGuard.peer_update``), in simulated time.

:class:`PeerFeed` holds arms by name, each with its guard, where its state comes from (joint
positions and base pose, read when sent) and its clock; :meth:`PeerFeed.tick` hands every arm's
state to every other arm's guard once every ``every`` calls (a heartbeat of ``every`` loop
periods), stamped with the receiver's time less ``age_s`` (how old a state is when it arrives).
Nothing here is the network: the cell link is built elsewhere.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from occ.kinematics.collision import CollisionGuard

__all__ = ["PeerFeed"]

State = tuple[Sequence[float], Any]


@dataclass
class _Arm:
    guard: CollisionGuard
    state: Callable[[], State]
    now: Callable[[], float]


class PeerFeed:
    """Every arm's state to every other arm's guard, every ``every`` ticks, ``age_s`` old."""

    def __init__(self, every: int = 1, age_s: float = 0.0) -> None:
        if every < 1 or age_s < 0.0:
            raise ValueError("every >= 1 tick and age_s >= 0")
        self.every = every
        self.age_s = age_s
        self.arms: dict[str, _Arm] = {}
        self.ticks = 0
        self.sent = 0

    def add(
        self,
        name: str,
        guard: CollisionGuard,
        state: Callable[[], State],
        now: Callable[[], float],
    ) -> None:
        """The arm ``name``: its guard, its (joint positions, base pose) now, its clock."""
        self.arms[name] = _Arm(guard, state, now)

    def tick(self) -> None:
        """One loop period: a heartbeat when its turn has come."""
        self.ticks += 1
        if (self.ticks - 1) % self.every:
            return
        states = {name: arm.state() for name, arm in self.arms.items()}
        for name, arm in self.arms.items():
            t = arm.now() - self.age_s
            for other, (q, base) in states.items():
                if other != name:
                    arm.guard.peer_update(other, q, base, t)
                    self.sent += 1
