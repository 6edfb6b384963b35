"""What the Robot's front desk may use of it: the port the operator desk (occ/operators.py) and
the run-time recording control (occ/reccontrol.py) are given, instead of the Robot class.

They answer operators about everything (``GetStats`` reads every part), so the port is wide;
but it is written here, one list, and neither module imports occ/robot.py, which builds them:
no module knows one that knows it (tests/test_imports.py).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from .alarms import Alarms
    from .clock import Clock
    from .collab import Collaboration
    from .collision import CollisionGuard
    from .config import DaemonConfig
    from .controllers import ControllerSet
    from .data import RobotData
    from .hardware import HardwareSet
    from .interfaces import InterfaceManager
    from .loop import ControlLoop
    from .motion import Motion
    from .safety import StateMachine, Supervisor, Watchdog
    from .statetable import StateTable
    from .stats import LoopStats
    from .streams import StreamInputs
    from .supervision import SupervisorThread, Worker


class RobotPort(Protocol):
    """The Robot as its desk sees it (attributes and the four calls it makes)."""

    name: str
    config: DaemonConfig
    clock: Clock
    state_machine: StateMachine
    data: RobotData
    hardware: HardwareSet
    interfaces: InterfaceManager
    streams: StreamInputs
    motion: Motion
    controller: ControllerSet
    collab: Collaboration | None
    collision: CollisionGuard | None
    alarms: Alarms
    worker: Worker
    loop: ControlLoop
    stats: LoopStats
    watchdog: Watchdog
    supervisor: Supervisor
    supervisor_thread: SupervisorThread | None
    state_table: StateTable | None
    recorder: Any | None

    @property
    def last_alert(self) -> str: ...

    def handover(self, to: str, interface: str, now: float) -> str: ...

    def reset_monitors(self) -> None: ...

    def set_recorder(self, recorder: Any | None) -> None: ...
