"""The slave side of the OCC pair (the package docstring tells the whole story)."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import pydantic.main  # noqa: F401 - mypyc: the module its run-time BaseModel checks look up
from mypy_extensions import mypyc_attr
from pydantic import BaseModel

from occ.config import DaemonConfig
from occ.controllers import Controller, ControllerContext, Problem, SourceFn
from occ.controllers.teleop.absolute import ServoTarget
from occ.controllers.teleop.checks import check_slave
from occ.controllers.teleop.common import MM, as_mm
from occ.controllers.teleop.instrument import build_force, define_tissue, tare
from occ.controllers.teleop.phaselock import PhaseLock
from occ.controllers.teleop.returnsrc import ReturnSource
from occ.controllers.teleop.shaping import ContactShaper
from occ.controllers.teleop.sixdof import SixDof
from occ.controllers.teleop_params import SlaveParams
from occ.core.safety import RobotState
from occ.core.stats import Histogram
from occ.errors import CommandError, ConfigError, KinematicsError
from occ.events import InputEvent
from occ.haptics.forces import SlaveForce
from occ.haptics.forceviz import ForceView
from occ.haptics.gripper import GripperFollower
from occ.samples import PoseSample

if TYPE_CHECKING:
    from occ.core.data import RobotData
    from occ.net.commands import Request
    from occ.net.outputs import Outgoing, Output

log = logging.getLogger(__name__)


@mypyc_attr(allow_interpreted_subclasses=True)  # mypyc: plugins extend built-ins
class SlaveController(Controller):
    """The slave side of the OCC pair: follows the master's POSITION stream, scaled and
    re-indexed so it never jumps; the base pose from the config or a tracker. Output source
    ``teleop-return``: its tip (patient frame, as 3D Slicer's ``Tip``) back to the master at the
    stream rate, the tool of the master's virtual fixtures (occ/haptics/returnlink.py)."""

    name = "teleop-slave"
    Params = SlaveParams

    def __init__(self, params: BaseModel | dict[str, Any] | None = None) -> None:
        super().__init__(params)
        p = self.params
        assert isinstance(p, SlaveParams)
        self.scale = p.scale
        self.rotation = np.eye(3) if p.rotation is None else np.array(p.rotation, dtype=float)
        # scale * R as nested floats: the per-sample mapping is plain arithmetic (small-array
        # numpy costs more than the arithmetic on the loop thread)
        self._sr: list[list[float]] = (self.scale * self.rotation).tolist()
        self.input_interface = p.input_interface
        self.input_device = p.input_device
        self.base_mm = p.base_mm
        self.base_interface = p.base_interface
        self.base_device = p.base_device
        #: the loop phase-locked to the master's stream (phaselock.py), or None
        self.phase = None if p.phase_lock_us is None else PhaseLock(p.phase_lock_us * 1e-6)
        self.master_pos: tuple[float, float, float] | None = None
        self.master_run = False
        self.master_clutch = False
        self.master_ref: tuple[float, float, float] | None = None
        self.slave_ref: tuple[float, float, float] | None = None
        self._q_last: list[float] | None = None
        self._fresh = False
        #: the interface the followed samples come from (several with collaborative control)
        self.source: str | None = None
        self.source_changes = 0
        self.last_seq: int | None = None
        self.last_sample_t: float | None = None
        self.samples = 0
        self.reindexes = 0
        self.clamped = 0
        self.ik_failures = 0
        # latency probe: master sample time (its POSITION timestamp, wall clock) to the tick
        # whose driver write used it (same machine, same clock)
        self.pending_ts: float | None = None
        # O(1) per sample, fixed memory, cheap percentiles (a list of every sample cost 38 ms
        # of percentiles per GetStats)
        self.latency_us = Histogram()
        self.rx_latency_us = Histogram()
        self.pending_rx = 0.0
        #: the tip force sent on the return channel (occ/haptics/forces.py), built at configure
        self.force_params = p.force
        self.force: SlaveForce | None = None
        self.force_view: ForceView | None = None
        #: orientation following (a 6-DOF arm): the master's quaternion, and at the
        #: re-index its rotation and the tool's (base frame)
        self.follow_orientation = p.orientation in ("follow", "rcm")
        self.six = SixDof(
            self.rotation, p.rotation_scale, p.rcm_mm if p.orientation == "rcm" else None
        )
        self.rcm_error_max = 0.0
        #: the last pose solve was slowed to the velocity limits short of its target: the
        #: ticks between samples go on toward it (a 500 Hz stream on the 1 kHz loop)
        self._behind = False
        #: ``absolute`` mapping (an external command source, CRTK ``servo_cp``)
        self.absolute = p.mapping == "absolute"
        self.servo = ServoTarget(p.max_jump_mm * MM, self.six, p.orientation)
        self.rate_limited = 0
        #: the jaw that follows the master's gripper value (occ/haptics/gripper.py)
        self._gripper_params = p.gripper
        self.gripper: GripperFollower | None = None
        #: the tip commanded: the force limit, the passivity port, the release (shaping.py)
        self.shaper = ContactShaper(p)
        #: the return channel, output source ``teleop-return`` (returnsrc.py)
        self.ret = ReturnSource(self.scale, self.rotation, self.shaper.port)

    @classmethod
    def check(cls, params: Any, config: DaemonConfig) -> list[Problem]:
        return check_slave(params, config)

    def outputs(self) -> dict[str, SourceFn]:
        out: dict[str, SourceFn] = {"teleop-return": self._source_return}
        if self.force_params is not None:
            out["force"] = self._source_force  # the force to 3D Slicer (occ/haptics/forceviz.py)
        return out

    def _source_force(self, out: Output, now: float) -> Outgoing | None:
        return None if self.force_view is None else self.force_view(out, now)

    def commands(self) -> tuple[str, ...]:
        return ("ForceTare",) if self.force_params is not None else ()

    def on_command(self, request: Request, now: float) -> str | None:
        if request.name.strip().lower() != "forcetare" or self.force is None:
            raise CommandError(f"unknown command {request.name!r}")
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        return tare(self.force, data, ctx, now)

    def on_input(self, event: InputEvent, now: float) -> None:
        if self._tissue(event):
            return
        if self.force is not None:
            self.force.on_input(event, now)

    def _tissue(self, event: Any) -> bool:
        """A tissue definition from 3D Slicer for the simulated world (:func:`define_tissue`):
        True when it was one."""
        return define_tissue(event, self.ctx)

    def _source_return(self, out: Output, now: float) -> PoseSample | None:
        """The return channel: the tip as 3D Slicer sees it (patient frame), to the master
        that streams to this interface (occ/haptics/returnlink.py has the format)."""
        if not self.ret.check(out):
            return None
        data = self.data
        assert data is not None
        following = (
            data.state is RobotState.RUNNING
            and self.source == out.interface.name
            and self.master_run
            and not self.master_clutch
            and self.master_ref is not None
        )
        return self.ret.sample(out, now, following)

    def configure(self, data: RobotData, ctx: ControllerContext) -> None:
        super().configure(data, ctx)
        self.six.bind(data, ctx)
        self.servo.bind(data, ctx)
        g = self._gripper_params
        if g is not None:
            i = data.joint_names.index(g.joint)
            moves = float(np.linalg.norm(ctx.frame.jacobian(data.q)[:3, i]))
            if moves > 1e-9:  # the IK would move it for the tip, the gripper for the jaw
                raise ConfigError(
                    f"teleop-slave gripper: joint '{g.joint}' moves the tool's tip "
                    f"({moves:.3g} m per unit): a jaw must not"
                )
            step = 0.9 * ctx.joint_limits[i].velocity * ctx.period_s
            self.gripper = GripperFollower(i, g.joint, g.open, g.closed, step)
        fp = self.force_params
        if fp is not None:
            self.force = build_force(fp, data, ctx)
            self.force_view = ForceView(self.force, data, ctx, fp.display_mm_per_n)
        self.shaper.bind(self.force, data, ctx)
        self.ret.bind(self.force, data, ctx)
        if self.base_mm is not None:
            b = np.eye(4)
            b[:3, 3] = np.array(self.base_mm, dtype=float) * MM
            data.base = b

    def on_sample(self, sample: PoseSample, now: float) -> None:
        if sample.kind == "TRANSFORM" and sample.meta.get("kind") == "tissue":
            self._tissue(sample)
            return
        if self.base_interface and sample.interface == self.base_interface:
            if sample.kind == "TRANSFORM" and sample.device == self.base_device:
                m = sample.matrix_mm()
                m[:3, 3] *= MM
                assert self.data is not None
                self.data.base = m
            return
        if self.input_interface and sample.interface != self.input_interface:
            return
        if self.input_device and sample.device != self.input_device:
            return
        pos = sample.position_mm
        if sample.interface != self.source:
            # another master has the motion (a collaborative hand-over): its first sample
            # re-indexes, as a rising ``run`` does, so the slave keeps its pose
            if self.source is not None:
                self.source_changes += 1
            self.source = sample.interface
            self.master_ref = None
            self.master_run = False
            if self.phase is not None:
                self.phase.phases.clear()
            self.shaper.port_active = False  # the new master's energy, when it sends some
        self.samples += 1
        self.last_seq = sample.seq
        self.last_sample_t = sample.t_rx
        energy = sample.meta.get("energy_j")
        if energy is not None:
            self.shaper.master_energy(energy)
        ts = sample.t_sample
        phase = self.phase
        if phase is not None:
            if ts > 0.0:  # when the master sampled, on our loop's clock
                phase.track(ts - self.ctx.wall_offset(), self.ctx)  # type: ignore[union-attr]
            else:
                phase.track(sample.t_rx, self.ctx)
        self.pending_ts = ts if ts > 0.0 else None
        self.pending_rx = sample.t_rx
        self.master_pos = (pos[0] * MM, pos[1] * MM, pos[2] * MM)
        self.six.master_quat = sample.quaternion
        self._fresh = True
        if self.gripper is not None:
            self.gripper.on_meta(sample.meta.get("gripper"))
        run = sample.run
        clutch = sample.clutch
        if (run and not self.master_run) or (self.master_clutch and not clutch):
            self.master_ref = None  # re-index on the next update
        self.master_run, self.master_clutch = run, clutch

    def on_state(self, old: RobotState, new: RobotState, now: float) -> None:
        if new is RobotState.STOPPED or old is RobotState.STOPPED:
            self.shaper.stop_changed()
        if new is RobotState.RUNNING:
            self.master_ref = None
            if self.gripper is not None:
                self.gripper.restart()
            if self.absolute:  # from where the drives hold; the last target checked afresh
                self.servo.drop()
                self._q_last = None
                self._fresh = self.master_pos is not None
            elif old is RobotState.STOPPED:
                # never the target of before the stop: a stop in contact let go of the tissue
                # (hold), and re-joining that target would press into it again; nor a
                # reference from the last sample before it (a latched loss: the master moved
                # on since, and its next sample would jump the tool by as much). The drives
                # hold until the next sample re-indexes from where they are.
                self._q_last = None
                self._fresh = False

    def update(self, now: float) -> Sequence[float] | None:
        q = self._follow(now)
        g = self.gripper
        if g is None or q is None:
            return q
        following = self.master_run and not self.master_clutch and self.master_ref is not None
        return g.apply(list(q), following)

    def _follow(self, now: float) -> Sequence[float] | None:
        """The arm's setpoints (every joint; the jaw's is the gripper's: :meth:`update`)."""
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        if self.absolute:
            return self._update_absolute(data, ctx)
        if self.master_pos is None or not self.master_run or self.master_clutch:
            self.master_ref = None
            return self._q_last if self._q_last is not None else None
        if self.master_ref is None:
            if not self._fresh:
                return self._q_last  # a reference only from a sample that just came
            if not all(math.isfinite(v) for v in self.master_pos):
                # never a reference from a sample that is no point (NaN, inf): every later
                # target would be NaN until the next re-index. Counted once, held meanwhile.
                if self._fresh:
                    self._fresh = False
                    self.ik_failures += 1
                return None
            self._reindex(data, ctx, now)
        assert self.slave_ref is not None and self.master_ref is not None
        shaper = self.shaper
        fresh = self._fresh
        if fresh:
            self._fresh = False
            (a, b, c), (d, e, f), (g, h, i) = self._sr
            mx, my, mz = self.master_pos
            rx, ry, rz = self.master_ref
            dx, dy, dz = mx - rx, my - ry, mz - rz
            sx, sy, sz = self.slave_ref
            raw = (
                sx + a * dx + b * dy + c * dz,
                sy + d * dx + e * dy + f * dz,
                sz + g * dx + h * dy + i * dz,
            )
            if not all(math.isfinite(v) for v in raw):
                self.ik_failures += 1  # no point: never a target (nor a gap) from it
                return self._q_last
            shaper.raw = raw
        # the contact force once a tick (base frame): whether to shape, and how
        force = shaper.force_base()
        # no new master sample since the last solve: the same target, reached already unless
        # the solve was slowed (then this tick goes on toward it, SR-SIXDOF-1)
        idle = not fresh and self._q_last is not None and not self._behind
        if idle and not shaper.shaping(force):
            return self._q_last
        before = shaper.cmd
        target = shaper.shape(now, force)
        if idle and target == before:
            return self._q_last
        try:
            if self.follow_orientation:
                q, clamped, limited = self.six.solve(target, self._q_last)
                self.rate_limited += limited
                self._behind = limited
            else:
                q, clamped = ctx.frame.ik_clamped(target, data.q)
        except (KinematicsError, ValueError):
            self.ik_failures += 1
            self._behind = False  # tried again with the next sample, not every tick
            return self._q_last
        if clamped:
            self.clamped += 1
        self._q_last = q
        if fresh and self.pending_ts is not None:
            wall, mono = ctx.clock.wall_time(), ctx.clock.now()
            self.latency_us.add((wall - self.pending_ts) * 1e6)
            # split: master timestamp -> received by our interface thread -> used here
            self.rx_latency_us.add((wall - (mono - self.pending_rx) - self.pending_ts) * 1e6)
            self.pending_ts = None
        return self._q_last

    def _reindex(self, data: RobotData, ctx: ControllerContext, now: float) -> None:
        """The references of a re-index, taken from the sample that just came."""
        self._fresh = True
        self.master_ref = self.master_pos
        # from where the drives are told to be (while RUNNING the last setpoint), not
        # where they lag behind it: a re-index while moving (a hand-over, a clutch) then
        # keeps the commanded pose exactly instead of stepping back by the servo lag
        here = data.commanded()
        self.slave_ref = ctx.frame.tip_position(here)
        if self.follow_orientation:
            self.six.reindex(here)
        self.reindexes += 1
        self._q_last = list(here)
        self._behind = False
        sx, sy, sz = self.slave_ref
        self.shaper.reindex((float(sx), float(sy), float(sz)), now)

    def hold(self, now: float, setpoint: list[float]) -> None:
        """While STOPPED: a stop in contact lets go of the tissue (DESIGN.md: "a stop in
        contact lets go of the tissue rather than holding a position inside it"): the held
        setpoint backs the tool out along the force (:meth:`ContactShaper.release`). The
        master sees the stop on the return channel (``state``) and tells the hand."""
        ctx = self.ctx
        step = self.shaper.release(setpoint)
        if step is None or ctx is None:
            return
        target, length = step
        try:
            if self.follow_orientation:
                pose = np.asarray(ctx.frame.fk(setpoint), dtype=float).copy()
                if self.six.rcm_mm is not None:
                    pose[:3, :3] = self.six.rcm_rotation(target, self._q_last)
                pose[:3, 3] = target
                q = ctx.frame.solve_ik(pose, setpoint, clamp=True, method="dls").q.tolist()
            else:
                q, _clamped = ctx.frame.ik_clamped(target, setpoint)
        except (KinematicsError, ValueError):
            self.ik_failures += 1
            return
        setpoint[:] = q
        self.shaper.released_mm += length / MM

    def _update_absolute(self, data: RobotData, ctx: ControllerContext) -> Sequence[float] | None:
        """The ``absolute`` mapping (absolute.py): each sample is the tip's target in the
        patient frame, judged against where the tip is told to be (``max_jump_mm``); every
        tick the joints go on toward it, together, within 0.9 of their velocity limits. A
        stopped stream (``run=0``), the clutch, a refused or unsolvable target: hold where the
        joints were told to be (never a jump when it comes back)."""
        here = self._q_last if self._q_last is not None else data.commanded()
        servo = self.servo
        if self.master_pos is None or not self.master_run or self.master_clutch:
            servo.drop()
            self.master_ref = None
            return self._q_last
        if self._fresh:
            self._fresh = False
            self.master_ref = None
            first = self._q_last is None
            taken, clamped, failed = servo.take(self.master_pos, here, first)
            if not taken:
                self.ik_failures += failed
                return self._q_last
            self.clamped += clamped
            self.master_ref = self.master_pos
            self.reindexes += first
        q, slowed, clamped, failed = servo.step(here)
        self.clamped += clamped
        if q is None:
            self.ik_failures += failed
            return self._q_last
        self.rate_limited += slowed
        self._q_last = q
        if self.pending_ts is not None:
            self.latency_us.add((ctx.clock.wall_time() - self.pending_ts) * 1e6)
            self.pending_ts = None
        return q

    def stats(self) -> dict[str, Any]:
        phase = self.phase
        out: dict[str, Any] = {
            "mapping": "absolute" if self.absolute else "relative",
            "samples": self.samples,
            "last_seq": self.last_seq,
            "master_run": self.master_run,
            "master_clutch": self.master_clutch,
            "reindexes": self.reindexes,
            "source": self.source,
            "source_changes": self.source_changes,
            "ik_clamped": self.clamped,
            "ik_failures": self.ik_failures,
            "phase_shifts": phase.shifts if phase is not None else 0,
            "phase_error_us": phase.error_us if phase is not None else None,
            "phase_history_us": list(phase.history) if phase is not None else [],
            # the references of the last re-index (mm): the tracking error of a recording is
            # measured against slave_ref + scale * (master - master_ref) (tools/soak.py paper)
            "master_ref_mm": as_mm(self.master_ref),
            "slave_ref_mm": as_mm(self.slave_ref),
        }
        if self.force is not None:
            out["instrument"] = self.shaper.stats()
            now = self.ctx.clock.now() if self.ctx is not None else math.nan
            out["force"] = self.force.stats(now)
            if self.force_view is not None:
                out["force"]["display"] = self.force_view.stats()
        if self.absolute:
            out["servo_refused"] = self.servo.refused
            out["servo_rate_limited"] = self.rate_limited
        if self.follow_orientation:
            out["rate_limited"] = self.rate_limited
        if self.gripper is not None:
            out["gripper"] = self.gripper.stats()
        if self.latency_us.count:
            lat = self.latency_us.summary()
            out["sample_to_write_us"] = {
                "n": self.latency_us.count,
                "p50": round(lat["p50"], 1),
                "p99": round(lat["p99"], 1),
                "max": round(lat["max"], 1),
            }
            rx = self.rx_latency_us.summary()
            out["sample_to_rx_us"] = {"p50": round(rx["p50"], 1), "p99": round(rx["p99"], 1)}
        return out
