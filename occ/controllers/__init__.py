"""Controllers: what the robot does while RUNNING.

A controller never touches hardware (ros2_control's rule): each tick it reads the robot's state
(joint positions, tip pose) and the samples drained from its input streams, and returns joint
setpoints. The robot passes those to its drivers, which check state and limits.

Hooks, all called on the loop thread:

- ``bind(robot)``: once, when the robot is built (register output sources, find interfaces);
- ``on_sample(item, now)``: every stream sample drained this tick, in arrival order;
- ``on_command(request, now) -> str | None``: an operator command the robot does not handle
  itself (e.g. ``Clutch``); return a reply message, or raise CommandError;
- ``on_state(old, new, now)``: after every state transition (re-reference on RUNNING);
- ``update(now) -> Sequence[float] | None``: joint setpoints while RUNNING; None = hold.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..commands import Request
    from ..interfaces import Inbound
    from ..robot import Robot
    from ..safety import RobotState


class Controller:
    """Base controller: holds position (returns None) and handles nothing."""

    name = "hold"
    #: False for devices moved by hand (a passive haptic master): the robot then never writes
    #: position commands to the drivers, it only reads them.
    drives_joints = True

    def __init__(self, params: dict[str, Any] | None = None) -> None:
        self.params = dict(params or {})
        self.robot: Robot | None = None

    def bind(self, robot: Robot) -> None:
        self.robot = robot

    def on_sample(self, item: Inbound, now: float) -> None:
        return None

    def on_command(self, request: Request, now: float) -> str | None:
        from ..errors import CommandError

        raise CommandError(f"unknown command {request.name!r}")

    def on_state(self, old: RobotState, new: RobotState, now: float) -> None:
        return None

    def update(self, now: float) -> Sequence[float] | None:
        return None

    def commands(self) -> tuple[str, ...]:
        """Extra operator commands this controller understands (for GetState/capabilities)."""
        return ()

    def stats(self) -> dict[str, Any]:
        return {}
