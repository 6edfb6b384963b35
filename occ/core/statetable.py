"""The State Data Table: the last seconds of a robot's state at the loop rate (the SAW's idea).

The loop writes one row per tick into a ring preallocated at start (``array('d')``, fixed size,
element assignments only: no allocation and no growth per tick, ~1 µs for a 3-joint robot);
operators read a time window with ``GetStateTable``, answered by the worker thread with an
``NDARRAY`` (float64, rows x columns, column names in the metadata), so a monitoring client sees
the last seconds at full rate without the loop paying for the reply.

Columns (the first ones are the recording's ``OCCState`` columns, :mod:`occ.recording.record`, in
the same units): ``t`` (daemon clock, s), ``state`` (code as in the recording), ``q.<joint>``,
``sp.<joint>`` (what the drivers hold: the running setpoint, else the held one),
``tip.x_mm tip.y_mm tip.z_mm`` (tip in the base frame), then ``eff.<joint>`` (measured effort,
N or N m) and ``owner`` (index of the master in control, -1 without collaboration). The loop
stores only what it already has (joints, setpoints, efforts, codes); the tip is forward
kinematics of ``q``, computed by the reader on its own copy of the kinematic model, so the loop
pays no forward kinematics for it.

Reading while the loop writes: rows are written before the row count moves, and the reader
copies, then reads the count again and keeps only the rows the writer cannot have reached in
between (the oldest ones may be dropped, a row is never torn).
"""

from __future__ import annotations

import math
import time
from array import array
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from occ.core.safety import RobotState
from occ.recording.record import STATE_CODES

if TYPE_CHECKING:
    from occ.core.data import RobotData
    from occ.joint import Joint
    from occ.kinematics.frame import Frame

#: a state's number in the recording and the State Data Table
STATE_NUMBER = {st: float(STATE_CODES.get(st.value, -1)) for st in RobotState}

#: rows one NDARRAY dimension can hold (IGTL: uint16 per dimension)
MAX_ROWS = 0xFFFF


class StateTable:
    """A bounded, time-indexed ring of robot state rows (see the module docstring)."""

    def __init__(self, joint_names: Sequence[str], capacity: int, frame: Frame) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.joint_names = tuple(joint_names)
        n = len(self.joint_names)
        self.n = n
        self.capacity = int(capacity)
        #: stored per row: t, state, owner, q[n], sp[n], eff[n]
        self.width = 3 + 3 * n
        # one slot more than the rows promised: the one the writer may be in the middle of
        self._slots = self.capacity + 1
        self._buf = array("d", bytes(8 * self._slots * self.width))
        self._view = np.frombuffer(self._buf, dtype=np.float64).reshape(self._slots, self.width)
        self._pos = 0  # where the next row starts in _buf
        self._end = self._slots * self.width
        #: rows written since start (the ring holds the last ``capacity`` of them)
        self.count = 0
        self._frame = frame.copy()  # the reader's own model: FK off the loop thread
        self.columns = (
            ["t", "state"]
            + [f"q.{j}" for j in self.joint_names]
            + [f"sp.{j}" for j in self.joint_names]
            + ["tip.x_mm", "tip.y_mm", "tip.z_mm"]
            + [f"eff.{j}" for j in self.joint_names]
            + ["owner"]
        )

    # ------------------------------------------------------------------ loop thread
    def write_data(
        self, now: float, owner: float, data: RobotData, joints: Sequence[Joint]
    ) -> None:
        """The robot's row for this tick (the loop, once a tick)."""
        self.write(now, STATE_NUMBER[data.state], owner, data.q, data.commanded(), joints)

    def write(
        self,
        now: float,
        state: float,
        owner: float,
        q: Sequence[float],
        sp: Sequence[float],
        joints: Sequence[Joint],
    ) -> None:
        """One row (the loop, once a tick): element assignments into the preallocated ring."""
        buf = self._buf
        i = self._pos
        buf[i] = now
        buf[i + 1] = state
        buf[i + 2] = owner
        i += 3
        for v in q:
            buf[i] = v
            i += 1
        for v in sp:
            buf[i] = v
            i += 1
        for jt in joints:
            buf[i] = jt.effort
            i += 1
        self._pos = 0 if i >= self._end else i
        self.count += 1  # after the row: a reader never takes a half-written one

    # ------------------------------------------------------------------ reader (any thread)
    def rows(self) -> np.ndarray:
        """The last :attr:`capacity` rows (fewer before that many were written), oldest
        first, as stored (t, state, owner, q, sp, eff)."""
        cap = self._slots
        n1 = self.count
        if n1 <= cap:
            out = self._view[:n1].copy()
            first = 0
        else:
            start = n1 % cap
            out = np.concatenate((self._view[start:], self._view[:start]))
            first = n1 - cap
        n2 = self.count
        # rows first .. n1-1 were copied; the writer meanwhile wrote rows n1 .. n2 (the last
        # perhaps in progress), each over the row ``cap`` before it
        lost = (n2 - cap + 1) - first
        if lost > 0:
            out = out[lost:]
        return out[-self.capacity :]

    def window(
        self,
        seconds: float | None = None,
        *,
        since: float | None = None,
        every: int = 1,
    ) -> np.ndarray:
        """The rows of the last ``seconds`` (of the newest row's time; None: all), or those
        after ``since`` (daemon clock), every ``every``-th, with the published columns
        (:attr:`columns`) in order. At most :data:`MAX_ROWS` rows (the newest)."""
        raw = self.rows()
        if len(raw):
            t = raw[:, 0]
            lo = 0
            if seconds is not None:
                lo = int(np.searchsorted(t, t[-1] - seconds - 1e-9, side="left"))
            if since is not None:
                lo = max(lo, int(np.searchsorted(t, since, side="right")))
            raw = raw[lo:]
        if every > 1:
            # keep the newest row and every every-th before it
            raw = raw[(len(raw) - 1) % every :: every]
        if len(raw) > MAX_ROWS:
            raw = raw[-MAX_ROWS:]
        return self._publish(raw)

    def _publish(self, raw: np.ndarray) -> np.ndarray:
        n = self.n
        out = np.empty((len(raw), len(self.columns)), dtype=np.float64)
        out[:, 0:2] = raw[:, 0:2]
        out[:, 2 : 2 + 2 * n] = raw[:, 3 : 3 + 2 * n]
        tip = 2 + 2 * n
        fk = self._frame.fk
        for r in range(len(raw)):
            if r & 15 == 15:
                time.sleep(0)  # hand the interpreter lock back: the loop may be waiting
            m = fk(raw[r, 3 : 3 + n].tolist())
            out[r, tip] = m[0, 3] * 1000.0
            out[r, tip + 1] = m[1, 3] * 1000.0
            out[r, tip + 2] = m[2, 3] * 1000.0
        out[:, tip + 3 : tip + 3 + n] = raw[:, 3 + 2 * n : 3 + 3 * n]
        out[:, -1] = raw[:, 2]
        return out

    def stats(self) -> dict[str, float | int]:
        held = min(self.count, self.capacity)
        return {"rows": held, "capacity": self.capacity, "written": self.count}


def table_for(
    seconds: float | None, joints: Sequence[Joint], rate_hz: float, frame: Frame
) -> StateTable | None:
    """The robot's table for ``state_table.seconds`` (None: no table)."""
    if seconds is None:
        return None
    return StateTable([j.name for j in joints], capacity_for(seconds, rate_hz), frame)


def capacity_for(seconds: float, rate_hz: float) -> int:
    """Rows for ``seconds`` of state at ``rate_hz``."""
    return max(1, math.ceil(seconds * rate_hz))
