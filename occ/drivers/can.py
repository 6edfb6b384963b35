"""Joint drives on a CAN bus, through python-can.

Frame protocol (classic CAN, 11-bit identifiers, DLC 8, all integers big-endian)
================================================================================

Command, host -> drive, identifier = the joint's ``can_id``::

    byte 0..3  int32   value: position in encoder counts (mode 1)
                              or effort in milli-units, mN*m or mN (mode 2)
    byte 4     uint8   mode: 0 = disabled (brake/hold, value ignored), 1 = position, 2 = effort
    byte 5     uint8   sequence number, +1 per command frame of this joint, wraps at 256
    byte 6     uint8   heartbeat, ms (1-255; 0 = off): the drive's consumer heartbeat time.
                       A drive in mode 1 or 2 that receives no command frame for that long
                       stops itself (mode 0, brake) and flags it in its feedback until it
                       receives a mode-0 frame (the host's acknowledgement)
    byte 7             reserved, 0

Feedback, drive -> host, identifier = the joint's ``feedback_id``::

    byte 0..3  int32   position, encoder counts
    byte 4..5  int16   velocity, counts per millisecond (saturating)
    byte 6..7  int16   effort, milli-units (saturating at +-32.767 N*m or N); the value
                       -32768 (never a saturated effort) flags "stopped by its heartbeat"

Scaling: ``position = counts / counts_per_unit`` (counts per radian or per metre),
``velocity = counts_per_ms * 1000 / counts_per_unit``, ``effort = milli / 1000``. Commands are
rounded to the nearest count and saturated to int32. A negative ``counts_per_unit`` is a drive
whose counts run against the joint (mounted reversed): its efforts are reversed too, both the
commanded and the reported ones (``effort = -milli / 1000``), so that a positive joint effort
still pushes the joint toward positive positions.

A drive answers every command frame with one feedback frame (in order: one node, one
identifier) and may also send feedback cyclically. Each :meth:`CANDriver.read` drains the
receive queue without blocking and keeps the newest feedback per joint.

Polling: while the driver is not ACTIVE (INACTIVE, or FAULT, where it is still read) a node
that answers only commands would fall silent, so each read sends every joint whose previous
command is answered (and whose last command is ``poll_period`` old) a mode-0 frame, the
*poll*. Mode 0 is what the drive is in anyway when the driver is not ACTIVE (brake/hold); to
its heartbeat logic it is the host's acknowledgement, which it already got when the driver
left ACTIVE (``deactivate`` and every fault send mode 0), and a drive in mode 0 runs no
heartbeat. While ACTIVE nothing is polled: a command goes to every joint every tick (a mode-0
frame then would brake the drive).

Feedback age, not arrival: the feedback frame carries no timestamp and no sequence number, so
a frame that arrives now may hold data of any age (a drive whose every answer is 50 ms late
delivers one frame a tick, each 50 ms old). The driver keeps, per joint, the send times (loop
clock) of its commands not yet answered, oldest first; a feedback frame is the answer to the
oldest one (a drive answers each command once, in order), and the drive sampled it no earlier
than that command was sent. A joint's *feedback age* is the larger of two ages, both measured
on the loop clock: ``now`` minus the send time of the oldest command it still owes an answer
to (that answer, whenever it comes, is at least that old: a silent drive), and the round trip
of its newest answer, at least: the last read that found the receive queue empty (the answer
came after it) minus the send time of its command (the age the data had when it arrived: a
drive whose answers come late, kept until a newer answer, so a reset does not make it
punctual). Above ``feedback_timeout`` the read raises
:class:`~occ.errors.DriverError` naming the joint, the age, the limit and the commands
unanswered, which latches FAULT in the driver base: a silent drive and a late one, at run time
and at the first read after a reset (the send times survive ``reset``: the answers a late
drive still owes from before are judged by when they were asked for). A pause of the host
(nothing asked for a while, e.g. between Enable and the loop's first tick) is not the drive's:
a drive that owes nothing, and answered on time, is not late. Commands sent outside a read or
a write (configure, deactivate, reset, the safe stop) are timed at the last ``now`` the driver
saw, which can only make them look older. :meth:`CANDriver.feedback_age` gives each joint's
data age (since the command its newest frame answers was sent).

Counting cannot tell an answer that was lost (a drive that was muted, or restarted) from one
that is still coming: a command is given up as unanswered only when it is older than
``lost_after`` (default ten times ``feedback_timeout``) and nothing has been heard from its
joint for as long (a drive late by up to ``lost_after`` would have answered it by then, and
while frames flow the counting stays in step); then the joint is polled afresh. So after a
silent or late drive is repaired, a reset passes once it has been quiet that long, not before.
A drive later than ``lost_after`` can pass single reads while the driver is not ACTIVE (its
answers to the commands given up stand in for answers to later polls); once ACTIVE it faults
soon after, as its late answers cannot keep up with a command every tick. A drive that also
sends cyclically: its frames cannot be told from answers, so they are taken as answers to the
oldest command, which judges a late cyclic drive too young; such frames are counted
(``unsolicited_frames``, a frame with no command outstanding) and logged once. Set drives to
answer only where the age must be judged. ``deactivate`` sends mode-0 frames so the drives
brake.

Parameters
==========

===================  ===============  ===================================================
key                  default          meaning
===================  ===============  ===================================================
interface            ``"socketcan"``  python-can interface name (``"virtual"`` in tests)
channel              ``"can0"``       python-can channel
bitrate              1000000          bit/s
bus_kwargs           {}               extra keyword arguments for ``can.Bus``
joints               required         ``{joint_name: {can_id, feedback_id, counts_per_unit}}``
                                      or a list of such dicts in joint order
feedback_timeout     0.01             s: the oldest feedback age (above) accepted
lost_after           null             s of quiet after which unanswered commands are given
                                      up as lost (null: 10 x ``feedback_timeout``; at
                                      least ``feedback_timeout``)
poll_period          0.0              s between polls of an answered joint while not
                                      ACTIVE (0: every read; below ``feedback_timeout``)
error_frames         10               error frames tolerated per 100 ms (0 = none)
send_timeout         0.0005           s a send may block on a full transmit queue
command_interface    ``"position"``   or ``"effort"`` (the base's PID makes the efforts)
period               0.001            nominal loop period (driver base)
===================  ===============  ===================================================

Real hardware (Linux SocketCAN)::

    sudo ip link set can0 up type can bitrate 1000000
    # params: {interface: socketcan, channel: can0, bitrate: 1000000, joints: {...}}

Bus errors: error frames (python-can's ``is_error_frame``; on SocketCAN the driver enables
them with ``CAN_RAW_ERR_FILTER``, which python-can leaves off) are counted in
``error_frames``. One that reports *bus-off* (the error class ``CAN_ERR_BUSOFF``, 0x40, in its
identifier) faults the driver at once: the controller has left the bus and no command reaches
the drives. More than ``error_frames`` in 100 ms fault it too: a bus that noisy loses frames.
A reset forgets the error frames up to the fault they caused, not those heard since: a bus
still flooding fails the first read after the reset. A drive that stops answering, or
answers later than ``feedback_timeout``, faults it through the feedback age.

SocketCAN takes its bitrate from ``ip link``, not from python-can. Without hardware use
``interface: virtual`` (every ``can.Bus`` opened on the same virtual channel name in one
process is connected) together with :class:`occ.drivers.can_sim.SimulatedDriveNode`.
"""

