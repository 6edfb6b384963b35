"""The hardware fault matrix: every fault a drive can have, injected into the shipped slave,
and what the robot did (docs/SAFETY.md, SR-HW-1; ``tools/fault_matrix.py`` prints the table,
``tests/occ/test_fault_matrix.py`` checks every row).

The robot is ``configs/slave.yaml`` (the checkout's, :data:`occ_testkit.CONFIGS`) with its
joints split over two drives: ``arm`` (yaw, pitch; simulated) and ``tool`` (insertion;
simulated, or the CAN driver on python-can's ``virtual`` bus talking to
:class:`~occ.drivers.can_sim.SimulatedDriveNode`, or the CiA 402 driver talking to
:class:`~occ.drivers.cia402_sim.DriveEmulator`, settled after every tick). The fault is always
in ``tool``; ``arm`` stays healthy, so a robot that went on moving ``arm`` alone would show.
Each run is in simulated time on in-process interfaces (:class:`~occ_testkit.testing.SimRobot`),
with an operator, a viewer (Slicer) and the master streaming a ramp; for the CAN and CiA 402
rows each tick waits for the drive node's answer, so the bus is real and the run still
deterministic.

For every row the run records: when the robot noticed (simulated ms after the injection), how
many ticks passed from then until every drive was in its safe state (0: the same tick), the
measured time from detection to the last drive safe (``time.perf_counter``), the final state,
the STATUS alert the operator and the viewer received, whether Enable was refused before a
Reset, and whether the robot worked again once the drive was repaired and reset.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import igtl
from occ.clock import SimClock
from occ.config import DaemonConfig
from occ.core.loader import load_config
from occ.core.safety import RobotState
from occ.drivers.base import DriverState
from occ.drivers.can_sim import DriveAxis, SimulatedDriveNode

from . import CONFIGS
from .testing import SimPeer, SimRobot

__all__ = ["ROWS", "Outcome", "Row", "run_row", "slave_config"]

COUNTS_PER_M = 1_000_000.0
_channels = itertools.count(1)


@dataclass(frozen=True)
class Row:
    """One fault: its name, the drive backend it needs, and when it strikes: at
    ``configure``, at ``enable``, or ``running`` (while following the master)."""

    name: str
    backend: str  # "sim" or "can"
    when: str  # "configure", "enable" or "running"
    what: str  # the fault in words (the table's first column)
    sim_faults: tuple[str, ...] = ()  # SimDriver faults (params at start, or injected)


ROWS: tuple[Row, ...] = (
    Row("configure", "sim", "configure", "configure fails", ("configure",)),
    Row("activate", "sim", "enable", "power-on (activate) fails", ("activate",)),
    Row("unmeasured", "sim", "enable", "a joint never measured", ("nan",)),
    Row("hook", "sim", "running", "a hook raises mid-run", ("hook",)),
    Row("write", "sim", "running", "a write that raises", ("write",)),
    Row("heartbeat", "sim", "running", "heartbeat lost", ("heartbeat",)),
    Row("nan", "sim", "running", "feedback NaN", ("nan",)),
    Row("frozen", "sim", "running", "feedback frozen, heartbeat alive", ("frozen",)),
    Row("jump", "sim", "running", "position jump beyond the velocity limit", ("jump",)),
    # issue 36: feedback that lies while the drive answers and its heartbeat lives
    Row("drift", "sim", "running", "runaway encoder, 0.1 mm a tick", ("drift:0:0.1",)),
    Row("drift-fast", "sim", "running", "runaway encoder, 0.5 mm a tick", ("drift:0:0.5",)),
    Row(
        "slip", "sim", "running", "encoder slip of 0.5 mm (5 x a tick's limit)", ("slip:0:0.0005",)
    ),
    Row("can-silent", "can", "running", "CAN node stops answering"),
    Row("can-late", "can", "running", "CAN node answers late"),
    Row("can-busoff", "can", "running", "CAN bus-off"),
    Row("can-errors", "can", "running", "CAN error frames"),
    Row("can-dither", "can", "running", "CAN node's stale position toggling by a count"),
    # issue 38: a CiA 402 drive (the cia402 driver, its emulator on a virtual bus)
    Row("cia402-emcy", "cia402", "running", "CiA 402 EMCY 0x2310 (overcurrent)"),
    Row("cia402-fault-bit", "cia402", "running", "CiA 402 statusword fault bit, no EMCY"),
    Row("cia402-heartbeat", "cia402", "running", "CiA 402 node's heartbeat stops"),
    Row("cia402-tpdo-late", "cia402", "running", "CiA 402 TPDOs 50 ms late"),
    Row("cia402-refuse", "cia402", "enable", "a CiA 402 node that will not enable"),
)
#: the CiA 402 rows' node id and encoder (the emulated drive of ``tool``)
CIA402_NODE = 3
CIA402_COUNTS_PER_M = 2_000_000.0


@dataclass
class Outcome:
    """What the robot did with one row's fault (see the module docstring)."""

    row: Row
    detected_ms: float | None = None
    ticks_to_safe: int | None = None
    fault_to_safe_us: float | None = None
    state: str = ""
    alert_operator: str = ""
    alert_viewer: str = ""
    enable_refused: bool = False
    enable_reply: str = ""
    recovered: bool = False
    partial_ticks: int = 0  # ticks RUNNING with a drive not ACTIVE (must be 0)
    #: simulated ms from the injected fault (not its detection) to the tick in which the last
    #: drive was safe (None when that never happened; a drive whose switch-off failed is not)
    inject_to_safe_ms: float | None = None
    #: the furthest the robot measured the faulty joint outside its limits, mm (0: never)
    outside_limits_mm: float = 0.0
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        refused_state = (
            self.state == RobotState.READY.value if self.row.name == "unmeasured" else True
        )
        return (
            self.partial_ticks == 0
            and self.ticks_to_safe == 0
            and "tool" in self.alert_operator
            and "tool" in self.alert_viewer
            and self.enable_refused
            and self.recovered
            and refused_state
        )


