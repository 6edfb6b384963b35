"""Frame: forward kinematics, Jacobian, analytic vs DLS inverse kinematics, limits, RCM."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from occ.errors import KinematicsError
from occ.kinematics.frame import Frame, robots_dir

RCM_HEIGHT = 0.30
TIP_PAST_RCM = 0.02
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def slave() -> Frame:
    return Frame.builtin("occ_slave")


@pytest.fixture(scope="module")
def master() -> Frame:
    return Frame.builtin("master3")


def expected_slave_tip(yaw: float, pitch: float, insertion: float) -> np.ndarray:
    d = TIP_PAST_RCM + insertion
    return np.array(
        (
            -math.sin(yaw) * math.sin(pitch) * d,
            math.cos(yaw) * math.sin(pitch) * d,
            RCM_HEIGHT - math.cos(pitch) * d,
        )
    )


def random_q(frame: Frame, n: int, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).uniform(frame.lower, frame.upper, size=(n, frame.nq))


def test_models_load_with_limits(slave: Frame, master: Frame) -> None:
    assert slave.joint_names == ("yaw", "pitch", "insertion")
    np.testing.assert_allclose(slave.lower, [-math.pi / 3, -math.pi / 3, 0.0])
    np.testing.assert_allclose(slave.upper, [math.pi / 3, math.pi / 3, 0.15])
    assert master.joint_names == ("x", "y", "z")
    assert slave.has_analytic_ik and master.has_analytic_ik
    np.testing.assert_allclose(slave.rcm, [0.0, 0.0, RCM_HEIGHT])
    assert master.rcm is None


def test_fk_known_poses(slave: Frame, master: Frame) -> None:
    home = slave.fk([0.0, 0.0, 0.0])
    np.testing.assert_allclose(home[:3, 3], [0, 0, RCM_HEIGHT - TIP_PAST_RCM], atol=1e-12)
    np.testing.assert_allclose(home[:3, :3], np.eye(3), atol=1e-12)
    # Pitch +90 deg about x swings the tool axis (-z) to +y.
    pose = slave.fk([0.0, math.pi / 2, 0.08])
    np.testing.assert_allclose(pose[:3, 3], [0, 0.10, RCM_HEIGHT], atol=1e-12)
    for q in random_q(slave, 20):
        np.testing.assert_allclose(slave.fk(q)[:3, 3], expected_slave_tip(*q), atol=1e-12)
        # The tool axis always passes through the RCM.
        tip = slave.position(q)
        axis = slave.fk(q)[:3, 2]
        np.testing.assert_allclose(np.cross(tip - slave.rcm, axis), 0.0, atol=1e-12)
    np.testing.assert_allclose(master.fk([0.05, -0.02, 0.1])[:3, 3], [0.05, -0.02, 0.35])
    with pytest.raises(ValueError):
        slave.fk([0.0, 0.0])


def test_jacobian_matches_finite_differences(slave: Frame) -> None:
    q = np.array([0.3, -0.4, 0.07])
    jac = slave.jacobian(q)
    assert jac.shape == (6, 3)
    eps = 1e-7
    for i in range(3):
        dq = np.zeros(3)
        dq[i] = eps
        numeric = (slave.position(q + dq) - slave.position(q - dq)) / (2 * eps)
        np.testing.assert_allclose(jac[:3, i], numeric, atol=1e-7)


@pytest.mark.parametrize("name", ["occ_slave", "master3"])
def test_analytic_equals_dls_on_random_reachable_targets(name: str) -> None:
    frame = Frame.builtin(name)
    for q in random_q(frame, 25, seed=3):
        target = frame.position(q)
        analytic = frame.solve_ik(target)
        dls = frame.solve_ik(target, method="dls")
        assert analytic.method == "analytic" and dls.method == "dls"
        np.testing.assert_allclose(analytic.q, q, atol=1e-9)
        np.testing.assert_allclose(dls.q, analytic.q, atol=1e-6)
        assert analytic.error < 1e-12 and dls.error < frame.tolerance
        # fk(ik(x)) == x
        np.testing.assert_allclose(frame.position(frame.ik(target)), target, atol=1e-12)


def test_ik_accepts_a_pose_and_picks_branch_in_limits(slave: Frame) -> None:
    q = np.array([-0.9, 0.5, 0.1])
    pose = slave.fk(q)
    np.testing.assert_allclose(slave.ik(pose), q, atol=1e-9)
    # Directly below the RCM yaw is free: the seed's yaw is kept.
    q_down = slave.ik([0.0, 0.0, RCM_HEIGHT - 0.1], q0=[0.4, 0.0, 0.0])
    np.testing.assert_allclose(q_down, [0.4, 0.0, 0.08], atol=1e-12)


def test_unreachable_targets_raise(slave: Frame, master: Frame) -> None:
    too_deep = [0.0, 0.0, RCM_HEIGHT - 0.5]  # insertion 0.48 > 0.15
    with pytest.raises(KinematicsError, match=r"joint insertion needs 0\.48"):
        slave.ik(too_deep)
    with pytest.raises(KinematicsError, match="unreachable"):
        slave.ik(too_deep, method="dls")
    beside = expected_slave_tip(0.0, 1.4, 0.05)  # pitch 1.4 rad > 60 deg
    with pytest.raises(KinematicsError, match="joint pitch"):
        slave.ik(beside)
    with pytest.raises(KinematicsError):
        slave.ik([0.0, 0.0, RCM_HEIGHT])  # the RCM itself
    with pytest.raises(KinematicsError, match="joint x"):
        master.ik([0.5, 0.0, 0.25])


def test_clamp_reports_limited_joints(slave: Frame, master: Frame) -> None:
    result = slave.solve_ik([0.0, 0.0, RCM_HEIGHT - 0.5], clamp=True)
    assert result.clamped == ("insertion",)
    np.testing.assert_allclose(result.q, [0.0, 0.0, 0.15], atol=1e-12)
    assert result.error == pytest.approx(0.5 - 0.17)
    assert slave.within_limits(result.q)
    dls = slave.solve_ik([0.0, 0.0, RCM_HEIGHT - 0.5], clamp=True, method="dls")
    assert "insertion" in dls.clamped and dls.q[2] == pytest.approx(0.15)
    res = master.solve_ik([0.5, 0.0, 0.25], clamp=True)
    assert res.clamped == ("x",) and res.q[0] == 0.1


def test_from_urdf_with_base_link_and_errors(tmp_path) -> None:  # type: ignore[no-untyped-def]
    frame = Frame.from_urdf(robots_dir() / "occ_slave.urdf", "tool_tip", base_link="rcm")
    np.testing.assert_allclose(frame.rcm, [0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(frame.position([0, 0, 0]), [0, 0, -TIP_PAST_RCM], atol=1e-12)
    q = np.array([0.2, 0.3, 0.1])
    np.testing.assert_allclose(frame.ik(frame.position(q)), q, atol=1e-9)
    with pytest.raises(KinematicsError, match="no link"):
        Frame.from_urdf(robots_dir() / "occ_slave.urdf", "nope")
    with pytest.raises(KinematicsError, match="must be fixed"):
        Frame.from_urdf(robots_dir() / "occ_slave.urdf", "tool_tip", base_link="yaw_link")
    with pytest.raises(KinematicsError, match="not found"):
        Frame.from_urdf(tmp_path / "missing.urdf", "tip")
    bad = tmp_path / "bad.urdf"
    bad.write_text("<robot name='x'><link name='a'></robot>")
    with pytest.raises(KinematicsError, match="cannot load") as info:
        Frame.from_urdf(bad, "a")
    assert info.value.__cause__ is not None
    with pytest.raises(KinematicsError, match="known: master3, occ_slave"):
        Frame.builtin("nope")


def test_dls_six_dof_pose_and_non_convergence() -> None:
    model = pin.buildSampleModelManipulator()
    frame = Frame(model, model.frames[-1].name)
    assert not frame.has_analytic_ik
    q = np.array([0.3, -0.2, 0.4, 0.1, 0.5, -0.3])
    pose = frame.fk(q)
    result = frame.solve_ik(pose, q0=q + 0.1)
    np.testing.assert_allclose(frame.fk(result.q), pose, atol=1e-6)
    strict = Frame(model, model.frames[-1].name, max_iterations=1)
    with pytest.raises(KinematicsError, match="did not converge"):
        strict.ik(pose, q0=q + 0.3)


@pytest.mark.parametrize("name", ["occ_slave", "master3"])
def test_per_tick_paths_match_the_numpy_ones(name: str) -> None:
    """The float-only paths the loop uses (tuple targets, closed-form tip) give the same
    answers as pinocchio and the array path."""
    frame = Frame.builtin(name)
    for q in random_q(frame, 25, seed=7):
        np.testing.assert_allclose(frame.tip_position(q), frame.position(q), atol=1e-9)
        np.testing.assert_allclose(frame.tip_position(q.tolist()), frame.position(q), atol=1e-9)
        target = frame.position(q)
        by_tuple = frame.solve_ik(tuple(target.tolist()), q.tolist())
        by_array = frame.solve_ik(target, q)
        np.testing.assert_allclose(by_tuple.q, by_array.q, atol=1e-12)
        np.testing.assert_allclose(by_tuple.q, q, atol=1e-9)
        assert by_tuple.error < 1e-9
    with pytest.raises(ValueError, match="finite"):
        frame.solve_ik((math.nan, 0.0, 0.0))
    with pytest.raises(ValueError, match="shape"):
        frame.solve_ik((0.0, 0.0, 0.1), [0.0, 0.0])


@pytest.mark.parametrize("name", ["occ_slave", "master3"])
def test_ik_clamped_matches_solve_ik(name: str) -> None:
    """The loop's plain-float IK gives solve_ik(clamp=True)'s answer, inside and outside the
    workspace (clamped flag included)."""
    import random

    frame = Frame.builtin(name)
    rng = random.Random(3)
    lo, hi = frame.lower.tolist(), frame.upper.tolist()
    for _ in range(300):
        q = [rng.uniform(a - 0.2 * (b - a), b + 0.2 * (b - a)) for a, b in zip(lo, hi, strict=True)]
        target = tuple(frame.tip_position(q))
        seed = [rng.uniform(a, b) for a, b in zip(lo, hi, strict=True)]
        ref = frame.solve_ik(target, seed, clamp=True)
        got, clamped = frame.ik_clamped(target, seed)
        assert got == pytest.approx(ref.q.tolist(), abs=1e-12)
        assert clamped == bool(ref.clamped)
    with pytest.raises(ValueError, match="finite"):
        frame.ik_clamped((math.nan, 0.0, 0.0), list(frame.neutral))


@pytest.mark.parametrize("name", ["occ_slave", "master3", "ur5"])
def test_closed_form_world_pose_matches_pinocchio_under_any_base(name: str) -> None:
    """The return channel's float-only pose (``RobotData.world_tip_pose``: the closed form
    where the model has one, else pinocchio) is ``base @ fk(q)``: with no base, a translated
    base and a rotated one."""
    from occ.clock import SimClock
    from occ.core.data import RobotData
    from occ.samples import rotation_to_quaternion

    if name == "ur5":
        from occ.core.loader import load_config

        fc = load_config(ROOT / "configs" / "ur5.yaml").robot.frame
        path = fc.urdf_path()
        assert path is not None and fc.tip_link is not None
        frame = Frame.from_urdf(path, fc.tip_link, fc.base_link)
        assert frame._analytic_pose is None  # the fallback path
    else:
        frame = Frame.builtin(name)
        assert frame._analytic_pose is not None
    data = RobotData("r", frame.joint_names, [0.0] * frame.nq, frame, SimClock())
    rot = pin.rpy.rpyToMatrix(0.3, -0.2, 1.1)
    bases = [np.eye(4), pin.SE3(np.eye(3), np.array([0.1, -0.2, 0.3])).homogeneous]
    bases.append(pin.SE3(rot, np.array([0.05, 0.07, -0.4])).homogeneous)
    for base in bases:
        data.base = base
        for q in random_q(frame, 10, seed=11):
            data.q[:] = q.tolist()
            data._tip_stale = True
            want = data.world_tip()
            rows, pos = data.world_tip_pose()
            np.testing.assert_allclose(np.array(rows), want[:3, :3], atol=1e-12)
            np.testing.assert_allclose(pos, want[:3, 3], atol=1e-12)
            np.testing.assert_allclose(
                rotation_to_quaternion(rows), rotation_to_quaternion(want[:3, :3]), atol=1e-12
            )


# A port off the base's axis with a tool turned on its tip, and a master mounted at an angle:
# the shipped models have the port on the z axis, the tool and the master's axes aligned with
# the base, where a closed form that drops or swaps a term still gives the right answer.
def _moved_port(tmp_path: Path, *, rcm_link: bool = True) -> Path:
    text = (robots_dir() / "occ_slave.urdf").read_text()
    text = text.replace(
        '<origin xyz="0 0 0.30" rpy="0 0 0"/>', '<origin xyz="0.04 -0.03 0.30" rpy="0 0 0"/>'
    )
    text = text.replace(
        '<origin xyz="0 0 -0.02" rpy="0 0 0"/>', '<origin xyz="0 0 -0.02" rpy="0.3 -0.2 0.5"/>'
    )
    # yaw to +-3 rad: both branches, (yaw, pitch) and (yaw -+ pi, -pitch), inside the limits
    text = text.replace(
        'lower="-1.0471975511965976" upper="1.0471975511965976" velocity="1.5" effort="20.0"/>\n'
        '    <dynamics damping="0.1" friction="0.05"/>\n  </joint>\n  <link name="yaw_link">',
        'lower="-3.0" upper="3.0" velocity="1.5" effort="20.0"/>\n'
        '    <dynamics damping="0.1" friction="0.05"/>\n  </joint>\n  <link name="yaw_link">',
    )
    if not rcm_link:
        start = text.index('<joint name="rcm_joint"')
        text = text[:start] + text[text.index('<link name="rcm"/>') + len('<link name="rcm"/>') :]
    path = tmp_path / f"occ_slave_moved_{rcm_link}.urdf"
    path.write_text(text)
    return path


def _tilted_master(tmp_path: Path) -> Path:
    text = (robots_dir() / "master3.urdf").read_text()
    text = text.replace(
        '<origin xyz="0 0 0.20" rpy="0 0 0"/>', '<origin xyz="0.03 -0.02 0.20" rpy="0.2 0.1 -0.3"/>'
    )
    text = text.replace(
        '<origin xyz="0 0 0.05" rpy="0 0 0"/>\n  </joint>',
        '<origin xyz="0 0 0.05" rpy="0.1 0.2 0.3"/>\n  </joint>',
    )
    path = tmp_path / "master3_tilted.urdf"
    path.write_text(text)
    return path


@pytest.mark.parametrize("name", ["occ_slave", "master3"])
def test_closed_forms_hold_off_axis_and_tilted(name: str, tmp_path: Path) -> None:
    """With the port off the base's axis and the tool turned on its tip (the slave), or the
    master's axes tilted and offset, the closed forms still match at load (the loop uses them)
    and give pinocchio's tip position, pose and inverse."""
    if name == "occ_slave":
        frame = Frame.from_urdf(_moved_port(tmp_path), "tool_tip")
        np.testing.assert_allclose(frame.rcm, [0.04, -0.03, 0.30], atol=1e-12)
        assert not np.allclose(frame.fk(np.zeros(3))[:3, :3], np.eye(3))
    else:
        frame = Frame.from_urdf(_tilted_master(tmp_path), "handle")
        axes = np.column_stack(
            [frame.position(np.eye(3)[i]) - frame.position(np.zeros(3)) for i in range(3)]
        )
        assert np.count_nonzero(np.abs(axes) > 1e-3) == 9  # every axis mixes every base axis
    assert frame.name == name and frame.has_analytic_ik
    assert frame._analytic_pose is not None  # the closed-form pose matched pinocchio at load
    for q in random_q(frame, 10, seed=5):
        np.testing.assert_allclose(frame.tip_position(q.tolist()), frame.position(q), atol=1e-12)
        rows, pos = frame.tip_pose(q.tolist())
        np.testing.assert_allclose(np.array(rows), frame.fk(q)[:3, :3], atol=1e-12)
        np.testing.assert_allclose(pos, frame.fk(q)[:3, 3], atol=1e-12)
        target = tuple(frame.position(q).tolist())
        got, clamped = frame.ik_clamped(target, (q + 0.01).tolist())
        assert got == pytest.approx(q.tolist(), abs=1e-9) and not clamped


