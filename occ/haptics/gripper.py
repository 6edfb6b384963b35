"""The gripper channel: the master's handle opens and closes the slave's grippers (issue 37).

The German Heart Center's master handle had a switch that opened and closed the instrument's
grippers. Here the master sends a *gripper value* with every sample of its stream, in the
POSITION's v2 metadata beside ``run`` and ``clutch``: ``gripper``, ``0`` open to ``1`` closed,
three decimals (a slave that does not know the key ignores it). Where it comes from
(teleop-master ``gripper.source``, :class:`GripperSource`):

``joint``    a joint of the master (a handle's grip angle or its switch read as a position by the
             master's drivers): ``(q - open) / (closed - open)``, limited to 0..1;
``command``  the operator's ``Grip`` command (``Value``: ``1``/``close``, ``0``/``open``, or a
             number 0..1), the switch as a button wired to an operator client, the way the
             clutch is the ``Clutch`` command;
``sim``      the simulated operator closes and opens it, a raised cosine of ``period_s``, while
             the master runs.

The slave (teleop-slave ``gripper``, :class:`GripperFollower`) maps the value onto one of its
joints, a jaw that does not move the tool's tip: ``open + value (closed - open)``, approached at
no more than 0.9 times the joint's velocity limit per tick, like every other setpoint. It follows
only while the slave follows its master (RUNNING, ``run=1``, the clutch released); otherwise,
and whenever the stream is late or lost, the jaw holds where it was told to be, as the arm does
(the robot holds the whole setpoint). A value that is not a number from 0 to 1 is refused and
counted; the jaw holds.

Loop thread only; plain floats (every tick).
"""

from __future__ import annotations

import math
from typing import Any

__all__ = ["GripperFollower", "GripperSource", "parse_gripper"]

#: ``Grip`` command values that mean closed or open
_CLOSED = ("1", "close", "closed", "on", "true")
_OPEN = ("0", "open", "opened", "off", "false")


def parse_gripper(text: str) -> float | None:
    """A ``gripper`` value: a number from 0 (open) to 1 (closed), else None."""
    try:
        v = float(text)
    except ValueError:
        return None
    return v if 0.0 <= v <= 1.0 else None  # NaN is neither


class GripperSource:
    """The master's gripper value (module docstring); ``joint`` the index of the source joint
    (``joint`` source)."""

    def __init__(
        self,
        source: str,
        *,
        joint: int | None = None,
        open_pos: float = 0.0,
        closed_pos: float = 1.0,
        period_s: float = 4.0,
    ) -> None:
        if source == "joint" and joint is None:
            raise ValueError("gripper source 'joint' needs a joint")
        self.source = source
        self.joint = joint
        self.open_pos = open_pos
        self.closed_pos = closed_pos
        self.period_s = period_s
        self.commanded = 0.0  # the ``Grip`` command's value: open until told
        self.value = 0.0

    def update(self, q: list[float], t_run: float) -> float:
        """The value now, from the joints ``q`` or the run time ``t_run`` (s)."""
        if self.source == "joint":
            assert self.joint is not None
            span = self.closed_pos - self.open_pos
            v = (q[self.joint] - self.open_pos) / span
            v = min(1.0, max(0.0, v)) if math.isfinite(v) else self.value  # a NaN read: kept
        elif self.source == "sim":
            v = 0.5 - 0.5 * math.cos(2.0 * math.pi * t_run / self.period_s)
        else:
            v = self.commanded
        self.value = v
        return v

    def command(self, text: str) -> str:
        """``Grip``: set the value (``command`` source), or CommandError-worthy ValueError."""
        if self.source != "command":
            raise ValueError(f"the gripper follows its {self.source}, not the Grip command")
        key = text.strip().lower()
        if key in _CLOSED:
            v: float | None = 1.0
        elif key in _OPEN:
            v = 0.0
        else:
            v = parse_gripper(key)
        if v is None:
            raise ValueError(f"Grip: {text!r} is not open, close or a number from 0 to 1")
        self.commanded = v
        return f"gripper {'closed' if v == 1.0 else 'open' if v == 0.0 else f'at {v:g}'}"

    def stats(self) -> dict[str, Any]:
        return {"source": self.source, "value": round(self.value, 3)}


class GripperFollower:
    """The slave's jaw (module docstring): joint ``index``, positions ``open_pos`` and
    ``closed_pos``, at most ``max_step`` per tick."""

    def __init__(
        self,
        index: int,
        name: str,
        open_pos: float,
        closed_pos: float,
        max_step: float,
    ) -> None:
        self.index = index
        self.name = name
        self.open_pos = open_pos
        self.closed_pos = closed_pos
        self.max_step = max_step
        #: the master's last value (None: none received yet) and the jaw's setpoint
        self.value: float | None = None
        self.setpoint: float | None = None
        self.samples = 0
        self.refused = 0
        self.last_error = ""

    def on_meta(self, text: str | None) -> None:
        """A sample's ``gripper`` metadata (None: the master sends none: no change)."""
        if text is None:
            return
        v = parse_gripper(text)
        if v is None:
            self.refused += 1
            self.last_error = f"gripper {text[:20]!r} is not a number from 0 to 1"
            return
        self.samples += 1
        self.value = v

    def restart(self) -> None:
        """Following (re)starts: the jaw continues from where the drives are told to be."""
        self.setpoint = None

    def apply(self, q: list[float], follow: bool) -> list[float]:
        """``q`` with the jaw's setpoint: toward the master's value while ``follow``, held
        otherwise (the first call takes the jaw where ``q`` has it)."""
        i = self.index
        sp = self.setpoint
        if sp is None:
            sp = q[i]
        if follow and self.value is not None:
            goal = self.open_pos + self.value * (self.closed_pos - self.open_pos)
            step = self.max_step
            sp = goal if abs(goal - sp) <= step else sp + math.copysign(step, goal - sp)
        self.setpoint = sp
        q[i] = sp
        return q

    def stats(self) -> dict[str, Any]:
        return {
            "joint": self.name,
            "value": self.value,
            "setpoint": None if self.setpoint is None else round(self.setpoint, 6),
            "samples": self.samples,
            "refused": self.refused,
            "last_error": self.last_error,
        }
