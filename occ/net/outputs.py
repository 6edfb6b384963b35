"""Output sources: what the robot sends out periodically, each at its own rate.

An interface's ``outputs`` name a source (``tip``, ``base``, ``status``, ``joints``, or one a
controller adds, e.g. ``teleop``); every tick the :class:`OutputScheduler` asks the sources that
are due for a message and queues it on the interface (never blocking the loop; a slow client
loses its own oldest messages inside the transport, OCC's per-subscriber ``Fq``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

import igtl
from igtl.messages.base import Message
from occ.core.safety import RobotState
from occ.errors import OCCError
from occ.events import MeshOut, PointsOut, PolylineOut, TransformOut, VectorOut
from occ.net.interfaces import Interface  # mypyc: Output's field types are looked up at import
from occ.net.packers import pack_output
from occ.samples import PoseSample, rotation_to_quaternion

if TYPE_CHECKING:
    from occ.core.data import RobotData

M_TO_MM = 1000.0

#: STATUS code sent with each state (operators see why, not just what).
STATE_STATUS_CODE = {
    RobotState.INIT: igtl.StatusCode.NOT_READY,
    RobotState.READY: igtl.StatusCode.OK,
    RobotState.ENABLED: igtl.StatusCode.OK,
    RobotState.RUNNING: igtl.StatusCode.OK,
    RobotState.STOPPED: igtl.StatusCode.DISABLED,
    RobotState.FAULT: igtl.StatusCode.HARDWARE_FAILURE,
    RobotState.ESTOP: igtl.StatusCode.PANICK_MODE,
    RobotState.SHUTDOWN: igtl.StatusCode.SHUT_DOWN,
}


@dataclass
class Output:
    """One periodic output: a message type built from a named source, every ``every`` ticks."""

    interface: Interface
    type: str
    device: str
    source: str
    every: int
    header_version: int
    seq: int = 0


#: what a controller's source returns: a typed value occ/net/packers.py packs as the output's
#: type (a pose, a point list, a polyline, readings, a model, a matrix); never a message
Outgoing = PoseSample | PointsOut | PolylineOut | VectorOut | MeshOut | TransformOut
SourceFn = Callable[[Output, float], Outgoing | None]
#: the built-in sources below, at the edge, build their messages themselves
BuiltinFn = Callable[[Output, float], Message | None]


def pose_to_message(
    pose: np.ndarray,
    mtype: str,
    device: str,
    header_version: int,
    timestamp: float,
    message_id: int = 0,
) -> Message:
    """A TRANSFORM or POSITION (mm) from a 4x4 pose in metres (``message_id``: a reply's,
    the request's own)."""
    if mtype == "TRANSFORM":
        m = pose.copy()
        m[:3, 3] *= M_TO_MM
        return igtl.TransformMessage.from_matrix(
            m,
            device_name=device,
            timestamp=timestamp,
            header_version=header_version,
            message_id=message_id,
        )
    if mtype == "POSITION":
        x, y, z = (pose[:3, 3] * M_TO_MM).tolist()
        return igtl.PositionMessage(
            (x, y, z),
            rotation_to_quaternion(pose[:3, :3]),
            device_name=device,
            timestamp=timestamp,
            header_version=header_version,
            message_id=message_id,
        )
    raise OCCError(f"output type {mtype} cannot carry a pose")


class BuiltinSources:
    """The sources every robot has: ``tip`` and ``base`` (poses in the world, as 3D Slicer
    shows them), ``status`` (the state and why), ``joints`` (measured positions), and the
    commanded side of the same: ``setpoint`` (the joint setpoints the drivers hold) and
    ``setpoint_tip`` (the tip where those setpoints put it, in the world): what ROS 2's
    ``setpoint_js`` and ``setpoint_cp`` carry (occ_ros2)."""

    def __init__(self, data: RobotData, describe: Callable[[], str]) -> None:
        self.data = data
        self.describe = describe

    def table(self) -> dict[str, BuiltinFn]:
        return {
            "tip": self.tip,
            "base": self.base,
            "status": self.status,
            "joints": self.joints,
            "setpoint": self.setpoint,
            "setpoint_tip": self.setpoint_tip,
        }

    def tip(self, out: Output, now: float) -> Message:
        # in world coordinates: the base pose (config or tracker) x the forward kinematics
        d = self.data
        return pose_to_message(
            d.world_tip(), out.type, out.device, out.header_version, d.clock.wall_time()
        )

    def base(self, out: Output, now: float) -> Message:
        d = self.data
        return pose_to_message(
            d.base, out.type, out.device, out.header_version, d.clock.wall_time()
        )

    def status(self, out: Output, now: float) -> Message:
        st = self.data.state
        return igtl.StatusMessage(
            code=int(STATE_STATUS_CODE[st]),
            error_name=st.value,
            status_message=self.describe(),
            device_name=out.device,
            header_version=out.header_version,
            timestamp=self.data.clock.wall_time(),
        )

    def joints(self, out: Output, now: float) -> Message:
        """Measured joint positions (SI) as NDARRAY; in header version 2 the joint names ride
        along as metadata ``joints`` (comma-separated), as a ROS 2 JointState needs them."""
        d = self.data
        return igtl.NDArrayMessage(
            array=np.array(d.q, dtype=np.float64),
            device_name=out.device,
            header_version=out.header_version,
            timestamp=d.clock.wall_time(),
            metadata={"joints": ",".join(d.joint_names)} if out.header_version == 2 else {},
        )

    def setpoint(self, out: Output, now: float) -> Message:
        """The joint setpoints the drivers hold now (the running setpoint, else the held one)
        as NDARRAY, SI, joint names in v2 metadata as for ``joints``."""
        d = self.data
        return igtl.NDArrayMessage(
            array=np.array(d.commanded(), dtype=np.float64),
            device_name=out.device,
            header_version=out.header_version,
            timestamp=d.clock.wall_time(),
            metadata={"joints": ",".join(d.joint_names)} if out.header_version == 2 else {},
        )

    def setpoint_tip(self, out: Output, now: float) -> Message:
        """The tip pose the setpoints command, in the world (base x forward kinematics of the
        setpoints): one forward kinematics per message, at the output's rate."""
        d = self.data
        assert d.frame is not None
        return pose_to_message(
            d.base @ d.frame.fk(d.commanded()),
            out.type,
            out.device,
            out.header_version,
            d.clock.wall_time(),
        )


#: the longest common period of a robot's outputs (in ticks) kept as a schedule
SCHEDULE_MAX = 10_000


class OutputScheduler:
    """Every output of every interface, each sent every ``every`` ticks from its source."""

    #: built from the configuration, never changed: not a checkpoint's (occ/core/checkpoint.py;
    #: the outputs themselves are, through ``outputs``: each one's ``seq``)
    checkpoint_fixed = ("_due", "_schedule")

    def __init__(
        self, outputs: Sequence[Output], sources: Mapping[str, SourceFn | BuiltinFn]
    ) -> None:
        for out in outputs:
            if out.source not in sources:
                raise OCCError(
                    f"interface {out.interface.name}: output source {out.source!r} unknown; "
                    f"known: {', '.join(sorted(sources))}"
                )
        self._due = [(out, sources[out.source]) for out in outputs]
        self.outputs = list(outputs)
        # the outputs due at each tick of one common period (in the configured order), so a
        # tick finds its few (most ticks: none) without testing every output; a period
        # longer than SCHEDULE_MAX falls back to testing each
        period = math.lcm(*(out.every for out in outputs)) if outputs else 1
        self._period = period if period <= SCHEDULE_MAX else 0
        self._schedule = [
            tuple((out, src) for out, src in self._due if k % out.every == 0)
            for k in range(self._period)
        ]

    @classmethod
    def for_interfaces(
        cls,
        interfaces: Iterable[Interface],
        rate_hz: float,
        sources: Mapping[str, SourceFn | BuiltinFn],
    ) -> OutputScheduler:
        """The outputs every interface's config lists, each every ``rate_hz / its rate`` ticks."""
        outputs = [
            Output(
                iface,
                oc.type,
                oc.device,
                oc.source,
                max(1, round(rate_hz / oc.rate_hz)),
                iface.cfg.header_version,
            )
            for iface in interfaces
            for oc in iface.cfg.outputs
        ]
        return cls(outputs, sources)

    def send_due(
        self, now: float, k: int, record: Callable[[Message, str, float], None] | None
    ) -> None:
        period = self._period
        for out, source in self._schedule[k % period] if period else self._due:
            if period or k % out.every == 0:
                value = source(out, now)
                if value is not None:
                    msg = value if isinstance(value, Message) else pack_output(value, out)
                    out.interface.send(msg)
                    if record is not None:
                        record(msg, out.interface.name, now)
