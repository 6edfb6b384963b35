"""A laparoscopic tool's port: the remote centre of motion its shaft must keep (issue 40).

A tool through a port (a trocar in the abdominal wall) may turn about the port and slide
through it; moved sideways at the port it tears the wall. The conventions are those of
``teleop-slave``'s ``orientation: rcm`` (occ/controllers/teleop/sixdof.py): the port is given in
the patient (world) frame in mm (``rcm_mm``) and used here in the robot's base frame in metres;
the tool's shaft is the tip frame's z axis, pointing from the port to the tip (the tip at the
shaft's end); the roll is the turn about that axis.

What a plan needs of it:

- :func:`port_in_base`: the port in the base frame.
- :func:`shaft_offset`: how far the port is from the shaft of a tool pose, and how deep the tip
  is beyond it. This is the number the plan check and the run bound (0.05 mm,
  :data:`SHAFT_BOUND_M`, the issue's figure for servo targets).
- :func:`keyframes_through_port`: each keyframe's orientation the one the port imposes at its
  tip: a given orientation turned the shortest way onto the port's axis (refused beyond a
  tolerance, with the angle), none given: the start's turned the shortest way onto it (the
  roll kept).
- :class:`PortTrajectory` (:func:`port_plan`): a :class:`~occ.kinematics.trajectory.Trajectory`
  whose position is planned as usual and whose orientation at every time is the port's: the z
  axis from the port to the planned tip, the roll interpolated between the keyframes' rolls
  with the segment's progress.

The orientation of :class:`PortTrajectory` at ``t``: the axis ``z = (p(t) - port) / |...|``; a
reference frame for it, ``F(z) = S(z_0 -> z) R_0`` (``R_0`` the start's orientation, ``z_0`` its
axis, ``S(a -> b)`` the shortest turn taking ``a`` to ``b``); each keyframe's roll ``psi_k`` the
angle from ``F(z_k)``'s x axis to its own about ``z_k`` (each the short way from the one
before); on segment ``k`` at progress ``u`` (the position profile's, as
:meth:`Trajectory.orientation` uses it) ``R(t) = Rot(z, psi_k + u (psi_k+1 - psi_k)) F(z)``. It
is a closed form of ``t`` (the planner's samples and the loop's ticks agree whatever the tick
times) and of the tip alone (no history: a plan that brings the tip back brings the tool back
to the same roll), exactly ``R_k`` at keyframe ``k``, continuous, and its axis passes through
the port by construction. Keyframes without a given orientation have ``psi = 0``: the roll
kept. ``F`` is singular only with the axis turned over (180 deg from the start's), which no
tool through a port can reach. The roll's rate follows the progress (it may step at a
keyframe passed without stopping, as slerp's does). The per-tick part is plain floats (~6 us,
docs/BENCHMARKS.md).

Pure numpy (no Frame, no robot): the caller turns joints into poses.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from occ.kinematics.trajectory import (
    Interpolation,
    Keyframe,
    Mode,
    Trajectory,
    checked_keyframes,
)
from occ.samples import quaternion_to_rotation, rotation_to_quaternion

#: the shaft's largest distance from the port, every sample of a plan and every tick of its
#: run (metres): issue 40's figure for servo targets of a tool through a port
SHAFT_BOUND_M = 0.05e-3
#: an axis is not defined closer to the port than this (metres)
_AT_PORT_M = 1e-6


def port_in_base(port_mm: Sequence[float], base: np.ndarray) -> np.ndarray:
    """The port ``port_mm`` (patient/world frame, mm) in the robot's base frame (metres);
    ``base`` is world <- base (metres). ValueError for a port that is not three finite numbers."""
    p = np.asarray(port_mm, dtype=float).reshape(-1)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"a port is x y z in mm, got {list(port_mm)!r}")
    b = np.asarray(base, dtype=float)
    return np.asarray(b[:3, :3].T @ (p * 1e-3 - b[:3, 3]), dtype=float)


def axis(tip: np.ndarray, port: np.ndarray) -> np.ndarray:
    """The tool's axis for a tip at ``tip``: the unit vector from the port to it; ValueError
    when the tip is at the port (no axis)."""
    z = np.asarray(tip, dtype=float) - np.asarray(port, dtype=float)
    n = float(np.linalg.norm(z))
    if n < _AT_PORT_M:
        raise ValueError("the tip is at the port: the tool's axis is not defined")
    return np.asarray(z / n, dtype=float)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def swing(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The shortest turn (3x3) taking unit vector ``a`` to unit vector ``b``; ValueError when
    they are opposite (no shortest turn: the tool would turn over)."""
    c = float(a @ b)
    if c < -1.0 + 1e-9:
        raise ValueError("the tool's axis would turn over (180 deg about the port)")
    k = _skew(np.cross(a, b))
    return np.asarray(np.eye(3) + k + (k @ k) / (1.0 + c))


