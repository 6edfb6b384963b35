"""The master side of the OCC pair (the package docstring tells the whole story)."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np
import pinocchio as pin
import pydantic.main  # noqa: F401 - mypyc: the module its run-time BaseModel checks look up
from mypy_extensions import mypyc_attr
from pydantic import BaseModel

from occ.config import DaemonConfig
from occ.controllers import Controller, ControllerContext, Problem, SourceFn
from occ.controllers.teleop_params import MasterParams
from occ.core.safety import RobotState
from occ.errors import CommandError, KinematicsError, OCCError, caused
from occ.events import InputEvent, VectorOut
from occ.haptics.fixture_defs import Defaults, DefinitionError, PatientMapping, from_markups_file
from occ.haptics.forces import sensor_force
from occ.haptics.gripper import GripperSource
from occ.haptics.master_fixtures import MasterFixtures
from occ.haptics.passivity import MasterPort, OnePort
from occ.haptics.returnlink import ReturnLink
from occ.net.collab import SlaveSelector
from occ.samples import PoseSample, rotation_to_quaternion

if TYPE_CHECKING:
    from occ.core.data import RobotData
    from occ.net.commands import Request
    from occ.net.outputs import Outgoing, Output

from occ.controllers.teleop.common import (
    _RUN_CLUTCH,
    MM,
    STATUS_OK,
    STATUS_TIME_OUT,
    _apply_jt,
    _interfaces_exist,
)

log = logging.getLogger(__name__)


@mypyc_attr(allow_interpreted_subclasses=True)  # mypyc: plugins extend built-ins
class MasterController(Controller):
    """The master side of the OCC pair: the handle follows the operator (simulated, an IGTL
    stream or a hand-moved device), and its position streams to the slave at 500 Hz (output
    source ``teleop``). Virtual fixtures (patient frame) push back on it, with the force where
    the slave's tool is: the slave's measured tip, sent back on the same link (``SlaveTip``,
    the return channel)."""

    name = "teleop-master"
    Params = MasterParams

    def __init__(self, params: BaseModel | dict[str, Any] | None = None) -> None:
        super().__init__(params)
        p = self.params
        assert isinstance(p, MasterParams)
        self.input = p.input
        self.amplitude = np.array(p.amplitude_mm, dtype=float) * MM
        self.offset = np.array(p.offset_mm, dtype=float) * MM
        self.frequency = p.frequency_hz
        self._rot_amp = tuple(math.radians(v) for v in p.orientation_amplitude_deg)
        #: the handle's orientation sent with each sample (x, y, z, w)
        self.handle_quat: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
        self.input_interface = p.input_interface
        self.input_device = p.input_device
        self.force_output = p.force_output
        # a hand-moved device is read, never position-commanded; with force_output its
        # efforts are commanded (the fixture force)
        self.drives_joints = self.input != "driver" or self.force_output
        self.clutch = p.clutch
        self.seq = p.first_seq & 0xFFFFFFFF
        self._first_seq = self.seq
        #: each teleop output's own sequence numbers (one stream per slave), by id(output)
        self._seqs: dict[int, int] = {}
        #: which slave the master drives when it has several (occ/net/collab.py)
        self.selector = SlaveSelector(
            p.slaves, p.slave, p.toggle_tap_ms * 1e-3 if p.toggle_tap_ms is not None else None
        )
        self.fixtures = MasterFixtures(
            Defaults(
                vfixture_kind=p.vfixture_kind,
                point_kind=p.point_kind,
                point_radius_mm=p.fixture_radius_mm,
                stiffness=p.fixture_hardness,
                damping=p.fixture_damping,
            ),
            PatientMapping(p.scale, p.rotation),
            max_force_n=p.max_force_n,
            slide_mm=p.fixture_slide_mm,
            max_primitives=p.max_fixtures,
            max_planes=p.max_planes,
        )
        self.slave_base_device = p.slave_base_device
        self.slave_tip_device = p.slave_tip_device
        self._fixture_files = p.fixture_files
        # : the return channel: each slave link's tip stream (occ/haptics/returnlink.py), by
        # interface
        self._links: dict[str, ReturnLink] = {}
        #: the interfaces this master streams to (its ``teleop`` outputs), learned as they send
        self._teleop_ifaces: list[str] = []
        self._tip_period_s = p.tip_period_ms * 1e-3
        self._tip_grace_s = p.tip_grace_ms * 1e-3
        self._fade_s = p.tip_fade_ms * 1e-3
        #: the share of the computed fixture force displayed (0..1: fades on a stale tip, the
        #: clutch, a slave not following this master; 0 at once when the tip is lost)
        self.gain = 0.0
        self._t_gain = math.nan
        self._linear_seen: object = None
        self._jt: list[list[float]] | None = None  # J^T of a Cartesian master (constant)
        self._efforts: list[float] = []
        self._models_sent: dict[int, int] = {}  # id(output) -> fixture version sent
        self._contact_sent: dict[int, bool] = {}
        self._centre: tuple[float, ...] | None = None  # origin + offset, once configured
        self._amp: tuple[float, ...] = tuple(self.amplitude.tolist())
        #: bilateral teleoperation: the slave's force displayed (occ/haptics/passivity.py keeps the
        #: loop passive); the displayed force is fixtures + feedback, clamped, passivated
        self.force_feedback = p.force_feedback
        self.force_scale = p.force_scale
        self.max_force = p.max_force_n
        self.passivity_on = p.passivity
        #: the master's port of the two-port passivity scheme (occ/haptics/passivity.py)
        self.passivity = MasterPort(p.passivity_max_damping)
        #: the share of the slave's force displayed (0..1): rises within ``tip_fade_ms`` while
        #: the slave follows with a fresh link, falls within ``feedback_fade_ms`` otherwise
        self.feedback_gain = 0.0
        self._feedback_fade_s = p.feedback_fade_ms * 1e-3
        self._x_handle: tuple[float, float, float] | None = None
        #: the driving slave's state as its return link last said, and its force then (N)
        self._slave_state = ""
        self.external_device = p.external_force_device
        self._external_timeout = p.external_force_timeout_ms * 1e-3
        #: the external force (CRTK servo_cf: N, the master's axes) and when it came
        self.external_n: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._t_external = -math.inf
        self.external_samples = 0
        self._feedback_raw: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self.feedback_n: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self.displayed_n: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self.clamped_ticks = 0
        #: the gripper value sent with each sample (occ/haptics/gripper.py), None: none sent
        self._gripper_params = p.gripper
        self.gripper: GripperSource | None = None
        #: a 6-axis sensor's torque from the slave (N m, the master's axes): displayed on a
        #: master with rotational axes (:meth:`_display_torque`), in the stats for the others
        self.max_torque = p.max_torque_nm
        self.torque_passivity = OnePort(p.passivity_max_rot_damping)
        self.rotational = False
        self.feedback_torque_nm: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self.displayed_torque_nm: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._t_torque = math.nan
        self._clamped_by = 1.0  # the last clamp's factor
        self._t_handle = math.nan
        self.target: np.ndarray | None = None
        self._t_run = 0.0
        self._t_held = 0.0  # trajectory time already run when RUNNING was left
        self.ik_failures = 0
        self.samples = 0

    @classmethod
    def check(cls, params: Any, config: DaemonConfig) -> list[Problem]:
        problems = _interfaces_exist(params, config, ("input_interface",))
        if params.input == "igtl" and params.input_interface is None:
            problems.append((("input_interface",), "required with input: igtl"))
        teleop = {
            itf.name for itf in config.interfaces for o in itf.outputs if o.source == "teleop"
        }
        for i, name in enumerate(params.slaves):
            if name not in teleop:
                problems.append(
                    (("slaves", i), f"interface '{name}' has no output with source teleop")
                )
        if params.slave is not None and params.slave not in params.slaves:
            problems.append((("slave",), f"'{params.slave}' is not one of slaves"))
        if params.tip_grace_ms < 3.25 * params.tip_period_ms:
            problems.append(
                (("tip_grace_ms",), "must be at least the deadline (3.25 x tip_period_ms)")
            )
        g = params.gripper
        if g is not None and g.source == "joint":
            joints = [j.name for j in config.robot.joints]
            if g.joint is None:
                problems.append((("gripper", "joint"), "required with source: joint"))
            elif g.joint not in joints:
                problems.append((("gripper", "joint"), f"no joint '{g.joint}' ({joints})"))
            if g.open == g.closed:
                problems.append((("gripper", "closed"), "must differ from open"))
        if params.force_output and params.input != "driver":
            problems.append((("force_output",), "needs input: driver (a hand-moved master)"))
        for i, f in enumerate(params.fixture_files):
            try:
                from_markups_file(f.file, kind=f.kind, radius_mm=f.radius_mm)
            except DefinitionError as err:
                problems.append((("fixture_files", i, "file"), str(err)))
        return problems

    def command_interfaces(self) -> tuple[str, ...]:
        assert self.data is not None
        if self.force_output:
            return tuple(f"{j}/effort" for j in self.data.joint_names)
        return super().command_interfaces()

    def configure(self, data: RobotData, ctx: ControllerContext) -> None:
        super().configure(data, ctx)
        self.origin = ctx.frame.position([0.0] * len(data.joint_names)).copy()
        self._centre = tuple((self.origin + self.offset).tolist())
        n = len(data.joint_names)
        self._efforts = [0.0] * n
        self.rotational = self.force_output and ctx.frame.nq >= 6
        g = self._gripper_params
        if g is not None:
            joint = data.joint_names.index(g.joint) if g.source == "joint" else None
            self.gripper = GripperSource(
                g.source, joint=joint, open_pos=g.open, closed_pos=g.closed, period_s=g.period_s
            )
        if self.force_output:
            # efforts = J^T F; a Cartesian master's Jacobian is constant: worked out once
            j0 = ctx.frame.jacobian([0.0] * n)[:3]
            j1 = ctx.frame.jacobian(data.q)[:3]
            if np.allclose(j0, j1, atol=1e-12) and any(abs(v) > 1e-6 for v in data.q):
                self._jt = j0.T.tolist()
        for f in self._fixture_files:
            count = self.fixtures.load_file(
                f.file,
                kind=f.kind,
                radius_mm=f.radius_mm,
                stiffness=f.stiffness,
                damping=f.damping,
            )
            log.info("virtual fixtures: %d from %s", count, f.file)

    def outputs(self) -> dict[str, SourceFn]:
        return {
            "teleop": self._source_teleop,
            "fixtures": self._source_fixtures,
            "contact": self._source_contact,
            "force": self._source_force,
        }

    # -------------------------------------------------------------- inputs
    def on_sample(self, sample: PoseSample, now: float) -> None:
        device = sample.device
        is_input = self.input == "igtl" and (
            self.input_interface is None or sample.interface == self.input_interface
        )
        if device in (self.slave_base_device, self.slave_tip_device) and not (
            is_input and self.input_device == device
        ):
            if device == self.slave_tip_device:
                self._tip_input(sample, now)
            else:
                self._mapping_input(sample, now)
            return
        if sample.kind == "TRANSFORM" and not (is_input and "kind" not in sample.meta):
            # a TRANSFORM that defines a fixture (Slicer's transform of a box, a plane)
            if self._fixture_input(sample, now) is not None:
                return
        if not is_input:
            return
        if self.input_device and device != self.input_device:
            return
        x, y, z = sample.position_mm
        self.samples += 1
        self.target = np.array([x * MM, y * MM, z * MM])
        self.handle_quat = sample.quaternion

    def on_input(self, event: InputEvent, now: float) -> None:
        """Fixture definitions (VFIXTURE, Markups POINT, POLYDATA) that share a stream, and
        the external force (a SENSOR ``external_force_device``: CRTK ``servo_cf``)."""
        if self.external_device is not None and event.device == self.external_device:
            force, error = sensor_force(event)
            if force is None:
                raise CommandError(f"{event.describe()}: {error}")
            self.external_n = force
            self._t_external = now
            self.external_samples += 1
            return
        self._fixture_input(event, now)

    def _fixture_input(self, event: Any, now: float) -> str | None:
        try:
            return self.fixtures.on_event(event, now)
        except DefinitionError as err:
            raise caused(CommandError(str(err)), err) from err

    def _tip_input(self, sample: PoseSample, now: float) -> None:
        """A sample of a slave's tip stream (the return channel, occ/haptics/returnlink.py)."""
        name = sample.interface
        if name not in self._teleop_ifaces:
            raise CommandError(
                f"{sample.kind} {sample.device!r} is a slave's return stream: taken only "
                f"on the interfaces this master streams to "
                f"({', '.join(self._teleop_ifaces) or 'none yet'})"
            )
        link = self._link(name)
        clock = self.ctx.clock  # type: ignore[union-attr]
        recovered = link.recoveries
        if not link.on_sample(sample, now, sample.t_rx + (clock.wall_time() - clock.now())):
            return
        if name != self._driving():
            return
        self.fixtures.tool_mm = link.tip  # type: ignore[assignment]
        lin = link.linear
        if lin is not None and lin is not self._linear_seen:
            self._linear_seen = lin
            try:
                self.fixtures.set_linear(lin, now)
            except DefinitionError as err:  # checked when parsed: cannot happen
                link.last_error = str(err)
        if link.recoveries != recovered and self.data is not None:
            if self.data.state is RobotState.RUNNING:
                self._alert(
                    "STREAM",
                    f"slave tip on {name} back; virtual-fixture force on again",
                    STATUS_OK,
                )

    def _link(self, name: str) -> ReturnLink:
        link = self._links.get(name)
        if link is None:
            link = ReturnLink(name, period_s=self._tip_period_s, grace_s=self._tip_grace_s)
            self._links[name] = link
        return link

    def _driving(self) -> str | None:
        """The slave link whose tip is the tool: the selected slave's, else the first (the
        only) interface this master streams to."""
        if self.selector.slaves:
            return self.selector.selected
        return self._teleop_ifaces[0] if self._teleop_ifaces else None

    def _alert(self, name: str, text: str, code: int) -> None:
        ctx = self.ctx
        alert = ctx.alert if ctx is not None else None
        if alert is not None:
            alert(name, text, code)

    def _mapping_input(self, sample: PoseSample, now: float) -> None:
        """The registration (the slave's base pose, a TRANSFORM): used for the map when the
        slave does not send its own."""
        try:
            if sample.kind == "TRANSFORM":
                self.fixtures.registration(sample.matrix_mm().tolist(), now)
        except DefinitionError as err:
            raise caused(CommandError(f"{sample.kind} {sample.device!r}: {err}"), err) from err

    def on_command(self, request: Request, now: float) -> str | None:
        key = request.name.lower()
        if key == "clutch":
            value = request.args.get("Value", request.args.get("value", "1"))
            self.clutch = value.strip().lower() in ("1", "true", "on", "yes")
            text = f"clutch {'pressed' if self.clutch else 'released'}"
            tapped = self.selector.on_clutch(self.clutch, now)
            return f"{text}; {tapped}" if tapped else text
        if key == "select":
            return self.selector.select(request.args.get("To", request.args.get("to", "")))
        if key == "toggle":
            return self.selector.toggle()
        if key == "grip" and self.gripper is not None:
            value = request.args.get("Value", request.args.get("value", "1"))
            try:
                return self.gripper.command(value)
            except ValueError as err:
                raise caused(CommandError(str(err)), err) from err
        if key == "clearfixtures":
            self.fixtures.clear()
            return "fixtures cleared"
        if key == "getfixtures":
            self._models_sent.clear()  # every fixtures output sends its model again
            return f"{len(self.fixtures.active)} fixtures; models follow"
        raise CommandError(f"unknown command {request.name!r}")

    def commands(self) -> tuple[str, ...]:
        grip = ("Grip",) if self.gripper is not None else ()
        return ("Clutch", "ClearFixtures", "GetFixtures", "Select", "Toggle", *grip)

    def on_state(self, old: RobotState, new: RobotState, now: float) -> None:
        # The simulated hand's time runs only while RUNNING: re-entering RUNNING resumes the
        # trajectory where the robot was held (restarting it at t = 0 jumped the handle back to
        # the start point in one tick, tests/occ/test_contracts.py).
        if new is RobotState.RUNNING:
            self._t_run = now - self._t_held
            # the tip stream's deadline starts now: a slave that never answers is caught by
            # the grace (an alert), as a dead one is
            for link in self._links.values():
                link.arm(now)
        elif old is RobotState.RUNNING:
            self._t_held = now - self._t_run
        self.gain = 0.0
        self._t_gain = math.nan
        self.fixtures.displayed((0.0, 0.0, 0.0))
        self.feedback_n = self.displayed_n = (0.0, 0.0, 0.0)
        self._t_handle = math.nan
        self._x_handle = None
        self.feedback_gain = 0.0
        self.passivity.reset()
        self.feedback_torque_nm = self.displayed_torque_nm = (0.0, 0.0, 0.0)
        self._t_torque = math.nan
        self.torque_passivity.reset()

    # -------------------------------------------------------------- loop
    def operator_target(self, now: float) -> np.ndarray | tuple[float, float, float] | None:
        if self.input == "sim":
            # plain floats: this runs every tick, where small-array numpy costs more than the
            # arithmetic
            t = now - self._t_run
            w = 2.0 * math.pi * self.frequency
            assert self._centre is not None  # set by bind()
            ox, oy, oz = self._centre
            ax, ay, az = self._amp
            st, ct = math.sin(w * t), math.cos(w * t)
            return (ox + ax * st, oy + ay * ct, oz)
        return self.target

    def update(self, now: float) -> Sequence[float] | None:
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        fx, fy, fz = self._display(now, self._fixture_force(now))
        if self.force_output:
            eff = self._efforts
            jt = self._jt
            if jt is not None:
                for i, (a, b, c) in enumerate(jt):
                    eff[i] = a * fx + b * fy + c * fz
            else:
                jac = ctx.frame.jacobian(data.q)[:3]
                eff[:] = (jac.T @ np.array([fx, fy, fz])).tolist()
            self._torque_feedback(now, eff)
            return eff
        self._torque_feedback(now, None)
        if self.input == "driver":
            return None
        target = self.operator_target(now)
        if target is None:
            return None
        if not isinstance(target, tuple):
            target = (float(target[0]), float(target[1]), float(target[2]))
        try:
            q, _clamped = ctx.frame.ik_clamped(target, data.q)
        except (KinematicsError, ValueError):
            self.ik_failures += 1
            return None
        return q

    def _fixture_force(self, now: float) -> tuple[float, float, float]:
        """The virtual-fixture force to display this tick (N, the master's axes).

        Computed where the slave's tool is: the tip of the driving slave's return stream
        (patient frame), each time a new one arrives. Displayed x ``gain``: the gain rises to
        1 within ``tip_fade_ms`` while the tip is fresh and the slave follows this master (the
        clutch released), and falls to 0 within ``tip_fade_ms`` otherwise, holding the last
        force computed from a fresh tip (never one from a stale pose); a lost or missing tip
        makes it 0 at once."""
        fixtures = self.fixtures
        name = self._driving()
        link = self._links.get(name) if name is not None else None
        if link is None and name is not None:
            link = self._link(name)
            link.arm(now)  # a link the master has not heard from: watched from now on
        for other in self._links.values():
            event = other.check(now)
            if event is not None:
                self._tip_event(other, event.kind, event.cause, other is link)
        last = self._t_gain
        dt = now - last if last == last else 0.0
        self._t_gain = now
        if link is None:
            self.gain = 0.0
            fixtures.displayed((0.0, 0.0, 0.0))
            return fixtures.force_n
        status = link.status
        if link.new and link.tip is not None:
            link.new = False
            fixtures.step(link.tip, link.t_tip)
            f = link.force
            if f is None or not self.force_feedback:
                self._feedback_raw = (0.0, 0.0, 0.0)
            else:
                k = self.force_scale
                mx, my, mz = fixtures.mapping.force(f)
                self._feedback_raw = (k * mx, k * my, k * mz)
                if link.energy is not None and k > 0.0:
                    # J at the instrument -> J at the handle: kf / kp (occ/haptics/passivity.py)
                    self.passivity.account.receive(link.energy * k / fixtures.mapping.factor)
            self._slave_news(link)
        fade = self._fade_s
        following = status == "fresh" and link.following and not self.clutch
        if status == "lost" or status == "none":
            self.gain = 0.0
        else:
            step = 1.0 if fade <= 0.0 else dt / fade
            if following:
                self.gain = min(1.0, self.gain + step)
            else:
                self.gain = max(0.0, self.gain - step)
        # the slave's force: held and faded, never dropped (issue 37): a force dropped to zero
        # and snapped back gave the hand energy it never put in
        if status == "none":
            self.feedback_gain = 0.0
        elif following:
            self.feedback_gain = min(1.0, self.feedback_gain + (1.0 if fade <= 0.0 else dt / fade))
        else:
            self.feedback_gain = max(0.0, self.feedback_gain - dt / self._feedback_fade_s)
        g = self.gain
        rx, ry, rz = fixtures.raw_force_n
        fixtures.displayed((g * rx, g * ry, g * rz))
        bx, by, bz = self._feedback_raw
        h = self.feedback_gain
        self.feedback_n = (h * bx, h * by, h * bz)
        return fixtures.force_n

    def _slave_news(self, link: ReturnLink) -> None:
        """The hand is told when its slave stops while pressing on tissue (it lets go of it:
        teleop-slave ``release_*``), and the force it feels then fades out."""
        state = link.slave_state
        if state == self._slave_state:
            return
        before, self._slave_state = self._slave_state, state
        bx, by, bz = self._feedback_raw
        force = math.sqrt(bx * bx + by * by + bz * bz)
        if before == "RUNNING" and state in ("STOPPED", "FAULT", "ESTOP") and force > 0.2:
            data = self.data
            if data is not None and data.state is RobotState.RUNNING:
                self._alert(
                    "ALERT",
                    f"slave on {link.interface} {state} while pressing {force:.1f} N: it lets go "
                    f"of the tissue; its force fades out within "
                    f"{self._feedback_fade_s * 1e3:g} ms",
                    STATUS_TIME_OUT,
                )

    def _display(
        self, now: float, fixture: tuple[float, float, float]
    ) -> tuple[float, float, float]:
        """The force to display this tick: the slave's (feedback) through the passivity
        controller (occ/haptics/passivity.py) with the handle's velocity, plus the fixtures',
        clamped to ``max_force_n``.

        Only the feedback is passivated: a virtual fixture defined with the tool outside its
        region starts stretched and pulls the hand in, giving energy it never received (by
        design); the observer would take that for the network's and damp the guidance away.
        The fixtures' own stability under delay is their proxy's (``fixture_slide_mm``). An
        external force (``servo_cf``) is displayed with the feedback, passivated too, for
        ``external_force_timeout_ms`` after it came."""
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        bx, by, bz = self.feedback_n
        if now - self._t_external <= self._external_timeout:
            ex, ey, ez = self.external_n
            bx, by, bz = bx + ex, by + ey, bz + ez
        t_last = self._t_handle
        self._t_handle = now
        port = self.passivity
        shown = port.shown
        if bx != 0.0 or by != 0.0 or bz != 0.0 or shown != (0.0, 0.0, 0.0):
            # (no feedback now or last tick: no power through the port, nothing to observe:
            # the common case costs nothing here)
            x = self._handle_position()
            last = self._x_handle
            self._x_handle = x
            if last is not None:
                # what the force displayed over the last tick did, exactly
                port.observe((x[0] - last[0], x[1] - last[1], x[2] - last[2]))
            if self.passivity_on and now > t_last:
                v = self._handle_velocity()
                bx, by, bz = port.step((bx, by, bz), v, now - t_last)
        else:
            self._x_handle = None
        fx, fy, fz = fixture[0] + bx, fixture[1] + by, fixture[2] + bz
        self.displayed_n = self._clamp(fx, fy, fz)
        k = self._clamped_by
        port.displayed((k * bx, k * by, k * bz))
        return self.displayed_n

    def _torque_feedback(self, now: float, eff: list[float] | None) -> None:
        """The slave's torque (a 6-axis sensor's, the return channel's ``torque_nm``) in the
        master's axes, ``force_scale Q^T t``, gated as the force is (the same gain: faded
        when late, zero when lost, the clutch); on a master with rotational axes, passivated
        against the handle's angular velocity, clamped to ``max_torque_nm`` and added to the
        efforts ``eff`` through the Jacobian's angular rows. Without them it is only in the
        stats (and in the recording, with the return channel's samples)."""
        name = self._driving()
        link = self._links.get(name) if name is not None else None
        t = link.torque if link is not None and self.force_feedback else None
        if t is None or self.gain == 0.0:
            self.feedback_torque_nm = self.displayed_torque_nm = (0.0, 0.0, 0.0)
            self._t_torque = now
            return
        k = self.force_scale * self.gain
        mx, my, mz = self.fixtures.mapping.force(t)  # a rotation, as for the force
        self.feedback_torque_nm = (k * mx, k * my, k * mz)
        if eff is None or not self.rotational:
            return
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        jac = ctx.frame.jacobian(data.q)[3:]
        out = self.feedback_torque_nm
        last, self._t_torque = self._t_torque, now
        if now > last:  # (NaN: the first tick, nothing to observe yet)
            w = jac @ np.asarray(data.qdot, dtype=float)
            wv = (float(w[0]), float(w[1]), float(w[2]))
            if self.passivity_on:
                out = self.torque_passivity.step(out, wv, now - last)
            else:
                self.torque_passivity.observe(out, wv, now - last)
        mag = math.sqrt(out[0] * out[0] + out[1] * out[1] + out[2] * out[2])
        if mag > self.max_torque:
            c = self.max_torque / mag
            out = (out[0] * c, out[1] * c, out[2] * c)
        self.displayed_torque_nm = out
        for i, v in enumerate((jac.T @ np.array(out)).tolist()):
            eff[i] += v

    def _handle_position(self) -> tuple[float, float, float]:
        """The handle's position (m, the master's axes; a Cartesian master's ``J q``: only its
        changes are used)."""
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        q = data.q
        jt = self._jt
        if jt is not None:
            return _apply_jt(jt, q)
        return tuple(float(v) for v in ctx.frame.tip_position(q))  # type: ignore[return-value]

    def energy_out(self) -> float | None:
        """The energy the hand has put into the channel (J at the slave's instrument: the
        stream's ``energy_j``), or None when this master sends none (no force displayed on a
        hand, or passivity off: the slave's port controller then stays off)."""
        k = self.force_scale
        if not (self.passivity_on and self.force_feedback and self.force_output and k > 0.0):
            return None
        return self.passivity.account.e_in * self.fixtures.mapping.factor / k

    def _handle_velocity(self) -> tuple[float, float, float]:
        """The handle's velocity (m/s, the master's axes) from the drives' joint velocities:
        ``J qdot`` (a Cartesian master's constant Jacobian, else the model's at ``q``)."""
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        qd = data.qdot
        jt = self._jt
        if jt is not None:
            return _apply_jt(jt, qd)
        v = ctx.frame.jacobian(data.q)[:3] @ np.asarray(qd, dtype=float)
        return (float(v[0]), float(v[1]), float(v[2]))

    def _clamp(self, fx: float, fy: float, fz: float) -> tuple[float, float, float]:
        mag = math.sqrt(fx * fx + fy * fy + fz * fz)
        if mag > self.max_force:
            self.clamped_ticks += 1
            k = self._clamped_by = self.max_force / mag
            return (fx * k, fy * k, fz * k)
        self._clamped_by = 1.0
        return (fx, fy, fz)

    def _tip_event(self, link: ReturnLink, kind: str, cause: str, driving: bool) -> None:
        where = f"slave tip on {link.interface}"
        if kind == "latch":
            text = (
                f"{where} lost: {cause}; virtual-fixture force off, the slave's force held "
                f"and fading"
            )
            if driving:
                log.error("ALERT: %s", text)
                self._alert("ALERT", text, STATUS_TIME_OUT)
            else:
                log.warning("%s (not the driving slave)", text)
        elif kind == "refused":
            log.warning("%s: %s", where, cause)
        else:  # hold (stale: the force fades), resume
            log.info("%s: %s", where, cause)

    # -------------------------------------------------------------- output
    def _source_teleop(self, out: Output, now: float) -> PoseSample:
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        x, y, z = ctx.frame.tip_position(data.q)
        # a slave not selected is told run=0 (it holds, its stream stays alive) and re-indexes
        # when it is selected again: no jump
        name = out.interface.name
        running = data.state is RobotState.RUNNING and self.selector.drives(name)
        if name not in self._teleop_ifaces:
            self._teleop_ifaces.append(name)
        key = id(out)
        self.seq = seq = (self._seqs.get(key, self._first_seq) + 1) & 0xFFFFFFFF
        self._seqs[key] = seq
        if out.type != "POSITION":
            raise OCCError("teleop output must be of type POSITION")
        energy = self.energy_out() if name == self._driving() else None
        meta = self._stream_meta(bool(running), now, energy)
        return PoseSample(
            name,
            None,
            out.device,
            (x / MM, y / MM, z / MM),
            self._handle_orientation(now),
            seq=seq,
            t_sample=ctx.clock.wall_time(),
            meta=meta,
        )

    def _stream_meta(
        self, running: bool, now: float, energy: float | None
    ) -> MappingProxyType[str, str]:
        """``run`` and ``clutch`` (one shared mapping each), with the gripper value when the
        master sends one (occ/haptics/gripper.py) and the hand's energy into the channel when it has
        one (``energy_j``: the slave's port puts no more into the tissue, occ/haptics/passivity.py);
        one mapping a sample."""
        meta = _RUN_CLUTCH[running, bool(self.clutch)]
        g = self.gripper
        if g is None and energy is None:
            return meta
        extra = dict(meta)
        if g is not None:
            data = self.data
            assert data is not None
            t = now - self._t_run if data.state is RobotState.RUNNING else self._t_held
            extra["gripper"] = f"{g.update(data.q, t):.3f}"
        if energy is not None:
            extra["energy_j"] = f"{energy:.9g}"
        return MappingProxyType(extra)

    def _handle_orientation(self, now: float) -> tuple[float, float, float, float]:
        """The handle's orientation: the simulated gimbal's (``orientation_amplitude_deg``),
        the input stream's, or the device's own (identity for a 3-DOF handle)."""
        if self.input == "sim":
            ax, ay, az = self._rot_amp
            if ax == 0.0 and ay == 0.0 and az == 0.0:
                return (0.0, 0.0, 0.0, 1.0)
            k = math.sin(2.0 * math.pi * self.frequency * (now - self._t_run))
            r = pin.utils.rpyToMatrix(ax * k, ay * k, az * k)
            return rotation_to_quaternion(r)
        if self.input == "igtl":
            return self.handle_quat
        data, ctx = self.data, self.ctx
        assert data is not None and ctx is not None
        if ctx.frame.nq < 6:
            return (0.0, 0.0, 0.0, 1.0)
        return rotation_to_quaternion(np.asarray(ctx.frame.fk(data.q))[:3, :3])

    def _source_fixtures(self, out: Output, now: float) -> Outgoing | None:
        """The fixtures' models, when they changed since this output last sent them (or an
        operator asked: GetFixtures)."""
        if out.type != "POLYDATA":
            raise OCCError("fixtures output must be of type POLYDATA")
        version = self.fixtures.version
        if self._models_sent.get(id(out)) == version:
            return None
        self._models_sent[id(out)] = version
        assert self.ctx is not None
        return self.fixtures.model(out.device, self.ctx.clock.wall_time())

    def _source_contact(self, out: Output, now: float) -> Outgoing | None:
        """The proxy and contact state, while in contact and once when it ends."""
        if out.type != "TRANSFORM":
            raise OCCError("contact output must be of type TRANSFORM")
        touching = bool(self.fixtures.active.contacts())
        if not touching and not self._contact_sent.get(id(out), True):
            return None
        self._contact_sent[id(out)] = touching
        assert self.ctx is not None
        return self.fixtures.proxy(out.device, self.ctx.clock.wall_time())

    def _source_force(self, out: Output, now: float) -> VectorOut:
        """The displayed force (N, the master's axes: fixtures and the slave's feedback, as
        the hand feels it), every time."""
        assert self.ctx is not None
        meta = None
        if self.rotational:  # the displayed torque beside it (N m, the master's axes)
            t = self.displayed_torque_nm
            meta = {"torque_nm": f"{t[0]:.5f},{t[1]:.5f},{t[2]:.5f}"}
        return VectorOut(self.displayed_n, self.ctx.clock.wall_time(), "N", meta)

    def stats(self) -> dict[str, Any]:
        fx = self.fixtures
        name = self._driving()
        link = self._links.get(name) if name is not None else None
        now = self.ctx.clock.now() if self.ctx is not None else math.nan
        tips = {k: v.stats(now) for k, v in self._links.items()}
        return {
            "input": self.input,
            "seq": self.seq,
            "clutch": self.clutch,
            # the tool: the driving slave's measured tip, patient frame (3D Slicer's Tip)
            "tool_mm": (
                None if link is None or link.tip is None else [round(v, 3) for v in fx.tool_mm]
            ),
            "tool_frame": "patient",
            # displayed on the hand: fixtures + feedback, clamped, passivated
            "force_n": [round(v, 4) for v in self.displayed_n],
            "fixture_force_n": [round(v, 4) for v in fx.force_n],
            "feedback_n": [round(v, 4) for v in self.feedback_n],
            "force_feedback": self.force_feedback,
            "force_scale": self.force_scale,
            # a 6-axis sensor's torque (N m, the master's axes): displayed with rotational axes
            "feedback_torque_nm": [round(v, 5) for v in self.feedback_torque_nm],
            "torque": {
                "displayed": self.rotational,
                "torque_nm": [round(v, 5) for v in self.displayed_torque_nm],
                "passivity": self.torque_passivity.stats(),
            },
            "external_n": [round(v, 4) for v in self.external_n],
            "external_samples": self.external_samples,
            "external_fresh": now - self._t_external <= self._external_timeout,
            "force_clamped_ticks": self.clamped_ticks,
            "passivity": {"on": self.passivity_on, **self.passivity.stats()},
            "feedback_gain": round(self.feedback_gain, 4),
            "fixture_gain": round(self.gain, 4),
            "force_output": self.force_output,
            "slave_tip": tips.get(name) if name is not None else None,
            **({"slave_tips": tips} if len(tips) > 1 else {}),
            "fixture_map": {
                "source": fx.mapping.source,
                "scale": round(fx.mapping.factor, 6),
            },
            **fx.stats(),
            "ik_failures": self.ik_failures,
            **({"slaves": self.selector.stats()} if self.selector.slaves else {}),
            **({"gripper": self.gripper.stats()} if self.gripper is not None else {}),
        }
