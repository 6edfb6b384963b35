"""Whole-arm collision checking (issue 28, item 4; occ/kinematics/collision.py, docs/SAFETY.md SR-COLL-1..3).

- A UR5 (configs/ur5.yaml) keyframe plan whose *elbow* (the forearm), not its tip, crosses a
  forbidden plane is refused naming the link, the region and the time; the same plan passes the
  tip-only check; a plan that stays clear passes and runs.
- Teleoperation toward the plane (a scripted master stream raising the tool) stops the robot
  before contact, with an ALERT naming the link and the region; a late verdict holds the loop.
- Self-collision, a mesh region from a Slicer-like POLYDATA, config errors with their lines.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

import igtl
from occ.kinematics.collision import CollisionModel, regions_from_event
from occ.config import CollisionConfig
from occ.net.decoders import event_of
from occ.errors import ConfigError
from occ.core.loader import load_config
from occ.core.safety import RobotState
from occ.core.supervision import Worker
from occ_testkit.testing import CONFIGS, SimRobot, wait_until

HOME = [0.0, -1.2, 1.5, -1.9, -1.57, 0.0]
#: the shoulder and elbow raised: the forearm rises through z = 560 mm, the tip sinks to 236 mm
RAISED = [0.0, -1.5, 2.0, -2.0, -1.57, 0.0]
CEILING = {"name": "ceiling", "kind": "plane", "point_mm": [0, 0, 560], "normal": [0, 0, -1]}


def ur5(
    collision: dict[str, Any] | None, controller: dict[str, Any] | None = None
) -> dict[str, Any]:
    cfg: dict[str, Any] = yaml.safe_load((CONFIGS / "ur5.yaml").read_text())
    if collision is not None:
        cfg["safety"]["collision"] = collision
    if controller is not None:
        cfg["controller"] = controller
        cfg["safety"]["loss"] = {"enabled": False}
        cfg["interfaces"] = cfg["interfaces"][:2]  # no master stream
        cfg["interfaces"][1]["outputs"] = [
            {"type": "POLYDATA", "device": "KeyframePath", "source": "keyframe-path", "rate_hz": 10}
        ]
    cfg["interfaces"][1]["inputs"] = [
        {"type": t, "queue": "command", "depth": 16} for t in ("POINT", "TRANSFORM", "POLYDATA")
    ]
    return cfg


def keyframe_robot(collision: dict[str, Any] | None, **params: Any) -> SimRobot:
    return SimRobot(ur5(collision, {"plugin": "keyframe", "params": {"space": "joint", **params}}))


def command(sim: SimRobot, name: str, **args: Any) -> Any:
    op = getattr(sim, "test_operator", None)
    if op is None:  # one operator per robot (the interface takes four)
        op = sim.test_operator = sim.peer("operator")  # type: ignore[attr-defined]
    attrs = "".join(f' {k}="{v}"' for k, v in args.items())
    cid = op.send_command(name, f'<Command Name="{name}"{attrs}/>')
    sim.step(1)
    kf = sim.robot.controller.controllers[0]
    if hasattr(kf, "wait_idle"):
        assert kf.wait_idle(60.0)
    sim.step(1)
    reply = op.reply_to(cid)
    assert reply is not None, name
    return reply.metadata


def raise_keyframes() -> list[dict[str, Any]]:
    return [{"t": 2.0, "pose": RAISED, "name": "raised"}]


# ------------------------------------------------------------------------------ plans
@pytest.mark.req("SR-COLL-1")
def test_a_plan_whose_elbow_crosses_a_forbidden_plane_is_refused_naming_the_link() -> None:
    sim = keyframe_robot({"margin_mm": 10.0, "regions": [CEILING]}, keyframes=raise_keyframes())
    try:
        command(sim, "Enable")
        reply = command(sim, "KeyframePlan")
        assert reply["Status"] == "FAIL", reply
        error = reply["Error"]
        assert "link 'forearm_link'" in error and "forbidden region 'ceiling'" in error, error
        assert "margin 10 mm" in error and "between the start" in error and "raised" in error
        t = float(error.split("t=")[1].split()[0])
        assert 0.0 < t < 2.0
    finally:
        sim.close()


@pytest.mark.req("SR-COLL-1")
def test_the_tip_alone_never_comes_near_the_plane() -> None:
    # the keyframe controller's own tip check, against the same plane: the plan passes (the
    # tip stays below 300 mm), which is why the whole arm is checked
    tip_only = {"forbidden": [{"point_mm": [0, 0, 560], "normal": [0, 0, -1], "name": "ceiling"}]}
    sim = keyframe_robot(None, keyframes=raise_keyframes(), **tip_only)
    try:
        command(sim, "Enable")
        assert command(sim, "KeyframePlan")["Status"] == "SUCCESS"
    finally:
        sim.close()


@pytest.mark.req("SR-COLL-1")
def test_a_plan_clear_of_the_regions_passes_and_runs() -> None:
    low = [0.3, -1.1, 1.6, -2.0, -1.57, 0.2]
    sim = keyframe_robot(
        {"margin_mm": 10.0, "regions": [CEILING]},
        keyframes=[{"t": 2.0, "pose": low, "name": "low"}],
    )
    try:
        command(sim, "Enable")
        command(sim, "Run")
        reply = command(sim, "KeyframePlan")
        assert reply["Status"] == "SUCCESS", reply
        plan_id = reply["Message"].split(":")[0].split()[1]
        sim.step(150)  # the preview goes out
        assert command(sim, "KeyframeAck", Plan=plan_id)["Status"] == "SUCCESS"
        sim.run_for(2.2)
        assert sim.robot.state is RobotState.RUNNING
        assert np.allclose(sim.robot.data.setpoint, low, atol=1e-9)
        guard = sim.robot.collision
        assert guard is not None and guard.stops == 0 and guard.holds == 0
        # every setpoint offered, each covered by a verdict; a new one only when due
        assert guard.verdicts + guard.skipped > 2000 and guard.verdicts < 200
    finally:
        sim.close()


# ------------------------------------------------------------------------------ teleoperation
class Teleop:
    """configs/ur5.yaml (teleop-slave, orientation follow) with a ceiling, and a scripted
    master stream raising the tool by ``mm_per_s`` (the master moves twice that: scale 0.5)."""

    def __init__(self, collision: dict[str, Any]) -> None:
        self.sim = SimRobot(ur5(collision))
        self.robot = self.sim.robot
        self.master = self.sim.peer("master")
        self.op = self.sim.test_operator = self.sim.peer("operator")  # type: ignore[attr-defined]
        self.seq = 0
        self.z = 0.0
        command(self.sim, "Enable")
        command(self.sim, "Run")

    def stream(self, ticks: int, mm_per_s: float, until_stopped: bool = True) -> int:
        for k in range(ticks):
            if k % 2 == 0:
                self.seq += 1
                self.z += 2.0 * mm_per_s * 2e-3
                self.master.send_position(
                    (0.0, 0.0, self.z), seq=self.seq, timestamp=self.robot.clock.wall_time()
                )
            self.sim.step(1)
            if until_stopped and self.robot.state is not RobotState.RUNNING:
                return k
        return ticks

    def gap(self, q: Any) -> float:
        """The smallest distance from any link to any region at ``q`` (m)."""
        guard = self.robot.collision
        assert guard is not None
        return guard.cm.checker().clearance(q, self.robot.data.base)[1]

    def close(self) -> None:
        self.sim.close()


@pytest.mark.req("SR-COLL-2")
@pytest.mark.parametrize("runtime_hz", [None, 100.0])
def test_teleoperation_toward_the_plane_stops_before_contact_naming_link_and_region(
    runtime_hz: float | None,
) -> None:
    t = Teleop({"margin_mm": 10.0, "regions": [CEILING], "runtime_hz": runtime_hz})
    try:
        start_gap = t.gap(t.robot.data.setpoint)
        assert start_gap > 0.015  # the run starts clear of the margin
        k = t.stream(8000, 50.0)
        r = t.robot
        assert r.state is RobotState.STOPPED, "never stopped"
        assert k > 500  # it moved a good way first
        alerts = [m for m in t.op.messages("STATUS") if m.error_name == "COLLISION"]
        assert len(alerts) == 1
        text = alerts[0].status_message
        assert "forbidden region 'ceiling'" in text and "link 'wrist_2_link'" in text, text
        assert "ceiling" in r.last_alert
        # the tip itself is far below the ceiling: a tip-only check would not have stopped it
        assert r.data.world_tip()[2, 3] < 0.45
        # held: the measured arm settles where it stopped, every link clear of the plane by
        # more than half the margin; the master keeps pushing, nothing moves
        t.stream(1000, 50.0, until_stopped=False)
        assert t.gap(r.data.q) > 0.005
        assert t.gap(r.data.hold_setpoint) > 0.005
        guard = r.collision
        assert guard is not None and guard.stops == 1
    finally:
        t.close()


@pytest.mark.req("SR-COLL-2")
def test_a_run_inside_the_margin_may_move_away_but_not_closer() -> None:
    t = Teleop({"margin_mm": 10.0, "regions": [CEILING]})
    try:
        t.stream(8000, 50.0)
        assert t.robot.state is RobotState.STOPPED
        inside = t.gap(t.robot.data.setpoint)
        command(t.sim, "Run")  # inside the margin: a run that goes on up stops again at once
        t.stream(400, 50.0)
        assert t.robot.state is RobotState.STOPPED
        assert t.gap(t.robot.data.setpoint) > inside - 0.001
        command(t.sim, "Run")  # and one that goes down leaves the margin
        t.stream(1500, -50.0)
        assert t.robot.state is RobotState.RUNNING
        assert t.gap(t.robot.data.setpoint) > 0.010
    finally:
        t.close()


@pytest.mark.req("SR-COLL-2")
def test_without_a_verdict_the_loop_holds_and_rejoins_after() -> None:
    t = Teleop({"margin_mm": 10.0, "regions": [CEILING]})
    guard = t.robot.collision
    assert guard is not None
    try:
        t.stream(200, 20.0)
        moving = list(t.robot.data.setpoint)
        assert moving != HOME
        # the worker falls silent (its verdicts stop coming): the loop holds what it had as
        # soon as the next setpoint leaves half the last clearance, without stopping
        guard.inline = False  # publish now submits to a worker that was never started
        guard._worker = Worker("silent")
        t.stream(600, 20.0)
        held = list(t.robot.data.setpoint)
        assert t.robot.state is RobotState.RUNNING
        assert guard.holds > 0 and t.robot.motion.refused > 0
        assert guard.cm.bound(held, guard.verdict.q) < 0.5 * guard.verdict.gap  # type: ignore[union-attr]
        t.stream(200, 20.0)
        assert t.robot.data.setpoint == held  # still held
        guard.inline = True  # verdicts again: it re-joins the master (half the velocity limits)
        t.stream(600, 20.0)
        assert t.robot.data.setpoint != held and t.robot.state is RobotState.RUNNING
    finally:
        t.close()


# ------------------------------------------------------------------------------ the model
def model(**cfg: Any) -> CollisionModel:
    from occ.core.assembly import build_hardware

    daemon = load_config(CONFIGS / "ur5.yaml")
    _joints, frame, _pairs = build_hardware(daemon.robot)
    return CollisionModel.build(CollisionConfig(**cfg), daemon.robot.frame, frame)


#: the wrist folded back onto the upper arm
FOLDED = [2.33, -0.32, 2.97, -1.03, -0.2, 3.06]


@pytest.mark.req("SR-COLL-1")
def test_self_collision_is_detected_and_adjacent_links_are_not_pairs() -> None:
    cm = model()
    names = {(cm.links[a].name, cm.links[b].name) for a, b in cm.self_pairs}
    assert ("upper_arm_link", "wrist_3_link") in names
    assert ("upper_arm_link", "forearm_link") not in names  # adjacent
    assert ("wrist_1_link", "wrist_3_link") not in names  # the package's SRDF disables it
    checker = cm.checker()
    assert checker.check(HOME) == []
    hits = checker.check(FOLDED)
    assert hits and hits[0].link == "upper_arm_link" and hits[0].region == "self:wrist_3_link"
    assert hits[0].distance < 0.0
    assert model(self_collision=False).checker().check(FOLDED) == []


@pytest.mark.req("SR-COLL-1")
def test_the_motion_bound_covers_every_link_point() -> None:
    # sampled: how far the links' hull vertices move never exceeds the bound
    cm = model()
    rng = np.random.default_rng(7)
    checker = cm.checker()
    import pinocchio as pin

    def points(q: Any) -> np.ndarray:
        pin.updateGeometryPlacements(cm.model, checker.data, cm.geom, checker.gdata, np.asarray(q))
        out = []
        for i, g in enumerate(cm.geom.geometryObjects):
            geo = g.geometry
            if hasattr(geo, "points"):
                pts = np.asarray(geo.points())
                m = checker.gdata.oMg[i]
                out.append(pts @ m.rotation.T + m.translation)
        return np.vstack(out)

    worst = 0.0
    for _ in range(200):
        qa = np.array(HOME) + rng.normal(0.0, 0.8, 6)
        qb = qa + rng.normal(0.0, 0.05, 6)
        moved = float(np.max(np.linalg.norm(points(qb) - points(qa), axis=1)))
        worst = max(worst, moved / cm.bound(qa, qb))
    assert 0.2 < worst <= 1.0


@pytest.mark.req("SR-COLL-3")
def test_a_slicer_polydata_mesh_becomes_a_region_and_a_bad_one_is_refused(monkeypatch) -> None:
    import occ.net.operators as operators

    pauses: list[int] = []  # the build gives the loop thread the interpreter between its parts
    monkeypatch.setattr(operators, "_let_others_run", lambda: pauses.append(1))
    sim = SimRobot(ur5({"margin_mm": 10.0}))
    try:
        guard = sim.robot.collision
        assert guard is not None and guard.cm.regions == ()
        # a box (mm, patient frame) around the wrist at home, six quads
        lo, hi = np.array([560.0, 40.0, 300.0]), np.array([700.0, 200.0, 450.0])
        corners = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        quads = ((0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3))
        box = igtl.PolyDataMessage(
            points=corners.astype(np.float32),
            polygons=quads,
            device_name="Tumour",
            header_version=2,
            metadata={"kind": "forbidden-region"},
        )
        op = sim.peer("operator")
        op.send(box)
        sim.step(2)  # built on the desk's worker: defined when built
        assert wait_until(lambda: guard.cm.regions)
        (region,) = guard.cm.regions
        assert region.name == "Tumour" and region.kind == "mesh"
        assert pauses  # it paused at least once while building
        # taken, so not refused: the asker is told nothing about it
        assert not [m for m in op.messages() if "Tumour" in str(getattr(m, "metadata", {}))
                    or "Tumour" in getattr(m, "status_message", "")]  # fmt: skip
        hits = guard.cm.checker().check(HOME, sim.robot.data.base)
        assert {h.region for h in hits} == {"Tumour"}, hits
        assert {"wrist_3_link", "ee_link"} <= {h.link for h in hits}, hits
        # the same node again, empty: removed
        op.send(
            igtl.PolyDataMessage(
                points=np.zeros((0, 3), np.float32),
                device_name="Tumour",
                header_version=2,
                metadata={"kind": "forbidden-region"},
            )
        )
        sim.step(2)
        assert wait_until(lambda: guard.cm.regions == ())
        # a polygon that points past the mesh's points: refused with the reason, nothing changes
        bad = igtl.PolyDataMessage(
            points=corners.astype(np.float32),
            polygons=((0, 1, 9),),
            device_name="Bad",
            header_version=2,
            metadata={"kind": "forbidden-region"},
        )
        op.send(bad)
        sim.step(2)

        def errors() -> list[Any]:
            return [
                m
                for m in op.messages()
                if "missing point" in str(getattr(m, "metadata", {}))
                or "missing point" in getattr(m, "status_message", "")
            ]

        assert wait_until(errors) and guard.cm.regions == ()
        # a Markups plane (TRANSFORM) and a point list: a half-space and spheres
        plane = np.eye(4)
        plane[:3, 3] = (0.0, 0.0, 560.0)
        plane[:3, 2] = (0.0, 0.0, -1.0)
        plane[:3, 1] = (0.0, -1.0, 0.0)
        op.send(
            igtl.TransformMessage.from_matrix(
                plane,
                device_name="Ceiling",
                header_version=2,
                metadata={"kind": "forbidden-region"},
            )
        )
        sim.step(2)
        assert [r.kind for r in guard.cm.regions] == ["plane"]
    finally:
        sim.close()


def test_regions_from_other_messages_are_not_regions() -> None:
    msg = igtl.TransformMessage.from_matrix(
        np.eye(4), device_name="Base", header_version=2, metadata={"kind": "plane"}
    )
    assert regions_from_event(event_of(msg)) is None


# ------------------------------------------------------------------------------ config
@pytest.mark.parametrize(
    ("collision", "message"),
    [
        ({"margin_mm": -1}, "safety.collision.margin_mm"),
        (
            {"regions": [{"name": "p", "kind": "plane", "normal": [0, 0, 0]}]},
            "safety.collision.regions[0].normal: must not be zero",
        ),
        (
            {"regions": [{"name": "m", "kind": "mesh"}]},
            "safety.collision.regions[0].file: required for a mesh region",
        ),
        ({"regions": [CEILING, CEILING]}, "safety.collision.regions[1].name: duplicate region"),
        (
            {"regions": [{**CEILING, "exclude_links": ["base_lnk"]}]},
            "safety.collision.regions[0].exclude_links[0]: no link 'base_lnk' in the URDF",
        ),
        (
            {"regions": [{"name": "s", "kind": "sphere", "radus_mm": 3}]},
            "safety.collision.regions[0].radus_mm",
        ),
    ],
)
def test_config_errors_have_their_lines(
    tmp_path: Path, collision: dict[str, Any], message: str
) -> None:
    path = tmp_path / "arm.yaml"
    path.write_text(yaml.safe_dump(ur5(collision), sort_keys=False))
    with pytest.raises(ConfigError) as err:
        load_config(path)
    text = str(err.value)
    assert message in text, text
    assert "arm.yaml:" in text  # FILE:LINE


def test_an_excluded_link_the_urdf_does_not_have_is_an_error() -> None:
    with pytest.raises(ConfigError, match="exclude_links: no link 'gripper'"):
        model(regions=[{**CEILING, "exclude_links": ["gripper"]}])


def test_a_urdf_without_collision_geometry_gets_capsules() -> None:
    from occ.core.assembly import build_hardware

    daemon = load_config(CONFIGS / "slave.yaml")
    _j, frame, _p = build_hardware(daemon.robot)
    cm = CollisionModel.build(
        CollisionConfig(
            link_radius_mm=5.0, regions=[{"name": "b", "kind": "sphere", "radius_mm": 5.0}]
        ),
        daemon.robot.frame,
        frame,
    )
    assert cm.geom.ngeoms >= 2 and cm.self_pairs == ()
    assert all(type(g.geometry).__name__ == "Capsule" for g in cm.geom.geometryObjects)
    assert math.isfinite(cm.checker().clearance([0.0, 0.0, 0.0])[1])


@pytest.mark.req("SR-COLL-2")
def test_the_guard_on_its_worker_thread_gives_verdicts_the_loop_admits_by() -> None:
    from occ.kinematics.collision import CollisionGuard
    from occ_testkit.testing import wait_until

    cm = model(regions=[CEILING])
    guard = CollisionGuard(cm, inline=False, name="test-collision")
    guard.start()
    try:
        base = np.eye(4)
        assert not guard.admit(HOME, base)  # no verdict yet: hold
        guard.publish(HOME, base)
        assert wait_until(lambda: guard.fresh is not None, 10.0)
        assert guard.verdict is None and not guard.admit(HOME, base)  # not the loop's yet
        guard.take()  # the loop takes it (after_control)
        v = guard.verdict
        assert v is not None and v.q == tuple(HOME) and 0.010 < v.gap < 0.020
        assert guard.admit(HOME, base)
        # within half the clearance: admitted; beyond it: held until a verdict covers it
        step = 0.4 * v.gap / cm.reach[1]
        near = list(HOME)
        near[1] -= step
        far = list(HOME)
        far[1] -= 2.0 * step
        assert guard.admit(near, base) and not guard.admit(far, base)
        assert not guard.admit(HOME, np.diag([1.0, 1.0, 1.0, 1.0]) + 0.001)  # another base
        guard.on_running(True)
        guard.publish(RAISED, base)  # the forearm through the ceiling
        assert wait_until(lambda: guard.fresh is not None and guard.fresh.q == tuple(RAISED))
        assert guard.poll() is None  # the loop has not taken it
        guard.take()
        why = guard.poll()
        assert why is not None and "forearm_link" in why and "ceiling" in why
        assert guard.poll() is None  # once per verdict
    finally:
        guard.stop()


def test_a_mesh_region_from_a_file(tmp_path: Path) -> None:
    # two triangles (mm) making a lid at z = 450 mm over the arm: an STL file
    square = [((-200, -300, 450), (700, -300, 450), (-200, 300, 450)),
              ((700, -300, 450), (700, 300, 450), (-200, 300, 450))]  # fmt: skip
    facets = "".join(
        "facet normal 0 0 1\n outer loop\n"
        + "".join(f"  vertex {x} {y} {zz}\n" for x, y, zz in tri)
        + " endloop\nendfacet\n"
        for tri in square
    )
    stl = tmp_path / "lid.stl"
    stl.write_text(f"solid lid\n{facets}endsolid lid\n")
    cm = model(regions=[{"name": "lid", "kind": "mesh", "file": str(stl)}])
    (region,) = cm.regions
    assert region.kind == "mesh"
    hits = cm.checker().check(RAISED)
    assert hits and {h.region for h in hits} == {"lid"}
    assert cm.checker().check([0.0, -0.6, 1.0, -1.9, -1.57, 0.0]) == []


@pytest.mark.req("SR-COLL-1")
def test_the_path_check_places_the_arm_where_its_base_is() -> None:
    """The whole-arm check of a plan takes the robot's base pose: the raise whose forearm
    crosses the ceiling with the base at the origin clears it with the base 300 mm lower (the
    regions stay where they are in the world), and is refused again back at the origin."""
    sim = keyframe_robot({"margin_mm": 10.0, "regions": [CEILING]}, keyframes=raise_keyframes())
    try:
        command(sim, "Enable")
        lowered = np.eye(4)
        lowered[2, 3] = -0.3
        sim.robot.data.base = lowered
        reply = command(sim, "KeyframePlan")
        assert reply["Status"] == "SUCCESS", reply
        sim.robot.data.base = np.eye(4)
        reply = command(sim, "KeyframePlan")
        assert reply["Status"] == "FAIL" and "forbidden region 'ceiling'" in reply["Error"]
    finally:
        sim.close()


# ------------------------------------------------------------------------------ the desk
def region_points(name: str, *radius: str) -> igtl.PointMessage:
    """A Markups point list from 3D Slicer marked as a forbidden region (far from the arm)."""
    meta = {"kind": "forbidden-region", **({"radius": radius[0]} if radius else {})}
    return igtl.PointMessage(
        points=(igtl.PointElement(name="p", position=(0.0, 0.0, -900.0), radius=5.0),),
        device_name=name,
        header_version=2,
        metadata=meta,
    )


def statuses(op: Any) -> list[str]:
    return [m.status_message for m in op.messages("STATUS") if m.code != int(igtl.StatusCode.OK)]


@pytest.mark.req("SR-COLL-3")
def test_a_region_from_slicer_is_defined_and_voids_a_plan_not_yet_acknowledged() -> None:
    """The operator desk (occ/net/operators.py ``_collision_region``): a forbidden region from
    3D Slicer replaces the node's definition in the collision model, a checked plan that was
    not yet acknowledged must be planned again (its Ack refused, saying why), the region is
    never taken as keyframes; one that cannot be used is refused to its sender with the
    reason and changes nothing; a node sent again replaces its own definition only; a robot
    that checks no collisions refuses every region."""
    low = [0.3, -1.1, 1.6, -2.0, -1.57, 0.2]
    sim = keyframe_robot({"margin_mm": 10.0}, keyframes=[{"t": 2.0, "pose": low, "name": "low"}])
    try:
        command(sim, "Enable")
        command(sim, "Run")
        reply = command(sim, "KeyframePlan")
        assert reply["Status"] == "SUCCESS", reply
        plan_id = reply["Message"].split(":")[0].split()[1]
        sim.step(150)  # the preview goes out
        guard = sim.robot.collision
        assert guard is not None and guard.cm.regions == ()
        op = sim.test_operator  # type: ignore[attr-defined]
        op.send(region_points("Vessel"))
        sim.step(2)
        (region,) = guard.cm.regions
        assert (region.name, region.kind, region.source) == ("Vessel:0", "sphere", "Vessel")
        assert statuses(op) == []  # taken, not refused (and not keyframes)
        kf = sim.robot.controller.controllers[0]
        assert kf.status == (
            f"plan {plan_id} invalidated: the forbidden region 'Vessel' changed; plan again"
        )
        ack = command(sim, "KeyframeAck", Plan=plan_id)
        assert ack["Status"] == "FAIL", ack
        # planned again: the stored keyframes are still the YAML's, not the region's point
        reply = command(sim, "KeyframePlan")
        assert reply["Status"] == "SUCCESS", reply
        plan = reply["Message"]
        assert plan.startswith("plan 2: 1 keyframes (joint, linear, stop), 2.000 s"), plan
        # a region that cannot be used: refused with the reason, nothing changes
        op.send(region_points("Bad", "wide"))
        sim.step(2)
        assert statuses(op) == ["region 'Bad': radius 'wide' is no number"]
        assert [r.source for r in guard.cm.regions] == ["Vessel"]
        assert sim.robot.state is RobotState.RUNNING
        assert sim.robot.snapshot()["collision"] == guard.stats()  # GetStats
    finally:
        sim.close()
    # a teleoperated arm (its controller has no plan to void): each node its own definition
    tele = SimRobot(ur5({"margin_mm": 10.0}))
    try:
        guard = tele.robot.collision
        assert guard is not None
        op = tele.peer("operator")
        for name in ("Vessel", "Nerve", "Vessel"):
            op.send(region_points(name))
            tele.step(2)
        assert sorted(r.source for r in guard.cm.regions) == ["Nerve", "Vessel"]
        assert statuses(op) == [] and tele.robot.state is RobotState.READY
    finally:
        tele.close()
    plain = SimRobot(ur5(None))
    try:
        assert plain.robot.collision is None
        op = plain.peer("operator")
        op.send(region_points("Vessel"))
        plain.step(2)
        assert statuses(op) == [
            "region 'Vessel': this robot checks no collisions (config safety.collision)"
        ]
        assert plain.robot.state is RobotState.READY
    finally:
        plain.close()
