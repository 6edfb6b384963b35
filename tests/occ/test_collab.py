"""Collaborative control in simulated time (issue 12): two masters, one slave, hand-over.

The shipped configs/collab/slave.yaml on in-process channels (occ_testkit.testing.SimRobot): the
mentor's and the trainee's POSITION streams come from two peers (a packet every 2 ms each, different
motions), the operators from the bedside port and the two consoles. Everything between the peers
and the loop is the daemon's own code, stepped tick by tick.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import pytest

import igtl
from occ.errors import ConfigError
from occ.core.loader import load_config, parse_config
from occ.core.safety import RobotState
from occ_testkit.testing import SimPeer, SimRobot
from occ_testkit.testing import wait_until as wait_for

ROOT = Path(__file__).resolve().parents[2]
SLAVE = ROOT / "configs" / "collab" / "slave.yaml"
MENTOR_ADDRESS = ("127.0.0.1", 41000)
TRAINEE_ADDRESS = ("127.0.0.1", 42000)
SCALE = 0.1


def mentor_mm(t: float) -> tuple[float, float, float]:
    """The mentor's hand: the 50 mm circle at 0.1 Hz (configs/collab/mentor.yaml)."""
    w = 2 * math.pi * 0.1 * t
    return (50.0 * math.sin(w), 50.0 * math.cos(w), 20.0)


def trainee_mm(t: float) -> tuple[float, float, float]:
    """The trainee's hand: a 20 x 60 mm ellipse at 0.25 Hz, 20 mm higher, far from the
    mentor's: a slave that followed it without re-indexing would jump by millimetres."""
    w = 2 * math.pi * 0.25 * t
    return (20.0 * math.sin(w) + 30.0, 60.0 * math.cos(w) - 40.0, 40.0)


class Collab:
    """The collaborative slave, its two masters' streams and its three operator ports."""

    def __init__(self, config: Any = SLAVE) -> None:
        self.sim = SimRobot(config)
        self.robot = self.sim.robot
        self.masters: dict[str, SimPeer] = {
            "mentor": self.sim.peer("mentor", address=MENTOR_ADDRESS),
            "trainee": self.sim.peer("trainee", address=TRAINEE_ADDRESS),
        }
        self.motion = {"mentor": mentor_mm, "trainee": trainee_mm}
        self.seq = {"mentor": 0, "trainee": 0}
        self.sent: dict[str, tuple[float, float, float]] = {}
        #: masters whose stream is silent (a dead console), and numbers to drop
        self.silent: set[str] = set()
        self.drops: dict[str, set[int]] = {"mentor": set(), "trainee": set()}
        self.bedside = self.sim.peer("operator", address=("127.0.0.1", 43000))
        self.desks = {
            "mentor": self.sim.peer("mentor_desk", address=("127.0.0.1", 43001)),
            "trainee": self.sim.peer("trainee_desk", address=("127.0.0.1", 43002)),
        }
        self.slicer = self.sim.peer("slicer", address=("127.0.0.1", 43003))

    @property
    def k(self) -> int:
        return self.sim.k

    def tick(self) -> None:
        if self.k % 2 == 0:
            t = self.sim.now
            for name, peer in self.masters.items():
                if name in self.silent:
                    continue
                self.seq[name] += 1
                if self.seq[name] in self.drops[name]:
                    continue
                pos = self.motion[name](t)
                self.sent[name] = pos
                peer.send_position(pos, seq=self.seq[name])
        self.sim.tick()

    def step_ms(self, ms: int) -> None:
        for _ in range(ms):
            self.tick()

    def command(self, peer: SimPeer, name: str, text: str = "") -> igtl.Message:
        cid = peer.send_command(name, text)
        self.tick()
        reply = peer.reply_to(cid)
        assert reply is not None, f"no reply to {name}"
        return reply

    def running(self) -> None:
        for cmd in ("Enable", "Run"):
            assert ok(self.command(self.bedside, cmd)), cmd
        self.step_ms(200)
        assert self.robot.state is RobotState.RUNNING

    def tip_mm(self) -> tuple[float, ...]:
        """Where the drivers are told to go (FK of the setpoint), mm."""
        x, y, z = self.robot.frame.tip_position(self.robot.data.setpoint)
        return (x * 1e3, y * 1e3, z * 1e3)

    def close(self) -> None:
        self.sim.close()


