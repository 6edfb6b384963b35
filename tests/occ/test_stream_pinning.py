"""The slave's master stream over real UDP: its first sender owns it, and from then on the
kernel lets no other sender's datagram reach the socket (a flood cannot crowd the master out);
an operator's Reset releases it."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from pathlib import Path

import pytest

import igtl
from occ.core.robot import Robot
from occ_testkit.testing import loopback_robot

ROOT = Path(__file__).resolve().parents[2]


def _slave() -> Robot:
    return loopback_robot(ROOT / "configs" / "slave.yaml")


def _position(seq: int) -> bytes:
    return igtl.PositionMessage(
        (0.0, 50.0, 270.0),
        (0.0, 0.0, 0.0, 1.0),
        24,
        device_name="Master",
        header_version=2,
        message_id=seq,
        metadata={"run": "1", "clutch": "0"},
    ).pack()


def _until(robot: Robot, cond: Callable[[], bool], timeout: float = 5.0) -> bool:
    end = time.monotonic() + timeout
    k = 0
    while time.monotonic() < end:
        k += 1
        robot.tick(robot.clock.now(), k)
        robot.clock.advance(0.001)  # type: ignore[attr-defined]
        if cond():
            return True
        time.sleep(0.001)
    return cond()


@pytest.mark.req("SR-OWN-1")
def test_first_sender_owns_the_socket_until_reset() -> None:
    slave = _slave()
    master = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    master.bind(("127.0.0.1", 0))
    intruder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    intruder.bind(("127.0.0.1", 0))
    iface = slave.interfaces["master"]
    dest = iface.address
    try:
        master.sendto(_position(1), dest)
        assert _until(slave, lambda: iface.stream_owner == master.getsockname())
        assert iface.transport.source == master.getsockname()  # type: ignore[union-attr]
        for seq in range(2, 200):
            intruder.sendto(_position(seq), dest)  # the kernel drops these
        master.sendto(_position(2), dest)
        q = iface.streams["POSITION"]
        assert _until(slave, lambda: q.received == 2)
        assert iface.counters.received == 2 and iface.counters.foreign == 0
        # an operator's Reset: the next sender owns the stream (a restarted master)
        slave.interfaces.interfaces["master"].release_stream()
        intruder.sendto(_position(1), dest)
        assert _until(slave, lambda: iface.stream_owner == intruder.getsockname())
    finally:
        master.close()
        intruder.close()
        slave.shutdown()