from __future__ import annotations

import logging
import math
import socket as _socket
import struct
from collections import deque
from collections.abc import Mapping, Sequence
from typing import Any

import can

from occ.drivers.base import CommandInterface, Driver, DriverState, LimitPolicy
from occ.errors import DriverError
from occ.joint import Joint

logger = logging.getLogger(__name__)

__all__ = [
    "CANDriver",
    "COMMAND_FRAME",
    "FEEDBACK_FRAME",
    "MODE_DISABLED",
    "MODE_POSITION",
    "MODE_EFFORT",
    "EFFORT_SCALE",
    "HEARTBEAT_LOST",
    "VELOCITY_SCALE",
]

COMMAND_FRAME = struct.Struct(">iBBBx")
FEEDBACK_FRAME = struct.Struct(">ihh")
MODE_DISABLED = 0
MODE_POSITION = 1
MODE_EFFORT = 2
EFFORT_SCALE = 1000.0  # milli-units per unit
HEARTBEAT_LOST = -32768  # the feedback effort value of a drive stopped by its heartbeat
#: a read takes at most this many frames per joint off the bus; the rest wait for the next tick,
#: so a babbling node costs the tick a bounded amount of work, never the loop itself
MAX_FRAMES_PER_JOINT = 64
VELOCITY_SCALE = 1000.0  # counts/ms -> counts/s

