"""Arm against arm (issue 40, item 3; occ/kinematics/collision.py, occ/kinematics/peers.py;
docs/SAFETY.md SR-ARMS-1..3).

Two UR5 (configs/ur5.yaml) face each other, bases 1.6 m apart along x (the second turned half
round, its wrist on the first's line): at home they are well apart, stretched out they overlap.

- The peer arm's geometry from its ``frame:`` configuration by the own arm's rules (hulls or
  meshes, the capsules' radius, its base link); a peer that cannot be used is refused; its
  pairs are lower bounds of coal's distances, exact near, each counted once; ``arm_distance``
  (the cell's plan check) names the nearest pair at the state it is given; a peer is placed
  once per state.
- The guard: an arm never heard of, or heard of too long ago, holds and says why; a peer that
  left the cell is no longer checked; what the peer can have moved since its state counts
  against half the clearance; a new verdict only when due (at exactly a quarter used); a state
  exactly ``stale_s`` old is not stale; the arms' epoch never comes back.
- Two guards fed each other's states in simulated time, driven toward each other at their
  velocity limits: both stop, never closer than half the margin; the same with two robots
  whose keyframe plans, each checked against the other standing at home, run into each other.
- A plan into the other arm's current envelope is refused naming both links.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import coal
import numpy as np
import pinocchio as pin
import pytest
import yaml

from occ.config import CollisionConfig, FrameConfig
from occ.core.assembly import build_hardware
from occ.core.loader import load_config
from occ.core.safety import RobotState
from occ.errors import ConfigError
from occ.kinematics import collision
from occ.kinematics.collision import (
    STALE_S,
    CollisionGuard,
    CollisionModel,
    Contact,
    PeerState,
    Verdict,
    plane_region,
    sphere_region,
)
from occ_testkit.cellarms import PeerFeed
from occ_testkit.testing import CONFIGS, SimRobot
from tests.occ.test_collision_model import MOUNTED

HOME = [0.0, -1.2, 1.5, -1.9, -1.57, 0.0]
#: stretched out along the base's x: the tip ~0.89 m out
REACH = [0.0, -0.3, 0.3, -1.57, -1.57, 0.0]
UR5 = load_config(CONFIGS / "ur5.yaml").robot
UR5_FRAME = build_hardware(UR5)[1]
VEL = [1.0] * 6  # configs/ur5.yaml's limits (its URDF says 3.15-3.2 rad/s)
PERIOD = 1e-3


def b_base() -> np.ndarray:
    """The second arm: 1.6 m along x, turned half round, its wrist on the first's line."""
    b = np.eye(4)
    b[:3, :3] = np.diag([-1.0, -1.0, 1.0])
    b[:3, 3] = [1.6, 0.218, 0.0]
    return b


def model(margin_mm: float = 20.0, **cfg: Any) -> CollisionModel:
    return CollisionModel.build(CollisionConfig(margin_mm=margin_mm, **cfg), UR5.frame, UR5_FRAME)


def pair_model(margin_mm: float = 20.0) -> CollisionModel:
    cm = model(margin_mm)
    cm.add_peer("ur5-b", UR5.frame, velocities=VEL)
    return cm


def brute(cm: CollisionModel, q: Any, base: Any, peer_q: Any, peer_base: Any) -> float:
    """The smallest distance from any own link to any peer link, by coal, no broad phase."""

    def placed(model: Any, geom: Any, q: Any, world: pin.SE3) -> list[Any]:
        data, gdata = model.createData(), pin.GeometryData(geom)
        pin.updateGeometryPlacements(model, data, geom, gdata, np.asarray(q, dtype=float))
        return [coal.Transform3s(world * m) for m in gdata.oMg]

    (arm,) = cm.peers
    own_world = pin.SE3(base) * cm.base_inv if cm.base_inv is not None else pin.SE3(base)
    peer_world = pin.SE3(peer_base)
    if arm.arm.base_inv is not None:
        peer_world = peer_world * arm.arm.base_inv
    a = placed(cm.model, cm.geom, q, own_world)
    b = placed(arm.arm.model, arm.arm.geom, peer_q, peer_world)
    best = math.inf
    for i, ga in enumerate(cm.geom.geometryObjects):
        for j, gb in enumerate(arm.arm.geom.geometryObjects):
            res = coal.DistanceResult()
            d = coal.distance(ga.geometry, a[i], gb.geometry, b[j], coal.DistanceRequest(), res)
            best = min(best, d)
    return best


