"""Threads sharing one robot get the answers one thread gets (the Python API)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import in_threads

from gcm_pipeline.config.robot_spec import load_robot
from gcm_pipeline.robot.ik import solve_ik


@pytest.mark.parametrize("name", ["panda", "ur5"])
def test_threads_sharing_a_robot_get_one_threads_answers(name: str) -> None:
    # the verification's forward kinematics once used one Pinocchio Data per
    # robot: another thread's configuration could overwrite it between a
    # solve and its check (false "unreachable", or a pose checked against
    # another target's answer)
    arm = load_robot(name)
    targets = arm.fk(arm.random_configurations(600, np.random.default_rng(8)))
    want = solve_ik(arm, targets)
    got: dict[int, list] = {}

    def work(k: int) -> None:
        got[k] = [solve_ik(arm, targets) for _ in range(4)]

    in_threads(work, 3)  # switching threads as often as Python allows
    assert sorted(got) == [0, 1, 2]
    for answers in got.values():
        for answer in answers:
            assert np.array_equal(answer.success, want.success)
            assert np.array_equal(answer.q, want.q, equal_nan=True)
