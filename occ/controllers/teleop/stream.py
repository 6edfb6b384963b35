"""The master's handle stream: the output source ``teleop``, the handle's pose to each slave
(POSITION, a sequence number per stream, ``run``/``clutch`` metadata, the gripper value and the
hand's energy when there are)."""

from __future__ import annotations

import math
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np
import pinocchio as pin

from occ.controllers.teleop.common import MM, RUN_CLUTCH
from occ.core.safety import RobotState
from occ.errors import OCCError
from occ.samples import PoseSample, rotation_to_quaternion

if TYPE_CHECKING:
    from occ.controllers import ControllerContext
    from occ.core.data import RobotData
    from occ.haptics.gripper import GripperSource
    from occ.net.outputs import Output

Quat = tuple[float, float, float, float]


class HandleStream:
    """The handle's samples as the slaves get them, and the simulated hand's clock (``t``
    counts time spent RUNNING only). ``p`` the master's parameters (MasterParams)."""

    def __init__(self, p: Any) -> None:
        self.input = p.input
        self.frequency = p.frequency_hz
        self._rot_amp = tuple(math.radians(v) for v in p.orientation_amplitude_deg)
        #: the handle's orientation sent with each sample (x, y, z, w)
        self.handle_quat: Quat = (0.0, 0.0, 0.0, 1.0)
        self.seq = p.first_seq & 0xFFFFFFFF
        self._first_seq = self.seq
        #: each teleop output's own sequence numbers (one stream per slave), by id(output)
        self._seqs: dict[int, int] = {}
        self.t_run = 0.0
        self.t_held = 0.0  # trajectory time already run when RUNNING was left
        self.gripper: GripperSource | None = None
        self.data: RobotData | None = None
        self.ctx: ControllerContext | None = None

    def bind(self, data: RobotData, ctx: ControllerContext, gripper: GripperSource | None) -> None:
        self.data, self.ctx, self.gripper = data, ctx, gripper

    def on_state(self, old: RobotState, new: RobotState, now: float) -> None:
        # The simulated hand's time runs only while RUNNING: re-entering RUNNING resumes the
        # trajectory where the robot was held (restarting it at t = 0 jumped the handle back to
        # the start point in one tick, tests/occ/test_contracts.py).
        if new is RobotState.RUNNING:
            self.t_run = now - self.t_held
        elif old is RobotState.RUNNING:
            self.t_held = now - self.t_run

    def sample(
        self, out: Output, now: float, running: bool, clutch: bool, energy: float | None
    ) -> PoseSample:
        """The next sample of output ``out``: the *measured* handle position (FK), ``running``
        (this slave is driven), ``clutch``, ``energy`` (the hand's, or None)."""
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        x, y, z = ctx.frame.tip_position(data.q)
        key = id(out)
        self.seq = seq = (self._seqs.get(key, self._first_seq) + 1) & 0xFFFFFFFF
        self._seqs[key] = seq
        if out.type != "POSITION":
            raise OCCError("teleop output must be of type POSITION")
        meta = self.meta(running, clutch, now, energy)
        return PoseSample(
            out.interface.name,
            None,
            out.device,
            (x / MM, y / MM, z / MM),
            self.orientation(now),
            seq=seq,
            t_sample=ctx.clock.wall_time(),
            meta=meta,
        )

    def meta(
        self, running: bool, clutch: bool, now: float, energy: float | None
    ) -> MappingProxyType[str, str]:
        """``run`` and ``clutch`` (one shared mapping each), with the gripper value when the
        master sends one (occ/haptics/gripper.py) and the hand's energy into the channel when
        it has one (``energy_j``: the slave's port puts no more into the tissue,
        occ/haptics/passivity.py); one mapping a sample."""
        meta = RUN_CLUTCH[running, clutch]
        g = self.gripper
        if g is None and energy is None:
            return meta
        extra = dict(meta)
        if g is not None:
            data = self.data
            assert data is not None
            t = now - self.t_run if data.state is RobotState.RUNNING else self.t_held
            extra["gripper"] = f"{g.update(data.q, t):.3f}"
        if energy is not None:
            extra["energy_j"] = f"{energy:.9g}"
        return MappingProxyType(extra)

    def orientation(self, now: float) -> Quat:
        """The handle's orientation: the simulated gimbal's (``orientation_amplitude_deg``),
        the input stream's, or the device's own (identity for a 3-DOF handle)."""
        if self.input == "sim":
            ax, ay, az = self._rot_amp
            if ax == 0.0 and ay == 0.0 and az == 0.0:
                return (0.0, 0.0, 0.0, 1.0)
            k = math.sin(2.0 * math.pi * self.frequency * (now - self.t_run))
            r = pin.utils.rpyToMatrix(ax * k, ay * k, az * k)
            return rotation_to_quaternion(r)
        if self.input == "igtl":
            return self.handle_quat
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        if ctx.frame.nq < 6:
            return (0.0, 0.0, 0.0, 1.0)
        return rotation_to_quaternion(np.asarray(ctx.frame.fk(data.q))[:3, :3])
