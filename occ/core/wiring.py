"""How a robot's parts are given to each other (what :class:`~occ.core.robot.Robot` is wired from):
the collision guard, the black box and its taps, the controllers' context, the operator desk
with its port and the recording control with theirs (occ/core/ports.py), the statistics of
every part registered for GetStats, and the scheduled outputs. The hardware side is
occ/core/assembly.py's."""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import pinocchio as pin

from occ import _native
from occ.clock import Clock, RealClock
from occ.config import DaemonConfig
from occ.controllers import Controller, ControllerContext, ControllerSet
from occ.core.alarms import Alarms
from occ.core.assembly import (
    attach_environment,
    build_hardware,
    build_watchdog,
    frame_for,
    realtime_settings,
)
from occ.core.cell import Cell
from occ.core.cell import build_cell as _build_cell
from occ.core.checkpoint import Checkpointer
from occ.core.data import RobotData
from occ.core.hardware import HardwareSet
from occ.core.loop import ControlLoop
from occ.core.motion import Motion
from occ.core.ports import DeskPort, RecordingPort
from occ.core.provenance import config_yaml, provenance
from occ.core.safety import LossMonitor, StateMachine, Supervisor, Watchdog
from occ.core.stats import LoopStats, StatsRegistry
from occ.core.transitions import StateEffects
from occ.haptics.contact import Environment
from occ.joint import Joint
from occ.kinematics.collision import CollisionGuard
from occ.kinematics.frame import Frame, chain_hash
from occ.net.collab import Collaboration
from occ.net.interfaces import InterfaceManager
from occ.net.operators import OperatorDesk
from occ.net.outputs import BuiltinFn, BuiltinSources, OutputScheduler, SourceFn
from occ.net.streams import StreamInputs
from occ.recording.blackbox import BlackBox, DumpWriter
from occ.recording.control import RecordingControl
from occ.recording.dump import DumpContext, write_dump, write_dump_forked
from occ.recording.record import writer_priority

if TYPE_CHECKING:
    from occ.core.statetable import StateTable
    from occ.core.supervision import SupervisorThread, Worker
    from occ.recording.record import Recorder


class Assembling(Protocol):
    """The robot under construction as its builders read it (occ/core/robot.py ``Robot``: a
    Protocol, so this module does not know the one that uses it). Each builder reads the
    parts built before it; the parts themselves get narrow ports (occ/core/ports.py)."""

    @property
    def name(self) -> str: ...
    @property
    def config(self) -> DaemonConfig: ...
    @property
    def clock(self) -> Clock: ...
    @property
    def rate_hz(self) -> float: ...
    @property
    def period(self) -> float: ...
    @property
    def state_machine(self) -> StateMachine: ...
    @property
    def joints(self) -> list[Joint]: ...
    @property
    def frame(self) -> Frame: ...
    @property
    def hardware(self) -> HardwareSet: ...
    @property
    def data(self) -> RobotData: ...
    @property
    def collision(self) -> CollisionGuard | None: ...
    @property
    def interfaces(self) -> InterfaceManager: ...
    @property
    def collab(self) -> Collaboration | None: ...
    @property
    def cell(self) -> Cell | None: ...
    @property
    def streams(self) -> StreamInputs: ...
    @property
    def alarms(self) -> Alarms: ...
    @property
    def watchdog(self) -> Watchdog: ...
    @property
    def supervisor(self) -> Supervisor: ...
    @property
    def supervisor_thread(self) -> SupervisorThread | None: ...
    @property
    def worker(self) -> Worker: ...
    @property
    def state_table(self) -> StateTable | None: ...
    @property
    def black_box(self) -> BlackBox: ...
    @property
    def stats(self) -> LoopStats: ...
    @property
    def loop(self) -> ControlLoop: ...
    @property
    def controller(self) -> ControllerSet: ...
    @property
    def motion(self) -> Motion: ...
    @property
    def effects(self) -> StateEffects: ...
    @property
    def operators(self) -> OperatorDesk: ...
    @property
    def recorder(self) -> Recorder | None: ...
    def set_recorder(self, recorder: Recorder | None) -> None: ...
    def reset_monitors(self) -> None: ...
    def handover(self, to: str, interface: str, now: float) -> str: ...
    def tick(self, now: float, k: int) -> None: ...
    def write(self, values: Sequence[float], now: float, effort: bool = False) -> None: ...


