"""Master mode: a ROS 2 pose topic becomes the master stream a slave daemon follows.

``occ-ros2 --master /occ/master=127.0.0.1:18946`` subscribes to ``/occ/master/servo_cp``
(geometry_msgs/PoseStamped, CRTK's Cartesian setpoint; metres) and sends what the
``teleop-master`` controller sends (occ/controllers/teleop/): POSITION, 24-byte variant
(position in mm + 3-element quaternion, w >= 0), header version 2, device ``Master``, the
message ID a sequence number (+1 per packet), metadata ``run`` and ``clutch``, at 500 Hz over
UDP, the latest pose each period.

Servo mode (``occ-ros2 --servo /occ/slave=127.0.0.1:18948``) is the same stream from a robot's
own namespace, device ``ServoCP``: CRTK ``servo_cp`` in the frame of ``measured_cp`` (the world
frame; a pose stamped in another frame is refused), to a slave whose controller takes it as an
absolute target (``teleop-slave`` with ``mapping: absolute``, configs/servo.yaml).

``run`` is ``1`` while poses keep coming (the latest younger than ``stale_s``, 0.1 s) and ``0``
otherwise, so a ROS 2 node that stops publishing makes the slave hold (a stopped master), not
jump when it comes back: the slave re-indexes when ``run`` returns to 1. ``clutch`` follows
``/occ/master/clutch`` (std_msgs/String: ``1``/``pressed`` or ``0``/``released``). The stream
itself never stops while the bridge runs, as the master daemon's does, so the slave can tell a
stopped master from a dead one; when the bridge exits, the slave's loss monitor sees a dead
master and stops.

The period is kept on absolute deadlines (sleep until the next one); a late period is sent late,
never skipped with a jump in the sequence numbers: for the slave, late is not lost.
"""

from __future__ import annotations

import logging
import math
import string
import threading
import time
from typing import Any

from cyclonedds.domain import DomainParticipant
from cyclonedds.sub import DataReader, InvalidSample
from cyclonedds.topic import Topic

import igtl
from igtl.auth import sign
from igtl.transport import UDPEndpoint

from . import msgs
from .bridge import QOS_DEFAULT, QOS_SENSOR, topic_name, typed_qos

log = logging.getLogger("occ_ros2.master")


#: what a host name or an IPv4/IPv6 address is made of (parse_master)
_HOST_CHARS = string.ascii_letters + string.digits + ".-_:"


def parse_master(text: str) -> tuple[str, str, int]:
    """``/NAMESPACE=HOST:PORT`` -> (namespace, host, port). The host is a name or an IPv4 or
    IPv6 address: letters, digits and ``.-_:`` (anything else is refused here, not later by
    the resolver)."""
    ns, sep, where = text.partition("=")
    host, _, port = where.rpartition(":")
    parts = ns.strip("/").split("/")
    if (
        not sep
        or not host
        or host.strip(_HOST_CHARS)
        or not port.isdigit()
        or not all(p.isidentifier() for p in parts)
    ):
        raise ValueError(f"expected /NAMESPACE=HOST:PORT, got {text!r}")
    return "/" + ns.strip("/"), host, int(port)


