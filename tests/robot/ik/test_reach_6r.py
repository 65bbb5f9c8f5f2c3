"""A 6R arm's reach proved in closed form (UR geometry): never wrong, and tight at the edge."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from helpers import CONFIGS, tilted_elbow_chain
from poses import pin_poses

from gcm_pipeline import pipeline as P
from gcm_pipeline.config import load_config
from gcm_pipeline.config.robot_spec import load_robot
from gcm_pipeline.robot.ik.analytic_6r import six_r_solver
from gcm_pipeline.robot.ik.lm import PinocchioIKOptions, levenberg_marquardt
from gcm_pipeline.robot.ik.reach_6r import SixRReach, six_r_reach
from gcm_pipeline.robot.model import Robot

TOL_P, TOL_R = 1e-4, 1e-3


@pytest.fixture(scope="module", params=["ur5_2f85", "ur10"])
def arm(request: pytest.FixtureRequest) -> Robot:
    """The UR5 with the Robotiq 2F-85 of the bottle example, and example-robot-data's UR10."""
    if request.param == "ur10":
        return load_robot(CONFIGS / "robots" / "ur10.yaml")
    return P.robot_from_config(load_config(CONFIGS / "bottle_side_ur5.yaml"))


def _stretched(robot: Robot, n: int, rng: np.random.Generator) -> np.ndarray:
    """Configurations (n, 6) with the elbow within 0.02 rad of straight (the edge of the reach)."""
    q = rng.uniform(-np.pi, np.pi, size=(n, 6))
    q[:, 2] = rng.uniform(-0.02, 0.02, size=n)
    return q


def _turned(rot: np.ndarray, angle: float, rng: np.random.Generator) -> np.ndarray:
    """Each rotation (N, 3, 3) turned by ``angle`` [rad] about a random axis."""
    axis = rng.normal(size=(len(rot), 3))
    axis /= np.linalg.norm(axis, axis=1)[:, None]
    return np.stack([pin.exp3(angle * a) for a in axis]) @ rot


def test_ur_arms_get_the_test_and_others_do_not(panda) -> None:
    assert six_r_reach(panda) is None  # 7 joints
    ur5 = load_robot("ur5")
    test = six_r_reach(ur5)
    assert isinstance(test, SixRReach)
    # the UR5's upper arm and forearm (DH a2, a3)
    assert test.reach == pytest.approx(0.425 + 0.39225, abs=1e-12)
    assert isinstance(six_r_reach(load_robot(CONFIGS / "robots" / "ur10.yaml")), SixRReach)
    # an elbow axis tilted by 0.05 rad is no longer parallel to the shoulder's: no test
    assert SixRReach.for_chain(tilted_elbow_chain(ur5)) is None


def test_poses_the_arm_reaches_are_never_proved_unreachable(arm: Robot) -> None:
    test = six_r_reach(arm)
    assert test is not None
    rng = np.random.default_rng(3)
    # anywhere, and at the edge of the reach (elbow nearly straight), any joint angles
    q = np.concatenate([rng.uniform(-np.pi, np.pi, size=(3000, 6)), _stretched(arm, 3000, rng)])
    poses = pin_poses(arm, q)
    rot, pos = poses[:, :3, :3], poses[:, :3, 3]
    assert not test.unreachable(rot, pos).any()
    # a target within the tolerances of a reached pose: some configuration reaches it
    step = rng.normal(size=pos.shape)
    step *= TOL_P / np.linalg.norm(step, axis=1)[:, None]
    assert not test.unreachable(_turned(rot, TOL_R, rng), pos + step, TOL_P, TOL_R).any()


def test_poses_beyond_the_links_are_proved_as_eaik_finds_no_answer(arm: Robot) -> None:
    test, six = six_r_reach(arm), six_r_solver(arm)
    assert test is not None and six is not None
    rng = np.random.default_rng(5)
    q = _stretched(arm, 400, rng)
    poses = pin_poses(arm, q)
    # each grasp frame carried 1 cm further from the shoulder, orientation kept: some
    # leave the reach (the elbow cannot stretch further), some another branch reaches
    away = poses[:, :3, 3] - test.shoulder
    away /= np.linalg.norm(away, axis=1)[:, None]
    far = poses.copy()
    far[:, :3, 3] += 0.01 * away
    rot, pos = far[:, :3, :3], far[:, :3, 3]
    # the reference: EAIK's exact answers, any joint angles
    idx, _ = six.raw(rot, pos)
    none = np.ones(len(far), dtype=bool)
    none[idx] = False
    assert 100 <= none.sum() <= 300
    # without tolerances the test is exact: proved where EAIK has no answer
    np.testing.assert_array_equal(test.unreachable(rot, pos), none)
    # with them, a margin: fewer, but most
    proved = test.unreachable(rot, pos, TOL_P, TOL_R)
    assert not (proved & ~none).any()
    assert proved.sum() >= 0.9 * none.sum()
    # ...and Levenberg-Marquardt, from the configuration the pose was moved off and from
    # random ones, without joint limits, stays off the pose by more than the tolerances
    # (Pinocchio's own forward kinematics)
    seeds = np.concatenate([q[proved], rng.uniform(-np.pi, np.pi, size=(int(proved.sum()), 6))])
    targets = np.concatenate([far[proved], far[proved]])
    unlimited = np.full(6, 1e3)
    qf = levenberg_marquardt(
        arm.chain, seeds, targets[:, :3, :3], targets[:, :3, 3], -unlimited, unlimited,
        TOL_P, TOL_R, PinocchioIKOptions(max_iterations=200, stall_ratio=0.0), clamp=False,
    )[0]  # fmt: skip
    reached = pin_poses(arm, qf)
    pe = np.linalg.norm(reached[:, :3, 3] - targets[:, :3, 3], axis=1)
    turn = np.einsum("nji,njk->nik", reached[:, :3, :3], targets[:, :3, :3])
    re = np.arccos(np.clip((np.trace(turn, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))
    assert np.all((pe > TOL_P) | (re > TOL_R))