def ok(reply: igtl.Message) -> bool:
    return reply.metadata.get("Status") == "SUCCESS"


def error_of(reply: igtl.Message) -> str:
    assert reply.metadata.get("Status") == "FAIL", reply.metadata
    return reply.metadata.get("Error", "") + reply.metadata.get("Message", "")


def handover(to: str) -> str:
    return f'<Command Name="Handover" To="{to}"/>'


def statuses(peer: SimPeer, name: str) -> list[igtl.Message]:
    return [m for m in peer.messages("STATUS") if getattr(m, "error_name", "") == name]


@pytest.fixture
def collab() -> Any:
    c = Collab()
    try:
        yield c
    finally:
        c.close()


def dist(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    return math.dist(a, b)


# ------------------------------------------------------------------------------ hand-over
def test_the_owner_moves_the_slave_and_the_other_master_does_not(collab: Collab) -> None:
    collab.running()
    ctrl = collab.robot.controller.controllers[0]
    assert collab.robot.collab is not None and collab.robot.collab.owner == "mentor"
    assert ctrl.source == "mentor"
    start, m0 = collab.tip_mm(), collab.sent["mentor"]
    collab.step_ms(500)
    moved = tuple(a - b for a, b in zip(collab.tip_mm(), start, strict=True))
    expect = tuple(SCALE * (a - b) for a, b in zip(collab.sent["mentor"], m0, strict=True))
    assert dist(moved, expect) < 1e-3  # the mentor's motion, scaled 10:1 (exact IK)
    assert collab.robot.streams.monitors["trainee"].accepted > 200  # judged, counted, not followed
    assert ctrl.source_changes == 0


def test_handover_re_indexes_without_a_jump(collab: Collab) -> None:
    collab.running()
    robot = collab.robot
    before = collab.tip_mm()
    reply = collab.command(collab.desks["mentor"], "Handover", handover("trainee"))
    assert ok(reply), reply.metadata
    assert robot.collab is not None and robot.collab.owner == "trainee"
    assert (
        robot.streams.input == "trainee"
        and robot.streams.monitor is robot.streams.monitors["trainee"]
    )
    # every operator and viewer hears of it (STATUS HANDOVER)
    for peer in (collab.bedside, collab.slicer, *collab.desks.values()):
        (st,) = statuses(peer, "HANDOVER")
        assert "mentor -> trainee" in st.status_message
    # no jump: tick by tick the commanded tip moves by what the trainee's motion asks at most
    path = [collab.tip_mm()]
    t_first = None
    for _ in range(600):
        collab.tick()
        path.append(collab.tip_mm())
        if t_first is None and robot.controller.controllers[0].source == "trainee":
            t_first = collab.sent["trainee"]
    steps = [dist(a, b) for a, b in zip(path, path[1:], strict=False)]
    # the trainee's hand moves at most 2 pi 0.25 Hz 60 mm = 94 mm/s: 18.8 um per 2 ms sample
    # at 10:1, and the re-index itself moves nothing
    assert max(steps) < 0.019, max(steps)
    assert dist(path[0], before) < 0.019  # the command's tick: the mentor's last sample
    assert steps[0] < 1e-9 and steps[1] < 1e-9  # re-indexed on the trainee's first sample
    # not re-indexed, the slave would have gone 0.1 x (trainee - mentor): millimetres away
    absolute = [SCALE * (a - b) for a, b in zip(trainee_mm(0.0), mentor_mm(0.0), strict=True)]
    assert math.hypot(*absolute) > 4.0
    # and it follows the trainee's motion from where it was (relative, scaled)
    assert t_first is not None
    moved = tuple(a - b for a, b in zip(path[-1], before, strict=True))
    expect = tuple(SCALE * (a - b) for a, b in zip(collab.sent["trainee"], t_first, strict=True))
    assert dist(moved, expect) < 0.02, (moved, expect)
    ctrl = robot.controller.controllers[0]
    assert ctrl.source == "trainee" and ctrl.source_changes == 1
    snap = robot.snapshot()
    assert snap["owner"] == "trainee" and snap["collaboration"]["handovers"] == 1
    assert snap["collaboration"]["history"][0]["by"] == "mentor (supervisor)"


def test_supervisor_takes_control_back_and_the_owner_may_give_it(collab: Collab) -> None:
    collab.running()
    co = collab.robot.collab
    assert co is not None
    assert ok(collab.command(collab.desks["mentor"], "Handover", handover("trainee")))
    collab.step_ms(50)
    # the trainee has it and gives it back (grant)
    assert ok(collab.command(collab.desks["trainee"], "Handover", handover("mentor")))
    assert co.owner == "mentor"
    collab.step_ms(50)
    assert ok(collab.command(collab.desks["mentor"], "Handover", handover("trainee")))
    collab.step_ms(50)
    # the supervisor takes it back while the trainee has it
    assert ok(collab.command(collab.desks["mentor"], "Handover", handover("mentor")))
    assert co.owner == "mentor" and co.handovers == 4
    # the bedside port acts as the supervisor (others: supervisor)
    assert ok(collab.command(collab.bedside, "Handover", handover("trainee")))
    assert co.owner == "trainee"
    # by STRING CMD_ as well (PLUS style)
    collab.desks["mentor"].send(
        igtl.StringMessage(handover("mentor"), device_name="CMD_7", header_version=2)
    )
    collab.tick()
    (ack,) = collab.desks["mentor"].messages("STRING", "ACK_7")
    assert 'Status="SUCCESS"' in ack.string and co.owner == "mentor"
    assert collab.robot.state is RobotState.RUNNING


def test_refused_handovers_change_nothing(collab: Collab) -> None:
    collab.running()
    co = collab.robot.collab
    assert co is not None
    desks = collab.desks
    # the trainee may not take control (not in request)
    assert "may not take control" in error_of(
        collab.command(desks["trainee"], "Handover", handover("trainee"))
    )
    # an unknown master, with a suggestion; no To at all
    assert "did you mean 'trainee'" in error_of(
        collab.command(desks["mentor"], "Handover", handover("trainea"))
    )
    assert "To=" in error_of(
        collab.command(desks["mentor"], "Handover", '<Command Name="Handover"/>')
    )
    # a silent master is never given control while RUNNING
    collab.silent.add("trainee")
    collab.step_ms(300)
    assert "not live" in error_of(collab.command(desks["mentor"], "Handover", handover("trainee")))
    assert co.owner == "mentor" and co.handovers == 0 and co.refused == 4
    assert not statuses(collab.bedside, "HANDOVER")
    assert collab.robot.snapshot()["collaboration"]["refused"] == 4
    assert collab.robot.state is RobotState.RUNNING


def test_others_refuse_and_no_collaboration() -> None:
    text = SLAVE.read_text().replace("others: supervisor", "others: refuse")
    c = Collab(parse_config(text, base_dir=SLAVE.parent))
    try:
        c.running()
        assert "may not hand over" in error_of(
            c.command(c.bedside, "Handover", handover("trainee"))
        )
    finally:
        c.close()
    # the one-master slave answers Handover with an error, as every unknown request
    sim = SimRobot(ROOT / "configs" / "slave.yaml")
    try:
        op = sim.peer("operator")
        cid = op.send_command("Handover", handover("master"))
        sim.tick()
        reply = op.reply_to(cid)
        assert reply is not None and "no collaboration" in error_of(reply)
    finally:
        sim.close()


# ------------------------------------------------------------------------------ loss rules
def test_a_non_owners_loss_only_alerts(collab: Collab) -> None:
    collab.running()
    robot = collab.robot
    # three numbers in a row missing from the trainee: proven loss, but not the owner's
    seq = collab.seq["trainee"]
    collab.drops["trainee"] = {seq + 3, seq + 4, seq + 5}
    collab.step_ms(30)
    (alert,) = statuses(collab.bedside, "ALERT")
    assert "trainee (not in control) lost" in alert.status_message
    assert robot.state is RobotState.RUNNING
    # the trainee's console then dies: silence past the grace is an alert too, never a stop
    collab.silent.add("trainee")
    before = collab.tip_mm()
    collab.step_ms(400)
    assert robot.state is RobotState.RUNNING and not robot.streams.monitor.holding  # type: ignore[union-attr]
    assert len(statuses(collab.bedside, "ALERT")) == 2
    assert dist(collab.tip_mm(), before) > 0.1  # still following the mentor
    counts = robot.snapshot()["loss_by_stream"]
    assert counts["trainee"]["trips"] == 2 and counts["mentor"]["trips"] == 0
    # the trainee's monitor re-armed: its console back, it can be handed control
    collab.silent.discard("trainee")
    collab.step_ms(20)
    assert ok(collab.command(collab.desks["mentor"], "Handover", handover("trainee")))


def test_the_owners_loss_holds_then_stops(collab: Collab) -> None:
    collab.running()
    robot = collab.robot
    collab.silent.add("mentor")
    held_at = None
    for _ in range(150):
        collab.tick()
        if held_at is None and robot.streams.monitor is not None and robot.streams.monitor.holding:
            held_at = collab.k
    assert held_at is not None
    assert robot.state is RobotState.STOPPED
    assert "packet loss on mentor" in robot.last_alert


def test_after_handover_the_new_owners_loss_stops_and_the_old_ones_does_not(
    collab: Collab,
) -> None:
    collab.running()
    robot = collab.robot
    assert ok(collab.command(collab.desks["mentor"], "Handover", handover("trainee")))
    collab.silent.add("mentor")
    collab.step_ms(300)
    assert robot.state is RobotState.RUNNING
    assert any(
        "mentor (not in control)" in s.status_message for s in statuses(collab.bedside, "ALERT")
    )
    seq = collab.seq["trainee"]
    collab.drops["trainee"] = {seq + 3, seq + 4, seq + 5}
    collab.step_ms(20)
    assert robot.state is RobotState.STOPPED
    assert "packet loss on trainee" in robot.last_alert


def test_getstats_names_the_owner_over_the_wire(collab: Collab) -> None:
    collab.running()
    peer = collab.desks["trainee"]
    cid = peer.send_command("GetStats")
    collab.tick()
    assert wait_for(lambda: peer.reply_to(cid) is not None)
    reply = peer.reply_to(cid)
    assert reply is not None
    snap = json.loads(reply.metadata["Message"])
    assert snap["owner"] == "mentor"
    assert set(snap["loss_by_stream"]) == {"mentor", "trainee"}


# ------------------------------------------------------------------------------ config
@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            "{input: trainee, console: trainee_desk}",
            "{input: traine, console: trainee_desk}",
            "unknown interface 'traine'",
        ),
        ("console: trainee_desk}", "console: slicer}", "needs role 'operator'"),
        ("owner: mentor ", "owner: slicer ", "is not one of the masters"),
        ("grant: [mentor, trainee]", "grant: [mentor, bedside]", "is not one of the masters"),
        (
            "input: null, period_ms",
            "input: slicer, period_ms",
            "must be null or one of the masters",
        ),
        (
            "{input: mentor, console: mentor_desk}",
            "{input: slicer, console: mentor_desk}",
            "has no stream input",
        ),
    ],
)
def test_bad_collaboration_configs_are_refused(
    tmp_path: Path, old: str, new: str, message: str
) -> None:
    text = SLAVE.read_text()
    assert old in text
    path = tmp_path / "slave.yaml"
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(ConfigError, match=message):
        load_config(path)


