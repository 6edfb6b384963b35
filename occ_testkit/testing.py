"""Test a robot without a network: a :class:`~occ.core.robot.Robot` in simulated time whose
interfaces are in-process channels (:class:`igtl.transport.InprocTransport`), and peers that
talk to it.

The robot is built from its own configuration file (or a :class:`~occ.config.DaemonConfig`, or a
mapping as the YAML file would hold it) with every interface turned into ``transport: inproc``
on a channel of its own; everything else (routing, queues, loss monitor, replies, outputs) is
the daemon's code, unchanged. A :class:`SimPeer` joins one interface's channel as a client
would: what it sends goes through the real codec into the interface's routing, and it receives
what the robot sends *to it* (replies go to the peer who asked; broadcasts and outputs to every
peer of that interface). Delivery is synchronous, so the whole run is deterministic: the loop is
stepped tick by tick on a :class:`~occ.clock.SimClock` (tick ``k`` runs at ``k / rate_hz``)::

    from occ_testkit.testing import SimRobot

    with SimRobot("configs/slave.yaml") as sim:
        master = sim.peer("master", address=("127.0.0.1", 40000))
        operator = sim.peer("operator")
        slicer = sim.peer("slicer")
        assert sim.command(operator, "Enable").metadata["Status"] == "SUCCESS"
        sim.command(operator, "Run")
        for seq in range(1, 101):
            master.send_position((0.0, 50.0, 270.0), seq=seq)
            sim.step(2)  # 500 Hz against a 1 kHz loop
        tips = slicer.messages("TRANSFORM", "Tip")

Tests use it (``tests/occ``; tests/occ/test_testing.py runs this example), and so does
``tools/soak.py sim``.
"""

from __future__ import annotations

import atexit
import itertools
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import igtl
from igtl.messages.base import Message
from igtl.transport import InprocTransport, Peer
from occ.clock import SimClock
from occ.config import DaemonConfig
from occ.core.loader import load_config
from occ.core.robot import Robot, build_robot

from . import CONFIGS

__all__ = [
    "CONFIGS",
    "SimPair",
    "SimPeer",
    "SimRobot",
    "SlaveTipFeed",
    "inproc_config",
    "loopback_robot",
    "wait_until",
]

_instances = itertools.count(1)


def inproc_config(config: DaemonConfig, prefix: str | None = None) -> DaemonConfig:
    """``config`` with every network interface on an in-process channel named
    ``PREFIX-INTERFACE`` (``prefix`` default: unique in the process). Interfaces already
    ``inproc`` keep their channel; host and port stay as the robot's address on the channel."""
    prefix = prefix or f"sim{next(_instances)}-{config.robot.name}"
    interfaces = tuple(
        itf
        if itf.transport == "inproc"
        else itf.model_copy(update={"transport": "inproc", "channel": f"{prefix}-{itf.name}"})
        for itf in config.interfaces
    )
    return config.model_copy(update={"interfaces": interfaces})


def _as_config(config: DaemonConfig | str | os.PathLike[str] | Mapping[str, Any]) -> DaemonConfig:
    if isinstance(config, DaemonConfig):
        cfg = config
    elif isinstance(config, Mapping):
        cfg = DaemonConfig.model_validate(dict(config), context={"base_dir": Path.cwd()})
    else:
        cfg = load_config(config)
    return scratch_black_box(cfg)


_scratch: list[Path] = []


def scratch_black_box(config: DaemonConfig) -> DaemonConfig:
    """``config`` with its black box dumped into a scratch directory of this process (removed
    at exit) unless its ``black_box.dir`` was set: a simulated robot that faults in a test
    must not write into the source tree beside its config."""
    bb = config.black_box
    if "dir" in bb.model_fields_set:
        return config
    if not _scratch:
        _scratch.append(Path(tempfile.mkdtemp(prefix="occ-blackbox-")))
        atexit.register(shutil.rmtree, _scratch[0], True)
    return config.model_copy(update={"black_box": bb.model_copy(update={"dir": _scratch[0]})})


