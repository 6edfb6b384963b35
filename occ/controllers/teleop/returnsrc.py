"""The slave's return channel: the output source ``teleop-return``, its tip (patient frame, as
3D Slicer's ``Tip``) back to the master that streams to this interface, with ``following``,
``state``, ``map`` and, with a force source, the tip force, the port's energy and a 6-axis
sensor's torque (occ/haptics/returnlink.py has the format)."""

from __future__ import annotations

from types import MappingProxyType
from typing import TYPE_CHECKING

import numpy as np

from occ.errors import OCCError
from occ.samples import PoseSample, rotation_to_quaternion

if TYPE_CHECKING:
    from occ.controllers import ControllerContext
    from occ.core.data import RobotData
    from occ.haptics.forces import SlaveForce
    from occ.haptics.passivity import SlavePort
    from occ.net.outputs import Output


class ReturnSource:
    """The slave's tip stream to its master: each output's sequence numbers, and its metadata
    by (following, state, map), built once each. ``scale`` and ``rotation`` the slave's mapping
    (its ``map``), ``port`` its passivity port (the energy sent)."""

    def __init__(self, scale: float, rotation: np.ndarray, port: SlavePort) -> None:
        self.scale = scale
        self.rotation = rotation
        self.port = port
        self._return_seqs: dict[int, int] = {}
        self._return_meta: dict[tuple[bool, str, str], MappingProxyType[str, str]] = {}
        self._map_base: np.ndarray | None = None
        self._map_text = ""
        self.returned = 0
        self.force: SlaveForce | None = None
        self.data: RobotData | None = None
        self.ctx: ControllerContext | None = None

    def bind(self, force: SlaveForce | None, data: RobotData, ctx: ControllerContext) -> None:
        self.force, self.data, self.ctx = force, data, ctx

    def check(self, out: Output) -> bool:
        """Is there a master to send ``out``'s samples to? (OCCError: not a POSITION output)"""
        if out.type != "POSITION":
            raise OCCError("teleop-return output must be of type POSITION")
        iface = out.interface
        # no master has streamed to this interface yet: nobody to tell
        return not (iface.stream_owner is None and iface.sends_to_owner)

    def force_meta(self, now: float) -> str:
        """The tip force now (``force_n``: N, patient frame, 4 decimals) for the return
        channel."""
        force, data, ctx = self.force, self.data, self.ctx
        assert force is not None and data is not None and ctx is not None
        f = force.estimate(
            now, ctx.frame, data.q, data.qdot, data.effort, data.base, lambda: data.tip[:3, :3]
        )
        return f"{f[0]:.4f},{f[1]:.4f},{f[2]:.4f}"

    def map(self) -> str:
        """The ``map`` metadata: how a handle displacement (master mm) moves the tip in the
        patient frame (mm): base rotation x scale x master-to-slave rotation, row by row.
        Rebuilt only when the base pose object changes (a tracker's TRANSFORM)."""
        data = self.data
        assert data is not None
        base = data.base
        if base is not self._map_base:
            self._map_base = base
            lin = (np.asarray(base, dtype=float)[:3, :3] @ (self.scale * self.rotation)).ravel()
            self._map_text = ",".join(f"{v:.9g}" for v in lin.tolist())
        return self._map_text

    def meta(self, following: bool, now: float) -> MappingProxyType[str, str]:
        """A sample's metadata (one mapping per (following, state, map) without a force)."""
        data = self.data
        assert data is not None
        key = (following, data.state.value, self.map())
        meta = self._return_meta.get(key)
        if meta is None:
            if len(self._return_meta) > 64:  # a tracker moving the base: keep it bounded
                self._return_meta.clear()
            meta = MappingProxyType(
                {"following": "1" if following else "0", "state": key[1], "map": key[2]}
            )
            self._return_meta[key] = meta
        if self.force is None:
            return meta
        # one estimate per return sample: the effort source's momentum observer takes the time
        # since its last estimate (a second one now would see dt = 0 and count the joints'
        # acceleration as a load)
        extra = {
            "force_n": self.force_meta(now),
            # this port's energy in (J at the instrument): what the master may give the hand
            # (occ/haptics/passivity.py)
            "energy_j": f"{self.port.account.e_in:.9g}",
        }
        t = self.force.torque_nm
        if t is not None:  # a 6-axis sensor's (occ/haptics/returnlink.py): old masters ignore it
            extra["torque_nm"] = f"{t[0]:.5f},{t[1]:.5f},{t[2]:.5f}"
        return MappingProxyType({**meta, **extra})

    def sample(self, out: Output, now: float, following: bool) -> PoseSample:
        """The next sample of output ``out``, ``following`` (the slave follows this master)."""
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        meta = self.meta(following, now)
        rows, (x, y, z) = data.world_tip_pose()
        k = id(out)
        seq = (self._return_seqs.get(k, 0) + 1) & 0xFFFFFFFF
        self._return_seqs[k] = seq
        self.returned += 1
        return PoseSample(
            out.interface.name,
            None,
            out.device,
            (x * 1e3, y * 1e3, z * 1e3),
            rotation_to_quaternion(rows),
            seq=seq,
            t_sample=ctx.clock.wall_time(),
            meta=meta,
        )