def test_shipped_collab_configs_load() -> None:
    for name in ("slave", "mentor", "trainee"):
        load_config(ROOT / "configs" / "collab" / f"{name}.yaml")


def test_request_and_grant_policies() -> None:
    """``request``: a console may take control for itself; ``grant`` restricted: an owner not
    listed may not give control away (only the supervisor then takes it back)."""
    text = SLAVE.read_text()
    text = text.replace("request: []", "request: [trainee]")
    text = text.replace("grant: [mentor, trainee]", "grant: [mentor]")
    c = Collab(parse_config(text, base_dir=SLAVE.parent))
    try:
        c.running()
        co = c.robot.collab
        assert co is not None
        assert ok(c.command(c.desks["trainee"], "Handover", handover("trainee")))  # request
        assert co.owner == "trainee"
        c.step_ms(20)
        refused = c.command(c.desks["trainee"], "Handover", handover("mentor"))
        assert "may not give it away" in error_of(refused) and co.owner == "trainee"
        assert ok(c.command(c.desks["mentor"], "Handover", handover("mentor")))  # supervisor
        assert co.owner == "mentor" and co.handovers == 2 and co.refused == 1
    finally:
        c.close()


# ------------------------------------------------------------------ issue 29: the liveness check
def _refused_handover(collab: Collab, to: str) -> str:
    reply = collab.command(collab.desks["mentor"], "Handover", handover(to))
    assert reply.metadata.get("Status") == "FAIL", reply.metadata
    return str(reply.metadata["Error"])