_INT32_MAX = 2**31 - 1
_INT32_MIN = -(2**31)
_DEFAULTS: dict[str, Any] = {
    "interface": "socketcan",
    "channel": "can0",
    "bitrate": 1_000_000,
    "bus_kwargs": {},
    "joints": None,
    "feedback_timeout": 0.01,
    "lost_after": None,
    "poll_period": 0.0,
    "error_frames": 10,
    "send_timeout": 0.0005,
    "command_interface": "position",
    "period": 0.001,
}


#: the error class bits of a SocketCAN error frame's identifier (linux/can/error.h)
CAN_ERR_BUSOFF = 0x40
CAN_ERR_MASK = 0x1FFFFFFF
#: the socket option that lets error frames through (linux/can/raw.h; the socket module
#: has it, typeshed does not)
CAN_RAW_ERR_FILTER = 2
#: the window over which ``error_frames`` are counted, s
ERROR_WINDOW = 0.1


def round_saturated(value: float, lo: int, hi: int) -> int:
    """Round to nearest and saturate to [lo, hi]: a command must never wrap around to the
    other sign (the integers of a CAN frame: this driver's, CiA 402's PDOs)."""
    if value != value:
        raise ValueError("NaN cannot be sent")
    if value >= hi:
        return hi
    if value <= lo:
        return lo
    return int(math.floor(value + 0.5))


