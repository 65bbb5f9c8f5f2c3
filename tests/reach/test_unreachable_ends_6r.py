"""Move ends a UR5 cannot reach are proved (UR geometry) and change no result of the engine."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import CONFIGS

from gcm_pipeline import pipeline as P
from gcm_pipeline.config import load_config
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.reach import path as path_module
from gcm_pipeline.reach import solution_checks as checks_module
from gcm_pipeline.reach.engine import ReachabilityEngine
from gcm_pipeline.reach.moves import Move, unreachable_ends
from gcm_pipeline.robot.ik import solve_ik

UR5_BOTTLE = CONFIGS / "bottle_side_ur5.yaml"


@pytest.fixture(scope="module")
def bottle_ur5():
    """The UR5 with its 2F-85, its checker and the bottle example's 72 side grasps."""
    cfg = load_config(UR5_BOTTLE)
    robot = P.robot_from_config(cfg)
    return (
        robot,
        P.make_checker(robot, cfg.environment, cfg.object),
        dq_to_matrix(P.generate_candidates(cfg)["dq"]),
    )


def test_ends_proved_beyond_reach_have_no_ik(bottle_ur5) -> None:
    robot, _, grasps = bottle_ur5
    long_approach = Move(distance=0.25, direction=(0, 0, -1), frame="grasp", steps=10)
    proved = unreachable_ends(robot, grasps, long_approach, 1e-4, 1e-3)
    assert proved.sum() >= 10
    ends = grasps.copy()
    ends[:, :3, 3] += long_approach.offsets(grasps)
    # the default backend (closed form and LM seeds) reaches none of them, and some others
    res = solve_ik(robot, ends, "pinocchio", position_tolerance=1e-4, orientation_tolerance=1e-3)
    assert not (proved & res.success).any()
    assert res.success.sum() >= 10


def test_moves_proved_beyond_reach_change_no_result(bottle_ur5, monkeypatch) -> None:
    """The engine fails such moves without planning them and tries no other branch of
    their grasp; the result is the one of planning every move and every branch."""
    robot, checker, grasps = bottle_ur5
    long_approach = Move(distance=0.25, direction=(0, 0, -1), frame="grasp", steps=10)
    proved = unreachable_ends(robot, grasps, long_approach, 1e-4, 1e-3)
    fast = ReachabilityEngine(robot, checker, approach=long_approach).run(grasps)
    assert np.count_nonzero(proved & (fast.reason == "approach")) >= 10
    assert not (proved & fast.reachable).any()

    for module in (path_module, checks_module):
        monkeypatch.setattr(
            module, "unreachable_ends", lambda robot, poses, *_: np.zeros(len(poses), bool)
        )
    slow = ReachabilityEngine(robot, checker, approach=long_approach).run(grasps)
    assert [name for name, a in zip(fast._fields, fast, strict=True) if a is None] == [
        name for name, b in zip(slow._fields, slow, strict=True) if b is None
    ]
    for a, b in zip(fast, slow, strict=True):
        if a is not None:
            np.testing.assert_array_equal(a, b)