@pytest.mark.req("SR-SEC-6")
def test_a_handover_names_why_the_new_owners_stream_is_not_live() -> None:
    """While RUNNING, control goes only to a live stream; the refusal says which check failed:
    silent since Run (or since its loss, after which a bystander's monitor re-arms) or late
    (holding); before Run a silent master may be given control (it is judged when the robot
    runs)."""
    c = Collab()
    try:
        c.silent.add("trainee")
        co = c.robot.collab
        assert co is not None
        # not running: a silent master may be handed control (and back)
        assert ok(c.command(c.desks["mentor"], "Handover", handover("trainee")))
        assert ok(c.command(c.desks["mentor"], "Handover", handover("mentor")))
        c.running()
        assert _refused_handover(c, "trainee") == (
            "trainee's stream is not live (silent since Run): control stays with mentor"
        )
        c.silent.discard("trainee")
        c.step_ms(50)
        c.silent.add("trainee")
        c.step_ms(20)  # past the 7 ms deadline, within the 100 ms grace: holding
        assert _refused_handover(c, "trainee") == (
            "trainee's stream is not live (late): control stays with mentor"
        )
        c.step_ms(200)  # past the grace: its loss alerted, its monitor re-armed, unheard since
        assert _refused_handover(c, "trainee") == (
            "trainee's stream is not live (silent since Run): control stays with mentor"
        )
        assert co.owner == "mentor" and co.refused == 3 and co.handovers == 2
    finally:
        c.close()


