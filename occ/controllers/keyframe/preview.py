"""A checked plan's preview in 3D Slicer: the output sources ``keyframe-path`` (POLYDATA, the
tip's path) and ``keyframe-points`` (POINT, the keyframes), sent once per new plan and again
every ``preview_repeat_s``, an empty one when the plan is dropped (package docstring, "Plan,
check and preview")."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from occ.controllers.keyframe.plan import CheckedPlan
from occ.events import PointsOut, PolylineOut

if TYPE_CHECKING:
    from occ.net.outputs import Output


@dataclass
class _Shown:
    version: int = 0
    plan: CheckedPlan | None = None
    sent: dict[int, tuple[int, float]] = field(default_factory=dict)  # output -> (version, t)


class Preview:
    """What the preview outputs send. :meth:`show` is called under the controller's lock (on
    either thread); it swaps one reference, which the loop's output sources read."""

    def __init__(self, repeat_s: float | None) -> None:
        self.repeat_s = repeat_s
        self._shown = _Shown()

    def show(self, plan: CheckedPlan | None) -> None:
        """A new plan to preview, or None: an empty preview clears the viewer's (when there
        was one)."""
        shown = self._shown
        if plan is not None or shown.plan is not None:
            self._shown = _Shown(shown.version + 1, plan if plan is not None else None, {})

    @property
    def sent(self) -> bool:
        """Whether the preview of the current plan has gone out on some output."""
        return bool(self._shown.sent)

    def _due(self, out: Output, now: float) -> _Shown | None:
        shown = self._shown
        key = id(out)
        last = shown.sent.get(key)
        repeat = self.repeat_s
        if last is not None and (shown.plan is None or repeat is None or now - last[1] < repeat):
            return None
        if last is None and shown.version == 0:
            return None  # nothing was ever previewed
        shown.sent[key] = (shown.version, now)
        return shown

    @staticmethod
    def _meta(out: Output) -> dict[str, str]:
        return {"MRMLNodeName": out.device} if out.header_version == 2 else {}

    def path(self, out: Output, now: float, wall: Callable[[], float]) -> PolylineOut | None:
        """The ``keyframe-path`` source: the tip's path (world mm), when due."""
        shown = self._due(out, now)
        if shown is None:
            return None
        pts = shown.plan.path_mm if shown.plan is not None else np.zeros((0, 3))
        return PolylineOut(pts, wall(), self._meta(out))

    def points(self, out: Output, now: float, wall: Callable[[], float]) -> PointsOut | None:
        """The ``keyframe-points`` source: the keyframes (world mm), when due."""
        shown = self._due(out, now)
        if shown is None:
            return None
        plan = shown.plan
        names: list[str] = []
        keys: list[list[float]] = []
        if plan is not None:
            names = list(plan.point_names)
            keys = plan.keys_mm.tolist()
        return PointsOut(names, keys, wall(), "Keyframe", meta=self._meta(out))