class CANDriver(Driver):
    """Joints driven over CAN with the frame protocol of the module docstring."""

    supported_interfaces = ("position", "effort")
    DEFAULT_PARAMS = _DEFAULTS

    def __init__(
        self,
        name: str,
        joints: Sequence[Joint],
        params: Mapping[str, Any] | None = None,
        on_limit: LimitPolicy = "clamp",
        command_interface: CommandInterface | None = None,
    ) -> None:
        super().__init__(name, joints, params, on_limit, command_interface)
        p = self.params  # defaults merged, unknown keys refused by the base
        self._bus_args: dict[str, Any] = {
            "interface": p["interface"],
            "channel": p["channel"],
            "bitrate": int(p["bitrate"]),
            **dict(p["bus_kwargs"]),
        }
        self._timeout = float(p["feedback_timeout"])
        self._send_timeout = float(p["send_timeout"])
        if not self._timeout > 0.0:
            raise ValueError("can driver: feedback_timeout must be > 0")
        lost = p["lost_after"]
        self._lost_after = 10.0 * self._timeout if lost is None else float(lost)
        if not self._lost_after >= self._timeout:
            # quicker would give up answers a drive on time still owes
            raise ValueError("can driver: lost_after must be >= feedback_timeout")
        self._poll_period = float(p["poll_period"])
        if not 0.0 <= self._poll_period < self._timeout:
            # rarer would let a healthy drive's feedback age pass the timeout between polls
            raise ValueError("can driver: poll_period must be >= 0 and < feedback_timeout")
        axes = self._parse_axes(p["joints"])
        self._can_ids = [a[0] for a in axes]
        self._feedback_ids = [a[1] for a in axes]
        self._counts_per_unit = [a[2] for a in axes]
        # milli-units per unit, in the drive's sense: reversed with its counts
        self._effort_scale = [EFFORT_SCALE if a[2] > 0.0 else -EFFORT_SCALE for a in axes]
        self._index_of_feedback = {fid: i for i, fid in enumerate(self._feedback_ids)}
        if len(self._index_of_feedback) != len(axes):
            raise ValueError("can driver: feedback_id values must be distinct")
        if len(set(self._can_ids)) != len(axes):
            raise ValueError("can driver: can_id values must be distinct")

        n = len(self.joints)
        self._bus: can.BusABC | None = None
        self._messages = [
            can.Message(arbitration_id=cid, is_extended_id=False, data=bytearray(8))
            for cid in self._can_ids
        ]
        self._seq = [0] * n
        # the drive's consumer heartbeat time travels in every command frame (byte 6, ms)
        hb_ms = round(self.heartbeat_s * 1e3)
        if hb_ms > 255:
            raise ValueError(f"can driver {name!r}: heartbeat_ms must be <= 255, got {hb_ms}")
        self._heartbeat_byte = hb_ms
        # unknown until the drive answers: a position the robot never measured must not
        # become a setpoint (it would send the drive there in one step when enabled)
        self._pos = [math.nan] * n
        self._vel = [0.0] * n
        self._eff = [0.0] * n
        # Feedback age (module docstring): per joint, the send times of the commands not yet
        # answered, oldest first (deque: the supervisor's safe stop appends from its thread
        # while the loop pops, each one atomic); the send time of the command the newest
        # frame answers; when the last frame arrived and the last command left (quiet)
        self._forget_answers()
        self._now = math.nan  # the last now seen: the send time of a hook's frames
        self._feedback_frames = 0
        self._ignored_frames = 0
        self._command_frames = 0
        self._polls = 0
        self._lost_answers = 0
        self._unsolicited_frames = 0
        self._error_frames = 0
        self._error_limit = int(p["error_frames"])
        if self._error_limit < 0:
            raise ValueError("can driver: error_frames must be >= 0")
        self._error_window: list[float] = []  # times of the error frames in the window
        self._errors_judged_at = math.nan  # the now of the error frames that faulted it

    def _forget_answers(self) -> None:
        """No command owed an answer, none answered, no frame heard (feedback age, module
        docstring)."""
        n = len(self.joints)
        self._pending: list[deque[float]] = [deque() for _ in range(n)]
        self._answered = [math.nan] * n
        # the newest answer's round trip, at least: when the receive queue was last seen
        # empty (it arrived later) minus its command's send time
        self._round_trip = [math.nan] * n
        self._empty_at = math.nan  # the now of the last read that emptied the receive queue
        self._last_rx = [math.nan] * n
        self._last_tx = [math.nan] * n
        self._t0 = math.nan  # the first read's now: the age of a joint never answered

    def _parse_axes(self, spec: Any) -> list[tuple[int, int, float]]:
        if spec is None:
            raise ValueError("can driver: params['joints'] is required (can_id, feedback_id, ...)")
        if isinstance(spec, Mapping):
            missing = [j.name for j in self.joints if j.name not in spec]
            extra = set(spec) - {j.name for j in self.joints}
            if missing or extra:
                raise ValueError(f"can driver: joints params missing {missing}, unknown {extra}")
            entries = [spec[j.name] for j in self.joints]
        else:
            entries = list(spec)
            if len(entries) != len(self.joints):
                raise ValueError("can driver: one joints entry per joint is required")
        axes = []
        for joint, entry in zip(self.joints, entries, strict=True):
            try:
                can_id = int(entry["can_id"])
                feedback_id = int(entry["feedback_id"])
                cpu = float(entry.get("counts_per_unit", 1.0))
            except (KeyError, TypeError, ValueError) as err:
                raise ValueError(f"can driver: joint {joint.name!r}: bad entry {entry!r}") from err
            for ident in (can_id, feedback_id):
                if not 0 <= ident <= 0x7FF:
                    raise ValueError(f"can driver: joint {joint.name!r}: id {ident:#x} not 11-bit")
            if cpu == 0.0 or not math.isfinite(cpu):
                raise ValueError(f"can driver: joint {joint.name!r}: counts_per_unit must be != 0")
            axes.append((can_id, feedback_id, cpu))
        return axes

    def stats(self) -> dict[str, int]:
        """Base counters plus ``feedback_frames``, ``ignored_frames`` (foreign/malformed),
        ``error_frames``, ``command_frames`` (every frame sent, polls and stops included),
        ``polls``, ``lost_answers`` (commands given up as unanswered) and
        ``unsolicited_frames`` (feedback with no command outstanding)."""
        out = super().stats()
        out["feedback_frames"] = self._feedback_frames
        out["ignored_frames"] = self._ignored_frames
        out["error_frames"] = self._error_frames
        out["command_frames"] = self._command_frames
        out["polls"] = self._polls
        out["lost_answers"] = self._lost_answers
        out["unsolicited_frames"] = self._unsolicited_frames
        return out

    def feedback_age(self, now: float) -> list[float]:
        """Each joint's data age at ``now``, s: since the command its newest frame answers was
        sent (module docstring; NaN before any read)."""
        t0 = self._t0
        return [now - (t if t == t else t0) for t in self._answered]

    # ------------------------------------------------------------------ hooks
    def _configure(self) -> None:
        try:
            bus = can.Bus(**self._bus_args)
        except (can.CanError, OSError, ImportError, ValueError, TypeError) as err:
            raise DriverError(
                f"can driver {self.name!r}: cannot open bus {self._bus_args}: {err}"
            ) from err
        sock = getattr(bus, "socket", None)
        if self._bus_args["interface"] == "socketcan" and sock is not None:
            # kernel filters for the feedback identifiers, and error frames, all classes
            bus.set_filters(
                [{"can_id": f, "can_mask": 0x7FF, "extended": False} for f in self._feedback_ids]
            )
            try:
                sock.setsockopt(
                    _socket.SOL_CAN_RAW, CAN_RAW_ERR_FILTER, struct.pack("=I", CAN_ERR_MASK)
                )
            except (OSError, AttributeError) as err:
                logger.warning("can driver %s: error frames not enabled: %s", self.name, err)
        # elsewhere python-can filters in software anyway, and its filters would drop error
        # frames: this driver sorts the frames itself (foreign ones are counted as ignored)
        self._bus = bus
        self._error_window = []
        self._forget_answers()
        # ask every drive for a first feedback frame: a command in the disabled mode moves
        # nothing, and drives that only answer commands then report where they are
        for i in range(len(self.joints)):
            self._send(i, MODE_DISABLED, 0)

    def _activate(self) -> None:
        # Nothing to send: the first write commands every joint. What the drives owe stays
        # owed: a drive late while INACTIVE is late now.
        pass

    def _deactivate(self) -> None:
        for i in range(len(self.joints)):
            self._send(i, MODE_DISABLED, 0)

    def _default_noise(self) -> Sequence[float] | None:
        # one count: what a healthy encoder's reading toggles by at rest
        return [1.0 / abs(c) for c in self._counts_per_unit]

    def _reset(self) -> None:
        # A mode-0 frame to each drive: it acknowledges a heartbeat stop and answers where it
        # is. The feedback age is NOT restarted: the answers a late drive owes from before
        # the fault are still judged by when they were asked for, so the first read after
        # the reset fails for a drive that is still late or silent. The error frames that
        # caused the fault are forgotten (acted on), the ones heard since are kept: a bus
        # still flooding fails that read too.
        cut = self._errors_judged_at
        if cut == cut:
            self._error_window = [t for t in self._error_window if t > cut]
            self._errors_judged_at = math.nan
        self._deactivate()

    def _safe_stop(self) -> None:
        # From the supervisor's thread: python-can buses take sends from several threads
        # (SocketCAN: one write() per frame; virtual: a locked queue). A separate frame object
        # per call, so the loop thread's frames are not touched.
        bus = self._bus
        if bus is None:
            return
        for i, msg in enumerate(self._messages):
            data = bytearray(8)
            COMMAND_FRAME.pack_into(data, 0, 0, MODE_DISABLED, self._seq[i], self._heartbeat_byte)
            stop = can.Message(arbitration_id=msg.arbitration_id, is_extended_id=False, data=data)
            # owed an answer like any command (else its answer would be taken for another's)
            self._pending[i].append(self._now)
            self._command_frames += 1
            try:
                bus.send(stop, timeout=self._send_timeout)
            except can.CanError:
                logger.exception("can driver %s: safe stop frame not sent", self.name)

    def _shutdown(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None:
            bus.shutdown()

    def _read(self, now: float) -> tuple[Sequence[float], Sequence[float], Sequence[float]]:
        bus = self._bus
        assert bus is not None  # the base only reads once configured
        if self._t0 != self._t0:
            self._t0 = now
        self._now = now
        self._drain(bus, now)
        self._give_up_and_poll(now)
        self._judge_age(now)
        return self._pos, self._vel, self._eff

    def _drain(self, bus: can.BusABC, now: float) -> None:
        """The frames received since the last read (at most ``MAX_FRAMES_PER_JOINT`` a
        joint): the feedback taken, each answering its joint's oldest command owed."""
        index_of = self._index_of_feedback
        unpack = FEEDBACK_FRAME.unpack_from
        pending = self._pending
        answered = self._answered
        round_trip = self._round_trip
        last_rx = self._last_rx
        # What is in the queue now arrived after it was last seen empty: a lower bound of each
        # frame's arrival that a pause of the host (a late read) does not move.
        empty_at = self._empty_at
        # Bounded drain: a babbling node must not keep the loop here forever.
        for _ in range(MAX_FRAMES_PER_JOINT * len(last_rx)):
            try:
                msg = bus.recv(timeout=0.0)
            except can.CanError as err:
                raise DriverError(f"can driver {self.name!r}: receive failed: {err}") from err
            if msg is None:
                self._empty_at = now
                break
            if msg.is_error_frame:
                self._on_error_frame(msg, now)
                continue
            i = index_of.get(msg.arbitration_id)
            # an 11-bit identifier only: a 29-bit frame with the same number is another one
            if i is None or msg.is_extended_id or msg.is_remote_frame or msg.dlc < 8:
                self._ignored_frames += 1
                continue
            counts, vel, eff = unpack(msg.data)
            if eff == HEARTBEAT_LOST:
                eff = 0  # a flag, not an effort
                # once ACTIVE only: faulted, we sent mode 0, which clears the drive's flag
                if self.state is DriverState.ACTIVE:
                    raise DriverError(
                        f"can driver {self.name!r}: joint {self.joints[i].name}: heartbeat "
                        f"lost: the drive stopped itself (no command for "
                        f"{self.heartbeat_s * 1e3:.0f} ms)"
                    )
            cpu = self._counts_per_unit[i]
            self._pos[i] = counts / cpu
            self._vel[i] = vel * VELOCITY_SCALE / cpu
            self._eff[i] = eff / self._effort_scale[i]
            last_rx[i] = now
            self._feedback_frames += 1
            owed = pending[i]
            if owed:
                sent = owed.popleft()
                # the answer to the oldest command: its data is no older than that command
                sent = sent if sent == sent else self._t0
                answered[i] = sent
                trip = empty_at - sent
                round_trip[i] = trip if trip > 0.0 else 0.0  # NaN (first read) -> 0
            else:
                # sent on its own: its age is unknown, so it does not make the joint fresh
                if not self._unsolicited_frames:
                    logger.warning(
                        "can driver %s: joint %s sends feedback on its own: cyclic frames "
                        "cannot be told from answers, its feedback age is judged too young "
                        "if they are late",
                        self.name,
                        self.joints[i].name,
                    )
                self._unsolicited_frames += 1

    def _give_up_and_poll(self, now: float) -> None:
        """Commands owed for ``lost_after`` by a joint heard nothing from since are given up
        as lost; while not ACTIVE, a joint owed nothing is asked every ``poll_period``."""
        pending = self._pending
        last_rx = self._last_rx
        polling = self.state is not DriverState.ACTIVE
        lost_after = self._lost_after
        t0 = self._t0
        for i, owed in enumerate(pending):
            if owed:
                heard = last_rx[i]
                if now - (heard if heard == heard else t0) >= lost_after:
                    # nothing heard that long: the commands older than that are not going to
                    # be answered (module docstring); newer ones (a reset's) are still owed
                    lost = 0
                    while owed:
                        sent = owed[0]
                        if now - (sent if sent == sent else t0) < lost_after:
                            break
                        owed.popleft()
                        lost += 1
                    if lost:
                        self._lost_answers += lost
                        logger.warning(
                            "can driver %s: joint %s: %d commands unanswered for %.0f ms "
                            "given up as lost",
                            self.name,
                            self.joints[i].name,
                            lost,
                            lost_after * 1e3,
                        )
            if polling and not owed:
                sent = self._last_tx[i]
                if sent != sent or now - sent >= self._poll_period:
                    self._polls += 1
                    self._send(i, MODE_DISABLED, 0, now)

    def _judge_age(self, now: float) -> None:
        """Raise DriverError for a joint whose feedback is older than ``feedback_timeout``."""
        pending = self._pending
        answered = self._answered
        round_trip = self._round_trip
        t0 = self._t0
        # Judged (module docstring): the oldest command a joint still owes an answer to (that
        # answer, whenever it comes, is at least that old) and the round trip of its newest
        # answer (kept until a newer one: a reset does not make a late drive punctual). Not
        # now minus the newest answer's command: after a pause of the host (nothing asked,
        # e.g. between Enable and the loop's first tick) that is old through no fault of the
        # drive. (The slack: now - sent in float may exceed a timeout it equals in ms.)
        timeout = self._timeout
        limit = timeout * (1.0 + 1e-9)
        for i, owed in enumerate(pending):
            waited = 0.0
            if owed:
                sent = owed[0]
                waited = now - (sent if sent == sent else t0)
            trip = round_trip[i]
            if waited > limit or trip > limit:
                n_owed = len(owed)
                tail = (
                    f"{n_owed} command{'' if n_owed == 1 else 's'} unanswered"
                    + (", none ever answered" if answered[i] != answered[i] else "")
                    + ")"
                )
                fid = self._feedback_ids[i]
                where = f"can driver {self.name!r}: joint {self.joints[i].name}"
                if waited >= trip or trip != trip:
                    raise DriverError(
                        f"{where}: no feedback on id {fid:#x} for {waited * 1e3:.1f} ms: "
                        f"feedback age {waited * 1e3:.1f} ms > feedback_timeout "
                        f"{timeout * 1e3:.1f} ms ({tail}"
                    )
                raise DriverError(
                    f"{where}: feedback on id {fid:#x} answers a command sent at least "
                    f"{trip * 1e3:.1f} ms before it arrived: feedback age {trip * 1e3:.1f} ms "
                    f"> feedback_timeout {timeout * 1e3:.1f} ms (answer late; {tail}"
                )

    def _on_error_frame(self, msg: can.Message, now: float) -> None:
        self._error_frames += 1
        if self.state is not DriverState.FAULT:
            # the frames up to here fault the driver; a reset forgets these, not later ones
            self._errors_judged_at = now
        if msg.arbitration_id & CAN_ERR_BUSOFF:
            raise DriverError(
                f"can driver {self.name!r}: bus-off on {self._bus_args['channel']}: the "
                f"controller left the bus (error frame {msg.arbitration_id:#x})"
            )
        window = self._error_window
        window.append(now)
        while window and now - window[0] > ERROR_WINDOW:
            window.pop(0)
        if len(window) > self._error_limit:
            raise DriverError(
                f"can driver {self.name!r}: {len(window)} error frames in "
                f"{ERROR_WINDOW * 1e3:.0f} ms on {self._bus_args['channel']} (limit "
                f"{self._error_limit}; last {msg.arbitration_id:#x})"
            )

    def _write(self, values: Sequence[float], now: float) -> None:
        if self.command_interface == "position":
            for i, x in enumerate(values):
                self._send(
                    i,
                    MODE_POSITION,
                    round_saturated(x * self._counts_per_unit[i], _INT32_MIN, _INT32_MAX),
                    now,
                )
        else:
            scale = self._effort_scale
            for i, u in enumerate(values):
                self._send(
                    i, MODE_EFFORT, round_saturated(u * scale[i], _INT32_MIN, _INT32_MAX), now
                )

    def _send(self, i: int, mode: int, value: int, now: float | None = None) -> None:
        """One command frame to joint ``i``, owed an answer from ``now`` (None: from the
        last now the driver saw, for the hooks that get none: an answer looks older)."""
        bus = self._bus
        if bus is None:
            return
        if now is None:
            now = self._now
        else:
            self._now = now
        msg = self._messages[i]
        seq = self._seq[i]
        COMMAND_FRAME.pack_into(msg.data, 0, value, mode, seq, self._heartbeat_byte)
        self._seq[i] = (seq + 1) & 0xFF
        # owed before it leaves: on the virtual bus the answer can come before send returns
        self._pending[i].append(now)
        self._last_tx[i] = now
        self._command_frames += 1
        try:
            bus.send(msg, timeout=self._send_timeout)
        except can.CanError as err:
            # not sent, not owed (the newest entry is this frame's: sends are from one thread
            # but the safe stop's, which only runs once the loop is hung)
            self._pending[i].pop()
            self._command_frames -= 1
            raise DriverError(
                f"can driver {self.name!r}: send to id {msg.arbitration_id:#x} failed: {err}"
            ) from err