@pytest.mark.req("SR-SEC-6")
def test_a_handover_rejoins_the_new_target_through_the_re_entry(
    collab: Collab, caplog: pytest.LogCaptureFixture
) -> None:
    """The new owner's target is re-joined through the re-entry (at half the velocity limits,
    counted in ``reentries``), never taken in one step; the hand-over is logged."""
    collab.running()
    before = collab.robot.motion.reentries
    caplog.set_level(logging.WARNING, logger="occ.core.robot")
    # the PLUS spelling of the argument, lower case, is taken as well
    reply = collab.command(
        collab.desks["mentor"], "Handover", '<Command Name="Handover" to="trainee"/>'
    )
    assert ok(reply) and reply.metadata["Message"] == (
        "control mentor -> trainee (by mentor (supervisor))"
    )
    assert [r.getMessage() for r in caplog.records if r.name == "occ.core.robot"] == [
        "handover: control mentor -> trainee (by mentor (supervisor))"
    ]
    collab.step_ms(50)
    assert collab.robot.motion.reentries == before + 1
    assert collab.robot.snapshot()["reentries"] == before + 1


@pytest.mark.req("SR-SEC-6")
def test_a_handover_without_a_target_or_without_collaboration_says_so_exactly() -> None:
    c = Collab()
    try:
        reply = c.command(c.desks["mentor"], "Handover", '<Command Name="Handover"/>')
        assert reply.metadata["Error"] == 'Handover needs To="MASTER INTERFACE"'
    finally:
        c.close()
    sim = SimRobot(ROOT / "configs" / "slave.yaml")
    try:
        op = sim.peer("operator")
        cid = op.send_command("Handover", handover("master"))
        sim.tick()
        reply = op.reply_to(cid)
        assert reply is not None and reply.metadata["Error"] == (
            "Handover: no collaboration configured (this slave has one master)"
        )
    finally:
        sim.close()