def shaft_offset(pose: np.ndarray, port: np.ndarray) -> tuple[float, float]:
    """(the port's distance from the tool's shaft, the tip's depth beyond the port along the
    shaft), metres, for a tool at ``pose`` (4x4, base frame). The shaft runs back from the tip
    along -z; a port ahead of the tip (depth < 0) is as far from it as from the tip."""
    z = pose[:3, 2]
    r = port - pose[:3, 3]
    depth = -float(r @ z)
    if depth < 0.0:
        return float(np.linalg.norm(r)), depth
    return float(np.linalg.norm(r + depth * z)), depth


@dataclass
class ShaftWatch:
    """The worst shaft offset over a plan's samples (:func:`shaft_offset`), and where."""

    port: np.ndarray
    worst: float = 0.0
    worst_at: int = -1
    seen: int = 0

    def see(self, index: int, pose: np.ndarray) -> None:
        dist, _ = shaft_offset(pose, self.port)
        self.seen += 1
        if dist > self.worst or self.worst_at < 0:
            self.worst, self.worst_at = dist, index


class PortMismatch(ValueError):
    """A keyframe's given orientation contradicts the port: ``index`` and ``angle`` (rad, its
    axis from the port's axis at its tip)."""

    def __init__(self, index: int, angle: float) -> None:
        super().__init__(
            f"keyframe {index}: the tool's axis is {math.degrees(angle):.3g} deg from the port's"
        )
        self.index = index
        self.angle = angle


def keyframes_through_port(
    frames: Sequence[Keyframe], port: np.ndarray, tolerance: float
) -> tuple[list[Keyframe], list[float]]:
    """``frames`` (Cartesian, base frame metres; frame 0 with the tool's orientation where the
    plan starts) with every orientation on the port's axis at its tip: a given one turned the
    shortest way onto it when within ``tolerance`` (rad; else :class:`PortMismatch`), none
    given: the start's turned the shortest way onto it (the roll kept). Returns the keyframes
    and the angle each was turned by (0 for those without). ValueError for a tip at the port
    or an axis that would turn over."""
    if not frames or frames[0].rotation is None:
        raise ValueError("the first keyframe needs the tool's orientation")
    out: list[Keyframe] = []
    turns: list[float] = []
    start: np.ndarray | None = None
    for i, k in enumerate(frames):
        z = axis(np.asarray(k.pose, dtype=float), port)
        if k.rotation is None:
            assert start is not None
            r = swing(start[:, 2], z) @ start
            turned = 0.0
        else:
            given = quaternion_to_rotation(k.rotation)
            turned = math.acos(max(-1.0, min(1.0, float(given[:, 2] @ z))))
            if turned > tolerance and i > 0:
                raise PortMismatch(i, turned)
            r = swing(given[:, 2], z) @ given
        if start is None:
            start = r
        out.append(Keyframe(k.t, k.pose, rotation_to_quaternion(r)))
        turns.append(turned)
    return out, turns


Vec = tuple[float, float, float]


def _cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a: Vec, b: Vec) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _swung(a: Vec, b: Vec, v: Vec) -> Vec:
    """``swing(a, b) @ v`` in plain floats (the loop's per-tick path)."""
    c = _dot(a, b)
    if c < -1.0 + 1e-9:
        raise ValueError("the tool's axis would turn over (180 deg about the port)")
    w = _cross(a, b)
    wv = _cross(w, v)
    wwv = _cross(w, wv)
    f = 1.0 / (1.0 + c)
    return (v[0] + wv[0] + f * wwv[0], v[1] + wv[1] + f * wwv[1], v[2] + wv[2] + f * wwv[2])


