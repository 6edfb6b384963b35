"""Controllers: what the robot does while RUNNING, as plugins (the way drivers are).

A controller never touches hardware and never holds the Robot (ros2_control's rule). It is
given, once, the robot's :class:`~occ.core.data.RobotData` (joint state, tip, base, robot state) and
a narrow :class:`ControllerContext` (clock, kinematics, the loop's phase, the interface names);
each tick it reads the samples drained from its input streams and returns joint setpoints. The
Robot passes those to its drivers, which check state and limits.

Plugins
    Looked up by name like drivers and python-can's buses: the built-in table below, then the
    entry points of group ``occ.controllers`` (``name = "package.module:Class"``), then
    :func:`register_controller`. A config selects one or several::

        controller: {plugin: teleop-slave, params: {scale: 0.1}}
        controller: [{plugin: a, params: {...}}, {plugin: b}]

    Each class declares its parameters as a pydantic model (``Params``, unknown keys refused):
    they are validated when the file is loaded (``FILE:LINE`` errors, ``occd --check``) and
    listed in docs/CONFIG.md. ``check(params, config)`` adds checks against the rest of the file
    (e.g. that a named interface exists).

Interfaces (ros2_control's model)
    ``state_interfaces()`` names what it reads (``yaw/position``), ``command_interfaces()`` what
    it commands; each command interface has one owner, checked when the robot is built, so two
    controllers never fight over a joint. A controller that commands nothing (a monitor, a
    hand-moved master) returns ``()``.

Hooks, all on the loop thread: ``configure(data, ctx)`` once; ``on_sample(sample, now)`` for
every stream pose the loss monitor accepted, a typed :class:`~occ.samples.PoseSample` (who, the
sequence number, sample and arrival times, the pose in mm, ``run``, ``clutch``, the rest of
the metadata: no wire message to parse), and ``on_input(event, now)`` for the discrete inputs
(fixture definitions, keyframes, tissue, force readings), each a typed event the interface
decoded (:mod:`occ.events`: a controller never sees a wire message), both in arrival order;
``on_command(request, now) -> str | None`` for the operator commands it lists in
``commands()`` (a command nobody lists is offered to each in turn; work too long for a tick
returns a :class:`~occ.net.commands.Deferred`, answered later); ``on_state(old, new, now)`` after
every transition; ``update(now) -> setpoints | None`` while RUNNING (None = hold);
``hold(now, setpoint)`` while STOPPED (the held setpoint, changed in place to let go of a
contact, or left alone); ``outputs()``
the named output sources it adds (``source: NAME`` in an
interface's outputs); ``stats()``.

Imports: the vocabulary of ``occ`` (typed events, samples, errors), the configuration's models,
``occ.kinematics``, ``occ.haptics`` and, of ``occ.net``, the command and output types; of the
core only RobotData and RobotState. Never ``igtl``, never the Robot (tests/test_imports.py).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import pydantic.main  # noqa: F401 - mypyc: declares the module its BaseModel subclasses reference
from mypy_extensions import mypyc_attr
from pydantic import BaseModel, ConfigDict, ValidationError

from occ.clock import Clock  # mypyc: a native dataclass's field types are looked up at import
from occ.errors import CommandError, ConfigError, caused
from occ.joint import JointLimits
from occ.kinematics.frame import Frame
from occ.plugins import PluginRegistry

if TYPE_CHECKING:
    from occ.config import DaemonConfig
    from occ.core.data import RobotData
    from occ.core.safety import RobotState
    from occ.events import InputEvent
    from occ.net.commands import ArrayReply, Deferred, Request
    from occ.net.outputs import Outgoing, Output
    from occ.samples import PoseSample

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "occ.controllers"

BUILTIN_CONTROLLERS: dict[str, str] = {
    "hold": "occ.controllers:Controller",
    "teleop-master": "occ.controllers.teleop:MasterController",
    "teleop-slave": "occ.controllers.teleop:SlaveController",
    "keyframe": "occ.controllers.keyframe:KeyframeController",
}

SourceFn = Callable[["Output", float], "Outgoing | None"]
#: a problem found by :meth:`Controller.check`: (path inside the controller's params, message)
Problem = tuple[tuple[str | int, ...], str]


class NoParams(BaseModel):
    """A controller without parameters."""

    model_config = ConfigDict(extra="forbid", frozen=True)


@dataclass(frozen=True)
class ControllerContext:
    """What a controller may use besides the robot's data: no Robot, no drivers."""

    clock: Clock
    frame: Frame
    rate_hz: float
    #: names of the daemon's interfaces (a controller filters its samples by them)
    interfaces: tuple[str, ...]
    #: the loop's phase: its first deadline (NaN while not running) and period, in seconds
    loop_t0: Callable[[], float]
    period_s: float
    #: ask the loop to move its next deadlines by this many seconds (phase lock)
    shift: Callable[[float], None]
    #: each joint's limits (the drivers enforce them), in ``RobotData.joint_names`` order
    joint_limits: tuple[JointLimits, ...] = ()
    #: a STATUS to every viewer and operator (name, text, code), as the robot's own alerts
    #: go (None: logged only, e.g. in a unit test)
    alert: Callable[[str, str, int], None] | None = None
    #: the simulated world the robot's ``sim`` drive touches (occ/haptics/contact.py), None on real
    #: hardware: a simulated slave's force sensor reads its contact force
    environment: Any = None
    #: the whole-arm collision model (occ/kinematics/collision.py ``CollisionModel``, from
    #: ``safety.collision``), None without one: a planner checks its plans against it
    collision: Any = None
    #: this robot's name in its cell (occ/core/cell.py), None in no cell
    cell_member: str | None = None
    #: ``cell_stop(cause)``: this member stops the whole cell for ``cause`` (every other member
    #: holds until this one runs again), as its safety stops do; None in no cell
    cell_stop: Callable[[str], None] | None = None
    #: ``note(what, result)``: a worker's result the loop took (a plan it runs), recorded with
    #: the tick by the black box (occ/recording/blackbox.py); None when nothing records
    note: Callable[[str, Any], None] | None = None
    #: ``to_wall()``: wall time minus loop time, read once a tick (the streams' reading: the
    #: one the black box records, so a replay reads it again), None outside a robot
    to_wall: Callable[[], float] | None = None

    def wall_offset(self) -> float:
        """Wall time minus loop time for this tick (one clock reading a tick, recorded)."""
        if self.to_wall is not None:
            return self.to_wall()
        return self.clock.wall_time() - self.clock.now()


