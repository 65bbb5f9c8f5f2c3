"""``solve_ik(workers=...)`` takes what ``ik.workers`` takes, and refuses the rest."""

from __future__ import annotations

import numpy as np
import pytest

from gcm_pipeline.errors import InputError
from gcm_pipeline.robot.ik import solve_ik


def test_solve_ik_reads_workers_as_the_config_does(panda):
    robot = panda
    targets = robot.fk(np.tile(robot.home, (4, 1)))
    assert solve_ik(robot, targets, workers="auto").success.all()  # as the config says it
    for bad in (True, -1, "two", 1.5):
        with pytest.raises(InputError, match="workers must be 'auto' or an int >= 0"):
            solve_ik(robot, targets, workers=bad)
