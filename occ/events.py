"""Typed values at the daemon's edge: what an input *is* once it has been read, and what an
output *says* before it is packed.

Inputs
    The interface layer (occ/net/interfaces.py) decodes every message a controller may take into
    one of these, once, on its own thread (occ/net/decoders.py holds the table); the loop and the
    controllers never see a wire message. Every event carries who sent it (``interface``,
    ``peer``: the transport's peer, to answer), when it arrived (``t_rx``, the daemon's clock),
    its wire ``kind`` (the message type), its ``device`` name and its ``meta`` (the sender's
    metadata, where 3D Slicer says what a definition means: ``kind=tissue``,
    ``kind=forbidden-region``, ``kind=plane``...), then its content:

    ==================  ===========================================================
    event               content
    ==================  ===========================================================
    PoseSample          a pose of a stream (occ/samples.py): POSITION, TRANSFORM
    PointList           a Markups point list (POINT): fixtures, keyframes, tissue,
                        forbidden regions
    TrajectoryList      a TRAJ: keyframes (each element's entry and target)
    SphereList          a VFIXTURE: the OCC paper's spheres and their hardness
    Mesh                a POLYDATA: guides, planes, forbidden meshes
    ForceReading        a SENSOR: a force (torque) reading, the unit as sent
    ArrayInput          an NDARRAY: its array as sent (a cell plan's joint path)
    UnknownInput        a message no decoder takes: its type and device, to refuse
    ==================  ===========================================================

    What a content *means* is the receiver's to say (a POINT is a fixture to a master, a
    keyframe list to the keyframe controller): the helpers that interpret them
    (occ/haptics/fixture_defs.py, occ/haptics/contact.py, occ/kinematics/collision.py,
    occ/kinematics/keyframe_inputs.py,
    occ/haptics/forces.py) take these values.

Outputs
    What a controller's output source, :mod:`occ.haptics.master_fixtures` and
    :mod:`occ.haptics.forceviz` return
    instead of a message: occ/net/packers.py packs them as the output is configured.

This module imports nothing of the wire protocol: a controller and its helpers import it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from occ.samples import PoseSample

__all__ = [
    "ArrayInput",
    "Event",
    "ForceReading",
    "InputEvent",
    "Mesh",
    "MeshOut",
    "Point",
    "PointList",
    "PointsOut",
    "PolylineOut",
    "PoseSample",
    "SphereList",
    "TrajectoryElement",
    "TrajectoryList",
    "TransformOut",
    "UnknownInput",
    "VectorOut",
]

Vec3 = tuple[float, float, float]
Cells = tuple[tuple[int, ...], ...]


# ------------------------------------------------------------------------------ inputs
@dataclass(frozen=True, slots=True)
class Event:
    """What every input says of itself (the module docstring)."""

    interface: str
    #: the sender (the transport's peer; an answer goes there)
    peer: Any
    #: when it arrived (the daemon's clock, monotonic seconds)
    t_rx: float
    #: the wire type it came as (POINT, TRAJ, VFIXTURE, POLYDATA, SENSOR...)
    kind: str
    device: str
    meta: Mapping[str, str]

    def describe(self) -> str:
        """``TYPE 'device'``: how an error names this input."""
        return f"{self.kind} {self.device!r}"


@dataclass(frozen=True, slots=True)
class Point:
    """One point of a Markups point list (mm; ``radius`` 0: none given)."""

    name: str
    position: Vec3
    radius: float
    #: drawn (alpha > 0): a hidden point is no fixture, keyframe or tissue
    visible: bool


@dataclass(frozen=True, slots=True)
class PointList(Event):
    points: tuple[Point, ...]


@dataclass(frozen=True, slots=True)
class TrajectoryElement:
    """One element of a TRAJ: ``type`` 1 entry only, 2 target only, 3 both (mm)."""

    name: str
    type: int
    entry: Vec3
    target: Vec3
    visible: bool


@dataclass(frozen=True, slots=True)
class TrajectoryList(Event):
    elements: tuple[TrajectoryElement, ...]


@dataclass(frozen=True, slots=True)
class SphereList(Event):
    """A VFIXTURE: spheres (x, y, z, r mm) and their hardness, in the paper's format
    ``version``."""

    version: int
    hardness: float
    spheres: tuple[tuple[float, float, float, float], ...]


@dataclass(frozen=True, slots=True, eq=False)
class Mesh(Event):
    """A POLYDATA: points (N x 3 mm) and cells indexing them."""

    points: np.ndarray
    lines: Cells
    polygons: Cells
    strips: Cells


@dataclass(frozen=True, slots=True)
class ForceReading(Event):
    """A SENSOR: its values in ``unit`` (the unit's name as sent: ``N``, ``milliN``...)."""

    unit: str
    values: tuple[float, ...]


@dataclass(frozen=True, slots=True, eq=False)
class ArrayInput(Event):
    """An NDARRAY: its array (read-only, the type and shape as sent)."""

    array: np.ndarray


@dataclass(frozen=True, slots=True)
class UnknownInput(Event):
    """A message no decoder takes: a controller that must take it refuses it by
    :meth:`~Event.describe`."""


#: what a controller's ``on_input`` receives (a pose goes to ``on_sample``)
InputEvent = (
    PointList | TrajectoryList | SphereList | Mesh | ForceReading | ArrayInput | UnknownInput
)


# ------------------------------------------------------------------------------ outputs
@dataclass
class PointsOut:
    """A named point list for 3D Slicer (a Markups point list): what a controller's source
    returns instead of packing a POINT message itself."""

    names: Sequence[str]
    positions_mm: Sequence[Sequence[float]]
    timestamp: float
    group: str = "Point"
    rgba: tuple[int, int, int, int] = (255, 200, 0, 255)
    meta: Mapping[str, str] | None = None


@dataclass
class PolylineOut:
    """A polyline (N x 3, mm) for 3D Slicer, sent as POLYDATA with one line through the points."""

    points_mm: np.ndarray
    timestamp: float
    meta: Mapping[str, str] | None = None


@dataclass
class VectorOut:
    """A few readings in one SI unit (a force: ``unit="N"``), sent as SENSOR (OpenIGTLink's
    sensor message, its unit field set) or NDARRAY (float64; in header v2 the unit rides as
    metadata ``unit``)."""

    values: Sequence[float]
    timestamp: float
    unit: str = ""
    meta: Mapping[str, str] | None = None


@dataclass
class MeshOut:
    """A model for 3D Slicer (POLYDATA): points (N x 3, mm), line and polygon cells, cell
    scalars by name. Metadata goes in header version 2 only; ``v2`` sends it so whatever the
    output's version (the fixtures' models, which 3D Slicer must name)."""

    points_mm: np.ndarray
    timestamp: float
    lines: Cells = ()
    polygons: Cells = ()
    cell_scalars: tuple[tuple[str, np.ndarray], ...] = ()
    meta: Mapping[str, str] | None = None
    v2: bool = False


@dataclass
class TransformOut:
    """A 4x4 matrix (translation mm) for 3D Slicer (TRANSFORM), not necessarily a rigid pose
    (a force arrow's scale); metadata as :class:`MeshOut`'s."""

    matrix_mm: np.ndarray
    timestamp: float
    meta: Mapping[str, str] | None = None
    v2: bool = False