@mypyc_attr(allow_interpreted_subclasses=True)  # mypyc: plugins and tests subclass it
class Controller:
    """Base controller: holds position (returns None) and handles nothing. Plugin name
    ``hold``."""

    name: ClassVar[str] = "hold"
    Params: ClassVar[type[BaseModel]] = NoParams
    #: False for devices moved by hand (a passive haptic master): the robot then never writes
    #: position commands to the drivers, it only reads them.
    drives_joints = True

    def __init__(self, params: BaseModel | Mapping[str, Any] | None = None) -> None:
        self.params = params if isinstance(params, BaseModel) else self.Params(**dict(params or {}))
        self.data: RobotData | None = None
        self.ctx: ControllerContext | None = None

    @classmethod
    def check(cls, params: Any, config: DaemonConfig) -> list[Problem]:
        """Problems of validated ``params`` against the rest of the configuration."""
        return []

    def configure(self, data: RobotData, ctx: ControllerContext) -> None:
        self.data = data
        self.ctx = ctx

    def state_interfaces(self) -> tuple[str, ...]:
        assert self.data is not None
        return tuple(f"{j}/position" for j in self.data.joint_names)

    def command_interfaces(self) -> tuple[str, ...]:
        assert self.data is not None
        if not self.drives_joints:
            return ()
        return tuple(f"{j}/position" for j in self.data.joint_names)

    def outputs(self) -> dict[str, SourceFn]:
        return {}

    def on_sample(self, sample: PoseSample, now: float) -> None:
        return None

    def on_input(self, event: InputEvent, now: float) -> None:
        return None

    def on_command(self, request: Request, now: float) -> str | Deferred | ArrayReply | None:
        raise CommandError(f"unknown command {request.name!r}")

    def on_state(self, old: RobotState, new: RobotState, now: float) -> None:
        return None

    def update(self, now: float) -> Sequence[float] | None:
        return None

    def hold(self, now: float, setpoint: list[float]) -> None:
        """While STOPPED, every tick: the held setpoint, which a controller may change in place
        for its own joints (a slave in contact lets go of the tissue); the default holds."""
        return None

    def commands(self) -> tuple[str, ...]:
        """Extra operator commands this controller understands (for GetState/capabilities)."""
        return ()

    def stats(self) -> dict[str, Any]:
        return {}

    def shutdown(self) -> None:
        """The daemon is ending (after the loop's last tick, before the drivers are shut
        down): end threads, close files. Called once; the default has nothing to release."""
        return None