class MasterStream:
    """One ROS 2 namespace's ``servo_cp`` as a 500 Hz POSITION stream (module docstring)."""

    def __init__(
        self,
        participant: DomainParticipant,
        ns: str,
        remote: tuple[str, int],
        *,
        rate_hz: float = 500.0,
        device: str = "Master",
        stale_s: float = 0.1,
        first_seq: int = 0,
        auth_key: bytes | None = None,
        frames: tuple[str, ...] | None = None,
    ) -> None:
        self.ns = ns
        #: the ``header.frame_id`` values taken (None: any); a pose in another frame is
        #: refused, counted and logged (servo mode: the world frame of ``measured_cp``)
        self.frames = frames
        self.refused_frames = 0
        #: the slave's shared key (its `auth_key_file`): every POSITION carries the HMAC tag
        self.auth_key = auth_key
        self.remote = remote
        self.period = 1.0 / rate_hz
        self.device = device
        self.stale_s = stale_s
        self.seq = first_seq & 0xFFFFFFFF
        dp = participant
        # best effort reads from reliable and best-effort publishers alike
        self._poses: DataReader[Any] = DataReader(
            dp,
            Topic(dp, topic_name(ns, "servo_cp"), msgs.PoseStamped),
            typed_qos(QOS_SENSOR, msgs.PoseStamped),
        )
        self._clutch: DataReader[Any] = DataReader(
            dp,
            Topic(dp, topic_name(ns, "clutch"), msgs.String),
            typed_qos(QOS_DEFAULT, msgs.String),
        )
        self.udp = UDPEndpoint("127.0.0.1" if remote[0] == "127.0.0.1" else "0.0.0.0", 0,
                               remote=remote, name=f"occ-ros2-master-{ns}")  # fmt: skip
        self.pose: tuple[tuple[float, float, float], tuple[float, float, float, float]] | None
        self.pose = None
        self.pose_t = -math.inf
        self.clutch = False
        self.sent = 0
        self.late = 0
        self.poses = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> MasterStream:
        self.udp.start()
        self._thread = threading.Thread(target=self._run, name="occ-ros2-master", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.udp.stop()

    def _read_topics(self, now: float) -> None:
        for s in self._poses.take(N=64):
            if isinstance(s, InvalidSample):
                continue  # a publisher gone (its node exited): no pose
            frames = self.frames
            if frames is not None and s.header.frame_id not in frames:
                if not self.refused_frames:
                    log.warning(
                        "%s/servo_cp: a pose in frame %r refused (takes %s)",
                        self.ns, s.header.frame_id, " or ".join(repr(f) for f in frames),
                    )  # fmt: skip
                self.refused_frames += 1
                continue
            p, q = s.pose.position, s.pose.orientation
            sign = -1.0 if q.w < 0.0 else 1.0  # the 24-byte variant drops w: send w >= 0
            self.pose = (
                (p.x * 1e3, p.y * 1e3, p.z * 1e3),
                (sign * q.x, sign * q.y, sign * q.z, sign * q.w),
            )
            self.pose_t = now
            self.poses += 1
        for c in self._clutch.take(N=16):
            if isinstance(c, InvalidSample):
                continue  # as above: the clutch stays as it was last set
            self.clutch = c.data.strip().lower() in ("1", "true", "on", "pressed")

    def _run(self) -> None:
        deadline = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            self._read_topics(now)
            self._send(now)
            deadline += self.period
            delay = deadline - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            elif delay < -self.period:
                # more than a period behind (the machine was busy): start counting again from
                # now rather than sending a burst; the numbers stay consecutive
                self.late += 1
                deadline = time.monotonic()

    def _send(self, now: float) -> None:
        if self.pose is None:
            return  # nothing to follow yet: the slave, armed by the first packet, holds still
        running = now - self.pose_t <= self.stale_s
        self.seq = (self.seq + 1) & 0xFFFFFFFF
        position, quat = self.pose
        msg = igtl.PositionMessage(
            position,
            quat,
            24,
            device_name=self.device,
            timestamp=time.time(),
            header_version=2,
            message_id=self.seq,
            metadata={"run": "1" if running else "0", "clutch": "1" if self.clutch else "0"},
        )
        out: igtl.Message = msg if self.auth_key is None else sign(msg, self.auth_key)
        self.sent += self.udp.send(out)

    def stats(self) -> dict[str, Any]:
        return {
            "remote": f"{self.remote[0]}:{self.remote[1]}",
            "poses": self.poses,
            "sent": self.sent,
            "seq": self.seq,
            "late_periods": self.late,
            "clutch": self.clutch,
            "refused_frames": self.refused_frames,
        }
