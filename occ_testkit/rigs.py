"""The two robots the simulated-time tests drive most: a slave with its command stream
(:class:`SlaveRig`) and a master with the far side of its link (:class:`SimMaster`), each on
in-process channels (:class:`~occ_testkit.testing.SimRobot`) with an operator beside it.

Both default to the checkout's shipped configs (:data:`occ_testkit.CONFIGS`); a test that needs
another robot passes its config (a path, a :class:`~occ.config.DaemonConfig` or a mapping) and
the controller's ``params``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from igtl.messages.base import Message
from igtl.messages.status import StatusMessage
from occ.config import DaemonConfig
from occ.core.safety import RobotState
from occ.recording.record import Recorder

from . import CONFIGS
from .testing import SimPeer, SimRobot, SlaveTipFeed

__all__ = ["SimMaster", "SlaveRig"]

Config = DaemonConfig | str | os.PathLike[str] | Mapping[str, Any]


def _text(msg: Message) -> str:
    assert isinstance(msg, StatusMessage)
    return msg.status_message


def _name(msg: Message) -> str:
    assert isinstance(msg, StatusMessage)
    return msg.error_name


class SlaveRig:
    """A slave, the source of its command stream and an operator.

    The source is a peer on the ``stream`` interface (``master`` in the shipped slave, ``servo``
    in configs/servo.yaml) that sends :attr:`target` (mm) every other tick (500 Hz against the
    1 kHz loop) with the flags :attr:`run` and :attr:`clutch`, the device name ``device`` and,
    when :attr:`timestamped`, the simulated wall time in the header; :attr:`sending` False
    silences it. ``target`` defaults to where the slave's tip is (the patient frame).
    """

    def __init__(
        self,
        config: Config = CONFIGS / "slave.yaml",
        *,
        params: Mapping[str, Any] | None = None,
        stream: str = "master",
        device: str = "Master",
        target: Sequence[float] | None = None,
    ) -> None:
        self.sim = SimRobot(config, params=params or None)
        self.robot = self.sim.robot
        self.ctl: Any = self.robot.controller
        self.source = self.sim.peer(stream, address=("127.0.0.1", 40000))
        self.operator = self.sim.peer("operator", address=("127.0.0.1", 40001))
        self.device = device
        self.seq = 0
        self.target: list[float] = (
            [float(v) for v in target] if target is not None else self.world_tip_mm().tolist()
        )
        self.run = True
        self.clutch = False
        self.sending = True
        self.timestamped = False

    def tip_mm(self) -> npt.NDArray[np.float64]:
        """The tip of the setpoint the slave writes, in its base frame, mm."""
        return np.array(self.robot.frame.tip_position(self.robot.data.setpoint)) * 1e3

    def world_tip_mm(self) -> npt.NDArray[np.float64]:
        """The world (patient) position of the setpoint the slave writes, mm."""
        tip = np.append(np.array(self.robot.frame.tip_position(self.robot.data.setpoint)), 1.0)
        return np.asarray(self.robot.data.base @ tip)[:3] * 1e3

    def send(self, **kw: Any) -> None:
        """One sample of :attr:`target` with the next sequence number (``kw``: the fields of
        :meth:`SimPeer.send_position` to set otherwise)."""
        self.seq += 1
        kw.setdefault("device", self.device)
        if self.timestamped:
            kw.setdefault("timestamp", self.sim.clock.wall_time())
        self.source.send_position(self.target, seq=self.seq, run=self.run, clutch=self.clutch, **kw)

    def step(self, ms: int) -> list[list[float]]:
        """``ms`` ticks, a sample before every other one; the setpoints written, one a tick."""
        out = []
        for _ in range(ms):
            if self.sending and self.sim.k % 2 == 0:
                self.send()
            self.sim.tick()
            out.append(list(self.robot.data.setpoint))
        return out

    def command(self, name: str) -> None:
        """The operator's command ``name``, answered with SUCCESS."""
        reply = self.sim.command(self.operator, name)
        assert reply.metadata["Status"] == "SUCCESS", name

    def running(self) -> None:
        """Enable, Run, and 20 ms of the stream: the slave follows."""
        self.command("Enable")
        self.command("Run")
        self.step(20)
        assert self.robot.state is RobotState.RUNNING

    def alerts(self) -> list[str]:
        """The text of every STATUS the operator received."""
        return [_text(m) for m in self.operator.messages("STATUS")]

    def close(self) -> None:
        self.sim.close()

    def __enter__(self) -> SlaveRig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class SimMaster:
    """A master and an operator (on ``127.0.0.1:41000``), and its slave link's far end.

    Without ``feed`` that end is a peer on ``link`` whose received messages are :attr:`sent`
    (the stream as the slave gets it), and :meth:`step` ticks the master. With ``feed`` it is a
    :class:`SlaveTipFeed` (a slave that follows the handle at once, sending its tip before
    every tick: the return channel the master's fixtures and force display read), started
    after the master's first tick, and :meth:`step` ticks through it.
    """

    def __init__(
        self,
        config: Config | None = None,
        *,
        params: Mapping[str, Any] | None = None,
        recorder: Recorder | None = None,
        link: str = "slave",
        feed: bool = False,
    ) -> None:
        self.sim = SimRobot(
            config if config is not None else CONFIGS / "master.yaml",
            params=params or None,
            recorder=recorder,
        )
        self.robot = self.sim.robot
        self.ctl: Any = self.robot.controller.controllers[0]
        self._link: SimPeer | None = None if feed else self.sim.peer(link)
        self.op = self.sim.peer("operator", address=("127.0.0.1", 41000))
        #: everything the robot sent to the operator (replies, alerts)
        self.replies = self.op.received
        self._feed: SlaveTipFeed | None = None
        if feed:
            self.sim.step(1)  # the master's first output: its slave link is known
            self._feed = SlaveTipFeed(self.sim, link)

    @property
    def feed(self) -> SlaveTipFeed:
        assert self._feed is not None, "a SimMaster made with feed=True has a feed"
        return self._feed

    @property
    def sent(self) -> list[Message]:
        """What the master sent on its slave link (without ``feed``)."""
        assert self._link is not None, "a SimMaster with a feed has no peer of its own there"
        return self._link.received

    @property
    def k(self) -> int:
        return self.sim.k

    def step(self, n: int = 1) -> None:
        """``n`` ticks (each after a tip sample, with ``feed``)."""
        if self._feed is not None:
            self._feed.step(n)
        else:
            self.sim.step(n)

    def command(self, name: str, text: str = "") -> Message:
        """The operator's command ``name`` (``text``: its XML), one :meth:`step`, the reply."""
        cid = self.op.send_command(name, text)
        self.step(1)
        reply = self.op.reply_to(cid)
        assert reply is not None, f"no RTS_COMMAND for {name} (command ID {cid})"
        return reply

    def run(self, settle: int = 30) -> None:
        """Enable and Run (each answered with SUCCESS), then ``settle`` ticks."""
        for name in ("Enable", "Run"):
            assert self.command(name).metadata["Status"] == "SUCCESS", name
        assert self.robot.state is RobotState.RUNNING
        self.step(settle)

    def alerts(self, name: str | None = None) -> list[str]:
        """The text of the STATUS messages the operator received (``name``: of that error name
        only, e.g. ``ALERT``)."""
        return [_text(m) for m in self.op.messages("STATUS") if name is None or _name(m) == name]

    def close(self) -> None:
        self.sim.close()

    def __enter__(self) -> SimMaster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
