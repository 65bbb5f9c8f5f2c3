"""Inverse kinematics: round trips, verification, false positives, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import ROBOT_SPECS
from poses import backward_poses

from gcm_pipeline.config.robot_spec import load_robot
from gcm_pipeline.errors import GeometryError, InputError
from gcm_pipeline.robot.ik import IKResult, solve_ik, verify_solutions
from gcm_pipeline.robot.model import Robot

TOL_P, TOL_R = 1e-4, 1e-3


@pytest.fixture(scope="module")
def ur5() -> Robot:
    return load_robot("ur5")


def _assert_verified(robot: Robot, res: IKResult, targets: np.ndarray) -> None:
    """Every success re-checked independently with Pinocchio FK and the limits."""
    ok = res.success
    pe, re, inside = verify_solutions(robot, res.q[ok], targets[ok])
    assert np.all(pe <= TOL_P) and np.all(re <= TOL_R) and np.all(inside)
    np.testing.assert_allclose(res.pos_err[ok], pe)
    assert np.all(np.isnan(res.q[~ok]))
    assert np.all(res.reason[ok] == "") and np.all(res.reason[~ok] != "")


def _unreachable(robot: Robot, n: int, seed: int, lo: float, hi: float) -> np.ndarray:
    """Backward-pointing poses at ``lo``-``hi`` [m] from the shoulder (no IK exists)."""
    return backward_poses(robot, n, np.random.default_rng(seed), lo, hi)


@pytest.mark.parametrize("name,n", [("panda", 300), ("ur5", 150)])
def test_pinocchio_round_trip(name: str, n: int):
    robot = load_robot(name)
    targets = robot.fk(robot.random_configurations(n, 42))
    res = solve_ik(robot, targets)
    assert res.success.mean() >= 0.99
    _assert_verified(robot, res, targets)
    assert np.all(res.pos_err[res.success] < TOL_P * 0.1)
    assert "reached" in repr(res)


@pytest.mark.parametrize("name,n", [("panda", 12), ("ur5", 6)])
def test_mink_round_trip(name: str, n: int):
    robot = load_robot(name)
    targets = robot.fk(robot.random_configurations(n, 7))
    res = solve_ik(robot, targets, backend="mink")
    assert res.backend == "mink"
    assert res.success.mean() >= 0.9
    _assert_verified(robot, res, targets)


def test_unreachable_targets_are_never_successes(panda: Robot):
    far = _unreachable(panda, 40, 1, 1.0, 1.3)  # beyond max_reach: pre-filter
    # within max_reach, but the wrist would lie beyond the elbow's reach: the Panda's
    # reach proof rejects them before any seed
    behind = _unreachable(panda, 40, 2, 0.8, 0.94)
    assert np.all(np.linalg.norm(behind[:, :3, 3] - panda.shoulder, axis=1) < panda.max_reach)
    for backend in ("pinocchio", "mink"):
        res = solve_ik(panda, np.concatenate([far, behind]), backend=backend)
        assert not res.success.any()
        assert np.all(res.reason == "out_of_reach")
        assert np.isnan(res.pos_err).all()  # no attempt was made
    # an arm without a reach proof (the UR5): the IK runs and fails
    ur5 = load_robot("ur5")
    near = _unreachable(ur5, 40, 2, 0.8 * ur5.max_reach, 0.94 * ur5.max_reach)
    assert np.all(np.linalg.norm(near[:, :3, 3] - ur5.shoulder, axis=1) < ur5.max_reach)
    res = solve_ik(ur5, near)
    assert not res.success.any()
    assert np.all(np.isin(res.reason, ["no_ik", "joint_limits"]))
    assert np.all(res.pos_err > TOL_P)
    res = solve_ik(ur5, near[:3], backend="mink")
    assert not res.success.any()


def test_joint_limits_reason(tmp_path: Path, panda: Robot):
    # joints 1 and 3 held near 0 (+-0.1 rad after the 0.1 rad margin): the arm cannot
    # turn to the side
    spec = (ROBOT_SPECS / "panda.yaml").read_text()
    spec += "joint_limits:\n  panda_joint1: [-0.2, 0.2]\n  panda_joint3: [-0.2, 0.2]\n"
    path = tmp_path / "narrow.yaml"
    path.write_text(spec)
    narrow = load_robot(path)
    q = np.array(panda.home)
    q[0] = 2.0
    res = solve_ik(narrow, panda.fk(q))
    assert not res.success[0]
    assert res.reason[0] == "joint_limits"


def test_warm_starts_seeds_and_neighbours(panda: Robot):
    q = panda.random_configurations(20, 5)
    targets = panda.fk(q)
    # a seed at the solution converges at once to that very solution
    res = solve_ik(panda, targets, seeds=q[:, None, :])
    assert res.success.all()
    np.testing.assert_allclose(res.q, q, atol=1e-12)
    # rows 10.. are the poses of rows 0..9: seeded from those rows' solutions
    both = np.concatenate([targets[:10], targets[:10]])
    nb = np.full((20, 2), -1)
    nb[10:, 0] = np.arange(10)
    res = solve_ik(panda, both, neighbours=nb)
    assert res.success.all()
    np.testing.assert_allclose(res.q[10:], res.q[:10], atol=1e-12)


def test_validator_and_all_candidates(panda: Robot):
    targets = panda.fk(panda.random_configurations(10, 9))

    def reject_all(q: np.ndarray) -> np.ndarray:
        return np.full(len(q), "collision_self")

    res = solve_ik(panda, targets, validator=reject_all, return_all=True)
    assert not res.success.any() and np.all(res.reason == "collision_self")
    cand = res.candidates
    assert cand is not None and len(cand.index) >= 10
    assert set(cand.index) == set(range(10)) and np.all(cand.reason == "collision_self")
    pe, re, inside = verify_solutions(panda, cand.q, targets[cand.index])
    assert np.all(pe < TOL_P) and np.all(re < TOL_R) and inside.all()

    def left_only(q: np.ndarray) -> np.ndarray:
        return np.where(q[:, 0] < 0, "", "collision_environment")

    res = solve_ik(panda, targets, validator=left_only, first_round_seeds=3)
    assert np.all(res.q[res.success, 0] < 0)
    assert set(res.reason[~res.success]) <= {"collision_environment"}


def test_best_manipulability_among_converged(panda: Robot):
    from gcm_pipeline.robot.manipulability import manipulability

    targets = panda.fk(panda.random_configurations(10, 4))
    res = solve_ik(panda, targets, first_round_seeds=4, return_all=True)
    assert res.success.all()
    cand = res.candidates
    w_all = manipulability(panda, cand.q)
    w_res = manipulability(panda, res.q)
    for i in range(10):
        assert w_res[i] >= w_all[cand.index == i].max() - 1e-12


def test_workers_agree_with_one_process(panda: Robot):
    targets = panda.fk(panda.random_configurations(60, 8))
    one = solve_ik(panda, targets)
    two = solve_ik(panda, targets, workers=2)
    # every decision is per target: chunking over processes changes nothing
    np.testing.assert_array_equal(one.success, two.success)
    np.testing.assert_array_equal(one.q, two.q)
    _assert_verified(panda, two, targets)


def test_bad_input_errors(panda: Robot):
    good = panda.fk(panda.random_configurations(2, 0))
    with pytest.raises(GeometryError, match=r"shape \(N, 4, 4\)"):
        solve_ik(panda, np.zeros((3, 3, 3)))
    bad = good.copy()
    bad[1, 0, 3] = np.nan
    with pytest.raises(GeometryError, match=r"targets\[1\] has non-finite"):
        solve_ik(panda, bad)
    bad = good.copy()
    bad[0, :3, :3] *= 1.1
    with pytest.raises(GeometryError, match=r"targets\[0\] is not a rigid transform"):
        solve_ik(panda, bad)
    bad = good.copy()
    bad[1, 3, 0] = 1.0
    with pytest.raises(GeometryError, match=r"targets\[1\]"):
        solve_ik(panda, bad)
    for kw in ({"position_tolerance": 0.0}, {"orientation_tolerance": -1e-3}):
        with pytest.raises(InputError, match="must be a positive"):
            solve_ik(panda, good, **kw)
    with pytest.raises(InputError, match=r"unknown IK backend 'minc'.*'mink'.*pinocchio"):
        solve_ik(panda, good, backend="minc")
    with pytest.raises(InputError, match=r"unknown pinocchio IK option 'max_iteration'"):
        solve_ik(panda, good, max_iteration=3)
    with pytest.raises(InputError, match="seeds must have shape"):
        solve_ik(panda, good, seeds=np.zeros((2, 1, 6)))
    with pytest.raises(InputError, match="neighbours"):
        solve_ik(panda, good, neighbours=np.array([[5], [0]]))
    # a single (4, 4) pose is one target
    assert solve_ik(panda, good[0]).q.shape == (1, 7)


def test_null_space_steps_raise_manipulability(panda: Robot):
    from gcm_pipeline.robot.manipulability import manipulability

    targets = panda.fk(panda.random_configurations(30, 12))
    plain = solve_ik(panda, targets)
    better = solve_ik(panda, targets, manipulability_steps=5, manipulability_step=0.1)
    ok = plain.success & better.success
    assert ok.sum() >= 29
    _assert_verified(panda, better, targets)
    w0 = manipulability(panda, plain.q[ok])
    w1 = manipulability(panda, better.q[ok])
    assert np.all(w1 >= w0 - 1e-12) and w1.mean() > w0.mean()


def test_log3_and_rotation_angle_match_scipy_near_zero_and_pi():
    from scipy.spatial.transform import Rotation

    from gcm_pipeline.robot.ik.lm import log3, rotation_angle

    rng = np.random.default_rng(0)
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate(
        [rng.uniform(0, np.pi, 150), [0.0, 1e-9, 1e-6], np.pi - np.logspace(-9, -3, 47)]
    )
    rotvec = axes * angles[:, None]
    mats = Rotation.from_rotvec(rotvec).as_matrix()
    np.testing.assert_allclose(rotation_angle(mats), angles, atol=1e-8)
    out = log3(mats)
    # equal up to the sign ambiguity at exactly pi
    np.testing.assert_allclose(Rotation.from_rotvec(out).as_matrix(), mats, atol=1e-7)
    small = angles < 1.0
    np.testing.assert_allclose(out[small], rotvec[small], atol=1e-12)