class _BytesEndpoint(InprocTransport):
    """An in-process client that hands over what it receives as wire bytes, undecoded (what a
    packet capture or a forwarding proxy sees): :class:`SimPeer` with ``on_bytes``."""

    def __init__(self, channel: str, *, on_bytes: Callable[[bytes], None], **kw: Any) -> None:
        super().__init__(channel, **kw)
        self._on_bytes = on_bytes

    def _receive(self, sender: InprocTransport, data: bytes) -> None:
        link = self._by_remote.get(id(sender))
        if link is None:  # we left between its send and this delivery
            return
        link.peer.received += 1
        self._on_bytes(data if type(data) is bytes else bytes(data))


class SimPeer:
    """A client on an in-process channel: sends like a TCP/UDP client, records what it gets.

    ``received`` holds every decoded message in arrival order, unless ``on_message`` is given
    (called with each message instead: a long soak keeps what it needs, not hours of outputs),
    or ``on_bytes`` (called with each message's wire bytes, not decoded: a forwarding proxy's
    view, as tools/stability.py uses it; ``received`` then stays empty).
    ``header_version`` is the version
    the peer announces (2: a modern Slicer/PLUS, answered with metadata and message IDs; 1: an
    old client, answered in version 1). ``address`` is how the robot sees it (stream ownership).
    """

    def __init__(
        self,
        channel: str,
        *,
        address: tuple[str, int] | None = None,
        header_version: int = 2,
        on_message: Callable[[Message], None] | None = None,
        on_bytes: Callable[[bytes], None] | None = None,
        name: str = "sim-peer",
    ) -> None:
        if on_message is not None and on_bytes is not None:
            raise ValueError("SimPeer: on_message or on_bytes, not both")
        self.received: list[Message] = []
        self._callback = on_message
        self._ids = itertools.count(100)
        kind: Any = InprocTransport
        extra: dict[str, Any] = {}
        if on_bytes is not None:
            kind, extra = _BytesEndpoint, {"on_bytes": on_bytes}
        self.transport = kind(
            channel,
            address=address,
            header_version=header_version,
            negotiate=False,  # a client sends each message in its own version
            listen=False,  # two clients of one daemon do not hear each other
            on_message=self._on_message,
            name=name,
            **extra,
        ).start()

    def _on_message(self, peer: Peer, msg: Message) -> None:
        if self._callback is not None:
            self._callback(msg)
        else:
            self.received.append(msg)

    @property
    def address(self) -> tuple[str, int]:
        return self.transport.address

    @property
    def connected(self) -> bool:
        return bool(self.transport.peers)

    def send(self, msg: Message | bytes) -> int:
        """Send ``msg`` (or raw bytes) to the robot; returns 1, or 0 when it is not there."""
        return self.transport.send(msg)

    def messages(self, type: str | None = None, device: str | None = None) -> list[Message]:
        """What this peer received, optionally only one message type (and device name)."""
        return [
            m
            for m in self.received
            if (type is None or m.message_type == type)
            and (device is None or m.device_name == device)
        ]

    def send_command(self, name: str, text: str = "", *, message_id: int = 0) -> int:
        """Send an OpenIGTLink v3 COMMAND (as Slicer does); returns its command ID."""
        cid = next(self._ids)
        self.send(
            igtl.CommandMessage(
                command_id=cid,
                command_name=name,
                command=text,
                device_name="command",
                header_version=2,
                message_id=message_id,
            )
        )
        return cid

    def reply_to(self, command_id: int) -> Message | None:
        """The RTS_COMMAND that answered ``command_id``, if it came."""
        for m in reversed(self.received):
            if m.message_type == "RTS_COMMAND" and getattr(m, "command_id", None) == command_id:
                return m
        return None

    def send_position(
        self,
        position_mm: Sequence[float],
        *,
        seq: int,
        run: bool = True,
        clutch: bool = False,
        timestamp: float = 0.0,
        device: str = "Master",
    ) -> int:
        """One sample of the master's stream, as the master daemon sends it (POSITION, 24-byte
        variant, v2, message ID = sequence number, ``run``/``clutch`` metadata)."""
        x, y, z = position_mm
        return self.send(
            igtl.PositionMessage(
                (float(x), float(y), float(z)),
                (0.0, 0.0, 0.0, 1.0),
                24,
                device_name=device,
                timestamp=timestamp,
                header_version=2,
                message_id=seq,
                metadata={"run": "1" if run else "0", "clutch": "1" if clutch else "0"},
            )
        )

    def send_tip(
        self,
        tip_mm: Sequence[float],
        *,
        seq: int,
        following: bool = True,
        linear: str = "0.1,0,0,0,0.1,0,0,0,0.1",
        state: str = "RUNNING",
        timestamp: float = 0.0,
        device: str = "SlaveTip",
        force_n: Sequence[float] | str | None = None,
        torque_nm: Sequence[float] | str | None = None,
    ) -> int:
        """One sample of a slave's return channel, as the slave daemon sends it (POSITION,
        v2, message ID = sequence number, metadata ``following``, ``map``, ``state``, and
        ``force_n`` and ``torque_nm`` when given (three numbers, or the text as is);
        occ/haptics/returnlink.py): the tip
        in the patient frame (mm)."""
        x, y, z = tip_mm
        meta = {"following": "1" if following else "0", "map": linear, "state": state}
        if force_n is not None:
            meta["force_n"] = (
                force_n if isinstance(force_n, str) else ",".join(f"{v:.6g}" for v in force_n)
            )
        if torque_nm is not None:
            meta["torque_nm"] = (
                torque_nm if isinstance(torque_nm, str) else ",".join(f"{v:.6g}" for v in torque_nm)
            )
        return self.send(
            igtl.PositionMessage(
                (float(x), float(y), float(z)),
                (0.0, 0.0, 0.0, 1.0),
                device_name=device,
                timestamp=timestamp,
                header_version=2,
                message_id=seq,
                metadata=meta,
            )
        )

    def close(self) -> None:
        self.transport.stop()