# ------------------------------------------------------------------------------ the model
@pytest.mark.req("SR-ARMS-1")
def test_a_peer_arm_is_built_from_its_frame_config_by_the_own_arms_rules() -> None:
    cm = model()
    arm = cm.add_peer("ur5-b", UR5.frame, velocities=VEL)
    assert [lk.name for lk in arm.arm.links] == [lk.name for lk in cm.links]
    # hulls like the own arm's (its meshes made convex), the same reach
    own_kinds = [type(g.geometry).__name__ for g in cm.geom.geometryObjects]
    assert [type(g.geometry).__name__ for g in arm.arm.geom.geometryObjects] == own_kinds
    assert arm.arm.reach == pytest.approx(cm.reach)
    assert arm.speed == pytest.approx(sum(cm.reach))  # 1 rad/s each
    assert cm.peer_epoch == 1 and cm.peer("ur5-b") is arm
    # without velocities: its URDF's
    other = cm.add_peer("ur5-c", UR5.frame)
    urdf_v = [float(v) for v in other.arm.model.velocityLimit]
    assert urdf_v == pytest.approx([3.15, 3.15, 3.15, 3.2, 3.2, 3.2])
    assert other.speed == pytest.approx(sum(v * r for v, r in zip(urdf_v, cm.reach, strict=True)))
    # a tool on the peer: one more link
    tooled = cm.add_peer("ur5-d", UR5.frame, velocities=VEL, tool=(0.2, 0.005))
    assert tooled.arm.links[-1].name == "tool"
    assert set(cm.describe()["peers"]) == {"ur5-b", "ur5-c", "ur5-d"}
    assert cm.describe()["peers"]["ur5-b"] == {
        "links": [lk.name for lk in cm.links],
        "speed_m_s": round(arm.speed, 4),
        "present": True,
        "t": None,
    }


@pytest.mark.req("SR-ARMS-1")
def test_a_peer_arm_or_a_state_that_cannot_be_used_is_refused() -> None:
    cm = pair_model()
    for bad in ("", "a:b", "self", "two words"):
        with pytest.raises(ConfigError, match="a name without"):
            cm.add_peer(bad, UR5.frame, velocities=VEL)
    with pytest.raises(ConfigError, match="already added"):
        cm.add_peer("ur5-b", UR5.frame, velocities=VEL)
    with pytest.raises(ConfigError, match="5 velocity limits for 6 joints"):
        cm.add_peer("x", UR5.frame, velocities=VEL[:5])
    with pytest.raises(ConfigError, match="must be a number > 0"):
        cm.add_peer("x", UR5.frame, velocities=[1.0] * 5 + [0.0])
    guard = CollisionGuard(cm, inline=True)
    guard.peer_update("ur5-b", HOME, b_base(), 1.0)
    arm = cm.peer("ur5-b")
    kept = arm.state
    with pytest.raises(ValueError, match="no peer arm 'ur5-z' \\(peer arms: ur5-b\\)"):
        guard.peer_update("ur5-z", HOME, b_base(), 1.0)
    with pytest.raises(ValueError, match="5 positions for 6 joints"):
        guard.peer_update("ur5-b", HOME[:5], b_base(), 1.0)
    with pytest.raises(ValueError, match="not finite"):
        guard.peer_update("ur5-b", [math.nan, *HOME[1:]], b_base(), 1.0)
    with pytest.raises(ValueError, match="not finite"):
        guard.peer_update("ur5-b", HOME, b_base(), math.inf)
    with pytest.raises(ValueError, match="finite 4x4"):
        guard.peer_update("ur5-b", HOME, np.eye(3), 1.0)
    assert arm.state is kept and cm.peer_epoch == 1  # nothing changed
    with pytest.raises(ValueError, match="no peer arm"):
        guard.peer_gone("ur5-z")


@pytest.mark.req("SR-ARMS-1")
def test_every_pair_with_a_peer_is_a_lower_bound_of_coal_and_exact_near() -> None:
    cm = pair_model()
    arm = cm.peer("ur5-b")
    checker = cm.checker()
    rng = np.random.default_rng(4)
    near_seen = 0
    for _ in range(40):
        q = np.array(REACH) + rng.normal(0.0, 0.25, 6)
        pq = np.array(REACH) + rng.normal(0.0, 0.25, 6)
        arm.update(pq, b_base(), 0.0)
        checker.clearance(q, np.eye(4))
        ((seen, st, d),) = checker.peer_seen
        assert seen is arm and st is arm.state
        exact = brute(cm, q, np.eye(4), pq, b_base())
        assert d <= exact + 1e-9
        if exact <= cm.margin + 0.05:  # near: coal's own number
            near_seen += 1
            assert d == pytest.approx(exact, abs=1e-9)
    assert near_seen > 5
    # a peer that left is not checked; one never heard of is seen as unknown
    arm.gone()
    checker.clearance(REACH, np.eye(4))
    assert checker.peer_seen == []
    arm.present = True
    checker.clearance(REACH, np.eye(4))
    assert checker.peer_seen == [(arm, None, math.inf)]


@pytest.mark.req("SR-ARMS-1")
def test_a_contact_with_another_arm_names_both_links() -> None:
    c = Contact("wrist_3_link", "arm:ur5-b:forearm_link", 0.004)
    assert c.pair == "wrist_3_link vs ur5-b:forearm_link"
    assert c.describe() == (
        "link 'wrist_3_link' is 4.00 mm from link 'forearm_link' of the arm 'ur5-b' "
        "(wrist_3_link vs ur5-b:forearm_link)"
    )
    assert Contact("a", "arm:b:c", -0.001).describe().startswith("link 'a' penetrates link 'c'")
    assert Contact("a", "self:b", 0.0).pair == "a vs b"
    assert Contact("a", "ceiling", 0.0).pair == "a vs ceiling"
    # a link name with a colon (a tf prefix): the arm's name never has one
    assert Contact("a", "arm:ur5-b:left:flange", 0.002).describe() == (
        "link 'a' is 2.00 mm from link 'left:flange' of the arm 'ur5-b' (a vs ur5-b:left:flange)"
    )


