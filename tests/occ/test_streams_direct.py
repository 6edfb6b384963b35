"""A datagram the loop polls goes straight to the tick: routed by its interface (every check
of the I/O thread's path), judged and followed in the tick that read it, never through the
stream queue; a routing error is counted and the tick goes on, a controller's error reaches
the tick (FAULT naming it), as for a queued sample."""

from __future__ import annotations

import socket
import time
from pathlib import Path
from typing import Any

import pytest

import igtl
from occ.clock import SimClock
from occ.core.robot import Robot
from occ.core.safety import RobotState
from occ_testkit.testing import loopback_robot

ROOT = Path(__file__).resolve().parents[2]


def _slave() -> Robot:
    return loopback_robot(ROOT / "configs" / "slave.yaml", run=True)


def _position(seq: int, clock: SimClock) -> bytes:
    return igtl.PositionMessage(
        (0.0, 50.0, 270.0), (0.0, 0.0, 0.0, 1.0), 24, device_name="Master", header_version=2,
        message_id=seq, timestamp=clock.wall_time(), metadata={"run": "1", "clutch": "0"},
    ).pack()  # fmt: skip


def _readable(robot: Robot) -> None:
    ready = robot.interfaces["master"].transport._ready  # type: ignore[union-attr]
    end = time.monotonic() + 2.0
    while not ready(0) and time.monotonic() < end:
        time.sleep(0.0005)


class _CountingLock:
    """Stands in for a stream queue's lock: how often anyone took it (the direct path never
    does)."""

    def __init__(self) -> None:
        self.taken = 0

    def __enter__(self) -> None:
        self.taken += 1

    def __exit__(self, *exc: object) -> None:
        return None


@pytest.fixture
def slave() -> Any:
    robot = _slave()
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.bind(("127.0.0.1", 0))
    yield robot, tx
    tx.close()
    robot.shutdown()


def _send_and_tick(robot: Robot, tx: socket.socket, seq: int, k: int) -> None:
    clock = robot.clock
    assert isinstance(clock, SimClock)
    address = robot.interfaces["master"].address
    assert address is not None
    tx.sendto(_position(seq, clock), address)
    _readable(robot)
    clock.set(k * 0.001)
    robot.tick(clock.now(), k)


def test_a_polled_position_is_followed_in_the_tick_that_read_it_without_the_queue(
    slave: Any,
) -> None:
    robot, tx = slave
    iface = robot.interfaces["master"]
    q = iface.streams["POSITION"]
    lock = q._lock = _CountingLock()
    ctl = robot.controller.controllers[0]
    for seq in range(1, 11):
        _send_and_tick(robot, tx, seq, 2 * seq)
        # judged and followed in this very tick
        assert ctl.samples == seq and ctl.last_seq == seq
        assert robot.streams.monitor.received == seq
    assert lock.taken == 0 and len(q) == 0  # never queued, the queue's lock never taken
    assert q.received == 10 and iface.counters.received == 10  # counted as before
    assert robot.state is RobotState.RUNNING


def test_a_polled_datagram_still_passes_every_check_of_its_interface(slave: Any) -> None:
    """Ownership: the first sender owns the stream; another sender's datagram (the kernel
    filter off, so it reaches the socket) is refused and counted, never judged or followed."""
    robot, tx = slave
    iface = robot.interfaces["master"]
    iface.cfg = iface.cfg.model_copy(update={"kernel_filter": False})
    robot.interfaces["master"].transport.pin_source(None)
    _send_and_tick(robot, tx, 1, 2)
    assert iface.stream_owner == tx.getsockname()
    intruder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        intruder.sendto(_position(2, robot.clock), ("127.0.0.1", iface.address[1]))
        _readable(robot)
        robot.clock.set(0.003)
        robot.tick(0.003, 3)
    finally:
        intruder.close()
    assert iface.counters.foreign == 1
    assert robot.streams.monitor.received == 1  # the intruder's sample was never judged
    assert robot.controller.controllers[0].samples == 1


def test_a_routing_error_is_counted_and_the_tick_goes_on(
    slave: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    robot, tx = slave
    import occ.net.interfaces as interfaces_mod

    def broken(*args: Any) -> None:
        raise RuntimeError("routing bug")

    monkeypatch.setattr(interfaces_mod, "pose_sample", broken)
    _send_and_tick(robot, tx, 1, 2)
    assert robot.streams.route_errors == 1
    assert robot.state is RobotState.RUNNING
    monkeypatch.undo()
    _send_and_tick(robot, tx, 2, 4)
    assert robot.controller.controllers[0].samples == 1  # the next one is followed


def test_a_controller_error_on_a_polled_sample_faults_the_robot_naming_it(
    slave: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    robot, tx = slave
    ctl = robot.controller.controllers[0]

    def broken(sample: Any, now: float) -> None:
        raise RuntimeError("controller bug")

    monkeypatch.setattr(ctl, "on_sample", broken)
    _send_and_tick(robot, tx, 1, 2)
    assert robot.state is RobotState.FAULT
    assert "on_sample" in robot.last_alert and "controller bug" in robot.last_alert
    assert robot.streams.route_errors == 0
