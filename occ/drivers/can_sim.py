"""A simulated CAN drive node: answers on a python-can bus the way a real drive would.

:class:`SimulatedDriveNode` runs a thread that receives the command frames of
:mod:`occ.drivers.can` (one identifier per axis), advances a simple first-order model per
axis, and answers every command with a feedback frame (and, optionally, cyclically). It works
in drive units only (counts, counts/ms, milli-units), as real firmware does; the host does the
SI scaling.

Model, per axis, advanced to the node's ``clock()`` before every command or cyclic feedback:

* mode 1 (position): ``x`` follows the commanded counts with time constant ``tau`` seconds
  (``tau = 0``: exactly, which makes round-trip tests exact);
* mode 2 (effort): velocity ``= effort_milli * effort_gain`` counts/s (a velocity-saturated
  motor on a viscous load), effort reported back as commanded;
* mode 0 (disabled): the axis holds (brake), velocity and effort 0.

Heartbeat consumer: every command frame carries the host's heartbeat time (byte 6, ms). An
axis in mode 1 or 2 that receives no command for longer stops itself (mode 0, brake), counts
it (``heartbeat_trips``) and flags every feedback frame (effort ``-32768``) until a mode-0
frame acknowledges it; commands meanwhile are answered but not obeyed. The node checks at
least every quarter of the heartbeat time (its own thread and clock), as drive firmware does.

Fault modes, for tests of the host: :meth:`~SimulatedDriveNode.mute` (no feedback at all),
``delay`` (every feedback frame held back), :meth:`~SimulatedDriveNode.send_error_frame` (one
error frame), :meth:`~SimulatedDriveNode.error_flood` (error frames with every command, for
as long as the host sends: a bus that stays bad) and
:meth:`~SimulatedDriveNode.stale_dither` (feedback frozen at an old position that toggles by
one count while the axis moves on: a stuck encoder whose last bit flickers).

Use it without hardware with python-can's ``virtual`` interface: the node and the driver
open the same channel name in one process. With real drives, use SocketCAN instead
(``interface: socketcan``, ``channel: can0``, after ``ip link set can0 up type can bitrate
1000000``) and do not start this node.

Tests synchronise on :meth:`wait_feedback` / :meth:`wait_commands` (a condition variable
with a timeout), never on sleeps: python-can's virtual bus delivers a frame into the
receiver's queue before ``send`` returns, so once the node has counted a feedback frame the
driver's next non-blocking ``read`` sees it.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any

import can

from occ.drivers.can import (
    COMMAND_FRAME,
    FEEDBACK_FRAME,
    HEARTBEAT_LOST,
    MODE_DISABLED,
    MODE_EFFORT,
    MODE_POSITION,
)

__all__ = ["DriveAxis", "SimulatedDriveNode"]

_INT16 = 32767
_INT32_MAX = 2**31 - 1
_POLL = 0.01  # s; bounds how long stop() waits for the thread


def _sat16(value: float) -> int:
    v = int(round(value))
    return _INT16 if v > _INT16 else -_INT16 if v < -_INT16 else v


@dataclass
class DriveAxis:
    """One axis of the node: its identifiers and its model state (drive units)."""

    can_id: int
    feedback_id: int
    position: float = 0.0  # counts
    velocity: float = 0.0  # counts/s
    effort: int = 0  # milli-units
    mode: int = MODE_DISABLED
    target: float = 0.0  # counts
    last_seq: int = -1
    lost_commands: int = 0
    commands: int = field(default=0)
    heartbeat_s: float = 0.0  # from the last command frame; 0 = off
    last_command_t: float = math.nan
    heartbeat_lost: bool = False
    heartbeat_trips: int = 0
    #: the frozen (position, velocity) reported under stale_dither; None = live
    stale: tuple[int, int] | None = None
    stale_frames: int = 0  # frames sent frozen: the odd ones are one count off


class SimulatedDriveNode:
    """A thread that plays one or more CAN drives (see the module docstring).

    ``feedback_period``: seconds between unsolicited feedback frames for every axis, or
    None to answer commands only. ``clock`` is injectable so a test can drive time.
    """

    def __init__(
        self,
        axes: Sequence[DriveAxis],
        channel: str,
        interface: str = "virtual",
        tau: float = 0.005,
        effort_gain: float = 10.0,
        feedback_period: float | None = None,
        clock: Callable[[], float] = time.monotonic,
        **bus_kwargs: Any,
    ) -> None:
        if not axes:
            raise ValueError("a drive node needs at least one axis")
        if tau < 0.0:
            raise ValueError("tau must be >= 0")
        if feedback_period is not None and not feedback_period > 0.0:
            raise ValueError("feedback_period must be > 0 or None")
        self.axes: list[DriveAxis] = list(axes)
        self._by_id = {a.can_id: a for a in self.axes}
        self.tau = tau
        self.effort_gain = effort_gain
        self.feedback_period = feedback_period
        self._clock = clock
        self._bus = can.Bus(interface=interface, channel=channel, **bus_kwargs)
        self._bus.set_filters(
            [{"can_id": a.can_id, "can_mask": 0x7FF, "extended": False} for a in self.axes]
        )
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._muted = False
        #: seconds each feedback frame is held back (a drive that answers late); 0 = at once
        self.delay = 0.0
        self._late: list[tuple[float, can.Message]] = []
        self._flood = 0  # error frames after each command frame (error_flood)
        self._flood_class = 0x04
        self._dither = 0  # counts of the stale position's toggle; 0 = live feedback
        self.error_frames_sent = 0
        self._thread: threading.Thread | None = None
        self._t_model = clock()
        self.commands_received = 0
        self.feedback_sent = 0
        self.error: BaseException | None = None

    # ------------------------------------------------------------------ control
    def start(self) -> SimulatedDriveNode:
        """Start the node's thread (returns self, for chaining)."""
        if self._thread is not None:
            raise RuntimeError("node already started")
        self._thread = threading.Thread(target=self._run, name="sim-drive-node", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and close the bus; safe twice."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._bus.shutdown()

    def mute(self, muted: bool = True) -> None:
        """Stop (or resume) sending feedback, as a drive that lost power would."""
        self._muted = muted

    def send_error_frame(self, error_class: int = 0x04) -> None:
        """Put an error frame on the bus, as a CAN controller reports one (SocketCAN's error
        classes: 0x04 controller problem, 0x40 bus-off, ...)."""
        self._bus.send(can.Message(arbitration_id=error_class, is_error_frame=True, dlc=8))
        with self._cond:
            self.error_frames_sent += 1
            self._cond.notify_all()

    def error_flood(self, per_command: int, error_class: int = 0x04) -> None:
        """From now on put ``per_command`` error frames of ``error_class`` on the bus after
        every command frame received (before its answer), as a bus with a bad termination or
        a marginal transceiver corrupts traffic: the flood lasts as long as the host sends,
        across its faults and resets. 0 stops it. Tied to the traffic, not to a clock, so a
        test knows how many error frames each command brings."""
        if per_command < 0:
            raise ValueError("per_command must be >= 0")
        self._flood_class = error_class
        self._flood = per_command

    def stale_dither(self, counts: int = 1) -> None:
        """Freeze every axis's encoder feedback at the next frame it sends (position and
        velocity as they are then), the position toggling by ``counts`` every other frame,
        while the axes go on obeying commands (``DriveAxis.position`` moves): a stuck
        encoder whose lowest bit flickers, which a check for "no change at all" never calls
        frozen. The effort and the heartbeat flag stay live (the drive's, not the
        encoder's). 0 resumes live feedback."""
        if counts < 0:
            raise ValueError("counts must be >= 0")
        self._dither = counts

    def discard_late(self) -> None:
        """Forget the feedback frames still held back by ``delay``."""
        self._late.clear()

    def _flush_late(self) -> None:
        late = self._late
        now = self._clock()
        while late and late[0][0] <= now:
            self._bus.send(late.pop(0)[1])

    def __enter__(self) -> SimulatedDriveNode:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    def wait_commands(self, count: int, timeout: float = 1.0) -> bool:
        """Block until at least ``count`` command frames were received and acted on in total
        (each one's answer sent, or held back by ``delay``, or not sent while muted)."""
        with self._cond:
            return self._cond.wait_for(lambda: self.commands_received >= count, timeout)

    def wait_feedback(self, count: int, timeout: float = 1.0) -> bool:
        """Block until at least ``count`` feedback frames were sent in total."""
        with self._cond:
            return self._cond.wait_for(lambda: self.feedback_sent >= count, timeout)

    # ------------------------------------------------------------------ thread
    def _run(self) -> None:
        next_cyclic = (
            self._clock() + self.feedback_period if self.feedback_period is not None else math.inf
        )
        try:
            while not self._stop.is_set():
                wait = _POLL
                for axis in self.axes:
                    if axis.heartbeat_s > 0.0:
                        wait = min(wait, axis.heartbeat_s / 4.0)
                if self.feedback_period is not None:
                    wait = max(0.0, min(wait, next_cyclic - self._clock()))
                if self._late:
                    wait = max(0.0, min(wait, self._late[0][0] - self._clock()))
                msg = self._bus.recv(timeout=wait)
                self._flush_late()
                if msg is not None:
                    self._on_frame(msg)
                self._check_heartbeats()
                if self.feedback_period is not None and self._clock() >= next_cyclic:
                    next_cyclic += self.feedback_period
                    self._advance()
                    for axis in self.axes:
                        self._send_feedback(axis)
        except Exception as err:  # noqa: BLE001 - report to the test, do not die silently
            self.error = err
            with self._cond:
                self._cond.notify_all()

    def _on_frame(self, msg: can.Message) -> None:
        axis = self._by_id.get(msg.arbitration_id)
        if axis is None or msg.dlc < COMMAND_FRAME.size:
            return
        value, mode, seq, heartbeat_ms = COMMAND_FRAME.unpack_from(msg.data)
        self._advance()
        if axis.last_seq >= 0 and seq != (axis.last_seq + 1) & 0xFF:
            axis.lost_commands += (seq - axis.last_seq - 1) & 0xFF
        axis.last_seq = seq
        axis.commands += 1
        axis.heartbeat_s = heartbeat_ms * 1e-3
        axis.last_command_t = self._clock()
        for _ in range(self._flood):
            self.send_error_frame(self._flood_class)
        if axis.heartbeat_lost:
            if mode != MODE_DISABLED:  # stopped until the host acknowledges with mode 0
                self._send_feedback(axis)
                self._acted_on()
                return
            axis.heartbeat_lost = False
        axis.mode = mode
        if mode == MODE_POSITION:
            axis.target = float(value)
            axis.effort = 0
            if self.tau == 0.0:
                axis.position = axis.target
        elif mode == MODE_EFFORT:
            axis.effort = value
        else:
            axis.velocity = 0.0
            axis.effort = 0
        self._send_feedback(axis)
        self._acted_on()

    def _acted_on(self) -> None:
        # counted once its answer is on the bus (or held back, or muted): a waiter on
        # commands_received may read the answer at once
        with self._cond:
            self.commands_received += 1
            self._cond.notify_all()

    def _check_heartbeats(self) -> None:
        now = self._clock()
        for axis in self.axes:
            hb = axis.heartbeat_s
            if (
                hb > 0.0
                and axis.mode != MODE_DISABLED
                and not axis.heartbeat_lost
                and now - axis.last_command_t > hb
            ):
                self._advance()
                axis.mode = MODE_DISABLED
                axis.velocity = 0.0
                axis.effort = 0
                axis.heartbeat_lost = True
                axis.heartbeat_trips += 1
                self._send_feedback(axis)

    def _advance(self) -> None:
        now = self._clock()
        dt = now - self._t_model
        if dt <= 0.0:
            return
        self._t_model = now
        for axis in self.axes:
            before = axis.position
            if axis.mode == MODE_POSITION:
                if self.tau == 0.0:
                    axis.position = axis.target
                else:
                    alpha = 1.0 - math.exp(-dt / self.tau)
                    axis.position += (axis.target - axis.position) * alpha
            elif axis.mode == MODE_EFFORT:
                axis.position += axis.effort * self.effort_gain * dt
            axis.position = max(-_INT32_MAX, min(_INT32_MAX, axis.position))
            axis.velocity = (axis.position - before) / dt

    def _send_feedback(self, axis: DriveAxis) -> None:
        if self._muted:
            return
        effort = HEARTBEAT_LOST if axis.heartbeat_lost else _sat16(axis.effort)
        position, velocity = int(round(axis.position)), _sat16(axis.velocity / 1000.0)
        dither = self._dither
        if dither:
            # snapshot taken here, on the node's thread, where the model is consistent
            if axis.stale is None:
                axis.stale = (position, velocity)
            position, velocity = axis.stale
            if axis.stale_frames % 2:
                position += dither
            axis.stale_frames += 1
        else:
            axis.stale = None
        data = FEEDBACK_FRAME.pack(position, velocity, effort)
        frame = can.Message(arbitration_id=axis.feedback_id, is_extended_id=False, data=data)
        if self.delay > 0.0:
            self._late.append((self._clock() + self.delay, frame))
        else:
            self._bus.send(frame)
        with self._cond:
            self.feedback_sent += 1
            self._cond.notify_all()