def named_distances(
    cm: CollisionModel, arm: Any, q: Any, base: Any, st: PeerState
) -> dict[tuple[str, str], float]:
    """Every (own link, peer link) distance, by coal, no broad phase, the peer at ``st``."""

    def placed(model: Any, geom: Any, q: Any, world: pin.SE3) -> list[Any]:
        data, gdata = model.createData(), pin.GeometryData(geom)
        pin.updateGeometryPlacements(model, data, geom, gdata, np.asarray(q, dtype=float))
        return [coal.Transform3s(world * m) for m in gdata.oMg]

    own_world = pin.SE3(base) * cm.base_inv if cm.base_inv is not None else pin.SE3(base)
    peer_world = pin.SE3(st.base)
    if arm.arm.base_inv is not None:
        peer_world = peer_world * arm.arm.base_inv
    a = placed(cm.model, cm.geom, q, own_world)
    b = placed(arm.arm.model, arm.arm.geom, st.q, peer_world)
    out = {}
    for i, ga in enumerate(cm.geom.geometryObjects):
        for j, gb in enumerate(arm.arm.geom.geometryObjects):
            res = coal.DistanceResult()
            d = coal.distance(ga.geometry, a[i], gb.geometry, b[j], coal.DistanceRequest(), res)
            out[(cm.links[i].name, arm.arm.links[j].name)] = d
    return out


def shifted(base: np.ndarray) -> np.ndarray:
    """``base`` moved 0.4 m along y and 0.1 m down: neither arm stands at the origin."""
    out = np.eye(4)
    out[:3, 3] = [0.0, 0.4, -0.1]
    return out @ base


@pytest.mark.req("SR-ARMS-1")
def test_arm_distance_is_the_nearest_pair_of_the_two_arms_at_the_state_given() -> None:
    """The cell's plan check asks one arm at a configuration against another at a planned
    state: the smallest distance (a lower bound where far, coal's own number near) and the
    nearest pair, no regions and no self pairs, every pair counted once."""
    cm = pair_model()
    cm.define("t", [sphere_region("s", [0.0, 400.0, -100.0], 50.0)])  # around the own base
    arm = cm.peer("ur5-b")
    arm.update(HOME, b_base(), 0.0)  # its last known state: not the one asked
    checker = cm.checker()
    n_pairs = len(cm.links) * len(arm.arm.links)
    own_base, peer_base = shifted(np.eye(4)), shifted(b_base())
    rng = np.random.default_rng(11)
    near_seen = 0
    for _ in range(25):
        q = np.array(REACH) + rng.normal(0.0, 0.25, 6)
        st = PeerState(tuple(np.array(REACH) + rng.normal(0.0, 0.25, 6)), peer_base, 0.0)
        d, c = checker.arm_distance(q.tolist(), own_base, arm, st)
        truth = named_distances(cm, arm, q, own_base, st)
        nearest = min(truth, key=lambda k: truth[k])
        assert c is not None and c.distance == d and c.region.startswith("arm:ur5-b:")
        assert d <= truth[nearest] + 1e-9
        assert checker.exact + checker.bounded == n_pairs
        assert checker.exact >= sum(e <= cm.margin + 0.05 for e in truth.values())
        if truth[nearest] <= cm.margin + 0.05:
            near_seen += 1
            assert d == pytest.approx(truth[nearest], abs=1e-9)
            assert (c.link, c.region) == (nearest[0], f"arm:ur5-b:{nearest[1]}")
    assert near_seen > 3
    # far apart: every pair settled by the balls, the nearest balls' pair named
    far = PeerState(tuple(HOME), shifted(b_base()) @ _moved(-5.0), 0.0)
    d, c = checker.arm_distance(HOME, own_base, arm, far)
    truth = named_distances(cm, arm, HOME, own_base, far)
    assert (checker.exact, checker.bounded) == (0, n_pairs)
    assert c is not None and c.distance == d and 3.0 < d <= min(truth.values())


def _moved(x: float) -> np.ndarray:
    out = np.eye(4)
    out[0, 3] = x
    return out


@pytest.mark.req("SR-ARMS-1")
def test_with_every_pair_near_each_is_coal_s_distance_and_the_counts_add_up() -> None:
    """A margin of two metres: every pair of the two arms is near and computed by coal; the
    clearance counts each pair of regions, own links and the peer's links once."""
    cm = pair_model(margin_mm=2000.0)
    arm = cm.peer("ur5-b")
    checker = cm.checker()
    st = PeerState(tuple(REACH), b_base(), 0.0)
    d, c = checker.arm_distance(HOME, np.eye(4), arm, st)
    truth = named_distances(cm, arm, HOME, np.eye(4), st)
    nearest = min(truth, key=lambda k: truth[k])
    n_pairs = len(cm.links) * len(arm.arm.links)
    assert (checker.exact, checker.bounded) == (n_pairs, 0)
    assert d == pytest.approx(truth[nearest], abs=1e-9) and c == Contact(
        nearest[0], f"arm:ur5-b:{nearest[1]}", d
    )
    # regions, self pairs and the peer in one clearance: every pair once, some far, some near
    cm = pair_model()
    cm.define("t", [plane_region("ceiling", (0.0, 0.0, 560.0), (0.0, 0.0, -1.0))])
    arm = cm.peer("ur5-b")
    arm.update(REACH, b_base(), 0.0)
    checker = cm.checker()
    checker.clearance(REACH, np.eye(4))
    n_links = len(cm.links)
    total = n_links + len(cm.self_pairs) + n_links * len(arm.arm.links)
    assert checker.exact + checker.bounded == total
    assert checker.exact > 1 and checker.bounded > 1
    # only the peer, far: the clearance's slack is its lower bound less the margin
    cm = model(self_collision=False)
    arm = cm.add_peer("ur5-b", UR5.frame, velocities=VEL)
    arm.update(HOME, b_base() @ _moved(-3.0), 0.0)
    slack, gap, worst = cm.checker().clearance(HOME, np.eye(4))
    assert worst is not None and worst.region.startswith("arm:ur5-b:")
    assert 2.0 < gap == worst.distance and slack == gap - cm.margin