class SlaveTipFeed:
    """A master's slave, as far as its fixtures can tell: a peer on the master's slave link
    that sends, before every tick, the tip of a slave that follows the handle exactly and at
    once: ``tip = base_mm + scale * handle`` (patient mm; the map ``scale * I``). So a patient
    point ``P`` is the handle position ``(P - base_mm) / scale``, and tests can reason in
    either frame. ``following``, ``pause`` (no samples: a late or dead slave) and ``skip``
    (sequence numbers lost) play the return channel's failures."""

    def __init__(
        self,
        sim: SimRobot,
        interface: str = "slave",
        *,
        scale: float = 0.1,
        base_mm: Sequence[float] = (0.0, 0.0, 0.0),
        address: tuple[str, int] = ("127.0.0.1", 40000),
    ) -> None:
        self.sim = sim
        self.peer = sim.peer(interface, address=address)
        self.scale = scale
        self.base = tuple(float(v) for v in base_mm)
        self.seq = 0
        self.following = True
        self.paused = False
        #: the force on the slave's instrument sent with each tip (N, patient), None: none
        self.force: Sequence[float] | str | None = None
        #: the torque sent with it (N m, patient), None: none (a 3-axis force)
        self.torque: Sequence[float] | str | None = None
        self.linear = ",".join(f"{scale if i == j else 0.0:g}" for i in range(3) for j in range(3))

    def handle_mm(self) -> tuple[float, float, float]:
        r = self.sim.robot
        x, y, z = r.frame.tip_position(r.data.q)
        return (x * 1e3, y * 1e3, z * 1e3)

    def patient(self, handle_mm: Sequence[float]) -> tuple[float, float, float]:
        """Where this slave's tip is (patient mm) for the handle at ``handle_mm``."""
        s, b = self.scale, self.base
        return (b[0] + s * handle_mm[0], b[1] + s * handle_mm[1], b[2] + s * handle_mm[2])

    def tip(self) -> tuple[float, float, float]:
        return self.patient(self.handle_mm())

    def send(self) -> None:
        """One sample (none while ``paused``: a sender that stopped sends no numbers)."""
        if not self.paused:
            self.seq += 1
            self.peer.send_tip(
                self.tip(),
                seq=self.seq,
                following=self.following,
                linear=self.linear,
                force_n=self.force,
                torque_nm=self.torque,
            )

    def step(self, n: int = 1) -> None:
        """``n`` ticks of the master, each after a tip sample (1 kHz)."""
        for _ in range(n):
            self.send()
            self.sim.tick()

    def skip(self, n: int) -> None:
        """``n`` sequence numbers lost on the way."""
        self.seq += n