def build_drives(
    robot: Assembling,
) -> tuple[list[Joint], Frame, HardwareSet, RobotData, Environment | None]:
    """The joints, the kinematic model, the drives as one unit (occ/core/hardware.py), the robot's
    data and the simulated world its ``sim`` drive touches (None without one)."""
    joints, frame, pairs = build_hardware(robot.config.robot)
    hardware = HardwareSet(pairs)
    names, homes = [j.name for j in joints], [j.home for j in joints]
    data = RobotData(robot.name, names, homes, frame, robot.clock)
    rc = robot.config.robot
    if rc.base_mm is not None:  # where it stands in the patient frame (a controller may move it)
        data.base = base_pose(rc.base_mm, rc.base_rpy_deg)
    env = attach_environment(robot.config.environment, pairs, frame, lambda: data.base)
    hardware.environment = env  # simulated tissue (occ/haptics/contact.py), or None
    return joints, frame, hardware, data, env


def base_pose(xyz_mm: Sequence[float], rpy_deg: Sequence[float]) -> np.ndarray:
    """The 4x4 pose (metres) of ``xyz_mm`` turned by roll, pitch, yaw about the fixed x, y, z
    axes (degrees): R = Rz(yaw) Ry(pitch) Rx(roll) (pinocchio's rpyToMatrix)."""
    b = np.eye(4)
    b[:3, :3] = pin.utils.rpyToMatrix(*np.radians(np.asarray(rpy_deg, dtype=float)))
    b[:3, 3] = np.asarray(xyz_mm, dtype=float) * 1e-3
    return b


def build_inputs(
    config: DaemonConfig, clock: Clock
) -> tuple[InterfaceManager, Collaboration | None, StreamInputs]:
    """The interfaces, the collaboration of several masters (occ/net/collab.py, None with one)
    and the stream inputs (polled, judged, one in control: occ/net/streams.py)."""
    interfaces = InterfaceManager(
        config.interfaces, clock_now=clock.now, poll_streams=config.robot.realtime.poll_streams
    )
    co = config.collaboration
    collab = Collaboration(co) if co is not None else None
    streams = StreamInputs(interfaces, config.safety.loss, collab, clock.wall_time)
    return interfaces, collab, streams


def build_motion(
    robot: Assembling, controllers: Sequence[Controller], env: Environment | None
) -> tuple[ControllerSet, Motion]:
    """The controllers, configured, and the motion policy that writes their targets through
    the robot (occ/core/motion.py), with the collision guard's admission when it checks at run
    time."""
    controller = ControllerSet(controllers)
    controller.configure(robot.data, controller_context(robot, env))
    Motion.check_command_kinds(controller, robot.hardware)
    write = robot.write
    box = robot.black_box
    if box.enabled:  # what the drives are told, in the black box's row of the tick
        wrote, write_drives = box.wrote, robot.write

        def write(values: Sequence[float], now: float, effort: bool = False) -> None:
            wrote(values, effort)
            write_drives(values, now, effort)

    motion = Motion(robot.data, controller, robot.joints, robot.period, write)
    guard = robot.collision
    motion.admit = guard.admitter(robot.data) if guard is not None else None
    if controller.commands_effort:
        robot.data.effort_command = [0.0] * len(robot.joints)
    return controller, motion


def build_collision(robot: Assembling) -> CollisionGuard | None:
    """The whole-arm collision guard of ``safety.collision`` (occ/kinematics/collision.py),
    None without one: checked inline in simulated time, on a worker thread of its own on the
    real clock."""
    config = robot.config
    guard = CollisionGuard.build(
        config.safety.collision,
        config.robot.frame,
        robot.frame,
        [j.limits.velocity for j in robot.joints],
        robot.period,
        real=isinstance(robot.clock, RealClock),
        fifo_priority=writer_priority(config),
        name=f"occ-{config.robot.name}-collision",
    )
    cell = config.cell
    if guard is not None and cell is not None:  # the other arms of its cell (occ/core/cell.py)
        me = cell.me(config.robot.name)
        for m in cell.members:
            if m.name != me and m.frame is not None:
                tool = None if m.tool_mm is None else (m.tool_mm[0] * 1e-3, m.tool_mm[1] * 1e-3)
                guard.cm.add_peer(m.name, m.frame, velocities=m.velocities, tool=tool)
    return guard