# ------------------------------------------------------------------------------ registry
_REGISTRY: PluginRegistry[Controller] = PluginRegistry(
    "controller", ENTRY_POINT_GROUP, BUILTIN_CONTROLLERS, Controller, ConfigError
)


def register_controller(name: str, target: str | type[Controller]) -> None:
    """Register (or replace) a controller under ``name``: ``"module:Class"`` (imported when
    first used) or a :class:`Controller` subclass. Takes precedence over everything else."""
    _REGISTRY.register(name, target)


def available_controllers() -> list[str]:
    """Every controller name that can be chosen (nothing imported), sorted."""
    return _REGISTRY.available()


def load_controller_class(plugin: str) -> type[Controller]:
    """Import (if needed) and return the controller class registered as ``plugin``;
    ConfigError when there is none or it cannot be imported."""
    return _REGISTRY.load(plugin)


def create_controller(plugin: str, params: Mapping[str, Any] | None = None) -> Controller:
    """Build a controller by plugin name; ConfigError for unknown names or bad parameters."""
    cls = load_controller_class(plugin)
    try:
        model = cls.Params.model_validate(dict(params or {}))
    except ValidationError as err:
        raise caused(ConfigError(f"controller {plugin!r}: {err}"), err) from err
    return cls(model)


# a plain Python class in the compiled build too (its methods still compiled): tests and tools
# replace its methods on an instance, and it adds little to the tick
@mypyc_attr(native_class=False)
class ControllerSet:
    """The controllers of one robot, run in their configured order as one.

    Every controller sees every sample; a command goes to the controller that lists it;
    ``update`` merges each controller's setpoints for the joints whose command interfaces it
    owns (each owned by exactly one, checked in :meth:`configure`).
    """

    def __init__(self, controllers: Sequence[Controller]) -> None:
        self.controllers = list(controllers) or [Controller()]
        self.name = "+".join(c.name for c in self.controllers)
        self._owned: list[tuple[Controller, list[int]]] = []
        self._monitors: list[Controller] = []  # controllers that own no command interface
        #: the one controller owning every joint (the common case), else None
        self._sole: Controller | None = None
        self.drives_joints = False
        #: the owned command interfaces are ``JOINT/effort`` (a haptic master displaying a
        #: force), not positions; one kind per robot
        self.commands_effort = False

    def configure(self, data: RobotData, ctx: ControllerContext) -> None:
        owner: dict[str, str] = {}
        states = {f"{j}/{k}" for j in data.joint_names for k in ("position", "velocity", "effort")}
        index = {f"{j}/position": i for i, j in enumerate(data.joint_names)}
        index.update({f"{j}/effort": i for i, j in enumerate(data.joint_names)})
        kinds: set[str] = set()
        for c in self.controllers:
            c.configure(data, ctx)
            for s in c.state_interfaces():
                if s not in states:
                    raise ConfigError(f"controller {c.name}: no state interface {s!r}")
            joints: list[int] = []
            for cmd in c.command_interfaces():
                if cmd not in index:
                    raise ConfigError(f"controller {c.name}: no command interface {cmd!r}")
                if cmd in owner:
                    raise ConfigError(
                        f"command interface {cmd!r} claimed by controllers {owner[cmd]!r} and "
                        f"{c.name!r}: each command has one owner"
                    )
                owner[cmd] = c.name
                joints.append(index[cmd])
                kinds.add(cmd.rsplit("/", 1)[1])
            if joints:
                self._owned.append((c, joints))
        if len(kinds) > 1:
            raise ConfigError(
                "controllers command both positions and efforts: one kind of command "
                "interface per robot"
            )
        self.commands_effort = kinds == {"effort"}
        self.drives_joints = bool(self._owned)
        owners = [c for c, _ in self._owned]
        self._monitors = [c for c in self.controllers if c not in owners]
        n = len(data.joint_names)
        if len(self._owned) == 1 and len(self._owned[0][1]) == n and not self._monitors:
            self._sole = self._owned[0][0]

    def outputs(self) -> dict[str, SourceFn]:
        out: dict[str, SourceFn] = {}
        for c in self.controllers:
            out.update(c.outputs())
        return out

    def on_sample(self, sample: PoseSample, now: float) -> None:
        for c in self.controllers:
            c.on_sample(sample, now)

    def on_input(self, event: InputEvent, now: float) -> None:
        for c in self.controllers:
            c.on_input(event, now)

    def on_command(self, request: Request, now: float) -> str | Deferred | ArrayReply | None:
        key = request.name.strip().lower()
        for c in self.controllers:
            if key in (n.lower() for n in c.commands()):
                return c.on_command(request, now)
        # not listed by anyone: each in turn may still know it (the first that does answers)
        refusal: CommandError | None = None
        for c in self.controllers:
            try:
                return c.on_command(request, now)
            except CommandError as err:
                refusal = err
        raise refusal or CommandError(f"unknown command {request.name!r}")

    def on_state(self, old: RobotState, new: RobotState, now: float) -> None:
        for c in self.controllers:
            c.on_state(old, new, now)

    def update(self, now: float, current: Sequence[float]) -> Sequence[float] | None:
        """The merged setpoints (``current`` where an owner holds), or None when all hold."""
        sole = self._sole
        if sole is not None:
            return sole.update(now)  # the common case: one controller owns every joint
        merged: list[float] | None = None
        for c, joints in self._owned:
            target = c.update(now)
            if target is None:
                continue
            if merged is None:
                merged = list(current)
            for i in joints:
                merged[i] = target[i]
        for c in self._monitors:
            c.update(now)  # monitors run too
        return merged

    def hold(self, now: float, setpoint: list[float]) -> None:
        """Each controller's :meth:`Controller.hold` (while STOPPED)."""
        for c in self.controllers:
            c.hold(now, setpoint)

    def commands(self) -> tuple[str, ...]:
        return tuple(n for c in self.controllers for n in c.commands())

    def shutdown(self) -> None:
        """Every controller's :meth:`Controller.shutdown`, each one whatever the others
        raised (logged: the drivers' safe shutdown comes next and must not be skipped)."""
        for c in self.controllers:
            try:
                c.shutdown()
            except Exception:  # noqa: BLE001 - one plugin's error must not skip the rest
                log.exception("controller %s: shutdown failed", c.name)

    def stats(self) -> dict[str, Any]:
        if len(self.controllers) == 1:
            return self.controllers[0].stats()
        return {c.name: c.stats() for c in self.controllers}
