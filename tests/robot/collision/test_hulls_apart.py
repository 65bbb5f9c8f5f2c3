"""Level 3 of a self pair of two robot polytopes: a face of one's box between them.

Each robot polytope's hull vertices lie in a box of its joint's frame; a self
pair of two polytopes is free where every hull vertex of one lies more than
``BROAD_MARGIN`` beyond the plane of a face of the other's box (compiled only:
``hulls_apart``). Checked for the Panda, the UR5 with the Robotiq 2F-85 (its
links against each other and against the gripper's body, a box, and fingers)
and a user URDF (``write_mixed_arm``: its concave mesh forearm against the
convex mesh and the box of wrists 2 and 3, and the boxes of wrists 1 and 3), on
configurations near contact
(random configurations and, pair by pair, both sides of its contact bisected
to 1e-4 rad):

* the boxes hold every hull vertex (so the geometry);
* every (pair, configuration) the kernel calls free, coal (as the checker asks
  it) calls free, and the kernel decides most of the free ones;
* the checker's decisions with the level equal those of a checker without it
  and those of the NumPy code.
"""

from __future__ import annotations

import numpy as np
import pytest
from urdfs import assert_same_without_level, level_case, level_columns

from gcm_pipeline.robot.collision.broadphase import BROAD_MARGIN, stacked

#: Each test starts with the kernels on, whatever the environment says.
pytestmark = pytest.mark.usefixtures("kernels_on")

_ROBOTS = ("panda", "ur5_robotiq", "user_mixed")


def _columns(checker):
    """The two-polytope columns: [(screen, column, pair)]."""
    return level_columns(checker, "self_hulls")


@pytest.fixture(scope="module", params=_ROBOTS)
def case(request, tmp_path_factory):
    """A checker, per two-polytope column configurations near that pair's contact, and
    the same checker without the level."""
    return level_case(request.param, tmp_path_factory, "self_hulls", seed=11, keep=600)


def test_the_boxes_hold_every_hull_vertex(case):
    name, checker, _, _ = case
    columns = _columns(checker)
    assert columns, name
    for screen, k, _ in columns:
        for _joint, verts, box in screen.self_hulls[k]:
            assert verts.shape[0] == 3 and box.shape == (2, 3)
            assert np.all(np.abs(verts - box[0][:, None]) <= box[1][:, None] + 1e-15), name


def test_free_only_where_coal_is_free(compiled, case):
    """Every row the kernel calls free, coal calls free; most free rows are decided."""
    name, checker, near, _ = case
    free_rows = decided = colliding = 0
    for screen, k, c in _columns(checker):
        q = near[c]
        tfs = stacked(checker._frames.compute(q).transforms)
        (ja, va, box_a), (jb, vb, box_b) = checker._compiled_screen(screen)[4][k]
        np.testing.assert_array_equal(box_a[0], screen.self_hulls[k][0][2][0])
        assert np.all(box_a[1] > screen.self_hulls[k][0][2][1] + BROAD_MARGIN)
        rows = np.arange(len(q))
        apart = compiled.hulls_apart(tfs, ja, jb, rows, va, box_a, vb, box_b)
        coal_hit = checker._run(checker._pair_pool[c], q)
        wrong = apart & coal_hit
        assert not wrong.any(), (name, checker._pairs[c], np.flatnonzero(wrong)[:5])
        free_rows += int((~coal_hit).sum())
        decided += int(apart.sum())
        colliding += int(coal_hit.sum())
        assert compiled.hulls_apart(tfs, ja, jb, rows[:0], va, box_a, vb, box_b).shape == (0,)
    assert colliding > 100, (name, colliding)  # both sides of the contacts are tested
    assert decided > 0.8 * free_rows, (name, decided, free_rows)


@pytest.mark.parametrize("mode", ["grasp", "approach"])
def test_same_decisions_without_the_level(case, mode, numpy_code):
    """The checker's answers equal those of the same checker without the level, and NumPy's."""
    assert_same_without_level(case, mode, numpy_code, {"", "collision_self"})
