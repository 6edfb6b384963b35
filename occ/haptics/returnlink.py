"""The return channel, slave -> master: where the slave's tool is, as the master sees it.

The slave (``teleop-slave``, output source ``teleop-return``) sends its measured tip back to
the master that streams to it, on the same UDP link and at the stream rate (500 Hz in the
shipped configs): one POSITION ``SlaveTip`` per sample, header version 2, the message ID a
sequence number (+1 per packet), the header timestamp when it was measured, HMAC-signed when
the link has a key (:mod:`igtl.auth`, like the forward stream). The pose is the one the slave
shows 3D Slicer as ``Tip`` (the patient frame: base pose x forward kinematics), position mm and
the full quaternion. Everything else rides in the v2 metadata of the same message:

``following``
    ``1`` while the slave follows *this* master (RUNNING, this master's stream the one it
    follows, ``run=1``, clutch released), else ``0``;
``map``
    9 numbers, row by row: how a handle displacement (master mm) moves the tip in the patient
    frame (mm), i.e. the slave's base rotation x motion scaling x master-to-slave rotation.
    The master maps fixtures and tool with it (:class:`~occ.haptics.fixture_defs.PatientMapping`),
    so nothing is calibrated by hand;
``state``
    the slave's state (``RUNNING``, ``STOPPED``, ...);
``force_n``
    (a slave with a force source) the force on its instrument, ``fx,fy,fz`` in N, patient
    frame: what the master displays (bilateral teleoperation, issue 27);
``torque_nm``
    (a slave whose force comes from a 6-axis sensor) the torque about the sensor's origin,
    ``tx,ty,tz`` in N m, patient frame (issue 37): displayed by a master with rotational axes,
    recorded by the others. Absent otherwise; a reader that does not know it ignores it.
``energy_j``
    (with ``force_n``) the energy that has flowed into the channel at the slave's port since it
    started (J at the instrument, never decreasing): the master's port controller gives the hand
    no more than this (occ/haptics/passivity.py, issue 37).

**One message, not a pair.** The slave's contact force rides in the same message (metadata
``force_n``), not in a SENSOR beside a POSITION: one datagram is one sample with one
sequence number, one timestamp and one HMAC tag, so pose and force can never be paired wrongly,
half-lost or half-authenticated, and the loss rules below cover both. Metadata is text, a few
microseconds to format and parse at 500 Hz.

:class:`ReturnLink` is the master's view of one such stream, judged by the slave's own
:class:`~occ.core.safety.LossMonitor` (its existing API: sequence numbers, lateness, loss, a dead
peer). Its :attr:`ReturnLink.status`:

``none``   no tip yet (the slave not started, or no return channel configured);
``fresh``  a tip within the deadline (3 periods + a quarter: 6.5 ms at 500 Hz);
``stale``  late (overdue past the deadline, not yet lost): the last tip is kept and shown,
           marked stale; the controller fades the fixture force it last computed to zero
           within ``tip_fade_ms`` and computes none from the stale pose;
``lost``   three or more consecutive sequence numbers missing, or silence past the grace
           (100 ms: a dead slave): the fixture force is zero at once and the operators get an
           ALERT; the next good sample re-arms it (a STATUS ``STREAM`` says so).

The slave's force (``force_n``) is not dropped with the link: late or lost, the master holds
the last one and fades it out within ``feedback_fade_ms``, its energy accounted by the
passivity controller all along (a force dropped to zero and snapped back gave the hand energy
it never put in: issue 37).

A sample whose content is refused (a tip that is not a point, a malformed ``map`` or
``force_n``: counted in ``bad``) still arrived, so the monitor accounts for its sequence number
(never a loss), but its tip is not used: it is not a fresh tip either. A slave that keeps
sending only such samples is late, then lost, by the same deadline and grace as a silent one
(``stale`` after 6.5 ms without a usable tip: the force fades; ``lost`` past the grace: zero
and an ALERT, once), never a fresh link holding the last good force on the hand.

Loop thread only; O(1) per sample and per tick.
"""

from __future__ import annotations

import math
from typing import Any

from occ.core.safety import LossEvent, LossMonitor, Verdict
from occ.haptics.fixture_defs import DefinitionError, Vec3, parse_linear
from occ.haptics.passivity import parse_energy
from occ.samples import PoseSample