def slave_config(backend: str, sim_faults: tuple[str, ...] = (), channel: str = "") -> DaemonConfig:
    """The shipped slave with its joints on two drives, ``arm`` and ``tool`` (module doc)."""
    cfg = load_config(CONFIGS / "slave.yaml")
    shipped = cfg.robot.drivers[0]
    arm = shipped.model_copy(update={"name": "arm", "joints": ("yaw", "pitch")})
    if backend == "sim":
        params = {**dict(shipped.params), "faults": list(sim_faults)}
        tool = shipped.model_copy(
            update={"name": "tool", "joints": ("insertion",), "params": params}
        )
    elif backend == "cia402":
        node = {"node_id": CIA402_NODE, "counts_per_unit": CIA402_COUNTS_PER_M}
        tool = shipped.model_copy(
            update={
                "name": "tool",
                "plugin": "cia402",
                "joints": ("insertion",),
                "params": {
                    "interface": "virtual",
                    "channel": channel,
                    "nodes": {"insertion": node},
                    "feedback_timeout": 10.0,
                },
            }
        )
    else:
        tool = shipped.model_copy(
            update={
                "name": "tool",
                "plugin": "can",
                "joints": ("insertion",),
                "params": {
                    "interface": "virtual",
                    "channel": channel,
                    "joints": {
                        "insertion": {
                            "can_id": 0x101,
                            "feedback_id": 0x181,
                            "counts_per_unit": COUNTS_PER_M,
                        }
                    },
                    "feedback_timeout": 0.010,
                    # the drive's own figures, as a lab sets a CiA 402 drive's following
                    # error window: the node's servo (tau 2 ms) trails by 2 ms of motion
                    "following_error": {"window": 0.0002, "lag_ms": 5.0},
                },
            }
        )
    robot = cfg.robot.model_copy(update={"drivers": (arm, tool)})
    # No black box here: in simulated time its dump is written inline, in the tick of the
    # FAULT (tens of ms of wall time), while the CAN rows' drive node answers on a thread of
    # its own that must keep pace with the ticks (``_Run.tick``'s sync); the pause put the
    # node and the harness out of step and a repaired node's Reset read failed (the drive
    # faults' dumps are tests/occ/test_blackbox.py's)
    box = cfg.black_box.model_copy(update={"enabled": False})
    return cfg.model_copy(update={"robot": robot, "black_box": box})


