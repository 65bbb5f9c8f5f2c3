"""Level 3 of a self pair against a robot's own box: ``hull_vs_robot_box`` (compiled only).

A robot polytope against another link's box (a gripper piece from the gripper
registry, a box of the URDF) is free where every hull vertex lies more than
``BROAD_MARGIN`` beyond a face's plane of the box, in the box's frame, and collides
where one lies ``INSIDE_DEPTH`` inside it. Checked for the Panda (its fingers'
boxes against its base and upper links), the UR5 with the Robotiq 2F-85 (its body's
and fingers' boxes against the arm's meshes) and a user URDF (``write_mixed_arm``:
the boxes of wrists 1 and 3 against the concave mesh forearm and each other), on
configurations near contact (random ones and, column by column, both sides of the
pair's contact bisected to 1e-4 rad):

* every (pair, configuration) the kernel calls free, coal (as the checker asks it)
  calls free, and every one it calls colliding, coal calls colliding; it decides
  more than half of the free ones (the user URDF's boxes beside a concave mesh
  least often);
* the checker's decisions equal those of the same checker without the level and
  those of the NumPy code (which leaves these pairs to coal).
"""

from __future__ import annotations

import numpy as np
import pytest
from urdfs import assert_same_without_level, level_case, level_columns

from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.collision.broadphase import BROAD_MARGIN, INSIDE_DEPTH, stacked

#: Each test starts with the kernels on, whatever the environment says.
pytestmark = pytest.mark.usefixtures("kernels_on")

_ROBOTS = ("panda", "ur5_robotiq", "user_mixed")


@pytest.fixture(scope="module", params=_ROBOTS)
def case(request, tmp_path_factory):
    """A checker, per robot-box column configurations near that pair's contact, and the
    same checker without the level."""
    return level_case(request.param, tmp_path_factory, "self_boxes", seed=13, keep=400)


def test_robot_box_level_decides_as_coal(compiled, case):
    """Every row the kernel decides, coal decides the same; it decides both ways."""
    name, checker, near, _ = case
    columns = level_columns(checker, "self_boxes")
    assert columns, name
    counts = {kernels.FREE: 0, kernels.COLLIDES: 0, "coal free": 0, "coal hit": 0}
    for screen, k, c in columns:
        q = near[c]
        tfs = stacked(checker._frames.compute(q).transforms)
        joint, box_joint, verts, inv, halfs = screen.self_boxes[k]
        beyond = halfs + (BROAD_MARGIN + kernels.SLACK)
        deep = halfs - (INSIDE_DEPTH + kernels.SLACK)
        rows = np.arange(len(q))
        status = compiled.hull_vs_robot_box(tfs, joint, box_joint, rows, verts, inv, beyond, deep)
        coal_hit = checker._run(checker._pair_pool[c], q)
        wrong_free = (status == kernels.FREE) & coal_hit
        wrong_hit = (status == kernels.COLLIDES) & ~coal_hit
        assert not wrong_free.any(), (name, checker._pairs[c], np.flatnonzero(wrong_free)[:5])
        assert not wrong_hit.any(), (name, checker._pairs[c], np.flatnonzero(wrong_hit)[:5])
        for s in (kernels.FREE, kernels.COLLIDES):
            counts[s] += int((status == s).sum())
        counts["coal free"] += int((~coal_hit).sum())
        counts["coal hit"] += int(coal_hit.sum())
    assert counts["coal hit"] > 100, (name, counts)  # both sides of the contacts are tested
    assert counts[kernels.FREE] > 0.5 * counts["coal free"], (name, counts)
    # a hull vertex deep inside the box (none of the Panda's rows here has one)
    assert counts[kernels.COLLIDES] > 0 or name == "panda", (name, counts)


@pytest.mark.parametrize("mode", ["grasp", "approach"])
def test_same_decisions_without_the_robot_box_level(case, mode, numpy_code):
    """The checker's answers equal those of the same checker without the level, and NumPy's."""
    assert_same_without_level(case, mode, numpy_code, {"", "collision_self"})