__all__ = ["ReturnLink"]


def _three(text: str) -> Vec3 | None:
    """``"x,y,z"``: three finite numbers, else None."""
    try:
        x, y, z = (float(v) for v in text.split(","))
    except ValueError:
        return None
    return (x, y, z) if math.isfinite(x) and math.isfinite(y) and math.isfinite(z) else None


class ReturnLink:
    """One slave's tip stream as the master sees it (see the module docstring)."""

    def __init__(
        self,
        interface: str,
        *,
        period_s: float = 0.002,
        max_consecutive: int = 2,
        grace_s: float = 0.1,
    ) -> None:
        self.interface = interface
        self.monitor = LossMonitor(period_s, max_consecutive, grace_s=grace_s)
        #: the last accepted tip, patient frame (mm), and its orientation (x, y, z, w)
        self.tip: Vec3 | None = None
        self.quaternion: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
        #: loop time when the last tip was accepted
        self.t_tip = math.nan
        #: loop time of the last usable tip, or of arm(): the deadline and the grace of a
        #: stream whose samples arrive but are refused for their content run from it
        self._t_usable = math.nan
        #: samples arrive (the monitor is content) but none usable past the deadline
        self.unusable = False
        self._bad_run = 0  # samples refused for their content since the last usable tip
        #: a tip arrived that the fixtures have not used yet
        self.new = False
        self.following = False
        self.slave_state = ""
        self.seq: int | None = None
        #: the force on the slave's instrument (N, patient frame) with the last tip; None
        #: while it sends none
        self.force: Vec3 | None = None
        #: the torque with it (N m, patient frame, about the slave's sensor), None: none sent
        self.torque: Vec3 | None = None
        #: the slave's port energy in (J at its instrument, cumulative:
        #: occ/haptics/passivity.py) with the last tip; None while it sends none
        self.energy: float | None = None
        #: the slave's map (handle mm -> patient mm), parsed; None until it sends one
        self.linear: tuple[tuple[float, float, float], ...] | None = None
        self._map_text = ""
        self.lost = False
        self.lost_cause = ""
        self.samples = 0
        self.refused = 0
        self.bad_metadata = 0
        self.losses = 0
        self.recoveries = 0
        self.last_error = ""

    # ------------------------------------------------------------------ samples
    def on_sample(self, sample: PoseSample, now: float, rx_wall: float) -> bool:
        """Judge one ``SlaveTip`` sample; True when it was accepted (its tip is the tool)."""
        mon = self.monitor
        if mon.tripped:
            # lost before: the stream is back. Re-armed from this sample on (the sequence
            # numbers start over: the gap was the loss already told)
            mon.reset(now)
        seq = sample.seq
        ts = sample.t_sample if sample.t_sample > 0.0 else None
        verdict = mon.on_packet(seq, ts, now, rx_wall)
        if verdict is not Verdict.ACCEPT:
            self.refused += 1
            return False
        if sample.kind == "POSITION":
            self.quaternion = sample.quaternion
        tip = sample.position_mm
        if not all(math.isfinite(v) for v in tip):
            self.bad_metadata += 1
            self._bad_run += 1
            self.last_error = f"seq {seq}: tip {tip} is not a point"
            return False
        meta = sample.meta
        text = meta.get("map", "")
        if text and text != self._map_text:
            try:
                self.linear = parse_linear(text)
            except DefinitionError as err:
                self.bad_metadata += 1
                self._bad_run += 1
                self.last_error = f"seq {seq}: {err}"
                return False
            self._map_text = text
        force_text = meta.get("force_n")
        force: Vec3 | None = None
        if force_text is not None:
            parts = force_text.split(",")
            try:
                fx, fy, fz = (float(v) for v in parts)
            except ValueError:
                fx = fy = fz = math.nan
            if not (math.isfinite(fx) and math.isfinite(fy) and math.isfinite(fz)):
                self.bad_metadata += 1
                self._bad_run += 1
                self.last_error = f"seq {seq}: force_n {force_text[:40]!r} is not 3 numbers"
                return False
            force = (fx, fy, fz)
        torque_text = meta.get("torque_nm")
        torque: Vec3 | None = None
        if torque_text is not None:
            torque = _three(torque_text)
            if torque is None:
                self.bad_metadata += 1
                self._bad_run += 1
                self.last_error = f"seq {seq}: torque_nm {torque_text[:40]!r} is not 3 numbers"
                return False
        energy_text = meta.get("energy_j")
        energy: float | None = None
        if energy_text is not None:
            energy = parse_energy(energy_text)
            if energy is None:
                self.bad_metadata += 1
                self._bad_run += 1
                self.last_error = f"seq {seq}: energy_j {energy_text[:40]!r} is not an energy"
                return False
        self.force = force
        self.torque = torque
        self.energy = energy
        self.following = meta.get("following", "1") == "1"
        self.slave_state = meta.get("state", "")
        self.tip = tip
        self.t_tip = self._t_usable = now
        self.unusable = False
        self._bad_run = 0
        self.seq = seq
        self.new = True
        self.samples += 1
        if self.lost and not mon.tripped:
            self.lost = False
            self.recoveries += 1
        return True

    # ------------------------------------------------------------------ every tick
    def check(self, now: float) -> LossEvent | None:
        """The monitor's event this tick (hold, resume, latch, refused), if any, or the
        link's own latch when samples come but none usable past the grace; a latch marks the
        link lost (told once: lost already, a latch is not told again)."""
        mon = self.monitor
        event = mon.check(now)
        if event is not None and event.kind == "latch":
            if self.lost:
                return None  # lost already, told once: the same outage until a usable tip
            self.lost = True
            self.losses += 1
            self.lost_cause = event.cause
        elif not (self.lost or mon.holding):
            # samples may come while none is usable: late and lost by the same rules
            idle = now - self._t_usable  # NaN before any usable tip or arm(): never
            if idle > mon.deadline_s:
                if idle > mon.grace_s:
                    cause = (
                        f"no usable tip for {idle * 1e3:.2f} ms (limit "
                        f"{mon.grace_s * 1e3:.1f} ms): {self._bad_run} samples refused, the last: "
                        f"{self.last_error}"
                    )
                    self.lost = True
                    self.unusable = False
                    self.losses += 1
                    self.lost_cause = cause
                    run = int((idle - mon.tolerance_s) / mon.period_s)
                    event = LossEvent("latch", cause, "content", run, now, idle)
                else:
                    self.unusable = True
        return event

    def arm(self, now: float) -> None:
        """Start the deadline at ``now`` (the master enters RUNNING): a slave that never
        sends is then caught by the grace, as a dead one is."""
        self.monitor.reset(now)
        self.lost = False
        self.unusable = False
        self._t_usable = now

    @property
    def status(self) -> str:
        """``none``, ``fresh``, ``stale`` or ``lost`` (see the module docstring)."""
        if self.lost or self.monitor.tripped:
            return "lost"
        if self.tip is None:
            return "none"
        return "stale" if self.monitor.holding or self.unusable else "fresh"

    def stats(self, now: float) -> dict[str, Any]:
        age = now - self.t_tip if self.tip is not None else None
        status = self.status
        if status == "fresh" and age is not None and age > self.monitor.deadline_s:
            status = "stale"  # the monitor is checked only while RUNNING
        c = self.monitor.counters()
        return {
            "interface": self.interface,
            "status": status,
            "age_ms": None if age is None else round(age * 1e3, 1),
            "tip_mm": None if self.tip is None else [round(v, 3) for v in self.tip],
            "force_n": None if self.force is None else [round(v, 4) for v in self.force],
            "torque_nm": None if self.torque is None else [round(v, 5) for v in self.torque],
            "energy_mj": None if self.energy is None else round(self.energy * 1e3, 4),
            "following": self.following,
            "slave_state": self.slave_state,
            "seq": self.seq,
            "map": None if self.linear is None else [list(r) for r in self.linear],
            "samples": self.samples,
            "refused": self.refused,
            "bad": self.bad_metadata,
            "last_error": self.last_error,
            "late": c["holds"],
            "lost_total": c["lost_total"],
            "losses": self.losses,
            "recoveries": self.recoveries,
            "lost_cause": self.lost_cause,
        }