class _Run:
    """One row's run: the robot, its peers, and the bus node for the CAN rows."""

    def __init__(self, row: Row) -> None:
        self.row = row
        self.node: SimulatedDriveNode | None = None
        self.emulator: Any = None
        channel = f"occ-faults-{next(_channels)}-{id(self)}"
        at_start = row.sim_faults if row.when != "running" else ()
        clock = SimClock()
        if row.backend == "can":
            # the drive's model runs on the robot's simulated clock: its motion between two
            # ticks is one period's, however long the machine took between them
            axis = DriveAxis(can_id=0x101, feedback_id=0x181, position=0.05 * COUNTS_PER_M)
            self.node = SimulatedDriveNode([axis], channel, tau=0.002, clock=clock.now).start()
        elif row.backend == "cia402":
            from occ.drivers.cia402_sim import DriveEmulator

            # the emulated drive on the robot's simulated clock, settled after every tick
            self.emulator = DriveEmulator([CIA402_NODE], channel=channel, clock=clock.now)
            self.emulator.node(CIA402_NODE).position = 0.05 * CIA402_COUNTS_PER_M
            self.emulator.start()
        self.sim = SimRobot(slave_config(row.backend, at_start, channel), clock=clock)
        if self.node is not None:  # the drive's first answer (to configure's mode-0 frame)
            self.node.wait_feedback(1, timeout=1.0)
        if self.emulator is not None and row.when != "running":
            self.inject()  # a fault there before the robot is asked for anything
        self.robot = self.sim.robot
        self.op: SimPeer = self.sim.peer("operator")
        self.viewer: SimPeer = self.sim.peer("slicer")
        self.master: SimPeer = self.sim.peer("master", address=("127.0.0.1", 40000))
        self.seq = 0
        self.sync = True  # CAN rows: each tick waits for the drive's answer
        self.partial_ticks = 0

    @property
    def tool(self) -> Any:
        return self.robot.hardware.drivers[1]

    def close(self) -> None:
        self.sim.close()
        if self.node is not None:
            self.node.stop()
        if self.emulator is not None:
            self.emulator.stop()

    def tick(self, stream: bool = False) -> None:
        node = self.node
        if stream and self.sim.k % 2 == 0:
            self.seq += 1
            # a ramp: 200 mm/s at the master, 20 mm/s at the tool (scale 0.1)
            x = 0.4 * self.seq
            self.master.send_position((0.3 * x, 0.3 * x, -x), seq=self.seq)
        self.sim.tick()
        if self.emulator is not None:
            self.emulator.settle()  # its TPDOs are there for the next tick's read
        r = self.robot
        if r.state is RobotState.RUNNING and any(
            d.state is not DriverState.ACTIVE for d in r.hardware.drivers
        ):
            self.partial_ticks += 1
        if node is not None and self.sync:
            # every frame the driver sent (commands and its polls while not powered) answered
            # before the next tick, so the simulated clock never outruns the node's thread.
            # Counted by the commands the node acted on, not by the answers it sent: after
            # can-late's repair the answers it held back and dropped were counted as sent and
            # again as lost by the driver, and the wait returned before a poll was answered
            node.wait_commands(self.tool.stats()["command_frames"], 1.0)

    def command(self, name: str) -> tuple[bool, str]:
        cid = self.op.send_command(name)
        self.tick()
        if self.robot.effects.powering_up:
            # the CiA 402 drive powers up off the loop thread: waited for without ticking (the
            # run stays deterministic), then completed by the next tick, which replies
            self.robot.effects.await_power_up(10.0)
            self.tick()
        reply = self.op.reply_to(cid)
        if reply is None:
            return False, "no reply"
        meta = reply.metadata
        return meta.get("Status") == "SUCCESS", meta.get("Message", "") or str(reply)

    def alert(self, peer: SimPeer, after: int) -> str:
        texts = [
            m.status_message
            for m in peer.messages("STATUS")[after:]
            if isinstance(m, igtl.StatusMessage)
            and m.error_name.upper() in ("FAULT", "ALERT")
            and "tool" in m.status_message
        ]
        return texts[0] if texts else ""

    def inject(self) -> None:
        row = self.row
        if row.backend == "sim":
            for spec in row.sim_faults:
                kind, _, rest = spec.partition(":")
                joint, _, amount = rest.partition(":")
                self.tool.inject(kind, int(joint or 0), float(amount) if amount else None)
            return
        emu = self.emulator
        if emu is not None:
            if row.name == "cia402-emcy":
                emu.inject_emcy(CIA402_NODE, 0x2310)
            elif row.name == "cia402-fault-bit":
                emu.inject_fault_bit(CIA402_NODE)
            elif row.name == "cia402-heartbeat":
                emu.stop_heartbeat(CIA402_NODE)
            elif row.name == "cia402-tpdo-late":
                emu.pause_tpdos(CIA402_NODE, 0.050)
            elif row.name == "cia402-refuse":
                emu.refuse_enable(CIA402_NODE)
            return
        node = self.node
        assert node is not None
        if row.name == "can-silent":
            node.mute()
            self.sync = False
        elif row.name == "can-late":
            node.delay = 0.5  # half a second: far past the 10 ms deadline
            self.sync = False
        elif row.name == "can-busoff":
            node.send_error_frame(0x40)
        elif row.name == "can-errors":
            for _ in range(11):
                node.send_error_frame(0x04)
        elif row.name == "can-dither":
            node.stale_dither(1)

    def repair(self) -> None:
        if self.row.backend == "sim":
            self.tool.clear_faults()
            return
        if self.emulator is not None:
            self.emulator.clear(CIA402_NODE)
            return
        node = self.node
        assert node is not None
        node.mute(False)
        node.delay = 0.0
        node.discard_late()
        node.stale_dither(0)
        self.sync = True


