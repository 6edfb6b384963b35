"""Keyframes from 3D Slicer's messages: a Markups point list (POINT) or a TRAJ, made into
Cartesian ``(t, position mm, name)`` items for the keyframe controller
(occ/controllers/keyframe.py), which takes them as a discrete input, decoded by the interface
layer (occ/events.py: a ``PointList`` or a ``TrajectoryList``), and never reads a wire message.
"""

from __future__ import annotations

import math
from typing import Any

__all__ = ["items_from_event", "parse_times"]


def parse_times(text: str, count: int) -> list[float]:
    """``times`` metadata: ``count`` seconds separated by commas or spaces."""
    parts = [p for p in text.replace(",", " ").split() if p]
    if len(parts) != count:
        raise ValueError(f"metadata 'times' has {len(parts)} values for {count} points")
    try:
        values = [float(p) for p in parts]
    except ValueError as err:
        raise ValueError(f"metadata 'times': {err}") from err
    if not all(math.isfinite(v) for v in values):
        raise ValueError("metadata 'times' must be finite")
    return values


def items_from_event(
    event: Any, interval_s: float
) -> list[tuple[float, tuple[float, float, float], str]]:
    """Cartesian ``(t, position mm, name)`` from a POINT (visible points) or a TRAJ (each
    element's entry then target, as its type says); times from metadata ``times`` (one per
    point of the message, hidden ones included) else every ``interval_s``."""
    raw: list[tuple[tuple[float, float, float], str, bool]] = []
    if event.kind == "POINT":
        for p in event.points:
            raw.append((p.position, p.name, p.visible))
    elif event.kind == "TRAJ":
        for tr in event.elements:
            visible = tr.visible
            if tr.type in (1, 3):
                raw.append((tr.entry, f"{tr.name} entry" if tr.name else "entry", visible))
            if tr.type in (2, 3):
                raw.append((tr.target, f"{tr.name} target" if tr.name else "target", visible))
            if tr.type not in (1, 2, 3):
                raise ValueError(f"TRAJ element {tr.name!r}: unknown type {tr.type}")
    else:
        raise ValueError(f"{event.kind} carries no keyframes")
    text = event.meta.get("times") if event.meta else None
    if text is not None:
        times = parse_times(text, len(raw))
    else:
        times = [interval_s * (i + 1) for i in range(len(raw))]
    out = [(t, pos, name) for t, (pos, name, visible) in zip(times, raw, strict=True) if visible]
    if not out:
        raise ValueError(f"{event.kind} {event.device!r} has no visible points")
    return out