def test_the_branch_nearest_the_seed_is_kept(tmp_path: Path) -> None:
    """Where both of the port's branches are inside the limits, the one nearest the seed (the
    joints where they are) is the answer: never the tool swung round by pi to the same tip."""
    frame = Frame.from_urdf(_moved_port(tmp_path), "tool_tip")
    for q in ([0.5, 0.4, 0.05], [-0.7, -0.3, 0.1], [2.0, 0.6, 0.02]):
        flipped = [q[0] - math.pi if q[0] > 0.0 else q[0] + math.pi, -q[1], q[2]]
        assert frame.within_limits(flipped)
        target = frame.tip_position(q)
        for want in (q, flipped):
            seed = [want[0] + 0.05, want[1] - 0.05, want[2] + 0.01]
            got, clamped = frame.ik_clamped(target, seed)
            assert got == pytest.approx(want, abs=1e-9) and not clamped
            assert frame.solve_ik(target, seed).q.tolist() == pytest.approx(want, abs=1e-9)


def test_the_port_is_the_closed_forms_without_an_rcm_link(tmp_path: Path) -> None:
    """A URDF without the ``rcm`` link: the port is the one the closed form found (the first
    joint's origin), which the slave's RCM checks and the 6-DOF port mapping use."""
    frame = Frame.from_urdf(_moved_port(tmp_path, rcm_link=False), "tool_tip")
    assert frame.has_analytic_ik
    np.testing.assert_allclose(frame.rcm, [0.04, -0.03, 0.30], atol=1e-12)