@pytest.mark.req("SR-ARMS-1")
def test_a_peer_takes_the_configured_link_radius_and_meshes_and_stands_on_its_base_link(
    tmp_path: Path,
) -> None:
    """The own arm's ``convex: false`` and ``link_radius_mm`` make the peers' geometry too;
    a peer whose base link is not its URDF's root (a plate 0.3 m up, turned; no collision
    geometry: capsules) is placed from that link, as coal finds it placed by hand."""
    urdf = tmp_path / "mounted.urdf"
    urdf.write_text(MOUNTED)
    cm = model(margin_mm=2000.0, convex=False, link_radius_mm=12.0)
    ur5b = cm.add_peer("ur5-b", UR5.frame, velocities=VEL)
    kinds = [type(g.geometry).__name__ for g in ur5b.arm.geom.geometryObjects]
    assert "BVHModelOBBRSS" in kinds and "Convex" not in kinds  # the meshes as they are
    fc = FrameConfig(urdf=urdf, tip_link="tip", base_link="plate")
    mnt = cm.add_peer("mnt", fc, velocities=[1.0, 1.0])
    caps = [g.geometry for g in mnt.arm.geom.geometryObjects]
    assert [type(g).__name__ for g in caps] == ["Capsule"] * 3
    assert [g.radius for g in caps] == [0.012] * 3
    assert mnt.arm.base_inv is not None and np.linalg.norm(mnt.arm.base_inv.translation) > 0.3
    checker = cm.checker()
    for q, pq in (([0.3, -1.0, 1.2, -1.0, 0.5, 0.0], [0.4, -0.7]), (HOME, [-1.0, 0.9])):
        st = PeerState(tuple(pq), shifted(np.eye(4)), 0.0)
        d, c = checker.arm_distance(q, np.eye(4), mnt, st)
        truth = named_distances(cm, mnt, q, np.eye(4), st)
        nearest = min(truth, key=lambda k: truth[k])
        assert d == pytest.approx(truth[nearest], abs=1e-9)
        assert c is not None and (c.link, c.region) == (nearest[0], f"arm:mnt:{nearest[1]}")