def build_safety(robot: Assembling, recorder: Any | None) -> tuple[Alarms, Watchdog, Supervisor]:
    """The robot's alarms (occ/core/alarms.py, given their narrow ports), the loop-period watchdog
    of ``safety.watchdog`` and the supervisor of ``safety.supervisor`` (its thread starts with
    the robot, ``SupervisorThread.build``), both ending in the alarms."""
    send, hw, streams = robot.interfaces.broadcast_operators, robot.hardware, robot.streams
    alarms = Alarms(robot.name, robot.state_machine, robot.clock, send, hw, streams, recorder)
    watchdog = build_watchdog(
        robot.config.safety.watchdog,
        robot.period,
        on_alert=alarms.watchdog_alert,
        on_stop=lambda reason, policy: alarms.safety_stop(f"watchdog: {reason}", policy),
    )
    timeout_s = robot.config.safety.supervisor.timeout_ms * 1e-3
    return alarms, watchdog, Supervisor(timeout_s, on_trip=alarms.supervisor_trip)


def build_black_box(robot: Assembling, controllers: Sequence[Controller]) -> BlackBox:
    """The flight recorder of ``black_box`` (occ/recording/blackbox.py), its taps on what the
    loop takes and sends (the streams, the alarms; the desk, the outputs and the motion take
    it from the robot), the state machine's listener that dumps it, and its writer thread
    (started with the robot) with what a dump says of the software (occ/core/provenance.py)."""
    cfg, config = robot.config.black_box, robot.config
    names = [j.name for j in robot.joints]
    world = robot.hardware.environment  # a simulated world: its force in every row
    box = BlackBox(
        robot.name,
        names,
        robot.rate_hz,
        cfg.seconds,
        cfg.events_per_s,
        enabled=cfg.enabled,
        world=world is not None,
    )
    if not cfg.enabled:
        return box
    model, n = robot.frame.copy(), len(names)  # the writer's own: FK off the loop thread

    def tip_mm(q: list[float]) -> tuple[float, float, float]:
        m = model.fk(q[:n])
        return (m[0, 3] * 1000.0, m[1, 3] * 1000.0, m[2, 3] * 1000.0)

    ctx = DumpContext(
        config_yaml=config_yaml(config),
        provenance=provenance(config, robot.hardware.drivers, controllers),
        tip_mm=tip_mm,
        max_dumps=cfg.max_dumps,
        max_bytes=int(cfg.max_mb * 1e6),
        tell=robot.alarms.black_box_written,
    )
    real = isinstance(robot.clock, RealClock)
    write = write_dump_forked if real and hasattr(os, "fork") else write_dump
    writer = DumpWriter(
        lambda req: write(box, req, ctx), f"occ-{robot.name}-blackbox", inline=not real
    )
    drives = robot.hardware.pairs
    box.bind(
        robot.data, robot.joints, robot.collision, writer, cfg.dir, drives, robot.streams, world
    )
    box.inline_checkpoints = writer.inline
    box.make_checkpointer = lambda: checkpointer(robot)
    for d, _ in drives:
        d.hook_tap = box.hook_failed
    robot.streams.tap = box.took
    robot.alarms.tap = box.sent
    if robot.cell is not None:
        robot.cell.tap = box.took
    robot.alarms.note = box.note  # the loss events and drive failures behind a stop
    robot.state_machine.add_listener(box.on_transition)
    return box


def checkpointer(robot: Assembling) -> Checkpointer:
    """What a checkpoint of ``robot`` takes (occ/core/checkpoint.py): every part but its I/O
    and its records (the interfaces and the cell's link, the recorders, the black box, the
    State Data Table, the loop and its clock, the report worker), the plugins' modules with
    occ's."""
    opaque = [
        robot.black_box,
        robot.state_table,
        robot.recorder,
        robot.loop,
        robot.clock,
        robot.worker,
        robot.stats,
        robot.supervisor_thread,
        robot.operators.recording,
    ]
    io = [robot.interfaces, robot.cell.link if robot.cell is not None else None]
    plugins = [*robot.hardware.drivers, *robot.controller.controllers]
    roots = {type(p).__module__.partition(".")[0] for p in plugins}
    return Checkpointer(robot, opaque=opaque, io=io, roots=roots)