class SimRobot:
    """A robot in simulated time on in-process interfaces (see the module docstring).

    ``config``: a path, a :class:`DaemonConfig` or a mapping; ``params``: parameters of its
    (single) controller plugin to override. The robot is configured (READY) and activated
    (its interfaces on their channels) on construction; :meth:`close` shuts it down.
    """

    def __init__(
        self,
        config: DaemonConfig | str | os.PathLike[str] | Mapping[str, Any],
        *,
        params: Mapping[str, Any] | None = None,
        recorder: Any | None = None,
        clock: SimClock | None = None,
    ) -> None:
        cfg = _as_config(config)
        if params:
            cfg = cfg.with_params(**params)
        self.config = inproc_config(cfg)
        self.clock = clock if clock is not None else SimClock()
        self.robot: Robot = build_robot(self.config, clock=self.clock, recorder=recorder)
        self.period = 1.0 / self.config.robot.rate_hz
        #: index of the next tick (it runs at ``k * period``)
        self.k = 0
        self._peers: list[SimPeer] = []
        try:
            self.robot.configure()
            self.robot.activate()
        except BaseException:
            self.robot.shutdown()
            raise

    def channel(self, interface: str) -> str:
        """The in-process channel of the robot's interface ``interface``."""
        channel = self.config.interface(interface).channel
        assert channel is not None  # inproc_config gave every interface one
        return channel

    def peer(
        self,
        interface: str,
        *,
        address: tuple[str, int] | None = None,
        header_version: int = 2,
        on_message: Callable[[Message], None] | None = None,
        on_bytes: Callable[[bytes], None] | None = None,
    ) -> SimPeer:
        """A new client of the robot's interface ``interface`` (closed with the robot)."""
        p = SimPeer(
            self.channel(interface),
            address=address,
            header_version=header_version,
            on_message=on_message,
            on_bytes=on_bytes,
            name=f"sim-peer-{interface}",
        )
        self._peers.append(p)
        return p

    @property
    def now(self) -> float:
        """Simulated time of the next tick."""
        return self.k * self.period

    def tick(self) -> None:
        """Run one tick of the loop at ``now`` and advance to the next."""
        now = self.k * self.period
        self.clock.set(now)
        self.robot.tick(now, self.k)
        self.k += 1

    def step(self, n: int = 1) -> None:
        """Run ``n`` ticks."""
        for _ in range(n):
            self.tick()

    def command(self, peer: SimPeer, name: str, text: str = "", ticks: int = 1) -> Message:
        """``peer`` sends the COMMAND ``name`` (``text``: its XML), the loop runs ``ticks``
        ticks, and the RTS_COMMAND that answered it is returned (AssertionError when none
        came: a command the tick did not answer is a test failure, not a None to check). An
        Enable whose drives power up off the loop thread (occ/core/powerup.py) is waited for
        on the wall clock without ticking, then the tick that completes it runs."""
        cid = peer.send_command(name, text)
        self.step(ticks)
        while self.robot.effects.powering_up:  # drives powering up off the loop thread (an Enable)
            assert self.robot.effects.await_power_up(10.0), f"{name}: the power-up did not end"
            self.tick()  # it completes the transition and replies
        reply = peer.reply_to(cid)
        assert reply is not None, f"no RTS_COMMAND for {name} (command ID {cid})"
        return reply

    def run_for(self, seconds: float) -> None:
        """Run the ticks of the next ``seconds`` of simulated time."""
        self.step(round(seconds / self.period))

    def stall(self, n: int) -> None:
        """The loop does not tick for ``n`` periods (a stalled process): time moves on."""
        self.k += n

    def close(self) -> None:
        """Shut the robot down (its interfaces leave their channels) and close the peers."""
        self.robot.shutdown()
        for p in self._peers:
            p.close()

    def __enter__(self) -> SimRobot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


