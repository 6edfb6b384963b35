"""The master side of the OCC pair (the package docstring tells the whole story)."""

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
from occ.controllers.teleop.checks import check_master
from occ.controllers.teleop.common import MM, STATUS_OK, STATUS_TIME_OUT
from occ.controllers.teleop.display import HapticDisplay
from occ.controllers.teleop.stream import HandleStream
from occ.controllers.teleop_params import MasterParams
from occ.core.safety import RobotState
from occ.errors import CommandError, KinematicsError, OCCError, caused
from occ.events import InputEvent
from occ.haptics.fixture_defs import Defaults, DefinitionError, PatientMapping
from occ.haptics.gripper import GripperSource
from occ.haptics.master_fixtures import MasterFixtures
from occ.haptics.returnlink import ReturnLink
from occ.net.collab import SlaveSelector
from occ.samples import PoseSample

if TYPE_CHECKING:
    from occ.core.data import RobotData
    from occ.net.commands import Request
    from occ.net.outputs import Outgoing, Output

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
        self.input_interface = p.input_interface
        self.input_device = p.input_device
        self.force_output = p.force_output
        # a hand-moved device is read, never position-commanded; with force_output its
        # efforts are commanded (the fixture force)
        self.drives_joints = self.input != "driver" or self.force_output
        self.clutch = p.clutch
        #: which slave the master drives when it has several (occ/net/collab.py)
        self.selector = SlaveSelector(
            p.slaves, p.slave, p.toggle_tap_ms * 1e-3 if p.toggle_tap_ms is not None else None
        )
        self.fixtures = build_fixtures(p)
        self.slave_base_device = p.slave_base_device
        self.slave_tip_device = p.slave_tip_device
        self._fixture_files = p.fixture_files
        #: the return channel: each slave link's tip stream (occ/haptics/returnlink.py), by
        #: interface
        self._links: dict[str, ReturnLink] = {}
        #: the interfaces this master streams to (its ``teleop`` outputs), learned as they send
        self._teleop_ifaces: list[str] = []
        self._tip_period_s = p.tip_period_ms * 1e-3
        self._tip_grace_s = p.tip_grace_ms * 1e-3
        self._linear_seen: object = None
        self._models_sent: dict[int, int] = {}  # id(output) -> fixture version sent
        self._contact_sent: dict[int, bool] = {}
        self._centre: tuple[float, ...] | None = None  # origin + offset, once configured
        self._amp: tuple[float, ...] = tuple(self.amplitude.tolist())
        #: what the hand feels: fixtures + the slave's force, clamped, passivated (display.py)
        self.display = HapticDisplay(p, self.fixtures, self._alert)
        #: the handle's samples to the slaves, the output source ``teleop`` (stream.py)
        self.stream = HandleStream(p)
        #: the gripper value sent with each sample (occ/haptics/gripper.py), None: none sent
        self._gripper_params = p.gripper
        self.gripper: GripperSource | None = None
        self.target: np.ndarray | None = None
        self.ik_failures = 0
        self.samples = 0

    @classmethod
    def check(cls, params: Any, config: DaemonConfig) -> list[Problem]:
        return check_master(params, config)

    def command_interfaces(self) -> tuple[str, ...]:
        assert self.data is not None
        if self.force_output:
            return tuple(f"{j}/effort" for j in self.data.joint_names)
        return super().command_interfaces()

    def configure(self, data: RobotData, ctx: ControllerContext) -> None:
        super().configure(data, ctx)
        self.origin = ctx.frame.position([0.0] * len(data.joint_names)).copy()
        self._centre = tuple((self.origin + self.offset).tolist())
        self.display.bind(data, ctx)
        g = self._gripper_params
        if g is not None:
            joint = data.joint_names.index(g.joint) if g.source == "joint" else None
            self.gripper = GripperSource(
                g.source, joint=joint, open_pos=g.open, closed_pos=g.closed, period_s=g.period_s
            )
        self.stream.bind(data, ctx, self.gripper)
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
            "force": self.display.source_force,
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
        self.stream.handle_quat = sample.quaternion

    def on_input(self, event: InputEvent, now: float) -> None:
        """Fixture definitions (VFIXTURE, Markups POINT, POLYDATA) that share a stream, and
        the external force (a SENSOR ``external_force_device``: CRTK ``servo_cf``)."""
        if self.display.external(event, now):
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
        recovered = link.recoveries
        if not link.on_sample(sample, now, sample.t_rx + self.ctx.wall_offset()):  # type: ignore[union-attr]
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
        self.stream.on_state(old, new, now)
        if new is RobotState.RUNNING:
            # the tip stream's deadline starts now: a slave that never answers is caught by
            # the grace (an alert), as a dead one is
            for link in self._links.values():
                link.arm(now)
        self.display.reset()

    # -------------------------------------------------------------- loop
    def operator_target(self, now: float) -> np.ndarray | tuple[float, float, float] | None:
        if self.input == "sim":
            # plain floats: this runs every tick, where small-array numpy costs more than the
            # arithmetic
            t = now - self.stream.t_run
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
        eff = self.display.tick(now, self._driving_link(now), self.clutch)
        if self.force_output:
            return eff
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

    def _driving_link(self, now: float) -> ReturnLink | None:
        """The driving slave's return link (watched from now on when the master has not heard
        from it yet), every link's deadline checked and its events told."""
        name = self._driving()
        link = self._links.get(name) if name is not None else None
        if link is None and name is not None:
            link = self._link(name)
            link.arm(now)  # a link the master has not heard from: watched from now on
        for other in self._links.values():
            event = other.check(now)
            if event is not None:
                self._tip_event(other, event.kind, event.cause, other is link)
        return link

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
        data = self.data
        assert data is not None
        # a slave not selected is told run=0 (it holds, its stream stays alive) and re-indexes
        # when it is selected again: no jump
        name = out.interface.name
        running = data.state is RobotState.RUNNING and self.selector.drives(name)
        if name not in self._teleop_ifaces:
            self._teleop_ifaces.append(name)
        energy = self.display.energy_out() if name == self._driving() else None
        return self.stream.sample(out, now, bool(running), bool(self.clutch), energy)

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

    def stats(self) -> dict[str, Any]:
        fx = self.fixtures
        name = self._driving()
        link = self._links.get(name) if name is not None else None
        now = self.ctx.clock.now() if self.ctx is not None else math.nan
        tips = {k: v.stats(now) for k, v in self._links.items()}
        return {
            "input": self.input,
            "seq": self.stream.seq,
            "clutch": self.clutch,
            # the tool: the driving slave's measured tip, patient frame (3D Slicer's Tip)
            "tool_mm": (
                None if link is None or link.tip is None else [round(v, 3) for v in fx.tool_mm]
            ),
            "tool_frame": "patient",
            **self.display.stats(now),
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


def build_fixtures(p: MasterParams) -> MasterFixtures:
    """The master's virtual fixtures (occ/haptics/master_fixtures.py), from its parameters."""
    return MasterFixtures(
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