def build_cell(robot: Assembling) -> Cell | None:
    """The robot's side of its cell (``cell``, occ/core/cell.py), None without one: its chain's
    hash, and each member's from its configured URDF (checked against what it announces)."""
    cfg = robot.config.cell
    if cfg is None:
        return None
    chains = {m.name: chain_hash(frame_for(m.frame)) for m in cfg.members if m.frame is not None}
    guard = robot.collision
    arms = {p.name for p in guard.cm.peers} if guard is not None else set()
    return _build_cell(
        cfg,
        robot.name,
        states=robot.state_machine,
        alarms=robot.alarms,
        data=robot.data,
        clock=robot.clock,
        chain=chain_hash(robot.frame),
        chains=chains,
        arms=_peer_feed(guard, arms) if guard is not None and arms else None,
    )


def _peer_feed(guard: CollisionGuard, arms: set[str]) -> tuple[Any, Any]:
    """The cell's heartbeats to the collision guard's peer arms: where each arm is (its joints,
    its base as 12 numbers, when), and which one an operator said is gone."""

    def update(name: str, q: tuple[float, ...], base: tuple[float, ...], t: float) -> None:
        if name in arms:
            b = np.eye(4)
            b[:3, :3] = np.asarray(base[:9]).reshape(3, 3)
            b[:3, 3] = base[9:12]
            guard.peer_update(name, q, b, t)

    def gone(name: str) -> None:
        if name in arms:
            guard.peer_gone(name)

    return update, gone


def build_loop(robot: Assembling) -> tuple[LoopStats, ControlLoop]:
    """The control loop that ticks the robot, and its statistics (every interface's too)."""
    budget_s = robot.config.safety.watchdog.budget_us * 1e-6
    stats = LoopStats(robot.rate_hz, budget_s=budget_s)
    for name, iface in robot.interfaces.interfaces.items():
        stats.interfaces[name] = iface.stats
    loop = ControlLoop(
        robot.rate_hz,
        robot.tick,
        clock=robot.clock,
        stats=stats,
        watchdog=robot.watchdog,
        realtime=realtime_settings(robot.config.robot.realtime),
    )
    # the run ended on purpose: the supervisor stops watching before the loop gives up its
    # priority (a loaded machine may then keep it off the CPU past the supervisor's timeout)
    loop.on_end = robot.supervisor.disarm
    if robot.black_box.enabled:
        loop.spare = robot.black_box.spare  # its checkpoints, in the time a tick leaves
        if isinstance(robot.clock, RealClock):  # its dumps' writer: only when the loop is idle
            robot.black_box.pace = loop.yield_to_loop
    return stats, loop


def build_effects(robot: Assembling) -> StateEffects:
    """What a state change means (occ/core/transitions.py), given to the robot's state machine as
    its listener, guard and effector."""
    effects = StateEffects(
        robot.hardware,
        robot.joints,
        robot.clock,
        robot.data,
        robot.controller,
        robot.motion,
        robot.streams,
        robot.alarms,
    )
    states = robot.state_machine
    effects.states = states
    if robot.cell is not None:  # --start's Run waits until every member has been heard
        effects.start_gate = robot.cell.start_wait
    states.add_listener(effects.on_transition)
    states.add_guard(effects.may_power)
    states.set_effector(effects.effect)
    return effects


def controller_context(robot: Assembling, environment: Environment | None) -> ControllerContext:
    """What the robot's controllers may use of it (occ/controllers: no Robot, no drivers)."""
    loop, collision = robot.loop, robot.collision
    return ControllerContext(
        clock=robot.clock,
        frame=robot.frame,
        rate_hz=robot.rate_hz,
        interfaces=tuple(robot.interfaces.interfaces),
        loop_t0=lambda: loop.t0,
        period_s=loop.period_s,
        shift=loop.shift,
        joint_limits=tuple(j.limits for j in robot.joints),
        alert=robot.alarms.broadcast,
        environment=environment,
        collision=collision.cm if collision is not None else None,
        cell_member=robot.cell.me if robot.cell is not None else None,
        cell_stop=robot.cell.announce_stop if robot.cell is not None else None,
        note=robot.black_box.note if robot.black_box.enabled else None,
        to_wall=robot.streams.to_wall,
    )


