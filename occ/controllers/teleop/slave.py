"""The slave side of the OCC pair (the package docstring tells the whole story)."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np
import pydantic.main  # noqa: F401 - mypyc: the module its run-time BaseModel checks look up
from mypy_extensions import mypyc_attr
from pydantic import BaseModel

from occ.config import DaemonConfig
from occ.controllers import Controller, ControllerContext, Problem, SourceFn
from occ.controllers.teleop_params import SlaveParams
from occ.core.safety import RobotState
from occ.core.stats import Histogram
from occ.errors import CommandError, ConfigError, KinematicsError, OCCError, caused
from occ.events import InputEvent
from occ.haptics.contact import tissue_from_event
from occ.haptics.forces import SlaveForce
from occ.haptics.forceviz import ForceView, check_outputs
from occ.haptics.gripper import GripperFollower
from occ.haptics.passivity import SlavePort, parse_energy
from occ.joint import step_toward
from occ.samples import PoseSample, rotation_to_quaternion

if TYPE_CHECKING:
    from occ.core.data import RobotData
    from occ.net.commands import Request
    from occ.net.outputs import Outgoing, Output

from occ.controllers.teleop.common import LIMIT_GAIN, MM, STATUS_OK, _interfaces_exist, _m, _mm
from occ.controllers.teleop.phaselock import PhaseLock
from occ.controllers.teleop.sixdof import SixDof

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
        #: the return channel (output source ``teleop-return``): each output's sequence
        #: numbers, and its metadata by (following, state, map), built once each
        self._return_seqs: dict[int, int] = {}
        self._return_meta: dict[tuple[bool, str, str], MappingProxyType[str, str]] = {}
        self._map_base: np.ndarray | None = None
        self._map_text = ""
        self.returned = 0
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
        #: ``absolute`` mapping (an external command source, CRTK ``servo_cp``)
        self.absolute = p.mapping == "absolute"
        self.max_jump = p.max_jump_mm * MM
        #: where the joints are going (absolute mapping): the last accepted target's solution
        self._q_goal: list[float] | None = None
        self._step: list[float] = []
        self._refusing = False
        self.refused = 0
        self.rate_limited = 0
        #: the jaw that follows the master's gripper value (occ/haptics/gripper.py)
        self._gripper_params = p.gripper
        self.gripper: GripperFollower | None = None
        #: the force limit at the instrument (N; None: none), resolved at configure
        self.max_tissue_force = p.max_tissue_force_n if p.force is not None else None
        # : the slave's port of the two-port passivity scheme (occ/haptics/passivity.py): on while
        # the : followed stream carries the master's energy
        self.port = SlavePort()
        self.port_on = p.passivity
        self._port_active = False
        self.bad_energy = 0
        self._drift_speed = p.drift_return_mm_s * MM
        #: the master's target mapped (base frame, m), the tip commanded, and the gap the
        #: port and the force limit left between them (commanded - mapped)
        self._raw: tuple[float, float, float] | None = None
        self._cmd: tuple[float, float, float] | None = None
        self._offset = (0.0, 0.0, 0.0)
        self._t_shape = math.nan
        self.offset_max_mm = 0.0
        self.limit_ticks = 0
        self.limit_hits = 0
        self._limiting = False
        #: a latched stop in contact lets go of the tissue (see :meth:`hold`)
        self._release_speed = p.release_speed_mm_s * MM
        self._release_force = p.release_force_n
        self._release_max = p.release_max_mm * MM
        self.releasing = False
        self.released_mm = 0.0
        self.releases = 0
        self._release_done = False

    @classmethod
    def check(cls, params: Any, config: DaemonConfig) -> list[Problem]:
        problems = _interfaces_exist(params, config, ("input_interface", "base_interface"))
        if params.orientation == "rcm" and params.rcm_mm is None:
            problems.append((("rcm_mm",), "required with orientation: rcm"))
        f = params.force
        if (
            f is not None
            and "tissue" in f.sources
            and (config.environment is None or not config.environment.contacts)
        ):
            problems.append((("force", "sources"), "tissue needs an environment with contacts"))
        n = len(config.robot.joints)
        for key in ("effort_damping", "effort_inertia"):
            values = getattr(f, key, None)
            if values is not None and len(values) != n:
                problems.append((("force", key), f"needs {n} values, one per joint"))
        if f is not None and "sensor" in f.sources:
            names = {i.name for i in config.interfaces}
            if f.sensor_interface is None:
                problems.append((("force", "sensor_interface"), "required with source sensor"))
            elif f.sensor_interface not in names:
                problems.append(
                    (("force", "sensor_interface"), f"no interface '{f.sensor_interface}'")
                )
        if f is not None and f.tool_mass_kg > 0.0:
            if "sensor" not in f.sources:
                problems.append(
                    (
                        ("force", "tool_mass_kg"),
                        "the weight beyond the sensor is removed from the sensor's readings: "
                        "needs `sensor` in sources (or 0)",
                    )
                )
            g = math.sqrt(sum(v * v for v in f.gravity_mps2))
            if not 9.76 <= g <= 9.84:  # the Earth's surface: 9.78 (equator) to 9.83 (poles)
                problems.append(
                    (
                        ("force", "gravity_mps2"),
                        f"magnitude {g:.4g} m/s^2: the Earth's is 9.78-9.83 m/s^2 (a unit or "
                        "sign slip would compensate a weight that is not there)",
                    )
                )
        g = params.gripper
        if g is not None:
            joints = {j.name: j for j in config.robot.joints}
            jc = joints.get(g.joint)
            if jc is None:
                problems.append((("gripper", "joint"), f"no joint '{g.joint}' ({list(joints)})"))
            else:
                lo, hi = jc.limits.min, jc.limits.max
                for key in ("open", "closed"):
                    v = getattr(g, key)
                    if not lo <= v <= hi:
                        problems.append(
                            (
                                ("gripper", key),
                                f"{v:g} is outside joint '{g.joint}' [{lo:g}, {hi:g}]",
                            )
                        )
            if g.open == g.closed:
                problems.append((("gripper", "closed"), "must differ from open"))
        if f is None and "max_tissue_force_n" in params.model_fields_set:
            if params.max_tissue_force_n is not None:
                problems.append(
                    (("max_tissue_force_n",), "needs `force` (a measured contact force to limit)")
                )
        return problems + check_outputs(config, f is not None)

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
        # at rest and touching nothing, or refused (occ/haptics/forces.py: a tare in contact hides a
        # real force from then on)
        v = ctx.frame.jacobian(data.q)[:3] @ np.asarray(data.qdot, dtype=float)
        env = ctx.environment
        contact = None
        if env is not None and env.in_contact:
            deep = max(env.depth_mm.items(), key=lambda kv: kv[1])
            contact = f"simulated tissue {deep[0]!r} {deep[1]:.2f} mm deep"
        try:
            return self.force.tare_all(now, data.effort, float(np.linalg.norm(v)), contact)
        except ValueError as err:
            raise caused(CommandError(str(err)), err) from err

    def on_input(self, event: InputEvent, now: float) -> None:
        if self._tissue(event):
            return
        if self.force is not None:
            self.force.on_input(event, now)

    def _tissue(self, event: Any) -> bool:
        """A tissue definition from 3D Slicer (``kind=tissue``: occ/haptics/contact.py) for the
        simulated world: True when it was one (CommandError when it is wrong, or when this
        robot has no simulated world to put it in)."""
        try:
            found = tissue_from_event(event)
        except ValueError as err:
            raise caused(CommandError(str(err)), err) from err
        if found is None:
            return False
        ctx = self.ctx
        env = ctx.environment if ctx is not None else None
        if env is None:
            raise CommandError(
                f"tissue {found[0]!r}: this robot has no simulated world (config `environment`)"
            )
        env.define(*found)
        log.info("tissue %r: %d shape(s) from 3D Slicer", found[0], len(found[1]))
        return True

    def _force_meta(self, now: float) -> str:
        """The tip force now (``force_n``: N, patient frame, 4 decimals) for the return
        channel."""
        force, data, ctx = self.force, self.data, self.ctx
        assert force is not None and data is not None and ctx is not None
        f = force.estimate(
            now, ctx.frame, data.q, data.qdot, data.effort, data.base, lambda: data.tip[:3, :3]
        )
        return f"{f[0]:.4f},{f[1]:.4f},{f[2]:.4f}"

    def _map(self) -> str:
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

    def _source_return(self, out: Output, now: float) -> PoseSample | None:
        """The return channel: the tip as 3D Slicer sees it (patient frame), to the master
        that streams to this interface (occ/haptics/returnlink.py has the format)."""
        if out.type != "POSITION":
            raise OCCError("teleop-return output must be of type POSITION")
        iface = out.interface
        if iface.stream_owner is None and iface.sends_to_owner:
            return None  # no master has streamed to this interface yet: nobody to tell
        data = self.data
        assert data is not None
        state = data.state
        following = (
            state is RobotState.RUNNING
            and self.source == iface.name
            and self.master_run
            and not self.master_clutch
            and self.master_ref is not None
        )
        key = (following, state.value, self._map())
        meta = self._return_meta.get(key)
        if meta is None:
            if len(self._return_meta) > 64:  # a tracker moving the base: keep it bounded
                self._return_meta.clear()
            meta = MappingProxyType(
                {"following": "1" if following else "0", "state": key[1], "map": key[2]}
            )
            self._return_meta[key] = meta
        if self.force is not None:
            # one estimate per return sample: the effort source's momentum observer takes
            # the time since its last estimate (a second one now would see dt = 0 and count
            # the joints' acceleration as a load)
            extra = {
                "force_n": self._force_meta(now),
                # this port's energy in (J at the instrument): what the master may give the
                # hand (occ/haptics/passivity.py)
                "energy_j": f"{self.port.account.e_in:.9g}",
            }
            t = self.force.torque_nm
            if (
                t is not None
            ):  # a 6-axis sensor's (occ/haptics/returnlink.py): old masters ignore it
                extra["torque_nm"] = f"{t[0]:.5f},{t[1]:.5f},{t[2]:.5f}"
            meta = MappingProxyType({**meta, **extra})
        rows, (x, y, z) = data.world_tip_pose()
        k = id(out)
        seq = (self._return_seqs.get(k, 0) + 1) & 0xFFFFFFFF
        self._return_seqs[k] = seq
        self.returned += 1
        assert self.ctx is not None
        return PoseSample(
            iface.name,
            None,
            out.device,
            (x * 1e3, y * 1e3, z * 1e3),
            rotation_to_quaternion(rows),
            seq=seq,
            t_sample=self.ctx.clock.wall_time(),
            meta=meta,
        )

    def configure(self, data: RobotData, ctx: ControllerContext) -> None:
        super().configure(data, ctx)
        self.six.bind(data, ctx)
        # absolute mapping: a step per tick within the velocity limits (the drivers' check
        # allows the limit itself; 0.9 keeps clear of it)
        self._step = [0.9 * lim.velocity * ctx.period_s for lim in ctx.joint_limits]
        g = self._gripper_params
        if g is not None:
            i = data.joint_names.index(g.joint)
            moves = float(np.linalg.norm(ctx.frame.jacobian(data.q)[:3, i]))
            if moves > 1e-9:  # the IK would move it for the tip, the gripper for the jaw
                raise ConfigError(
                    f"teleop-slave gripper: joint '{g.joint}' moves the tool's tip "
                    f"({moves:.3g} m per unit): a jaw must not"
                )
            self.gripper = GripperFollower(i, g.joint, g.open, g.closed, self._step[i])
        fp = self.force_params
        if fp is not None:
            self.force = SlaveForce(
                fp.sources,
                sensor_interface=fp.sensor_interface,
                sensor_device=fp.sensor_device,
                sensor_frame=fp.sensor_frame,
                sensor_timeout_s=fp.sensor_timeout_ms * 1e-3,
                damping=fp.damping,
                effort_damping=fp.effort_damping,
                effort_inertia=fp.effort_inertia,
                environment=ctx.environment,
                alert=ctx.alert,
                pose=lambda: (data.tip, data.base),
                tool_mass_kg=fp.tool_mass_kg,
                tool_com_m=_m(fp.tool_com_mm),
                gravity=fp.gravity_mps2,
                tare_window_s=fp.tare_window_ms * 1e-3,
                tare_max_speed=fp.tare_max_speed_mm_s * 1e-3,
                tare_max_spread_n=fp.tare_max_spread_n,
                tare_max_offset_n=fp.tare_max_offset_n,
            )
            self.force_view = ForceView(self.force, data, ctx, fp.display_mm_per_n)
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
            self._port_active = False  # the new master's energy, when it sends some
        self.samples += 1
        self.last_seq = sample.seq
        self.last_sample_t = sample.t_rx
        energy = sample.meta.get("energy_j")
        if energy is not None:
            self._master_energy(energy)
        ts = sample.t_sample
        phase = self.phase
        if phase is not None:
            clock = self.ctx.clock  # type: ignore[union-attr]
            if ts > 0.0:  # when the master sampled, on our loop's clock
                phase.track(ts - (clock.wall_time() - clock.now()), self.ctx)
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

    def _master_energy(self, text: str) -> None:
        """The master's energy in (``energy_j``: J at this instrument, cumulative): the budget
        of this port's controller. One that is no energy is counted and not used (the budget
        then stays where it was: the safe side)."""
        e = parse_energy(text)
        if e is None:
            self.bad_energy += 1
            return
        self.port.account.receive(e)
        self._port_active = True

    def on_state(self, old: RobotState, new: RobotState, now: float) -> None:
        if new is RobotState.STOPPED or old is RobotState.STOPPED:
            self.releasing = self._release_done = False
            self.released_mm = 0.0
        if new is RobotState.RUNNING:
            self.master_ref = None
            if self.gripper is not None:
                self.gripper.restart()
            if self.absolute:  # from where the drives hold; the last target checked afresh
                self._q_goal = None
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
            sx, sy, sz = self.slave_ref
            self._raw = self._cmd = (float(sx), float(sy), float(sz))
            self._offset = (0.0, 0.0, 0.0)
            self._t_shape = now
            self.port.reset()  # a new session: nothing the tissue stored before is counted
        assert self.slave_ref is not None
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
            self._raw = raw
        # the contact force once a tick (base frame): whether to shape, and how
        force = self._force_base()
        if not fresh and self._q_last is not None and not self._shaping(force):
            return self._q_last  # no new master sample since the last solve: same target
        before = self._cmd
        target = self._shape(now, force)
        if not fresh and target == before and self._q_last is not None:
            return self._q_last
        try:
            if self.follow_orientation:
                q, clamped, limited = self.six.solve(target, self._q_last)
                self.rate_limited += limited
            else:
                q, clamped = ctx.frame.ik_clamped(target, data.q)
        except (KinematicsError, ValueError):
            self.ik_failures += 1
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

    # ------------------------------------------------------------------ the instrument
    def _force_base(self) -> tuple[float, float, float] | None:
        """The contact force on the instrument (N, the base frame: the frame of the targets)
        from the last estimate (the return channel's: at most one stream period old), or None
        without a healthy force source."""
        force, data = self.force, self.data
        if force is None or force.used is None or data is None:
            return None
        fx, fy, fz = force.force_n
        r = data.base
        return (
            float(r[0, 0] * fx + r[1, 0] * fy + r[2, 0] * fz),
            float(r[0, 1] * fx + r[1, 1] * fy + r[2, 1] * fz),
            float(r[0, 2] * fx + r[1, 2] * fy + r[2, 2] * fz),
        )

    def _shaping(self, f: tuple[float, float, float] | None) -> bool:
        """Has the command to move without a new master sample? (a gap to give back, or the
        force limit backing the tool out; ``f``: :meth:`_force_base`)"""
        if self._cmd != self._raw:
            return True
        lim = self.max_tissue_force
        if lim is None or f is None:
            return False
        return f != (0.0, 0.0, 0.0)  # in contact: the approach to the limit is rate-limited

    def _shape(
        self, now: float, f: tuple[float, float, float] | None
    ) -> tuple[float, float, float]:
        """The tip to command (base frame, m): the master's mapped target, the gap left so far
        given back at up to ``drift_return_mm_s``, the motion into the tissue no faster than
        5 mm/s per N below 90 % of ``max_tissue_force_n`` (backing out as fast above it), the
        rest within the energy the hand put in (the slave's port, occ/haptics/passivity.py)."""
        raw, cmd = self._raw, self._cmd
        ctx = self.ctx
        assert raw is not None and cmd is not None and ctx is not None
        last = self._t_shape
        self._t_shape = now
        dt = now - last if last == last else ctx.period_s
        dt = min(max(dt, 0.0), 0.05)
        ox, oy, oz = self._offset
        gap = math.sqrt(ox * ox + oy * oy + oz * oz)
        if gap > 0.0:
            keep = max(0.0, 1.0 - self._drift_speed * dt / gap)
            ox, oy, oz = keep * ox, keep * oy, keep * oz
        dx, dy, dz = raw[0] + ox - cmd[0], raw[1] + oy - cmd[1], raw[2] + oz - cmd[2]
        if f is not None:
            fx, fy, fz = f
            mag = math.sqrt(fx * fx + fy * fy + fz * fz)
            lim = self.max_tissue_force
            if lim is not None and mag > 0.0:
                # into the tissue at no more than 5 mm/s per N below 90 % of the limit, and
                # out of it as fast per N above: a first-order approach to the limit that the
                # measurement's age and the servo's lag cannot carry far past it, however fast
                # the master moves (10 N/mm: 20 ms)
                engage = 0.9 * lim
                nx, ny, nz = fx / mag, fy / mag, fz / mag  # out of the tissue
                inward = -(dx * nx + dy * ny + dz * nz)
                room = (engage - mag) * LIMIT_GAIN * dt
                if inward > room:
                    push = inward - room
                    dx, dy, dz = dx + push * nx, dy + push * ny, dz + push * nz
                if mag >= engage:
                    self.limit_ticks += 1
                    if not self._limiting:
                        self._limiting = True
                        self.limit_hits += 1
                        self._tell(
                            "ForceLimit",
                            f"tissue force {mag:.2f} N at the limit (max_tissue_force_n {lim:g}): "
                            f"motion into the tissue stopped",
                            2,
                        )
                elif self._limiting and mag < 0.8 * lim:
                    self._limiting = False
            if self.port_on and self._port_active:
                dx, dy, dz = self.port.step(f, (dx, dy, dz))
        new = (cmd[0] + dx, cmd[1] + dy, cmd[2] + dz)
        ox, oy, oz = new[0] - raw[0], new[1] - raw[1], new[2] - raw[2]
        self._offset = (ox, oy, oz)
        gap_mm = math.sqrt(ox * ox + oy * oy + oz * oz) / MM
        if gap_mm > self.offset_max_mm:
            self.offset_max_mm = gap_mm
        self._cmd = new
        return new

    def _tell(self, name: str, text: str, code: int) -> None:
        log.warning("%s: %s", name, text)
        ctx = self.ctx
        alert = ctx.alert if ctx is not None else None
        if alert is not None:
            alert(name, text, code)

    def hold(self, now: float, setpoint: list[float]) -> None:
        """While STOPPED: a stop in contact lets go of the tissue (DESIGN.md: "a stop in
        contact lets go of the tissue rather than holding a position inside it"). While the
        measured contact force is over ``release_force_n`` the held setpoint backs the tool out
        along the force at ``release_speed_mm_s``, up to ``release_max_mm`` in all; under it,
        it holds (and backs out again if the tissue presses again: a compliant hold). The
        operators are told when it starts, when it is done and when the travel runs out; the
        master sees the stop on the return channel (``state``) and tells the hand."""
        data, ctx = self.data, self.ctx
        f = self._force_base()
        if f is None or data is None or ctx is None:
            return
        fx, fy, fz = f
        mag = math.sqrt(fx * fx + fy * fy + fz * fz)
        if mag <= self._release_force:
            if self.releasing:
                self.releasing = False
                self._tell(
                    "Release",
                    f"let go of the tissue: {mag:.2f} N after {self.released_mm:.2f} mm",
                    STATUS_OK,
                )
            return
        room = self._release_max - self.released_mm * MM
        if room <= 1e-12:
            if not self._release_done:
                self._release_done = True
                self._tell(
                    "Release",
                    f"still pressing {mag:.2f} N after backing out {self.released_mm:.2f} mm "
                    f"(release_max_mm): holding",
                    2,
                )
            return
        if not self.releasing:
            self.releasing = True
            self.releases += 1
            self._tell(
                "Release",
                f"stopped pressing {mag:.2f} N on tissue: backing out along the force until "
                f"it is under {self._release_force:g} N",
                2,
            )
        step = min(self._release_speed * ctx.period_s, room)
        tx, ty, tz = ctx.frame.tip_position(setpoint)
        target = (tx + step * fx / mag, ty + step * fy / mag, tz + step * fz / mag)
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
        self.released_mm += step / MM

    def _update_absolute(self, data: RobotData, ctx: ControllerContext) -> Sequence[float] | None:
        """The ``absolute`` mapping: each sample is the tip's target in the patient frame.

        A new target is checked against where the tip is told to be (``max_jump_mm``) and
        solved once; every tick the joints step toward the solution by at most 0.9 times their
        velocity limit. A stopped stream (``run=0``), the clutch, a refused or unsolvable
        target: hold where the joints were told to be (never a jump when it comes back)."""
        here = self._q_last if self._q_last is not None else data.commanded()
        if self.master_pos is None or not self.master_run or self.master_clutch:
            self._q_goal = None
            self.master_ref = None
            return self._q_last
        if self._fresh:
            self._fresh = False
            self._q_goal = None
            self.master_ref = None
            p = self.master_pos
            b = data.base
            # world -> base frame: R^T (p - t)
            dx, dy, dz = p[0] - b[0, 3], p[1] - b[1, 3], p[2] - b[2, 3]
            target = (
                float(b[0, 0] * dx + b[1, 0] * dy + b[2, 0] * dz),
                float(b[0, 1] * dx + b[1, 1] * dy + b[2, 1] * dz),
                float(b[0, 2] * dx + b[1, 2] * dy + b[2, 2] * dz),
            )
            if not all(math.isfinite(v) for v in target):
                self.ik_failures += 1
                return self._q_last
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
                return self._q_last
            try:
                q, clamped = ctx.frame.ik_clamped(target, list(here))
            except (KinematicsError, ValueError):
                self.ik_failures += 1
                return self._q_last
            if clamped:
                self.clamped += 1
            self._refusing = False
            self._q_goal = q
            self.master_ref = self.master_pos
            self.reindexes += self._q_last is None
        goal = self._q_goal
        if goal is None:
            return self._q_last
        out = list(here)
        self.rate_limited += step_toward(out, goal, self._step)
        self._q_last = out
        if self.pending_ts is not None:
            self.latency_us.add((ctx.clock.wall_time() - self.pending_ts) * 1e6)
            self.pending_ts = None
        return out

    def _instrument_stats(self) -> dict[str, Any]:
        """The instrument's limit, release and passivity port (GetStats ``instrument``)."""
        return {
            "max_tissue_force_n": self.max_tissue_force,
            "limit_hits": self.limit_hits,
            "limit_ticks": self.limit_ticks,
            "offset_max_mm": round(self.offset_max_mm, 4),
            "releasing": self.releasing,
            "releases": self.releases,
            "released_mm": round(self.released_mm, 4),
            "passivity": {
                "on": self.port_on,
                "active": self._port_active,
                "bad_energy": self.bad_energy,
                **self.port.stats(),
            },
        }

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
            "master_ref_mm": _mm(self.master_ref),
            "slave_ref_mm": _mm(self.slave_ref),
        }
        if self.force is not None:
            out["instrument"] = self._instrument_stats()
            now = self.ctx.clock.now() if self.ctx is not None else math.nan
            out["force"] = self.force.stats(now)
            if self.force_view is not None:
                out["force"]["display"] = self.force_view.stats()
        if self.absolute:
            out["servo_refused"] = self.refused
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