@pytest.mark.req("SR-ARMS-1")
def test_a_peer_is_placed_once_per_state_and_its_data_made_once_per_checker(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """What the broad phase promises for its cost: a peer's links are placed once per state
    it is checked at, however many checks use that state, and its pinocchio data and balls
    are made once per checker."""
    cm = pair_model()
    arm = cm.peer("ur5-b")
    placed: list[Any] = []
    balls: list[Any] = []
    real_place, real_balls = pin.updateGeometryPlacements, collision._balls

    def place(model: Any, *rest: Any) -> Any:
        if model is arm.arm.model:
            placed.append(rest[-1])
        return real_place(model, *rest)

    def count_balls(objs: Any) -> Any:
        balls.append(objs)
        return real_balls(objs)

    monkeypatch.setattr(pin, "updateGeometryPlacements", place)
    monkeypatch.setattr(collision, "_balls", count_balls)
    checker = cm.checker()
    assert len(balls) == 1  # the own arm's
    arm.update(REACH, b_base(), 0.0)
    for q in (HOME, REACH, HOME):
        checker.clearance(q, np.eye(4))
    assert len(placed) == 1 and len(balls) == 2
    st = PeerState(tuple(HOME), b_base(), 0.0)
    first = checker.arm_distance(REACH, np.eye(4), arm, st)
    assert checker.arm_distance(REACH, np.eye(4), arm, st) == first
    assert len(placed) == 2 and len(balls) == 2
    arm.update(HOME, b_base(), 0.001)  # a new state (the same place): placed again
    checker.clearance(HOME, np.eye(4))
    assert len(placed) == 3 and len(balls) == 2
    assert cm.checker() is not checker and len(balls) == 3  # a new checker: its own


# ------------------------------------------------------------------------------ the guard
@pytest.mark.req("SR-ARMS-2")
def test_an_arm_unknown_or_stale_holds_and_says_why_and_one_gone_is_not_checked() -> None:
    cm = pair_model()
    guard = CollisionGuard(cm, inline=True)
    eye = np.eye(4)
    guard.publish(HOME, eye, 1.0)
    assert not guard.admit(HOME, eye, 1.001)
    assert guard.held_for == "the arm 'ur5-b': where it is is unknown (an unknown obstacle)"
    assert guard.peer_problem(1.001) == guard.held_for
    guard.peer_update("ur5-b", HOME, b_base(), 1.001)
    assert guard.peer_problem(1.001) is None
    guard.publish(HOME, eye, 1.001)  # due: a state for an arm the verdict did not know
    assert guard.verdicts == 2 and guard.admit(HOME, eye, 1.002)
    # no update for longer than stale_s: an unknown obstacle again
    late = 1.001 + STALE_S + 0.001
    assert not guard.admit(HOME, eye, late)
    assert guard.held_for == (
        "the arm 'ur5-b': its state is 51 ms old (stale after 50 ms): an unknown obstacle"
    )
    assert guard.peer_problem(late) == guard.held_for
    guard.peer_update("ur5-b", HOME, b_base(), late)
    guard.publish(HOME, eye, late)
    assert guard.admit(HOME, eye, late + 0.001)
    # it leaves the cell: this verdict is for another set of arms (hold), the next one
    # checks no arm and nothing holds for it
    guard.peer_gone("ur5-b")
    assert not guard.admit(HOME, eye, late + 0.002)
    assert guard.held_for == "no verdict for these regions and arms yet"
    guard.publish(HOME, eye, late + 0.002)
    assert guard.verdict is not None and guard.verdict.peers == ()
    assert guard.admit(HOME, eye, late + 10.0) and guard.peer_problem(late + 10.0) is None
    # and comes back: checked again before anything is admitted
    guard.peer_update("ur5-b", HOME, b_base(), late + 10.0)
    assert not guard.admit(HOME, eye, late + 10.0)
    guard.publish(HOME, eye, late + 10.0)
    assert len(guard.verdict.peers) == 1 and guard.admit(HOME, eye, late + 10.001)  # type: ignore[union-attr]
    st = guard.stats()
    assert st["stale_s"] == STALE_S and st["peers"]["ur5-b"]["present"] is True


@pytest.mark.req("SR-ARMS-2")
def test_what_the_peer_can_have_moved_since_its_state_counts_against_half_the_clearance() -> None:
    cm = pair_model()
    arm = cm.peer("ur5-b")
    guard = CollisionGuard(cm, inline=True, stale_s=10.0)
    eye = np.eye(4)
    guard.peer_update("ur5-b", REACH, b_base(), 2.0)  # measured at t = 2.0
    guard.publish(HOME, eye, 2.0)
    v = guard.verdict
    assert v is not None
    ((seen, st, d),) = v.peers
    assert seen is arm and st is arm.state and d < v.gap  # the arm is the nearest
    assert v.clearance == d
    # standing still, the own arm is admitted while the peer's possible motion since 2.0 is
    # under half that distance
    t_edge = 2.0 + 0.5 * d / arm.speed
    assert guard.admit(HOME, eye, t_edge - 1e-6)
    assert not guard.admit(HOME, eye, t_edge + 1e-6)
    assert guard.held_for == "the arm 'ur5-b' may have moved into half the last clearance"
    # the own motion and the peer's add up
    step = 0.25 * d / cm.reach[0]
    moved = [HOME[0] + step, *HOME[1:]]
    t_quarter = 2.0 + 0.25 * d / arm.speed
    assert guard.admit(moved, eye, t_quarter - 1e-6)
    assert not guard.admit(moved, eye, t_quarter + 1e-6)
    # without a time nothing can be aged: held
    assert not guard.admit(HOME, eye)
    assert guard.held_for == "no time to age the other arms' states by"
    # a hand-made verdict: a state of t = 0, at 0.5 s: exactly half of the distance is held
    old = PeerState(tuple(REACH), b_base(), 0.0)
    for d_half, ok in ((arm.speed * 0.5, False), (arm.speed * 0.5 * (1 + 1e-9), True)):
        peers = ((arm, old, 2.0 * d_half),)
        guard.verdict = Verdict(tuple(HOME), eye, 1.0, 10.0, None, cm.version, peers, 1)
        assert guard.admit(HOME, eye, 0.5) is ok


@pytest.mark.req("SR-ARMS-2")
def test_a_new_verdict_is_due_only_when_something_changed_or_a_quarter_is_used() -> None:
    cm = pair_model()
    arm = cm.peer("ur5-b")
    guard = CollisionGuard(cm, inline=True, stale_s=10.0)
    eye = np.eye(4)
    guard.peer_update("ur5-b", REACH, b_base(), 2.0)
    guard.publish(HOME, eye, 2.0)
    v = guard.verdict
    assert v is not None
    d = v.peers[0][2]
    assert not guard.due(v, HOME, eye, 2.5)  # no newer state: nothing new to check against
    guard.publish(HOME, eye, 2.5)
    assert guard.verdicts == 1 and guard.skipped == 1
    assert d < v.gap  # the arm is the nearest: a quarter of d used by the own motion is due
    toward = [HOME[0] + 0.26 * d / cm.reach[0], *HOME[1:]]
    assert 0.26 * d < 0.25 * v.gap and guard.due(v, toward, eye, 2.0)
    guard.peer_update("ur5-b", REACH, b_base(), 2.0 + 0.1 * d / arm.speed)
    assert not guard.due(v, HOME, eye, 2.0 + 0.2 * d / arm.speed)  # newer, little used
    guard.publish(HOME, eye, 2.0 + 0.2 * d / arm.speed)  # so not checked again
    assert guard.verdicts == 1 and guard.skipped == 2
    assert guard.due(v, HOME, eye, 2.0 + 0.26 * d / arm.speed)
    own = [HOME[0] + 0.26 * v.gap / cm.reach[0], *HOME[1:]]
    assert guard.due(v, own, eye, 2.0)  # the own motion alone
    assert guard.due(v, HOME, b_base(), 2.0)  # another base pose
    cm.define("x", [])
    assert guard.due(v, HOME, eye, 2.0)  # other regions


@pytest.mark.req("SR-ARMS-2")
def test_a_verdict_is_due_at_exactly_a_quarter_of_each_clearance() -> None:
    """Hand-made verdicts at the boundary: the own motion using exactly a quarter of the
    clearance to the regions and own links, or of the distance to the peer, and the two arms'
    possible motion using exactly a quarter since the state the verdict used: due; a hair
    less: covered."""
    cm = pair_model()
    arm = cm.peer("ur5-b")
    arm.update(REACH, b_base(), 1.0)
    st = arm.state
    assert st is not None
    guard = CollisionGuard(cm, inline=True, stale_s=10.0)
    eye = np.eye(4)
    q = [HOME[0] + 0.01, *HOME[1:]]
    own = cm.bound(q, HOME)
    big = 10.0

    def due(gap: float, d: float, seen: PeerState) -> bool:
        peers = ((arm, seen, d),)
        v = Verdict(tuple(HOME), eye, 1.0, gap, None, cm.version, peers, cm.peer_epoch)
        return guard.due(v, q, eye, 1.0)

    assert due(4.0 * own, big, st) and not due(math.nextafter(4.0 * own, big), big, st)
    assert due(big, 4.0 * own, st) and not due(big, math.nextafter(4.0 * own, big), st)
    older = PeerState(st.q, st.base, 0.5)  # the verdict's state; the arm has a newer one
    used = own + arm.speed * (1.0 - older.t)
    assert due(big, 4.0 * used, older) and not due(big, math.nextafter(4.0 * used, 99.0), older)


@pytest.mark.req("SR-ARMS-2")
def test_each_arm_is_looked_at_past_one_that_left_or_is_unknown() -> None:
    """Three arms: one that left the cell or is unknown does not end the look at the others
    (the checker's, the guard's alert, a verdict due for the last one's newer state)."""
    cm = pair_model()
    b = cm.peer("ur5-b")
    c = cm.add_peer("ur5-c", UR5.frame, velocities=VEL)
    guard = CollisionGuard(cm, inline=True, stale_s=10.0)
    eye = np.eye(4)
    far_c = b_base() @ _moved(-3.0)
    b.gone()
    assert guard.peer_problem(1.0) == (
        "the arm 'ur5-c': where it is is unknown (an unknown obstacle)"
    )
    c.update(HOME, far_c, 1.0)
    checker = cm.checker()
    checker.clearance(HOME, eye)
    assert [(a.name, st is c.state) for a, st, _d in checker.peer_seen] == [("ur5-c", True)]
    b.present = True  # back, nothing known of it yet
    checker.clearance(HOME, eye)
    assert [(a.name, st) for a, st, _d in checker.peer_seen][0] == ("ur5-b", None)
    assert [a.name for a, st, d in checker.peer_seen[1:] if st is c.state and d < 9.0] == ["ur5-c"]
    b.update(REACH, b_base(), 2.0)
    c.update(HOME, far_c, 2.0)
    guard.publish(HOME, eye, 2.0)
    v = guard.verdict
    assert v is not None and [a.name for a, _s, _d in v.peers] == ["ur5-b", "ur5-c"]
    dc = v.peers[1][2]
    c.update(HOME, far_c, 2.1)  # newer for the second arm only
    assert guard.due(v, HOME, eye, 2.0 + 0.3 * dc / c.speed)
    assert not guard.due(v, HOME, eye, 2.0 + 0.2 * dc / c.speed)


@pytest.mark.req("SR-ARMS-2")
def test_a_state_is_stale_only_past_stale_s_and_the_hold_says_its_age() -> None:
    cm = pair_model()
    guard = CollisionGuard(cm, inline=True, stale_s=0.25)
    eye = np.eye(4)
    guard.publish(HOME, eye, 1.0)  # the arm unknown to this verdict
    guard.peer_update("ur5-b", HOME, b_base(), 1.0)  # its first state: the same arms
    assert cm.peer_epoch == 1
    assert not guard.admit(HOME, eye, 1.0)  # the verdict did not know where it was
    assert guard.held_for == "the arm 'ur5-b': where it is is unknown (an unknown obstacle)"
    assert guard.peer_problem(1.25) is None  # exactly stale_s old: not stale yet
    stale = "the arm 'ur5-b': its state is {} ms old (stale after 250 ms): an unknown obstacle"
    assert guard.peer_problem(math.nextafter(1.25, 2.0)) == stale.format(250)
    assert guard.peer_problem(2.0) == stale.format(1000)
    assert guard.peer_problem(2.9) == stale.format(1900)


@pytest.mark.req("SR-ARMS-2")
def test_every_change_of_the_cells_arms_voids_the_verdicts_before_it() -> None:
    """The arms' epoch never comes back to a value a verdict may carry: an arm added, one
    that leaves, one that comes back; a verdict for the arms before an addition holds."""
    cm = pair_model()
    guard = CollisionGuard(cm, inline=True, stale_s=10.0)
    eye = np.eye(4)
    epochs = [cm.peer_epoch]
    guard.peer_update("ur5-b", HOME, b_base(), 1.0)
    guard.publish(HOME, eye, 1.0)
    assert guard.admit(HOME, eye, 1.0)
    cm.add_peer("ur5-c", UR5.frame, velocities=VEL)
    epochs.append(cm.peer_epoch)
    assert not guard.admit(HOME, eye, 1.0)
    assert guard.held_for == "no verdict for these regions and arms yet"
    guard.peer_gone("ur5-b")
    epochs.append(cm.peer_epoch)
    guard.peer_update("ur5-b", HOME, b_base(), 1.0)  # back
    epochs.append(cm.peer_epoch)
    guard.peer_gone("ur5-c")
    epochs.append(cm.peer_epoch)
    assert len(set(epochs)) == len(epochs), epochs
    with pytest.raises(ValueError, match=r"^no peer arm 'x' \(peer arms: ur5-b, ur5-c\)$"):
        cm.peer("x")
    with pytest.raises(ValueError, match=r"^no peer arm 'x' \(peer arms: none\)$"):
        model().peer("x")


def drive(
    guards: dict[str, CollisionGuard],
    bases: dict[str, np.ndarray],
    goal: list[float],
    feed: PeerFeed,
    seconds: float,
    judge: CollisionModel,
) -> tuple[dict[str, list[float]], dict[str, str], float]:
    """Both arms from home toward ``goal`` at their velocity limits, a loop each (the order
    of the robot's tick: poll, admit the next step, publish), states exchanged by ``feed``;
    the smallest true distance between them over the run (``judge``: both placed exactly)."""
    q = {name: list(HOME) for name in guards}
    stopped: dict[str, str] = {}
    for name, g in guards.items():
        g.on_running(True)
        feed.add(name, g, lambda n=name: (q[n], bases[n]), lambda k=feed: k.ticks * PERIOD)
    peer = judge.peer("ur5-b")
    checker = judge.checker()
    closest = math.inf
    for k in range(int(seconds / PERIOD)):
        now = k * PERIOD
        feed.tick()
        for name, g in guards.items():
            why = g.poll()
            if why and name not in stopped:
                stopped[name] = why
            if name not in stopped:
                sp = [
                    a + max(-v * PERIOD, min(v * PERIOD, b - a))
                    for a, b, v in zip(q[name], goal, VEL, strict=True)
                ]
                if g.admit(sp, bases[name], now):
                    q[name] = sp
            g.publish(q[name], bases[name], now)
        peer.update(q["ur5-b"], bases["ur5-b"], now)
        checker.clearance(q["ur5-a"], bases["ur5-a"])
        closest = min(closest, checker.peer_seen[0][2])
    return q, stopped, closest


@pytest.mark.req("SR-ARMS-2")
@pytest.mark.parametrize(("every", "age_ms"), [(1, 0.0), (5, 1.0)])
def test_two_arms_driven_toward_each_other_both_stop_with_half_the_margin(
    every: int, age_ms: float
) -> None:
    """Two guards, each fed the other's state (every tick; or every 5 ticks, 1 ms old, as a
    200 Hz heartbeat), both arms driven at their velocity limits to a stretch where they
    overlap: both stop with a collision naming both links, and no two links ever came
    closer than half the margin."""
    margin = 0.02
    guards = {}
    for name, other in (("ur5-a", "ur5-b"), ("ur5-b", "ur5-a")):
        cm = model(margin * 1e3, self_collision=False)
        cm.add_peer(other, UR5.frame, velocities=VEL)
        guards[name] = CollisionGuard(cm, inline=True)
    bases = {"ur5-a": np.eye(4), "ur5-b": b_base()}
    judge = pair_model(margin * 1e3)
    feed = PeerFeed(every=every, age_s=age_ms * 1e-3)
    q, stopped, closest = drive(guards, bases, REACH, feed, 2.0, judge)
    assert set(stopped) == {"ur5-a", "ur5-b"}, stopped
    for name, why in stopped.items():
        other = "ur5-b" if name == "ur5-a" else "ur5-a"
        assert why.startswith("collision: link '") and f"of the arm '{other}'" in why, why
        assert f" vs {other}:" in why
    assert q["ur5-a"] != REACH and q["ur5-a"] != HOME  # stopped on the way
    assert closest >= 0.5 * margin, closest
    final = judge.checker()
    judge.peer("ur5-b").update(q["ur5-b"], bases["ur5-b"], 0.0)
    final.clearance(q["ur5-a"], bases["ur5-a"])
    assert 0.5 * margin <= final.peer_seen[0][2] < margin
    assert all(g.holds > 0 for g in guards.values())  # the peer's motion held them at times


# ------------------------------------------------------------------------------ two robots
def keyframe_ur5(margin_mm: float, goal: list[float]) -> SimRobot:
    cfg: dict[str, Any] = yaml.safe_load((CONFIGS / "ur5.yaml").read_text())
    cfg["safety"]["collision"] = {"margin_mm": margin_mm, "self_collision": False}
    cfg["safety"]["loss"] = {"enabled": False}
    cfg["interfaces"] = cfg["interfaces"][:2]  # no master stream
    cfg["interfaces"][1]["outputs"] = [
        {"type": "POLYDATA", "device": "KeyframePath", "source": "keyframe-path", "rate_hz": 10}
    ]
    cfg["controller"] = {
        "plugin": "keyframe",
        "params": {"space": "joint", "keyframes": [{"t": 2.5, "pose": goal, "name": "reach"}]},
    }
    return SimRobot(cfg)


def command(sim: SimRobot, name: str, **args: Any) -> Any:
    """An operator's command and its reply's metadata (a plan's check on its thread waited for)."""
    op = getattr(sim, "test_operator", None)
    if op is None:
        op = sim.test_operator = sim.peer("operator")  # type: ignore[attr-defined]
    attrs = "".join(f' {k}="{v}"' for k, v in args.items())
    cid = op.send_command(name, f'<Command Name="{name}"{attrs}/>')
    sim.step(1)
    kf = sim.robot.controller.controllers[0]
    assert kf.wait_idle(60.0)
    sim.step(1)
    reply = op.reply_to(cid)
    assert reply is not None, name
    return reply.metadata


class Cell:
    """Two keyframe robots, each told of the other (its guard's peer), their states fed every
    tick by a test-only driver (occ_testkit/cellarms.py), as the cell link will."""

    def __init__(self, margin_mm: float = 20.0) -> None:
        self.a = keyframe_ur5(margin_mm, REACH)
        self.b = keyframe_ur5(margin_mm, REACH)
        self.b.robot.data.base = b_base()
        self.feed = PeerFeed()
        for sim, name, other in ((self.a, "ur5-a", "ur5-b"), (self.b, "ur5-b", "ur5-a")):
            guard = sim.robot.collision
            assert guard is not None
            guard.cm.add_peer(other, UR5.frame, velocities=VEL)
            data = sim.robot.data
            self.feed.add(name, guard, lambda d=data: (d.commanded(), d.base), sim.robot.clock.now)

    def step(self, n: int = 1) -> None:
        for _ in range(n):
            self.feed.tick()
            self.a.step(1)
            self.b.step(1)

    def close(self) -> None:
        self.a.close()
        self.b.close()


@pytest.mark.req("SR-ARMS-2")
def test_two_robots_whose_plans_each_cleared_the_other_at_home_both_stop_before_contact() -> None:
    cell = Cell()
    try:
        cell.step(2)
        for sim in (cell.a, cell.b):
            command(sim, "Enable")
            cell.step(2)
            reply = command(sim, "KeyframePlan")
            # checked against the other arm where it stands now (at home): clear
            assert reply["Status"] == "SUCCESS", reply
            plan_id = reply["Message"].split(":")[0].split()[1]
            sim.step(150)
            command(sim, "Run")
            assert command(sim, "KeyframeAck", Plan=plan_id)["Status"] == "SUCCESS"
        closest = math.inf
        judge = pair_model()
        peer = judge.peer("ur5-b")
        checker = judge.checker()
        for _ in range(3500):
            cell.step(1)
            peer.update(cell.b.robot.data.q, b_base(), 0.0)
            checker.clearance(cell.a.robot.data.q, np.eye(4))
            closest = min(closest, checker.peer_seen[0][2])
        for sim, other in ((cell.a, "ur5-b"), (cell.b, "ur5-a")):
            r = sim.robot
            assert r.state is RobotState.STOPPED, r.state
            assert f"of the arm '{other}'" in r.last_alert and f" vs {other}:" in r.last_alert
        # the measured arms (the drives lag their setpoints) never closer than half the margin
        assert closest >= 0.01, closest
    finally:
        cell.close()


@pytest.mark.req("SR-ARMS-3")
def test_a_plan_into_the_other_arms_current_envelope_is_refused_naming_both_links() -> None:
    cell = Cell()
    try:
        b_guard = cell.b.robot.collision
        assert b_guard is not None
        # the other arm stands stretched out in the middle (its last known positions)
        cell.b.robot.data.setpoint[:] = REACH
        cell.b.robot.data.hold_setpoint[:] = REACH
        cell.step(2)
        command(cell.a, "Enable")
        reply = command(cell.a, "KeyframePlan")
        assert reply["Status"] == "FAIL", reply
        err = reply["Error"]
        assert "of the arm 'ur5-b'" in err and " vs ur5-b:" in err and "(margin 20 mm)" in err
        # the other arm back at home: the same plan passes
        cell.b.robot.data.setpoint[:] = HOME
        cell.b.robot.data.hold_setpoint[:] = HOME
        cell.step(2)
        assert command(cell.a, "KeyframePlan")["Status"] == "SUCCESS"
    finally:
        cell.close()


@pytest.mark.req("SR-ARMS-3")
def test_a_plan_is_refused_while_another_arm_is_unknown_and_checked_once_it_left() -> None:
    sim = keyframe_ur5(20.0, REACH)
    try:
        guard = sim.robot.collision
        assert guard is not None
        guard.cm.add_peer("ur5-b", UR5.frame, velocities=VEL)
        command(sim, "Enable")
        reply = command(sim, "KeyframePlan")
        assert reply["Status"] == "FAIL" and "the arm 'ur5-b' is not known" in reply["Error"]
        guard.peer_gone("ur5-b")  # it left the cell
        assert command(sim, "KeyframePlan")["Status"] == "SUCCESS"
    finally:
        sim.close()