def test_ik_clamped_below_the_port_keeps_the_seeds_yaw() -> None:
    """Straight below the port the yaw is free: the loop's IK keeps the joints' yaw (no spin of
    the tool), reachable or clamped to the insertion limit; at the port itself, a clear error."""
    frame = Frame.builtin("occ_slave")
    got, clamped = frame.ik_clamped((0.0, 0.0, RCM_HEIGHT - 0.1), [0.4, 0.2, 0.05])
    assert got == pytest.approx([0.4, 0.0, 0.08], abs=1e-12) and not clamped
    got, clamped = frame.ik_clamped((0.0, 0.0, RCM_HEIGHT - 0.5), [0.4, 0.2, 0.05])
    assert got == pytest.approx([0.4, 0.0, 0.15], abs=1e-12) and clamped
    with pytest.raises(KinematicsError, match="target at the RCM point: direction undefined"):
        frame.ik_clamped((0.0, 0.0, RCM_HEIGHT), [0.4, 0.2, 0.05])


def test_ik_clamped_never_sends_a_joint_past_its_limit() -> None:
    """A solution a rounding error past a limit (inside the solver's tolerance) is sent as the
    limit itself: a drive refuses any position past it."""
    frame = Frame.builtin("master3")
    lo, hi = frame.lower.tolist(), frame.upper.tolist()
    z = frame.tip_position([0.0, 0.0, 0.0])[2]
    for x, want in ((hi[0] + 5e-13, hi[0]), (lo[0] - 5e-13, lo[0])):
        got, clamped = frame.ik_clamped((x, 0.0, z), [0.0, 0.0, 0.0])
        assert got[0] == want and not clamped
        assert all(a <= v <= b for v, a, b in zip(got, lo, hi, strict=True))


def test_ik_clamped_without_a_closed_form_starts_from_the_seed() -> None:
    """A chain with no closed form (a 6-joint arm, position only): the loop's IK is the DLS
    from the seed, the joints' own pose, not from zero (a redundant arm would jump)."""
    model = pin.buildSampleModelManipulator()
    frame = Frame(model, model.frames[-1].name)
    assert not frame.has_analytic_ik
    q = np.array([0.3, -0.2, 0.4, 0.1, 0.5, -0.3])
    target = tuple(frame.position(q).tolist())
    seed = (q + 0.05).tolist()
    got, clamped = frame.ik_clamped(target, seed)
    np.testing.assert_allclose(frame.position(got), target, atol=1e-6)
    assert got == pytest.approx(frame.solve_ik(target, seed, clamp=True).q.tolist(), abs=1e-12)
    assert np.max(np.abs(np.array(got) - q)) < 0.2  # near the seed, not a far-off solution
    assert not clamped