def build_outputs(robot: Assembling) -> OutputScheduler:
    """The robot's scheduled outputs: the built-in sources and its controllers'."""
    sources: dict[str, SourceFn | BuiltinFn] = {
        **BuiltinSources(robot.data, robot.operators.describe_state).table(),
        **robot.controller.outputs(),
    }
    interfaces = robot.interfaces.interfaces.values()
    return OutputScheduler.for_interfaces(interfaces, robot.rate_hz, sources)


def build_desk(robot: Assembling) -> OperatorDesk:
    """The operator desk (occ/net/operators.py) with its recording control, each given its port
    (occ/core/ports.py), and the statistics of every part registered for GetStats."""
    recording = RecordingControl(
        RecordingPort(
            name=robot.name,
            config=robot.config.recording,
            fifo_priority=writer_priority(robot.config),
            worker=robot.worker,
            recorder=lambda: robot.recorder,
            set_recorder=robot.set_recorder,
        )
    )
    registry = StatsRegistry(robot.stats.snapshot)
    interfaces = robot.interfaces
    port = DeskPort(
        name=robot.name,
        clock=robot.clock,
        states=robot.state_machine,
        data=robot.data,
        alarms=robot.alarms,
        controller=robot.controller,
        worker=robot.worker,
        reply=lambda item, msg: interfaces.reply(item, msg),  # looked up when replying
        recorder=lambda: robot.recorder,
        stats=registry,
        lateness_buckets=robot.stats.lateness.buckets,
        reset_monitors=robot.reset_monitors,
        transition=robot.effects.request,
        handover=robot.handover,
        collision=robot.collision,
        state_table=robot.state_table,
        collab=robot.collab,
        cell=robot.cell.command if robot.cell is not None else None,
        black_box=robot.black_box if robot.black_box.enabled else None,
    )
    desk = OperatorDesk(port, recording)
    register_stats(registry, robot, desk)
    return desk


def register_stats(registry: StatsRegistry, robot: Assembling, desk: OperatorDesk) -> None:
    """Every part's statistics under its GetStats name, in the report's order (the parts a
    robot runs without, none)."""
    add = registry.add
    name, states, supervisor = robot.name, robot.state_machine, robot.supervisor
    add("robot", lambda: name)
    add("build", lambda: _native.BUILD)  # compiled or pure hot path (occ/_native.py)
    add("state", lambda: states.state.value)
    add("commands", desk.counters)
    add("watchdog", robot.watchdog.counters)

    def supervision() -> dict[str, Any]:
        thread = robot.supervisor_thread
        return {
            "timeout_ms": supervisor.timeout_s * 1e3,
            "trips": supervisor.trips,
            "tripped": supervisor.tripped,
            "thread": thread.report if thread else None,
        }

    add("supervisor", supervision)
    add("reentries", lambda: robot.motion.reentries)
    add("last_alert", lambda: robot.alarms.last_alert)
    streams = robot.streams
    if streams.monitor is not None:  # handover swaps the monitor, never to or from None
        add("loss", lambda: _counters(streams.monitor))
    if (collab := robot.collab) is not None:
        add("owner", lambda: collab.owner)
        add("collaboration", collab.stats)
        add("loss_by_stream", lambda: {n: m.counters() for n, m in streams.monitors.items()})
    if robot.state_table is not None:
        add("state_table", robot.state_table.stats)
    add("black_box", robot.black_box.stats)
    add("recording", desk.recording.stats)
    add("controller", robot.controller.stats)
    if robot.collision is not None:
        add("collision", robot.collision.stats)
    if robot.cell is not None:
        add("cell", robot.cell.stats)
    drivers = robot.hardware.drivers
    add("drivers", lambda: {drv.name: drv.stats() for drv in drivers})
    add("hardware", robot.hardware.stats)
    effects = robot.effects
    add(
        "power_up",
        lambda: {
            "under_way": effects.powering_up,
            "count": effects.powerups,
            "last_ms": effects.last_powerup_ms,
        },
    )
    loop = robot.loop
    add("realtime", lambda: loop.realtime_report)


def _counters(monitor: LossMonitor | None) -> dict[str, Any]:
    assert monitor is not None
    return monitor.counters()
