"""RobotData: the robot's state as controllers, output sources and the recorder see it.

The :class:`~occ.core.robot.Robot` owns one and writes it on the loop thread (measured joints after
the drivers are read, the setpoint it writes, the state after each transition); everyone else
reads it, on the loop thread too, and never holds the Robot. A controller may write two
things: the ``base`` pose (e.g. from a tracker) and nothing else; the setpoints it wants come
back from its ``update``, and the Robot decides what reaches the drivers (ros2_control's
split between state and command interfaces).

Units are SI (metres, radians); poses are 4x4 homogeneous matrices in metres.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from occ.core.safety import RobotState

if TYPE_CHECKING:
    from occ.clock import Clock
    from occ.joint import Joint
    from occ.kinematics.frame import Frame, Rows


class RobotData:
    """The state of one robot (see the module docstring)."""

    __slots__ = (
        "name",
        "joint_names",
        "q",
        "effort",
        "qdot",
        "setpoint",
        "hold_setpoint",
        "effort_command",
        "base",
        "state",
        "clock",
        "frame",
        "_tip",
        "_tip_stale",
        "_base_key",
        "_base_rt",
    )

    def __init__(
        self,
        name: str,
        joint_names: Sequence[str],
        home: Sequence[float],
        frame: Frame | None,  # None: occ/core/loader.py's claim check (mypyc checks the type)
        clock: Clock,
    ) -> None:
        self.name = name
        self.joint_names: tuple[str, ...] = tuple(joint_names)
        #: measured joint positions (the last driver read)
        self.q: list[float] = [float(v) for v in home]
        #: measured joint efforts (the last driver read: what the drives report they exert)
        self.effort: list[float] = [0.0] * len(self.q)
        #: measured joint velocities
        self.qdot: list[float] = [0.0] * len(self.q)
        #: what the drivers were last told while RUNNING
        self.setpoint: list[float] = list(self.q)
        #: the last safe setpoint: held while ENABLED or STOPPED, and while a stream is late
        self.hold_setpoint: list[float] = list(self.q)
        #: the efforts the drivers were last told, when the controllers command efforts (a
        #: haptic master's displayed force); None otherwise
        self.effort_command: list[float] | None = None
        #: base pose in the world (config or tracker): what 3D Slicer shows the tip relative to
        self.base: np.ndarray = np.eye(4)
        self.state = RobotState.INIT
        self.clock = clock
        self.frame = frame
        self._tip = np.eye(4)
        self._tip_stale = True
        #: the base pose as plain floats (rotation rows or None for none, translation), and
        #: the bytes it was made from: rebuilt when the base changes
        self._base_key = b""
        self._base_rt: tuple[Rows | None, tuple[float, float, float]] = (None, (0.0, 0.0, 0.0))

    def measured_from(self, joints: Sequence[Joint]) -> None:
        """New measurements: ``q``, ``qdot`` and ``effort`` from the joints' last reads (the
        Robot, each tick); the tip is recomputed when asked."""
        q = self.q
        eff, qd = self.effort, self.qdot
        for i, j in enumerate(joints):
            q[i] = j.position
            qd[i] = j.velocity
            eff[i] = j.effort
        self._tip_stale = True

    @property
    def tip(self) -> np.ndarray:
        """The tip pose in the base frame (forward kinematics of ``q``), computed lazily:
        outputs run at 10 Hz, the loop at 1 kHz."""
        if self._tip_stale:
            assert self.frame is not None
            self._tip = self.frame.fk(self.q)
            self._tip_stale = False
        return self._tip

    def world_tip(self) -> np.ndarray:
        """The tip pose in world coordinates (base pose x forward kinematics)."""
        return self.base @ self.tip

    def world_tip_pose(self) -> tuple[Rows, tuple[float, float, float]]:
        """:meth:`world_tip` as plain floats, (rotation rows, position in metres): the
        frame's closed form where it has one and no numpy (the 500 Hz return channel)."""
        assert self.frame is not None
        rows, (x, y, z) = self.frame.tip_pose(self.q)
        key = self.base.tobytes()
        if key != self._base_key:
            self._base_key = key
            b = self.base.tolist()
            rot = (
                (b[0][0], b[0][1], b[0][2]),
                (b[1][0], b[1][1], b[1][2]),
                (b[2][0], b[2][1], b[2][2]),
            )
            identity = rot == ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
            self._base_rt = (None if identity else rot, (b[0][3], b[1][3], b[2][3]))
        rot_b, (tx, ty, tz) = self._base_rt
        if rot_b is None:
            return rows, (x + tx, y + ty, z + tz)
        (b00, b01, b02), (b10, b11, b12), (b20, b21, b22) = rot_b
        c0, c1, c2 = zip(*rows, strict=True)
        return (
            (
                (
                    b00 * c0[0] + b01 * c0[1] + b02 * c0[2],
                    b00 * c1[0] + b01 * c1[1] + b02 * c1[2],
                    b00 * c2[0] + b01 * c2[1] + b02 * c2[2],
                ),
                (
                    b10 * c0[0] + b11 * c0[1] + b12 * c0[2],
                    b10 * c1[0] + b11 * c1[1] + b12 * c1[2],
                    b10 * c2[0] + b11 * c2[1] + b12 * c2[2],
                ),
                (
                    b20 * c0[0] + b21 * c0[1] + b22 * c0[2],
                    b20 * c1[0] + b21 * c1[1] + b22 * c1[2],
                    b20 * c2[0] + b21 * c2[1] + b22 * c2[2],
                ),
            ),
            (
                b00 * x + b01 * y + b02 * z + tx,
                b10 * x + b11 * y + b12 * z + ty,
                b20 * x + b21 * y + b22 * z + tz,
            ),
        )

    def commanded(self) -> list[float]:
        """The setpoint the drivers hold now: the running setpoint, else the held one."""
        return self.setpoint if self.state is RobotState.RUNNING else self.hold_setpoint
