"""Narrow ports: what each of the robot's collaborators is given of it, instead of the Robot.

occ/core/robot.py builds its parts (occ/core/assembly.py) and hands each one only what it uses: the
few parts it reads, and callables for what only the Robot can do (swap the recorder, reset the
monitors, hand the motion over). No collaborator imports occ/core/robot.py, so no module knows one
that knows it (tests/test_imports.py); the types below are imported for checking only.

- :class:`DeskPort`: the operator desk (occ/net/operators.py), which answers the robot's own
  commands (occ/net/commands.py ``ROBOT_COMMANDS``). It answers operators about the whole robot,
  so it names more parts than the others; the statistics come through one
  :class:`~occ.core.stats.StatsRegistry`.
- :class:`RecordingPort`: the run-time recording control (occ/recording/control.py).
- The alarms (occ/core/alarms.py), the supervisor's thread (``SupervisorThread.build``), the
  collision guard (``CollisionGuard.build``) and the motion (occ/core/motion.py) take their few
  parts as arguments of their own.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from igtl.messages.base import Message
    from occ.clock import Clock
    from occ.config import RecordingConfig
    from occ.controllers import ControllerSet
    from occ.core.alarms import Alarms
    from occ.core.data import RobotData
    from occ.core.safety import StateMachine
    from occ.core.statetable import StateTable
    from occ.core.stats import StatsRegistry
    from occ.core.supervision import Worker
    from occ.kinematics.collision import CollisionGuard
    from occ.net.collab import Collaboration
    from occ.net.commands import Deferred
    from occ.net.interfaces import Inbound
    from occ.recording.blackbox import BlackBox
    from occ.recording.record import Recorder


@dataclass(frozen=True)
class RecordingPort:
    """What StartRecording, StopRecording and GetRecordingStatus use of the robot."""

    #: the robot's name (a recording's default file name starts with it)
    name: str
    config: RecordingConfig
    #: SCHED_FIFO priority of a recorder's writer thread (``occ.recording.record.writer_priority``)
    fifo_priority: int | None
    #: opens and closes the files (never the loop)
    worker: Worker
    #: the recorder the loop writes to now (None: not recording)
    recorder: Callable[[], Recorder | None]
    #: attach (any thread) or detach (the loop thread only) the loop's recorder
    set_recorder: Callable[[Recorder | None], None]


@dataclass(frozen=True)
class DeskPort:
    """What the operator desk uses of the robot (occ/net/operators.py)."""

    name: str
    clock: Clock
    states: StateMachine
    data: RobotData
    #: a plugin's failure (FAULT with an alert) and the last alert (cleared by a Reset)
    alarms: Alarms
    controller: ControllerSet
    #: builds what the loop must not pay for (GetStats, GetStateTable); replies itself
    worker: Worker
    #: a reply to the sender of a request (thread-safe: queues it)
    reply: Callable[[Inbound, Message], object]
    #: the recorder the loop writes to now (None: not recording)
    recorder: Callable[[], Recorder | None]
    #: every part's statistics (GetStats)
    stats: StatsRegistry
    #: the loop lateness histogram's raw buckets (GetStats ``Histogram=lateness``)
    lateness_buckets: Callable[[], dict[int, int]]
    #: an operator's Reset of the watchdog, the supervisor and the loss monitors
    reset_monitors: Callable[[], None]
    #: ``transition(event, reason)``: a state-machine event; its text, or a Deferred answered
    #: when a power-up off the loop thread is done (occ/core/powerup.py); StateError if refused
    transition: Callable[[str, str], str | Deferred]
    #: ``handover(to, interface, now)``: the motion to another master, or CommandError
    handover: Callable[[str, str, float], str]
    collision: CollisionGuard | None
    state_table: StateTable | None
    collab: Collaboration | None
    #: ``cell(command, args)``: CellLeave, CellJoin, CellForget (occ/core/cell.py); its text,
    #: ValueError when refused; None without a cell
    cell: Callable[[str, dict[str, str]], str] | None = None
    #: the flight recorder (occ/recording/blackbox.py): what the desk takes and answers, and
    #: ``DumpBlackBox``
    black_box: BlackBox | None = None
