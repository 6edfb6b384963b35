"""Wire messages to typed events (occ/events.py): the one place that reads what a peer sent.

:func:`decode` looks a received message's type up in :data:`DECODERS` and returns its event,
or an :class:`~occ.events.UnknownInput` when no decoder takes it; the interface layer calls it
once per message, on its own thread (occ/net/interfaces.py), and keeps the message beside the
event for the recording and for replies. A pose (POSITION, TRANSFORM) becomes a
:class:`~occ.samples.PoseSample`: one object a pose, on the 500 Hz path.

No decoder depends on the device name: what a definition means rides in its metadata
(``kind``) and is the receiver's to interpret. The recordings' readers (occ/recording/export.py,
occ/recording/plot.py) read the forces a recorded message carries with :func:`message_force`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from igtl.messages.base import Message, RawMessage
from occ.events import (
    ArrayInput,
    Event,
    ForceReading,
    Mesh,
    Point,
    PointList,
    SphereList,
    TrajectoryElement,
    TrajectoryList,
    UnknownInput,
)
from occ.haptics.forceviz import parse_force
from occ.samples import PoseSample, rotation_to_quaternion

__all__ = ["DECODERS", "decode", "event_of", "message_force", "message_torque", "pose_sample"]

Vec3 = tuple[float, float, float]
Decoder = Callable[[str, Any, Any, float], Event]


def pose_sample(interface: str, peer: Any, msg: Any, t_rx: float) -> PoseSample | None:
    """The sample of a received POSITION or TRANSFORM (None for any other message)."""
    mtype = msg.message_type
    matrix = None
    if mtype == "POSITION":
        x, y, z = msg.position
        q = msg.quaternion
    elif mtype == "TRANSFORM":
        m = matrix = msg.matrix
        x, y, z = m[:3, 3].tolist()
        q = rotation_to_quaternion(m[:3, :3])
    else:
        return None
    meta = msg.metadata
    return PoseSample(
        interface,
        peer,
        msg.device_name,
        (float(x), float(y), float(z)),
        (float(q[0]), float(q[1]), float(q[2]), float(q[3])),
        kind=mtype,
        seq=msg.message_id if msg.header_version == 2 else None,
        t_sample=msg.timestamp,
        t_rx=t_rx,
        run=meta.get("run", "1") == "1",
        clutch=meta.get("clutch", "0") == "1",
        meta=meta,
        matrix=matrix,
    )


def _vec(v: Any) -> Vec3:
    return (float(v[0]), float(v[1]), float(v[2]))


def _points(interface: str, peer: Any, msg: Any, t_rx: float) -> PointList:
    points = tuple(
        Point(p.name, _vec(p.position), float(p.radius), p.rgba[3] > 0) for p in msg.points
    )
    return PointList(interface, peer, t_rx, msg.message_type, msg.device_name, msg.metadata, points)


def _trajectories(interface: str, peer: Any, msg: Any, t_rx: float) -> TrajectoryList:
    elements = tuple(
        TrajectoryElement(tr.name, int(tr.type), _vec(tr.entry), _vec(tr.target), tr.rgba[3] > 0)
        for tr in msg.trajectories
    )
    return TrajectoryList(
        interface, peer, t_rx, msg.message_type, msg.device_name, msg.metadata, elements
    )


def _spheres(interface: str, peer: Any, msg: Any, t_rx: float) -> SphereList:
    spheres = tuple((float(x), float(y), float(z), float(r)) for x, y, z, r in msg.spheres)
    return SphereList(
        interface,
        peer,
        t_rx,
        msg.message_type,
        msg.device_name,
        msg.metadata,
        int(msg.version),
        float(msg.hardness),
        spheres,
    )


def _mesh(interface: str, peer: Any, msg: Any, t_rx: float) -> Mesh:
    def cells(c: Any) -> tuple[tuple[int, ...], ...]:
        return tuple(tuple(int(i) for i in cell) for cell in c or ())

    return Mesh(
        interface,
        peer,
        t_rx,
        msg.message_type,
        msg.device_name,
        msg.metadata,
        np.asarray(msg.points, dtype=float).reshape(-1, 3),
        cells(msg.lines),
        cells(msg.polygons),
        cells(msg.strips),
    )


def _force(interface: str, peer: Any, msg: Any, t_rx: float) -> ForceReading:
    return ForceReading(
        interface,
        peer,
        t_rx,
        msg.message_type,
        msg.device_name,
        msg.metadata,
        str(msg.unit),
        tuple(float(v) for v in msg.data),
    )


def _array(interface: str, peer: Any, msg: Any, t_rx: float) -> ArrayInput:
    array = np.asarray(msg.array)
    array.flags.writeable = False  # shared with the message (its wire bytes)
    return ArrayInput(interface, peer, t_rx, msg.message_type, msg.device_name, msg.metadata, array)


def _pose(interface: str, peer: Any, msg: Any, t_rx: float) -> Event:
    sample = pose_sample(interface, peer, msg, t_rx)
    assert sample is not None
    return sample  # type: ignore[return-value]  # a PoseSample: an event of its own kind


#: every message type a controller takes, and its decoder
DECODERS: dict[str, Decoder] = {
    "POSITION": _pose,
    "TRANSFORM": _pose,
    "POINT": _points,
    "TRAJ": _trajectories,
    "VFIXTURE": _spheres,
    "POLYDATA": _mesh,
    "SENSOR": _force,
    "NDARRAY": _array,
}


def decode(interface: str, peer: Any, msg: Message, t_rx: float) -> Any:
    """The event of a received message (module docstring): a :class:`PoseSample` for a pose,
    an :class:`~occ.events.UnknownInput` for a type no decoder takes and for a message whose
    content was never decoded (a :class:`~igtl.messages.base.RawMessage`, whatever type it
    names: one made in the process, a replay's or a test's; from the wire a type the library
    knows is always decoded or refused)."""
    mtype = msg.message_type
    fn = DECODERS.get(mtype)
    if fn is None or isinstance(msg, RawMessage):
        return UnknownInput(interface, peer, t_rx, mtype, msg.device_name, msg.metadata)
    return fn(interface, peer, msg, t_rx)


# ------------------------------------------------------------------------------ recordings
def message_torque(msg: Any) -> Vec3 | None:
    """The torque (N m) a force message carries in its metadata ``torque_nm`` (a slave's
    return channel or force output with a 6-axis sensor), else None."""
    return parse_force(msg.metadata.get("torque_nm"))


def message_force(msg: Any) -> tuple[str, tuple[float, float, float]] | None:
    """(frame, force in N) of a recorded message that carries one (a slave's return channel,
    its ``force`` output), else None."""
    meta = msg.metadata
    mtype = msg.message_type
    if mtype in ("POSITION", "TRANSFORM"):
        # a slave's return channel (its map rides along) or its force output to Slicer; the
        # master's FixtureProxy has a force_n too, the fixtures' (in the master's axes)
        if "force_n" not in meta or not ("map" in meta or "mm_per_n" in meta):
            return None
        f = parse_force(meta["force_n"])
        return None if f is None else ("patient", f)
    if mtype in ("SENSOR", "NDARRAY") and msg.device_name == "Force":
        values = msg.data if mtype == "SENSOR" else np.asarray(msg.array).ravel()
        if len(values) not in (3, 6) or not all(math.isfinite(float(v)) for v in values[:3]):
            return None
        frame = "patient" if meta.get("frame") == "patient" else "base"
        return frame, (float(values[0]), float(values[1]), float(values[2]))
    return None


def event_of(msg: Message, interface: str = "", peer: Any = None, t_rx: float = 0.0) -> Any:
    """:func:`decode` outside an interface (a replay, a test, a benchmark): the event ``msg``
    decodes to as if it came on ``interface`` from ``peer`` at ``t_rx``."""
    return decode(interface, peer, msg, t_rx)
