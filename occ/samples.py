"""Typed stream samples: what the interfaces make of a POSITION or TRANSFORM as they receive it.

A :class:`PoseSample` carries everything the loss monitor and the controllers use of a stream
sample (who sent it, its sequence number, when it was sampled and when it arrived, the pose,
the master's ``run`` and ``clutch``, the rest of its metadata), so neither parses a wire
message: the interface does, once, on its own thread (or in the loop's poll of a UDP socket,
where the datagram goes straight to the tick: occ/net/decoders.py). The message itself stays with
the interface layer (``Inbound.msg``), for the recording and for replies.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

__all__ = ["PoseSample", "quaternion_to_rotation", "rotation_to_quaternion"]

_EMPTY: Mapping[str, str] = {}


class PoseSample:
    """One pose of a stream: millimetres and a unit quaternion (x, y, z, w) as on the wire."""

    __slots__ = (
        "interface",
        "peer",
        "device",
        "kind",
        "seq",
        "t_sample",
        "t_rx",
        "position_mm",
        "quaternion",
        "run",
        "clutch",
        "meta",
        "matrix",
    )

    def __init__(
        self,
        interface: str,
        peer: Any,
        device: str,
        position_mm: tuple[float, float, float],
        quaternion: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0),
        *,
        kind: str = "POSITION",
        seq: int | None = None,
        t_sample: float = 0.0,
        t_rx: float = 0.0,
        run: bool = True,
        clutch: bool = False,
        meta: Mapping[str, str] = _EMPTY,
        matrix: np.ndarray | None = None,
    ) -> None:
        self.interface = interface
        #: the sender (the transport's peer: its ``address``; an answer goes there)
        self.peer = peer
        self.device = device
        #: the wire type it came as: POSITION or TRANSFORM
        self.kind = kind
        #: the sender's sequence number (an IGTL v2 message ID; None from a v1 peer)
        self.seq = seq
        #: when the sender sampled it (its header timestamp, its wall clock; 0 = not set)
        self.t_sample = t_sample
        #: when it arrived (the daemon's clock, monotonic seconds)
        self.t_rx = t_rx
        self.position_mm = position_mm
        self.quaternion = quaternion
        #: a master's ``run`` and ``clutch`` (metadata; run defaults to 1, clutch to 0)
        self.run = run
        self.clutch = clutch
        #: the rest of the sender's metadata (a slave's ``following``, ``state``, ``map``)
        self.meta = meta
        #: a TRANSFORM's matrix as sent (4x4, translation mm: not necessarily a rotation, e.g.
        #: a Markups plane's), None for a POSITION or a pose the daemon built
        self.matrix = matrix

    def matrix_mm(self) -> np.ndarray:
        """The pose as a 4x4 matrix, translation in millimetres."""
        m = np.eye(4)
        m[:3, :3] = quaternion_to_rotation(self.quaternion)
        m[:3, 3] = self.position_mm
        return m

    def describe(self) -> str:
        """``TYPE 'device'``: how an error names this input (as every event, occ/events.py)."""
        return f"{self.kind} {self.device!r}"

    def __repr__(self) -> str:
        return (
            f"PoseSample({self.interface!r}, {self.device!r}, seq={self.seq}, "
            f"position_mm={self.position_mm}, run={self.run}, clutch={self.clutch})"
        )


def rotation_to_quaternion(
    r: np.ndarray | Sequence[Sequence[float]],
) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix (3x3 array or rows of floats), w >= 0 (Shepperd's
    method, numerically stable)."""
    m = r.tolist() if isinstance(r, np.ndarray) else r
    t = m[0][0] + m[1][1] + m[2][2]
    if t > 0.0:
        s = math.sqrt(t + 1.0) * 2.0
        q = ((m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s, 0.25 * s)
    elif m[0][0] > m[1][1] and m[0][0] > m[2][2]:
        s = math.sqrt(1.0 + m[0][0] - m[1][1] - m[2][2]) * 2.0
        q = (0.25 * s, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s, (m[2][1] - m[1][2]) / s)
    elif m[1][1] > m[2][2]:
        s = math.sqrt(1.0 + m[1][1] - m[0][0] - m[2][2]) * 2.0
        q = ((m[0][1] + m[1][0]) / s, 0.25 * s, (m[1][2] + m[2][1]) / s, (m[0][2] - m[2][0]) / s)
    else:
        s = math.sqrt(1.0 + m[2][2] - m[0][0] - m[1][1]) * 2.0
        q = ((m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, 0.25 * s, (m[1][0] - m[0][1]) / s)
    if q[3] < 0.0:
        q = (-q[0], -q[1], -q[2], -q[3])
    return q


def quaternion_to_rotation(q: Sequence[float]) -> np.ndarray:
    x, y, z, w = q
    n = math.sqrt(x * x + y * y + z * z + w * w) or 1.0
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
