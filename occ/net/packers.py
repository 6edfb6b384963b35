"""Typed output values (occ/events.py) to wire messages: the one place that packs what a
controller's output source, :mod:`occ.haptics.master_fixtures` or :mod:`occ.haptics.forceviz`
produced.

:func:`pack_output` packs a value as the output it goes to is configured (its type, device
and header version): the output scheduler (occ/net/outputs.py) calls it for every value a source
returns. A pose (:class:`~occ.samples.PoseSample`) goes as POSITION (header v2: its sequence
number and metadata) or TRANSFORM; readings (:class:`~occ.events.VectorOut`) as SENSOR or
NDARRAY; a point list as POINT; a polyline or a model (:class:`~occ.events.MeshOut`) as
POLYDATA; a matrix (:class:`~occ.events.TransformOut`) as TRANSFORM.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

import igtl
from igtl.messages.base import Message
from igtl.messages.polydata import CELL_SCALAR, PolyDataAttribute
from igtl.messages.sensor import UNITS, SensorMessage, Unit
from igtl.messages.transform import POSITION_ALL, POSITION_QUATERNION3, position_v2
from occ.errors import OCCError
from occ.events import MeshOut, PointsOut, PolylineOut, TransformOut, VectorOut
from occ.samples import PoseSample

__all__ = ["Target", "mesh_message", "pack_output", "transform_message"]

#: SENSOR's unit code of each SI unit name (``"N"`` -> 11), for :class:`VectorOut`
_UNIT_CODES = {name: code for code, name in UNITS.items()}

_NO_ROTATION = (0.0, 0.0, 0.0, 1.0)

Packable = PoseSample | PointsOut | PolylineOut | VectorOut | MeshOut | TransformOut


class Target(Protocol):
    """Where a value goes: an output's configured type, device and header version."""

    @property
    def type(self) -> str: ...
    @property
    def device(self) -> str: ...
    @property
    def header_version(self) -> int: ...


def _pack_vector(value: VectorOut, out: Target) -> Message:
    """A :class:`VectorOut` as SENSOR or NDARRAY (its docstring)."""
    meta = dict(value.meta or {}) if out.header_version == 2 else {}
    if out.type == "SENSOR":
        code = _UNIT_CODES.get(value.unit) if value.unit else None
        if value.unit and code is None:
            raise OCCError(f"SENSOR: no unit code for {value.unit!r}")
        return SensorMessage(
            data=tuple(float(v) for v in value.values),
            unit=Unit(0, ((code, 1),)) if code is not None else Unit(),
            device_name=out.device,
            header_version=out.header_version,
            timestamp=value.timestamp,
            metadata=meta,
        )
    if out.type == "NDARRAY":
        if value.unit and out.header_version == 2:
            meta["unit"] = value.unit
        return igtl.NDArrayMessage(
            array=np.array(value.values, dtype=np.float64),
            device_name=out.device,
            header_version=out.header_version,
            timestamp=value.timestamp,
            metadata=meta,
        )
    raise OCCError(f"readings go as SENSOR or NDARRAY, not {out.type}")


def _pack_pose(value: PoseSample, out: Target) -> Message:
    """A pose as a POSITION (header v2: its sequence number and metadata) or a TRANSFORM."""
    q = value.quaternion
    if q[3] < 0.0:
        q = (-q[0], -q[1], -q[2], -q[3])
    # the 24-byte variant (3-element quaternion) when there is no rotation to carry (a
    # master's handle position), else all four elements (a slave's tip)
    layout = POSITION_QUATERNION3 if q == _NO_ROTATION else POSITION_ALL
    if out.type == "POSITION" and out.header_version == 2:
        seq = value.seq if value.seq is not None else 0
        return position_v2(
            out.device, value.t_sample, seq, value.meta, value.position_mm, q, layout
        )
    if out.type == "POSITION":
        return igtl.PositionMessage(
            value.position_mm, q, layout, device_name=out.device, timestamp=value.t_sample
        )
    if out.type == "TRANSFORM":
        v2 = out.header_version == 2
        return igtl.TransformMessage.from_matrix(
            value.matrix_mm(),
            device_name=out.device,
            timestamp=value.t_sample,
            header_version=out.header_version,
            metadata=dict(value.meta) if v2 else {},
            message_id=(value.seq or 0) if v2 else 0,
        )
    raise OCCError(f"output type {out.type} cannot carry a pose")


def _pack_points(value: PointsOut, out: Target) -> Message:
    if out.type != "POINT":
        raise OCCError(f"a point list goes as POINT, not {out.type}")
    points = [
        igtl.PointElement(
            name=name.encode("utf-8")[:64].decode("utf-8", "ignore"),
            group=value.group,
            rgba=value.rgba,
            position=(float(p[0]), float(p[1]), float(p[2])),
        )
        for name, p in zip(value.names, value.positions_mm, strict=True)
    ]
    return igtl.PointMessage(
        points=tuple(points),
        device_name=out.device,
        header_version=out.header_version,
        timestamp=value.timestamp,
        metadata=dict(value.meta or {}) if out.header_version == 2 else {},
    )


def _pack_polyline(value: PolylineOut, out: Target) -> Message:
    if out.type != "POLYDATA":
        raise OCCError(f"a polyline goes as POLYDATA, not {out.type}")
    pts = value.points_mm
    return igtl.PolyDataMessage(
        points=np.asarray(pts, dtype=np.float32),
        lines=(tuple(range(len(pts))),) if len(pts) >= 2 else (),
        device_name=out.device,
        header_version=out.header_version,
        timestamp=value.timestamp,
        metadata=dict(value.meta or {}) if out.header_version == 2 else {},
    )


def mesh_message(value: MeshOut, device: str, header_version: int = 1) -> Message:
    """A :class:`MeshOut` as POLYDATA (header v2 when the output's version or the value's
    ``v2`` says so; its metadata only then)."""
    version = 2 if value.v2 else header_version
    return igtl.PolyDataMessage(
        points=np.asarray(value.points_mm, dtype=np.float32).reshape(-1, 3),
        lines=value.lines,
        polygons=value.polygons,
        attributes=tuple(
            PolyDataAttribute(CELL_SCALAR, name, data) for name, data in value.cell_scalars
        ),
        device_name=device,
        timestamp=value.timestamp,
        header_version=version,
        metadata=dict(value.meta or {}) if version == 2 else {},
    )


def transform_message(value: TransformOut, device: str, header_version: int = 1) -> Message:
    """A :class:`TransformOut` as TRANSFORM (header version as :func:`mesh_message`)."""
    version = 2 if value.v2 else header_version
    return igtl.TransformMessage.from_matrix(
        value.matrix_mm,
        device_name=device,
        timestamp=value.timestamp,
        header_version=version,
        metadata=dict(value.meta or {}) if version == 2 else {},
    )


def pack_output(value: Packable, out: Target) -> Message:
    """The message of a typed source value, as ``out`` is configured (type, device, version)."""
    if isinstance(value, PoseSample):
        return _pack_pose(value, out)
    if isinstance(value, VectorOut):
        return _pack_vector(value, out)
    if isinstance(value, PointsOut):
        return _pack_points(value, out)
    if isinstance(value, PolylineOut):
        return _pack_polyline(value, out)
    if isinstance(value, MeshOut):
        if out.type != "POLYDATA":
            raise OCCError(f"a model goes as POLYDATA, not {out.type}")
        return mesh_message(value, out.device, out.header_version)
    if out.type != "TRANSFORM":
        raise OCCError(f"a matrix goes as TRANSFORM, not {out.type}")
    return transform_message(value, out.device, out.header_version)
