"""Pre-grasp approach check and the collision stage helpers, on the real Panda model."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from gcm_pipeline.config import ApproachConfig, EnvironmentConfig
from gcm_pipeline.errors import InputError
from gcm_pipeline.geometry.dualquat import dq_from_matrix
from gcm_pipeline.robot.approach import approach_waypoints, check_approach_path
from gcm_pipeline.robot.collision import REASON_ENVIRONMENT, CollisionChecker
from gcm_pipeline.robot.ik import solve_ik
from gcm_pipeline.robot.model import load_robot
from gcm_pipeline.stages.collision import (
    REASON_APPROACH,
    add_clearance,
    check_approach,
    filter_collisions,
)
from gcm_pipeline.table import GraspTable


def _pose(p, z):
    z = np.asarray(z, float) / np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    t = np.eye(4)
    t[:3, :3] = np.c_[x, np.cross(z, x), z]
    t[:3, 3] = p
    return t


TOP_DOWN = _pose([0.5, 0.0, 0.2], [0, 0, -1])  # clear, approach from above
FROM_BELOW = _pose([0.45, 0.1, 0.3], [0, 0, 1])  # approach upward, from under the table


@pytest.fixture(scope="module")
def robot():
    return load_robot("panda")


@pytest.fixture(scope="module")
def checker(robot):
    return CollisionChecker(robot, EnvironmentConfig())


@pytest.fixture(scope="module")
def solved(robot, checker):
    targets = np.array([TOP_DOWN, FROM_BELOW])
    res = solve_ik(robot, targets, validator=checker.check)
    assert res.success.all(), res.reason  # both grasps themselves are reachable and free
    return targets, res


def test_waypoints_back_off_along_approach_axis():
    wp = approach_waypoints(np.array([TOP_DOWN, FROM_BELOW]), 0.1, 4)
    assert wp.shape == (5, 2, 4, 4)
    back = np.eye(4)
    back[2, 3] = -0.1
    np.testing.assert_allclose(wp[0], [TOP_DOWN, FROM_BELOW])
    np.testing.assert_allclose(wp[-1, 0], TOP_DOWN @ back, atol=1e-12)
    np.testing.assert_allclose(wp[-1, 1], FROM_BELOW @ back, atol=1e-12)
    assert wp[-1, 0, 2, 3] == pytest.approx(0.3)  # top-down: pre-grasp above
    assert wp[-1, 1, 2, 3] == pytest.approx(0.2)  # upward: pre-grasp below
    np.testing.assert_allclose(np.diff(wp[:, 0, 2, 3]), 0.025)


def test_top_down_accepted_from_below_rejected(robot, checker, solved):
    targets, res = solved
    out = check_approach_path(robot, targets, res.q, checker, distance=0.10, steps=10)
    assert out.ok.tolist() == [True, False]
    assert out.reason[1] == REASON_ENVIRONMENT  # the arm goes through the table
    assert 1 <= out.failed_step[1] <= 10
    # the pre-grasp configuration really reaches the pre-grasp pose, collision-free
    pre = approach_waypoints(targets[:1], 0.10, 10)[-1, 0]
    reached = robot.fk_pinocchio(out.q_pregrasp[0])[0]
    np.testing.assert_allclose(reached, pre, atol=2e-4)
    assert checker.check(out.q_pregrasp[0])[0] == ""
    assert 0 < out.max_joint_step[0] <= 0.25
    assert np.isnan(out.q_pregrasp[1]).all()


def test_joint_step_bound_and_zero_distance(robot, checker, solved):
    targets, res = solved
    out = check_approach_path(robot, targets[:1], res.q[:1], checker, max_joint_step=1e-4)
    assert out.reason.tolist() == ["joint_step"] and out.failed_step[0] == 1
    out = check_approach_path(robot, targets, res.q, checker, distance=0.0)
    assert out.ok.all()
    nan_q = np.full((1, robot.nq), np.nan)
    assert check_approach_path(robot, targets[:1], nan_q, checker).reason.tolist() == ["invalid"]


@pytest.mark.parametrize(
    ("kw", "match"),
    [({"distance": -0.1}, "distance"), ({"steps": 0}, "steps"), ({"max_joint_step": 0}, "max")],
)
def test_approach_errors(robot, checker, solved, kw, match):
    targets, res = solved
    with pytest.raises(InputError, match=match):
        check_approach_path(robot, targets, res.q, checker, **kw)


def _table(targets, res):
    return GraspTable(
        {
            "dq": dq_from_matrix(targets),
            "reachable": res.success,
            "reason": res.reason,
            "q": res.q,
            "pos_err": res.pos_err,
            "rot_err": res.rot_err,
        }
    )


def test_stage_check_approach_sets_reason(robot, checker, solved):
    targets, res = solved
    out = check_approach(
        robot=robot,
        grasps=_table(targets, res),
        checker=checker,
        approach=ApproachConfig(distance=0.1, steps=10),
    )
    assert out["reachable"].tolist() == [True, False]
    assert out["reason"].tolist() == ["", REASON_APPROACH]
    assert np.isnan(out["q"][1]).all() and np.isfinite(out["q"][0]).all()
    assert check_approach(_table(targets, res), robot, checker, None)["reachable"].all()


def test_filter_collisions_resolves_other_branch(robot):
    """The home solution hits an obstacle at the elbow; another IK branch avoids it."""
    elbow = robot.model.getJointId("panda_joint4")
    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, robot.home)
    p = data.oMi[elbow].translation.tolist()
    env = EnvironmentConfig.model_validate(
        {"obstacles": [{"shape": "sphere", "dims": {"radius": 0.06}, "pose": {"xyz": p}}]}
    )
    c = CollisionChecker(robot, env)
    assert c.check(robot.home)[0] == REASON_ENVIRONMENT
    target = robot.fk(robot.home)
    grasps = GraspTable(
        {
            "dq": dq_from_matrix(target),
            "reachable": [True],
            "reason": [""],
            "q": robot.home[None],
            "pos_err": [0.0],
            "rot_err": [0.0],
        }
    )
    out = filter_collisions(grasps, robot, c)
    assert out["reachable"].tolist() == [True], out["reason"]
    assert c.check(out["q"])[0] == ""
    np.testing.assert_allclose(robot.fk_pinocchio(out["q"])[0], target[0], atol=2e-4)
    # without re-solving the row is rejected with the collision reason
    out = filter_collisions(grasps, robot, c, resolve=False)
    assert out["reachable"].tolist() == [False]
    assert out["reason"].tolist() == [REASON_ENVIRONMENT]
    assert np.isnan(out["q"]).all()
    # clearance: NaN for unreachable, positive for the re-solved row
    cl = add_clearance(filter_collisions(grasps, robot, c), c)["clearance"]
    assert 0 < cl[0] < 0.5