class PortTrajectory(Trajectory):
    """A plan whose tool keeps the port: the position planned as :class:`Trajectory` plans it,
    the orientation the port's at every time (module docstring). Build it with
    :func:`port_plan`."""

    def __init__(
        self,
        keyframes: Sequence[Keyframe],
        interpolation: Interpolation,
        mode: Mode,
        steepness: float,
        ramp: float,
        port: np.ndarray,
    ) -> None:
        super().__init__(keyframes, interpolation, mode, steepness, ramp)
        self.port = np.asarray(port, dtype=float).copy()
        self._port: Vec = (float(self.port[0]), float(self.port[1]), float(self.port[2]))
        #: the roll's reference: the start's axis and x axis; each keyframe's roll from it
        self._z0: Vec = (0.0, 0.0, 1.0)
        self._x0: Vec = (1.0, 0.0, 0.0)
        self.rolls: list[float] = []
        for i, k in enumerate(self.keyframes):
            if k.rotation is None:
                raise ValueError(f"keyframe {i}: a plan through a port needs every orientation")
            r = quaternion_to_rotation(k.rotation)
            z = self._axis(self._points[i].tolist())
            x: Vec = (float(r[0, 0]), float(r[1, 0]), float(r[2, 0]))
            if i == 0:
                self._z0, self._x0 = z, x
            xf = _swung(self._z0, z, self._x0)
            roll = math.atan2(_dot(z, _cross(xf, x)), _dot(xf, x))
            if self.rolls:  # the short way from the keyframe before
                roll += 2.0 * math.pi * round((self.rolls[-1] - roll) / (2.0 * math.pi))
            self.rolls.append(roll)

    def _axis(self, tip: Sequence[float]) -> Vec:
        p = self._port
        d = (tip[0] - p[0], tip[1] - p[1], tip[2] - p[2])
        n = math.sqrt(_dot(d, d))
        if n < _AT_PORT_M:
            raise ValueError("the tip is at the port: the tool's axis is not defined")
        return (d[0] / n, d[1] / n, d[2] / n)

    def rotation(self, t: float) -> np.ndarray:
        """The tool's orientation at ``t`` (3x3, base frame): its axis from the port to the
        tip at ``t``, the roll interpolated between the keyframes' (module docstring).
        ValueError where the tip is at the port or the axis would turn over."""
        z = self._axis(self.position(t).tolist())
        rolls = self.rolls
        if t <= self.start:
            roll = rolls[0]
        elif t >= self.end:
            roll = rolls[-1]
        else:
            i, u = self.progress(t)
            roll = rolls[i] + u * (rolls[i + 1] - rolls[i])
        xf = _swung(self._z0, z, self._x0)
        yf = _cross(z, xf)
        c, s = math.cos(roll), math.sin(roll)
        x = (c * xf[0] + s * yf[0], c * xf[1] + s * yf[1], c * xf[2] + s * yf[2])
        y = _cross(z, x)
        return np.array([[x[0], y[0], z[0]], [x[1], y[1], z[1]], [x[2], y[2], z[2]]])

    def orientation(self, t: float) -> np.ndarray:
        """:meth:`rotation` as a unit quaternion (x, y, z, w)."""
        return np.array(rotation_to_quaternion(self.rotation(t)), dtype=float)

    def __repr__(self) -> str:
        return "Port" + super().__repr__()


def port_plan(
    keyframes: Sequence[Keyframe],
    port: np.ndarray,
    interpolation: Interpolation = "linear",
    mode: Mode = "stop",
    steepness: float = 6.0,
    ramp: float = 0.25,
) -> PortTrajectory:
    """Plan ``keyframes`` (tip positions in metres, base frame, each with its orientation on
    the port's axis: :func:`keyframes_through_port`) as :func:`~occ.kinematics.trajectory.plan`
    does, the orientation the port's. ValueError as ``plan``, or for a keyframe without an
    orientation or with three values not."""
    frames = checked_keyframes(keyframes, interpolation, mode, steepness, ramp)
    for i, k in enumerate(frames):
        if k.rotation is None or len(k.pose) != 3:
            raise ValueError(f"keyframe {i}: a plan through a port needs a tip (x y z) and a turn")
    p = np.asarray(port, dtype=float).reshape(-1)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"the port must be x y z, got {port!r}")
    return PortTrajectory(frames, interpolation, mode, float(steepness), float(ramp), p)