def run_row(row: Row, on_step: Callable[[str], None] | None = None) -> Outcome:
    """Run one row of the matrix and return what the robot did."""
    out = Outcome(row)
    try:
        run = _Run(row)
    except Exception as err:  # noqa: BLE001 - a robot that cannot even be built is an outcome
        out.notes.append(f"build failed: {type(err).__name__}: {err}")
        return out
    try:
        _play(run, out)
    finally:
        out.partial_ticks = run.partial_ticks
        run.close()
    return out


def _play(run: _Run, out: Outcome) -> None:
    row = run.row
    robot = run.robot
    hw = robot.hardware
    n_op = n_view = 0  # a fault at configure is told in the greeting
    for _ in range(3):
        run.tick()
    injected_at = run.sim.k
    if row.when == "running":
        ok, text = run.command("Enable")
        ok2, text2 = run.command("Run")
        if not (ok and ok2):
            out.notes.append(f"could not start: {text}; {text2}")
            return
        for _ in range(100):
            run.tick(stream=True)
        n_op = len(run.op.messages("STATUS"))
        n_view = len(run.viewer.messages("STATUS"))
        run.inject()
        injected_at = run.sim.k
        limits = robot.joints[2].limits  # the tool's joint, insertion
        for _ in range(500):
            run.tick(stream=True)
            x = robot.data.q[2]
            outside = max(limits.min - x, x - limits.max, 0.0) * 1e3
            out.outside_limits_mm = max(out.outside_limits_mm, outside)
            if robot.state is RobotState.FAULT:
                break
    elif row.when == "enable":
        ok, text = run.command("Enable")
        out.enable_reply = text
        if ok:
            out.notes.append("Enable was accepted")
    if robot.state is RobotState.FAULT or row.when == "enable":
        out.detected_ms = (run.sim.k - injected_at) * 1e3 / robot.rate_hz
        out.ticks_to_safe = 0 if hw.all_safe() else 1
        if hw.all_safe():
            out.inject_to_safe_ms = (run.sim.k - injected_at) * 1e3 / robot.rate_hz
        lat = hw.last_fault_to_safe_s
        out.fault_to_safe_us = None if lat is None else lat * 1e6
    out.state = robot.state.value
    out.alert_operator = run.alert(run.op, n_op)
    out.alert_viewer = run.alert(run.viewer, n_view)
    ok, text = run.command("Enable")
    out.enable_refused = not ok
    if not out.enable_reply:
        out.enable_reply = text
    # repaired and reset, the robot works again on all of its hardware (a CAN drive's
    # unanswered commands are given up as lost after its ``lost_after``, 100 ms, of quiet)
    run.repair()
    for _ in range({"sim": 3, "cia402": 60}.get(row.backend, 110)):
        run.tick()
    if robot.state is not RobotState.READY:
        run.command("Reset")
    for _ in range(3):
        run.tick()
    ok, text = run.command("Enable")
    ok2, text2 = run.command("Run")
    for _ in range(20):
        run.tick(stream=True)
    out.recovered = ok and ok2 and robot.state is RobotState.RUNNING
    if not out.recovered:
        out.notes.append(f"after repair: {text}; {text2}; {robot.state.value} ({robot.last_alert})")


def table(outcomes: list[Outcome]) -> str:
    """The matrix as a Markdown table (``tools/fault_matrix.py``)."""
    lines = [
        "| fault | drive | fault -> all safe (sim ms) | ticks to all safe | detection -> last "
        "drive safe (us) | state | Enable before Reset | alert to operators | pass |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for o in outcomes:
        det = "-" if o.inject_to_safe_ms is None else f"{o.inject_to_safe_ms:.0f}"
        lat = "-" if o.fault_to_safe_us is None else f"{o.fault_to_safe_us:.0f}"
        alert = o.alert_operator.replace("|", "/")
        lines.append(
            f"| {o.row.what} | {o.row.backend} | {det} | {o.ticks_to_safe} | {lat} | "
            f"{o.state} | {'refused' if o.enable_refused else 'ACCEPTED'} | {alert} | "
            f"{'PASS' if o.ok else 'FAIL'} |"
        )
    return "\n".join(lines)