#: a drop rule: (direction ``"forward"`` or ``"return"``, the message, its 0-based index in that
#: direction) -> True to lose it
DropRule = Callable[[str, Message, int], bool]


class SimPair:
    """A master and a slave daemon on one :class:`SimClock`, the master's stream and the
    slave's return channel wired both ways, each way through a line that can delay (whole
    ticks) and lose messages: the OCC paper's protocol and a network's delay, in simulated time.

    Each tick: the return messages due are handed to the master, the master ticks, the forward
    messages due are handed to the slave, the slave ticks (a message sent in tick ``k`` with no
    delay arrives before the other side's tick ``k``, or ``k + 1`` for the return way).
    ``master_link``/``slave_link`` name the interfaces of the stream on each side (the shipped
    configs: ``slave`` on the master, ``master`` on the slave). The operators are peers on each
    side's ``operator`` interface; :meth:`start` enables and runs both.
    """

    def __init__(
        self,
        master: DaemonConfig | str | os.PathLike[str] | Mapping[str, Any] = CONFIGS / "master.yaml",
        slave: DaemonConfig | str | os.PathLike[str] | Mapping[str, Any] = CONFIGS / "slave.yaml",
        *,
        master_params: Mapping[str, Any] | None = None,
        slave_params: Mapping[str, Any] | None = None,
        delay_ms: float = 0.0,
        return_delay_ms: float | None = None,
        drop: DropRule | None = None,
        master_link: str = "slave",
        slave_link: str = "master",
    ) -> None:
        self.clock = SimClock()
        self.master = SimRobot(master, params=master_params, clock=self.clock)
        try:
            self.slave = SimRobot(slave, params=slave_params, clock=self.clock)
        except BaseException:
            self.master.close()
            raise
        period = self.master.period
        self._delay = round(delay_ms * 1e-3 / period)
        back = delay_ms if return_delay_ms is None else return_delay_ms
        self._return_delay = round(back * 1e-3 / period)
        self._drop = drop
        self.k = 0
        self._forward: list[tuple[int, Message]] = []
        self._return: list[tuple[int, Message]] = []
        self.counts = {"forward": 0, "return": 0, "forward_lost": 0, "return_lost": 0}
        self.m_link = self.master.peer(master_link, on_message=self._from_master)
        self.s_link = self.slave.peer(
            slave_link, address=("127.0.0.1", 40000), on_message=self._from_slave
        )
        self.m_op = self.master.peer("operator", address=("127.0.0.1", 41000))
        self.s_op = self.slave.peer("operator", address=("127.0.0.1", 41001))

    def _from_master(self, msg: Message) -> None:
        i = self.counts["forward"]
        self.counts["forward"] = i + 1
        if self._drop is not None and self._drop("forward", msg, i):
            self.counts["forward_lost"] += 1
            return
        self._forward.append((self.k + self._delay, msg))

    def _from_slave(self, msg: Message) -> None:
        i = self.counts["return"]
        self.counts["return"] = i + 1
        if self._drop is not None and self._drop("return", msg, i):
            self.counts["return_lost"] += 1
            return
        self._return.append((self.k + 1 + self._return_delay, msg))

    @staticmethod
    def _due(line: list[tuple[int, Message]], k: int) -> list[Message]:
        n = 0
        while n < len(line) and line[n][0] <= k:
            n += 1
        out = [m for _, m in line[:n]]
        del line[:n]
        return out

    def step(self, n: int = 1) -> None:
        """``n`` ticks of both (see the class docstring)."""
        for _ in range(n):
            for msg in self._due(self._return, self.k):
                self.m_link.send(msg)
            self.master.tick()
            self._slave_tick()

    def _slave_tick(self) -> None:
        """The forward messages due handed to the slave, its tick, the next tick number."""
        for msg in self._due(self._forward, self.k):
            self.s_link.send(msg)
        self.slave.tick()
        self.k += 1

    def run_for(self, seconds: float) -> None:
        self.step(round(seconds / self.master.period))

    def stall_master(self, n: int) -> None:
        """The master's loop does not tick for ``n`` periods (a starved or frozen master
        process) while the slave ticks alone: the master sends nothing and skips no sequence
        number, and its time moves on (its motion continues from where the clock is when it
        ticks again). The slave sees a late stream without a gap: it holds at the loss
        monitor's deadline and resumes by itself, with no loss, when the silence is shorter
        than its grace (100 ms in the shipped configs); the master's own drive heartbeat
        (50 ms there) bounds ``n`` as well. Messages already on the forward line arrive on
        time; the slave's return messages wait for the master's next tick."""
        self.master.stall(n)
        for _ in range(n):
            self._slave_tick()

    def start(self) -> None:
        """Enable and Run the slave, then the master (each answered with SUCCESS)."""
        for op, sim in ((self.s_op, self.slave), (self.m_op, self.master)):
            for name in ("Enable", "Run"):
                cid = op.send_command(name)
                self.step(1)
                reply = op.reply_to(cid)
                assert reply is not None and reply.metadata.get("Status") == "SUCCESS", (
                    sim.robot.name, name, reply and reply.metadata,
                )  # fmt: skip

    def close(self) -> None:
        self.master.close()
        self.slave.close()

    def __enter__(self) -> SimPair:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def wait_until(
    pred: Callable[[], Any],
    timeout: float = 10.0,
    every: float = 0.005,
    *,
    each: Callable[[], object] | None = None,
) -> Any:
    """For tests with threads or processes (real sockets, a daemon, a worker's reply): call
    ``pred`` until it returns something true, and return that; after ``timeout`` seconds,
    return its last (false) value. ``each`` is called before every look (a loop on the real
    clock the test ticks itself). Simulated-time tests need none of this: they tick."""
    end = time.monotonic() + timeout
    while True:
        if each is not None:
            each()
        value = pred()
        if value or time.monotonic() >= end:
            return value
        time.sleep(every)


def loopback_robot(
    config: DaemonConfig | str | os.PathLike[str] | Mapping[str, Any], *, run: bool = False
) -> Robot:
    """The robot of ``config`` on a :class:`~occ.clock.SimClock`, with its interfaces on real
    sockets at ephemeral ports (``port: 0``), configured and its interfaces started, for tests
    of the socket paths (a polled UDP stream, the kernel filter) in simulated time; ``run``:
    Enable and Run too. The caller shuts it down."""
    cfg = _as_config(config)
    cfg = cfg.model_copy(
        update={"interfaces": tuple(i.model_copy(update={"port": 0}) for i in cfg.interfaces)}
    )
    robot = build_robot(cfg, clock=SimClock())
    robot.configure()
    robot.activate()
    if run:
        robot.state_machine.request("enable", "test")
        robot.state_machine.request("run", "test")
    return robot
